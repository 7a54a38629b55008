//! `--payload`: a shipped payload or a member of the generated training family by name, or a
//! payload URDF by path (see the [`moonhaul_sim::scene`] docs for what such a file must be).

use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{Context, Result};
use moonhaul_sim::{PayloadKind, SceneModel};

/// A `--payload` value before the scene loads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PayloadArg {
    /// A shipped payload or a generated one (`gen<i>`), which the scene must hold.
    Named(PayloadKind),
    File(PathBuf),
}

impl FromStr for PayloadArg {
    type Err = String;

    /// `box`, `bricks`, `sledge`, `gen<i>` (a generated payload: validation on the training
    /// family), or a path: anything ending in `.urdf` or containing `/`. Any other word is a
    /// typo, not a file name, so it is refused with the choices.
    fn from_str(s: &str) -> Result<Self, String> {
        if s.ends_with(".urdf") || s.contains('/') {
            return Ok(PayloadArg::File(PathBuf::from(s)));
        }
        s.parse::<PayloadKind>()
            .map(PayloadArg::Named)
            .map_err(|_| {
                format!(
                    "unknown payload {s:?} (expected box, bricks, sledge, gen<i> (a generated \
                 training payload) or a payload URDF path, e.g. ./crate.urdf)"
                )
            })
    }
}

impl PayloadArg {
    /// The name [`SceneModel::payload_name`] gives it once resolved (the file stem for a file),
    /// for reading back outputs without building a scene.
    pub fn name(&self) -> String {
        match self {
            PayloadArg::Named(kind) => kind.label(),
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
        PayloadArg::Named(kind) => Ok(*kind),
        // The error names the file already.
        PayloadArg::File(path) => scene.add_payload_file(path).context("--payload"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_paths_and_typos() {
        assert_eq!("sledge".parse(), Ok(PayloadArg::Named(PayloadKind::Sledge)));
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
        let generated = "gen15".parse::<PayloadArg>().unwrap();
        assert_eq!(generated, PayloadArg::Named(PayloadKind::Generated(15)));
        assert_eq!(generated.name(), "gen15");
        assert!("gen".parse::<PayloadArg>().is_err());
        assert_eq!(
            PayloadArg::File("dir/crate_small.urdf".into()).name(),
            "crate_small"
        );
    }
}
