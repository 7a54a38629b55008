//! `moonhaul-unit --hal can` on a kernel CAN interface: where it cannot be opened, the daemon
//! exits with an error naming the interface and what is missing (on a kernel without SocketCAN,
//! the address family AF_CAN), before it drives anything; and the CAN options are checked.

mod common;

use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Runs `moonhaul-unit` with the repo's unit config, a fresh key file and `args`, killed after
/// a minute at most.
fn daemon(args: &[&str]) -> Output {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.toml");
    common::stdout(&common::generate_keys(&keys, "2", &[]));
    let port = moonhaul_deploy::network::free_loopback_port().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_moonhaul-unit"))
        .arg("--config")
        .arg(moonhaul_core::config::repo_file("configs/unit.toml"))
        .args(["--controller", "scripted", "--keys"])
        .arg(&keys)
        .arg("--listen")
        .arg(format!("tcp/127.0.0.1:{port}"))
        .args(["--max-runtime-s", "1"])
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("moonhaul-unit {args:?} did not exit within a minute");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// Whether this kernel has SocketCAN loaded (its core creates `/proc/net/can`).
fn kernel_has_can() -> bool {
    std::path::Path::new("/proc/net/can").exists()
}

fn fails_with(args: &[&str], needles: &[&str]) -> String {
    let out = daemon(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        matches!(out.status.code(), Some(1 | 2)),
        "{args:?}: {:?}: {stderr}",
        out.status
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    for needle in needles {
        assert!(
            stderr.contains(needle),
            "{args:?}: no {needle:?} in {stderr}"
        );
    }
    stderr
}

#[test]
fn an_interface_that_cannot_be_opened_is_named_with_what_is_missing() {
    for name in ["vcan0", "can7"] {
        let missing = if kernel_has_can() {
            // vcan0 may exist on a machine with SocketCAN; no drives answer on it.
            "CAN"
        } else {
            "AF_CAN"
        };
        fails_with(&["--hal", "can", "--can-interface", name], &[name, missing]);
    }
}

#[test]
fn the_can_options_are_checked() {
    fails_with(&["--hal", "can"], &["--can-interface"]);
    fails_with(
        &["--hal", "mock", "--can-interface", "can0"],
        &["--can-interface", "--hal can"],
    );
    // The emulated bus needs no interface.
    let out = daemon(&["--hal", "can-emulated"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
