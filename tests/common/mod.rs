//! Helpers the CLI integration tests share: run the built `moonhaul` binary and judge its
//! output. Each test file includes this with `mod common;` and uses what it needs.
#![allow(dead_code)]

use std::process::{Command, Output};

/// Runs the `moonhaul` binary of this build with `args`.
pub fn moonhaul(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moonhaul"))
        .args(args)
        .output()
        .expect("the moonhaul binary of this build runs")
}

/// `moonhaul keys generate` of team `moonhaul` with `units` units into `out`, plus `extra`.
pub fn generate_keys(out: &std::path::Path, units: &str, extra: &[&str]) -> Output {
    let out = out.to_str().unwrap();
    let mut args = vec![
        "keys", "generate", "--team", "moonhaul", "--units", units, "--out", out,
    ];
    args.extend_from_slice(extra);
    moonhaul(&args)
}

/// Stdout of a run that must succeed.
pub fn stdout(output: &Output) -> String {
    assert!(
        output.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).unwrap()
}

/// Stderr of a run that must fail.
pub fn stderr(output: &Output) -> String {
    assert!(!output.status.success(), "unexpectedly succeeded");
    String::from_utf8(output.stderr.clone()).unwrap()
}

/// A run that must fail with a clear error: exit status 1 (ours) or 2 (clap), never a panic
/// (101) or a signal, with `needle` (the argument or path at fault) in the message.
pub fn fails_naming(args: &[&str], needle: &str) -> String {
    let output = moonhaul(args);
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(
        matches!(output.status.code(), Some(1 | 2)),
        "{args:?}: {:?}, stderr: {stderr}",
        output.status
    );
    assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    assert!(
        stderr.contains(needle),
        "{args:?}: no {needle:?} in {stderr}"
    );
    stderr
}
