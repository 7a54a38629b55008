//! Reading files that come from outside the process (URDFs, configs, policies, CAN logs) with
//! a size cap checked *before* the content is read, so a wrong path (a device, a FIFO, a
//! multi-gigabyte file) is a clear error instead of a hang or an exhausted memory.
//!
//! Each kind of file has its cap here, one place to read and change them. The caps are far
//! above any real file of that kind (the unit URDF is ~10 kB, a policy ~200 kB).

use std::fs::File;
use std::io::{self, Read};
use std::path::{Path, PathBuf};

/// Largest URDF accepted, bytes (the unit URDF is ~10 kB; meshes are never inlined).
pub const MAX_URDF_BYTES: u64 = 4 << 20;
/// Largest TOML config accepted, bytes (every shipped config is under 5 kB).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;
/// Largest policy file accepted, bytes ([256,128,64] actor ~0.2 MB; [1024]×4 ~13 MB).
pub const MAX_POLICY_BYTES: u64 = 64 << 20;
/// Largest training checkpoint accepted, bytes (actor, critic and Adam state of the widest
/// network a config allows stay well under it).
pub const MAX_CHECKPOINT_BYTES: u64 = 1 << 30;
/// Largest run log read back on resume (`metrics.csv`), bytes: a million iterations of
/// ~200-byte rows.
pub const MAX_RUN_LOG_BYTES: u64 = 256 << 20;
/// Largest candump log accepted for replay, bytes (~10 min of one unit's bus at 50 Hz).
pub const MAX_CANDUMP_BYTES: u64 = 256 << 20;

/// Shortens `text` from outside the process to at most `max_bytes` bytes for an error message,
/// cutting at a character boundary (a byte cut inside a multi-byte character would panic) and
/// marking the cut with "…".
pub fn clip_for_message(text: &mut String, max_bytes: usize) {
    if text.len() <= max_bytes {
        return;
    }
    let mut end = max_bytes;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    text.truncate(end);
    text.push('…');
}

/// Why a file from outside could not be read.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    // The I/O error is part of the message, not a `source`, so a chain prints it once.
    #[error("cannot read {}: {error}", path.display())]
    Io { path: PathBuf, error: io::Error },
    #[error("{} is not a regular file", path.display())]
    NotAFile { path: PathBuf },
    #[error("{} is larger than {max_bytes} bytes, the limit for this kind of file", path.display())]
    TooLarge { path: PathBuf, max_bytes: u64 },
    #[error("{} is not valid UTF-8 text (byte {valid_up_to})", path.display())]
    NotUtf8 { path: PathBuf, valid_up_to: usize },
}

/// Reads a whole regular file of at most `max_bytes`. Refuses anything that is not a regular
/// file before opening it (opening a FIFO would block), and never reads more than
/// `max_bytes + 1` bytes, whatever the metadata said (the file may grow meanwhile).
pub fn read_capped(path: &Path, max_bytes: u64) -> Result<Vec<u8>, InputError> {
    let len = check_readable(path, max_bytes)?;
    let io_error = |error| InputError::Io {
        path: path.to_owned(),
        error,
    };
    let too_large = || InputError::TooLarge {
        path: path.to_owned(),
        max_bytes,
    };
    let mut bytes = Vec::with_capacity(len as usize);
    File::open(path)
        .and_then(|file| file.take(max_bytes + 1).read_to_end(&mut bytes))
        .map_err(io_error)?;
    if bytes.len() as u64 > max_bytes {
        return Err(too_large());
    }
    Ok(bytes)
}

/// The checks [`read_capped`] makes before opening: `path` is a regular file of at most
/// `max_bytes` (returned), so a caller can refuse a bad input before starting long work.
pub fn check_readable(path: &Path, max_bytes: u64) -> Result<u64, InputError> {
    let metadata = std::fs::metadata(path).map_err(|error| InputError::Io {
        path: path.to_owned(),
        error,
    })?;
    if !metadata.is_file() {
        return Err(InputError::NotAFile {
            path: path.to_owned(),
        });
    }
    if metadata.len() > max_bytes {
        return Err(InputError::TooLarge {
            path: path.to_owned(),
            max_bytes,
        });
    }
    Ok(metadata.len())
}

/// [`read_capped`] for text files.
pub fn read_capped_text(path: &Path, max_bytes: u64) -> Result<String, InputError> {
    String::from_utf8(read_capped(path, max_bytes)?).map_err(|e| InputError::NotUtf8 {
        path: path.to_owned(),
        valid_up_to: e.utf8_error().valid_up_to(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_are_clipped_at_character_boundaries() {
        for max in 0..12 {
            let mut text = "añ€😀añ€😀".to_owned();
            clip_for_message(&mut text, max);
            let kept = text.trim_end_matches('…');
            assert!(
                kept.len() <= max && "añ€😀añ€😀".starts_with(kept),
                "{max}: {text}"
            );
        }
        let mut short = "ok".to_owned();
        clip_for_message(&mut short, 2);
        assert_eq!(short, "ok");
    }

    #[test]
    fn caps_size_and_refuses_non_files() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.toml");
        std::fs::write(&file, "x = 1\n").unwrap();
        assert_eq!(read_capped_text(&file, 6).unwrap(), "x = 1\n");
        assert!(matches!(
            read_capped(&file, 5),
            Err(InputError::TooLarge { max_bytes: 5, .. })
        ));
        let err = read_capped(dir.path(), 100).unwrap_err();
        assert!(matches!(err, InputError::NotAFile { .. }), "{err}");
        assert!(err.to_string().contains(&dir.path().display().to_string()));
        let dev = read_capped(Path::new("/dev/zero"), 100).unwrap_err();
        assert!(matches!(dev, InputError::NotAFile { .. }), "{dev}");
        let missing = read_capped(&dir.path().join("absent"), 100).unwrap_err();
        assert!(missing.to_string().contains("absent"), "{missing}");
        std::fs::write(&file, [0xff, 0xfe]).unwrap();
        assert!(matches!(
            read_capped_text(&file, 100),
            Err(InputError::NotUtf8 { valid_up_to: 0, .. })
        ));
    }
}
