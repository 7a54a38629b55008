//! The one rule for every file a command writes (`--log`, `--out`, `--record`, …): never over
//! one of the run's own inputs (its config, key file, policies, URDF, …), whatever the flags,
//! and never over any other existing file unless the user passed `--force`. Checked before the
//! run starts, so a refused output costs nothing; the message names both paths.
//!
//! Two paths are the same file when they resolve to the same device and inode, which also
//! catches a symbolic or hard link to an input and a path spelled another way (`./a/../keys`).

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

/// Why an output path is refused.
#[derive(Debug, thiserror::Error)]
pub enum OverwriteError {
    #[error(
        "{flag} {}: that is the run's {role} {}; refusing to write over an input",
        output.display(),
        input.display()
    )]
    IsInput {
        flag: String,
        output: PathBuf,
        role: String,
        input: PathBuf,
    },
    #[error(
        "{flag} {}: the file exists; pass --force to replace it",
        output.display()
    )]
    Exists { flag: String, output: PathBuf },
    #[error(
        "{flag} {}: the folder holds files (of an earlier run?); pass --force to write into it",
        output.display()
    )]
    FolderNotEmpty { flag: String, output: PathBuf },
    #[error("{flag} {}: exists and is not a folder", output.display())]
    NotAFolder { flag: String, output: PathBuf },
}

/// Refuses an output folder (`--out DIR` of a command whose files depend on the run) that
/// already holds anything, unless `force`; each file written into it still passes
/// [`RunInputs::check_output`] (with `force`), so no input in it is replaced.
pub fn check_output_folder(flag: &str, folder: &Path, force: bool) -> Result<(), OverwriteError> {
    let refuse =
        |make: fn(String, PathBuf) -> OverwriteError| Err(make(flag.to_owned(), folder.to_owned()));
    match std::fs::read_dir(folder) {
        Ok(mut entries) => {
            if !force && entries.next().is_some() {
                return refuse(|flag, output| OverwriteError::FolderNotEmpty { flag, output });
            }
            Ok(())
        }
        Err(_) if std::fs::symlink_metadata(folder).is_err() => Ok(()),
        Err(_) => refuse(|flag, output| OverwriteError::NotAFolder { flag, output }),
    }
}

/// The files a run reads, each with its role ("unit config", "key file", …).
#[derive(Debug, Default, Clone)]
pub struct RunInputs {
    files: Vec<Input>,
}

#[derive(Debug, Clone)]
struct Input {
    role: String,
    path: PathBuf,
    /// Device and inode; `None` for a path that does not exist (nothing to overwrite).
    id: Option<(u64, u64)>,
}

fn file_id(path: &Path) -> Option<(u64, u64)> {
    std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
}

impl RunInputs {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records one input file of the run.
    pub fn add(&mut self, role: impl Into<String>, path: impl Into<PathBuf>) -> &mut Self {
        let path = path.into();
        self.files.push(Input {
            role: role.into(),
            id: file_id(&path),
            path,
        });
        self
    }

    /// Refuses `output` (given as `flag`, e.g. `--log`) if it is one of the inputs, or if it
    /// exists and `force` is off. A missing output is fine: it will be created.
    pub fn check_output(
        &self,
        flag: &str,
        output: &Path,
        force: bool,
    ) -> Result<(), OverwriteError> {
        // `symlink_metadata`: a dangling link exists too (the writer refuses links anyway).
        if std::fs::symlink_metadata(output).is_err() {
            return Ok(());
        }
        let id = file_id(output);
        if let Some(input) = self.files.iter().find(|i| i.id.is_some() && i.id == id) {
            return Err(OverwriteError::IsInput {
                flag: flag.to_owned(),
                output: output.to_owned(),
                role: input.role.clone(),
                input: input.path.clone(),
            });
        }
        if force {
            Ok(())
        } else {
            Err(OverwriteError::Exists {
                flag: flag.to_owned(),
                output: output.to_owned(),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_are_never_overwritten_and_existing_files_only_with_force() {
        let dir = tempfile::tempdir().unwrap();
        let keys = dir.path().join("keys.toml");
        let config = dir.path().join("unit.toml");
        let other = dir.path().join("old.mcap");
        for f in [&keys, &config, &other] {
            std::fs::write(f, "x").unwrap();
        }
        let mut inputs = RunInputs::new();
        inputs
            .add("key file", &keys)
            .add("unit config", &config)
            .add("policy", dir.path().join("missing.safetensors"));
        // Every spelling of an input, with or without --force.
        std::os::unix::fs::symlink(&keys, dir.path().join("link")).unwrap();
        std::fs::hard_link(&config, dir.path().join("hard")).unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        for (output, role, input) in [
            (keys.clone(), "key file", &keys),
            (dir.path().join("sub/../keys.toml"), "key file", &keys),
            (dir.path().join("link"), "key file", &keys),
            (dir.path().join("hard"), "unit config", &config),
        ] {
            for force in [false, true] {
                let e = inputs.check_output("--log", &output, force).unwrap_err();
                let message = e.to_string();
                assert!(matches!(e, OverwriteError::IsInput { .. }), "{message}");
                assert!(
                    message.contains("--log")
                        && message.contains(&output.display().to_string())
                        && message.contains(role)
                        && message.contains(&input.display().to_string()),
                    "{message}"
                );
            }
        }
        // Another existing file: only with --force.
        let e = inputs.check_output("--out", &other, false).unwrap_err();
        assert!(
            matches!(e, OverwriteError::Exists { .. })
                && e.to_string().contains("--force")
                && e.to_string().contains("old.mcap"),
            "{e}"
        );
        inputs.check_output("--out", &other, true).unwrap();
        // A new file is fine; an input that does not exist matches nothing.
        inputs
            .check_output("--log", &dir.path().join("new.mcap"), false)
            .unwrap();
        inputs
            .check_output("--log", &dir.path().join("missing.safetensors"), false)
            .unwrap();
    }

    #[test]
    fn output_folders_must_be_new_or_empty_unless_forced() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        check_output_folder("--out", &out, false).unwrap();
        std::fs::create_dir(&out).unwrap();
        check_output_folder("--out", &out, false).unwrap();
        std::fs::write(out.join("000.csv"), "").unwrap();
        let e = check_output_folder("--out", &out, false).unwrap_err();
        assert!(
            matches!(e, OverwriteError::FolderNotEmpty { .. }) && e.to_string().contains("--force"),
            "{e}"
        );
        check_output_folder("--out", &out, true).unwrap();
        let e = check_output_folder("--out", &out.join("000.csv"), true).unwrap_err();
        assert!(matches!(e, OverwriteError::NotAFolder { .. }), "{e}");
    }
}
