//! Where a policy came from, recorded in its file: the source commit and a digest of every
//! setting that shaped it.

use sha2::{Digest, Sha256};

use crate::config::TrainConfig;
use crate::EnvError;

/// The git commit of the working tree the trainer runs in (`<hash>-dirty` with uncommitted
/// changes), or `unknown` outside a git checkout.
pub fn commit() -> String {
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
    };
    match git(&["rev-parse", "HEAD"]) {
        Some(hash) if !hash.is_empty() => {
            let dirty = git(&["status", "--porcelain", "--untracked-files=no"])
                .is_some_and(|s| !s.is_empty());
            if dirty {
                format!("{hash}-dirty")
            } else {
                hash
            }
        }
        _ => "unknown".into(),
    }
}

/// SHA-256 of the resolved training config and the bytes of every file it names (the sim and
/// task settings of a phase task), so two policies with the same digest were trained on the
/// same settings.
pub fn config_digest(config: &TrainConfig) -> Result<String, EnvError> {
    let mut hash = Sha256::new();
    let mut toml = config.clone();
    if let Some(world) = &mut toml.world {
        // The digest covers the files' contents, not where this checkout keeps them.
        for path in [&world.sim, &world.tasks] {
            let bytes =
                moonhaul_core::input::read_capped(path, moonhaul_core::input::MAX_CONFIG_BYTES)?;
            hash.update(&bytes);
        }
        world.sim = world.sim.file_name().map(Into::into).unwrap_or_default();
        world.tasks = world.tasks.file_name().map(Into::into).unwrap_or_default();
    }
    hash.update(toml.to_toml().as_bytes());
    Ok(hash.finalize().iter().map(|b| format!("{b:02x}")).collect())
}
