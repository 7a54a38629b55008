//! `--payload`: a shipped payload by name, or a payload URDF by path (see the
//! [`moonhaul_sim::scene`] docs for what such a file must be).

use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{Context, Result};
use moonhaul_sim::{PayloadKind, SceneModel};

/// A `--payload` value before the scene loads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PayloadArg {
    Shipped(PayloadKind),
    File(PathBuf),
}

impl FromStr for PayloadArg {
    type Err = String;

    /// `box`, `bricks`, `sledge`, or a path: anything ending in `.urdf` or containing `/`. Any
    /// other word is a typo, not a file name, so it is refused with the choices.
    fn from_str(s: &str) -> Result<Self, String> {
        if let Some(kind) = PayloadKind::ALL.into_iter().find(|p| p.name() == s) {
            return Ok(PayloadArg::Shipped(kind));
        }
        if s.ends_with(".urdf") || s.contains('/') {
            return Ok(PayloadArg::File(PathBuf::from(s)));
        }
        Err(format!(
            "unknown payload {s:?} (expected box, bricks, sledge or a payload URDF path, \
             e.g. ./crate.urdf)"
        ))
    }
}

impl PayloadArg {
    /// The name [`SceneModel::payload_name`] gives it once resolved (the file stem for a file),
    /// for reading back outputs without building a scene.
    pub fn name(&self) -> String {
        match self {
            PayloadArg::Shipped(kind) => kind.name().into(),
            PayloadArg::File(path) => path.file_stem().map_or_else(
                || PayloadKind::Custom.name().into(),
                |s| s.to_string_lossy().into_owned(),
            ),
        }
    }
}

/// The scene's payload for `arg`: a shipped one as is, a file loaded, checked and grasp-solved
/// into the scene's custom slot (replacing any earlier file).
pub fn resolve(scene: &mut SceneModel, arg: &PayloadArg) -> Result<PayloadKind> {
    match arg {
        PayloadArg::Shipped(kind) => Ok(*kind),
        // The error names the file already.
        PayloadArg::File(path) => scene.add_payload_file(path).context("--payload"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_paths_and_typos() {
        assert_eq!(
            "sledge".parse(),
            Ok(PayloadArg::Shipped(PayloadKind::Sledge))
        );
        for path in ["crate.urdf", "./crate", "a/b.xml", "/abs/box"] {
            assert_eq!(path.parse(), Ok(PayloadArg::File(path.into())), "{path}");
        }
        for bad in ["piano", "custom", "", "Box"] {
            let err = bad.parse::<PayloadArg>().unwrap_err();
            assert!(
                err.contains(&format!("{bad:?}")) && err.contains("bricks"),
                "{err}"
            );
        }
        assert_eq!(
            PayloadArg::File("dir/crate_small.urdf".into()).name(),
            "crate_small"
        );
    }
}
