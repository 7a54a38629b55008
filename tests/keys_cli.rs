//! `moonhaul keys generate`: writes a private key file, never prints a secret, never replaces
//! a key file unless told to, and refuses an empty team.

mod common;

use std::path::Path;

use common::{fails_naming, generate_keys, stdout};
use moonhaul_coord::KeyFile;

/// Every run of 64 hex digits in `text` (what a secret looks like in the file).
fn secrets(text: &str) -> Vec<String> {
    text.split(|c: char| !c.is_ascii_hexdigit())
        .filter(|w| w.len() == 64)
        .map(str::to_owned)
        .collect()
}

#[cfg(unix)]
fn mode(path: &Path) -> u32 {
    use std::os::unix::fs::PermissionsExt as _;
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

#[test]
fn generate_writes_a_private_file_and_prints_no_secret() {
    let dir = tempfile::tempdir().unwrap();
    // A missing folder is created too.
    let out = dir.path().join("config").join("moonhaul.keys.toml");
    let printed = stdout(&generate_keys(&out, "3", &["--epoch", "4"]));
    assert!(printed.contains(&out.display().to_string()), "{printed}");
    assert!(
        printed.contains("moonhaul") && printed.contains("epoch 4"),
        "{printed}"
    );
    #[cfg(unix)]
    {
        assert_eq!(mode(&out), 0o600);
        assert_eq!(mode(out.parent().unwrap()) & 0o077, 0);
    }
    let keys = KeyFile::load(&out).unwrap();
    assert_eq!(
        (keys.team(), keys.team_size(), keys.epoch()),
        ("moonhaul", 3, 4)
    );
    let text = std::fs::read_to_string(&out).unwrap();
    let written = secrets(&text);
    assert_eq!(written.len(), 4, "{} secrets in the file", written.len());
    for secret in &written {
        assert!(!printed.contains(secret.as_str()), "a secret was printed");
    }
}

#[test]
fn generate_never_replaces_a_key_file_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("team.keys.toml");
    stdout(&generate_keys(&out, "2", &[]));
    let before = std::fs::read(&out).unwrap();
    let err = fails_naming(
        &[
            "keys",
            "generate",
            "--team",
            "moonhaul",
            "--units",
            "2",
            "--out",
            out.to_str().unwrap(),
        ],
        "team.keys.toml",
    );
    assert!(err.contains("exists"), "{err}");
    assert_eq!(std::fs::read(&out).unwrap(), before);
    let printed = stdout(&generate_keys(&out, "2", &["--force", "--epoch", "2"]));
    assert!(printed.contains("replaced"), "{printed}");
    assert_ne!(std::fs::read(&out).unwrap(), before);
    assert_eq!(KeyFile::load(&out).unwrap().epoch(), 2);
    #[cfg(unix)]
    assert_eq!(mode(&out), 0o600);
    // No temporary is left beside it.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn generate_refuses_an_empty_team() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("team.keys.toml");
    let path = out.to_str().unwrap();
    let err = fails_naming(
        &[
            "keys", "generate", "--team", "moonhaul", "--units", "0", "--out", path,
        ],
        "--units",
    );
    assert!(err.contains("1 to"), "{err}");
    fails_naming(
        &[
            "keys", "generate", "--team", "", "--units", "2", "--out", path,
        ],
        "team",
    );
    assert!(!out.exists());
}
