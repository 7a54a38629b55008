//! Whole-or-nothing file writes, for every file moonhaul produces (policies, checkpoints,
//! logs, CSVs, plots): the content goes to a hidden temporary sibling, is synced to disk and
//! renamed over the target, so a reader — or a robot booting after a power cut — sees the
//! old file or the new one, never half of one.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Writes `path` by letting `write` create and fill a temporary sibling, then syncing and
/// renaming it into place. The temporary keeps the target's file name (and so its extension:
/// writers such as image encoders choose the format from it) behind a hidden, unique prefix.
/// On any error the temporary is removed; `io_error` turns I/O failures into the caller's
/// error type.
pub fn write_with<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl Fn(io::Error) -> E,
) -> Result<(), E> {
    let temp = temporary_sibling(path).map_err(&io_error)?;
    let result = write(&temp).and_then(|()| {
        File::open(&temp)
            .and_then(|file| file.sync_all())
            .and_then(|()| fs::rename(&temp, path))
            .map_err(&io_error)
    });
    if result.is_err() {
        // Best effort: the temporary may not exist, and the first error is the one to report.
        let _ = fs::remove_file(&temp);
    }
    result
}

/// Writes `bytes` to `path` atomically (see [`write_with`]).
pub fn write(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_with(
        path,
        |temp| {
            OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(temp)?
                .write_all(bytes)
        },
        |e| e,
    )
}

fn temporary_sibling(path: &Path) -> io::Result<PathBuf> {
    /// Distinguishes concurrent writers within one process.
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let name = path.file_name().ok_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{} has no file name", path.display()),
        )
    })?;
    Ok(path.with_file_name(format!(
        ".tmp-{}-{}-{}",
        std::process::id(),
        NEXT.fetch_add(1, Ordering::Relaxed),
        name.to_string_lossy()
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn replaces_whole_and_leaves_no_temporary() {
        let dir = std::env::temp_dir().join(format!("moonhaul-atomic-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let target = dir.join("policy.safetensors");
        write(&target, b"old").unwrap();
        write(&target, b"new").unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"new");
        assert_eq!(entries(&dir), ["policy.safetensors"]);

        // A failing writer leaves the old content and no temporary behind.
        let failed = write_with(
            &target,
            |temp| {
                assert!(temp.to_string_lossy().ends_with("policy.safetensors"));
                fs::write(temp, b"half")?;
                Err(io::Error::other("encoder failed"))
            },
            |e| e,
        );
        assert_eq!(failed.unwrap_err().to_string(), "encoder failed");
        assert_eq!(fs::read(&target).unwrap(), b"new");
        assert_eq!(entries(&dir), ["policy.safetensors"]);

        let missing_dir = write(&dir.join("absent").join("x.csv"), b"x").unwrap_err();
        assert_eq!(missing_dir.kind(), io::ErrorKind::NotFound);
        fs::remove_dir_all(&dir).unwrap();
    }
}
