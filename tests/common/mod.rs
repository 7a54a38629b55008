//! Helpers the CLI integration tests share: run the built `moonhaul` binary and judge its
//! output. Each test file includes this with `mod common;` and uses what it needs.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

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

/// The `moonhaul-unit` binary of this build.
pub fn unit_bin() -> &'static str {
    env!("CARGO_BIN_EXE_moonhaul-unit")
}

/// A fresh key file for a two-unit team `moonhaul` in `dir`.
pub fn keys(dir: &Path) -> PathBuf {
    let path = dir.join("keys.toml");
    stdout(&generate_keys(&path, "2", &[]));
    path
}

/// Waits for `child` to end, at most `timeout` (then kills it and fails the test).
pub fn wait_bounded(mut child: Child, timeout: Duration) -> Output {
    let deadline = Instant::now() + timeout;
    while child.try_wait().unwrap().is_none() {
        if Instant::now() >= deadline {
            let _ = child.kill();
            panic!("the process did not exit within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// Runs `cmd` to its end, at most `timeout`, capturing its output.
pub fn run_bounded(cmd: &mut Command, timeout: Duration) -> Output {
    let child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_bounded(child, timeout)
}

/// A daemon process, killed if the test fails before it ends it.
pub struct Daemon(pub Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Daemon {
    /// Unit `i` of a two-unit team on backend `hal` with the scripted controller (these tests
    /// are about processes, faults and logs, and it carries the team into transport for
    /// certain; the bundled policies are placeholders), its log `dir/unit-<i>.mcap` and its
    /// stderr in `dir/unit-<i>.log`; `net` and `extra` are more arguments.
    pub fn unit(
        dir: &Path,
        keys: &Path,
        i: usize,
        hal: &str,
        net: &[&str],
        extra: &[&str],
    ) -> Daemon {
        let log = std::fs::File::create(dir.join(format!("unit-{i}.log"))).unwrap();
        let pose = if i == 0 {
            "0,-0.8,0"
        } else {
            "0,0.8,3.141592653589793"
        };
        let child = Command::new(unit_bin())
            .arg("--config")
            .arg(moonhaul_core::config::repo_file("configs/unit.toml"))
            .args(["--hal", hal, "--unit-index", &i.to_string()])
            .args(["--controller", "scripted"])
            .arg(format!("--start-pose={pose}"))
            .arg("--keys")
            .arg(keys)
            .arg("--log")
            .arg(dir.join(format!("unit-{i}.mcap")))
            .args(net)
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        Daemon(child)
    }

    pub fn signal(&self, sig: &str) {
        Command::new("kill")
            .args([sig, &self.0.id().to_string()])
            .status()
            .unwrap();
    }

    pub fn wait(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.0.try_wait().unwrap() {
                return status;
            }
            assert!(Instant::now() < deadline, "daemon did not exit");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

/// The Python with the pinned ROS 2 tooling (`rosbags`, `eclipse-zenoh`) that `cargo xtask
/// test` installs and names in `MOONHAUL_ROS2_PYTHON`. Under xtask (`MOONHAUL_XTASK_TEST`
/// set) a missing one fails the test; under plain `cargo test` the test is skipped, saying
/// why (`None`).
pub fn ros2_python(test: &str) -> Option<PathBuf> {
    match std::env::var_os("MOONHAUL_ROS2_PYTHON") {
        Some(python) => {
            let python = PathBuf::from(python);
            assert!(
                python.is_file(),
                "MOONHAUL_ROS2_PYTHON={} is not a file",
                python.display()
            );
            Some(python)
        }
        None if std::env::var_os("MOONHAUL_XTASK_TEST").is_some() => panic!(
            "{test}: MOONHAUL_ROS2_PYTHON is not set, but cargo xtask test sets it to the \
             venv it prepares with rosbags and eclipse-zenoh"
        ),
        None => {
            eprintln!(
                "SKIPPED {test}: needs MOONHAUL_ROS2_PYTHON, a python with the pinned rosbags and \
                 eclipse-zenoh; `cargo xtask test` installs them and sets it"
            );
            None
        }
    }
}
