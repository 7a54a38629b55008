//! The daemon's start-up, arguments and exits: `moonhaul-unit` never writes over an input of
//! its run, refuses malformed endpoints and fault injections by name, never waits without a
//! bound (a `--hal sim` unit with no world), and a signal at its earliest moment still ends in
//! a hold with a finished log.

mod common;

use common::{keys, run_bounded, unit_bin, wait_bounded};

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use moonhaul_core::config::repo_file;
use moonhaul_deploy::mission_log::read_unit_log;

/// The magic an MCAP file starts and, once finished (summary and footer written), ends with.
const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// A unit on mock drives whose peers never come (its endpoint has nobody behind it).
fn mock_unit(keys: &Path, extra: &[&str]) -> Command {
    let port = moonhaul_deploy::network::free_loopback_port().unwrap();
    let mut cmd = Command::new(unit_bin());
    cmd.arg("--config")
        .arg(repo_file("configs/unit.toml"))
        .args(["--hal", "mock", "--controller", "scripted", "--keys"])
        .arg(keys)
        .args(["--listen", "tcp/127.0.0.1:0"])
        .args(["--connect", &format!("tcp/127.0.0.1:{port}")])
        .args(extra)
        .stdin(Stdio::null());
    cmd
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// A finished unit log: summary and footer written, and readable.
fn assert_finished(log: &Path) {
    let bytes = std::fs::read(log).unwrap();
    assert!(
        bytes.starts_with(MCAP_MAGIC) && bytes.ends_with(MCAP_MAGIC),
        "{} is not a finished MCAP",
        log.display()
    );
    read_unit_log(log).unwrap();
}

#[test]
fn the_log_never_replaces_an_input_and_an_existing_file_only_with_force() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let config = repo_file("configs/unit.toml");
    let policy = repo_file("assets/policies/lift.safetensors");
    let urdf = repo_file("assets/unit.urdf");
    // Every input of the run, even with --force, and even as a link to it.
    let link = dir.path().join("link.mcap");
    std::os::unix::fs::symlink(&policy, &link).unwrap();
    for (target, role) in [
        (keys.clone(), "key file"),
        (config.clone(), "unit config"),
        (policy.clone(), "lift policy"),
        (urdf.clone(), "unit model"),
        (link.clone(), "lift policy"),
    ] {
        let before = std::fs::read(&target).unwrap();
        for force in [false, true] {
            let mut cmd = mock_unit(&keys, &["--max-runtime-s", "0.2", "--log"]);
            cmd.arg(&target);
            if force {
                cmd.arg("--force");
            }
            let out = run_bounded(&mut cmd, Duration::from_secs(60));
            let stderr = text(&out.stderr);
            assert_eq!(out.status.code(), Some(1), "{}: {stderr}", target.display());
            assert!(
                stderr.contains("--log")
                    && stderr.contains(&target.display().to_string())
                    && stderr.contains(role),
                "{}: {stderr}",
                target.display()
            );
        }
        assert_eq!(
            std::fs::read(&target).unwrap(),
            before,
            "{}",
            target.display()
        );
    }
    // Another existing file: refused, then replaced with --force.
    let old = dir.path().join("old.mcap");
    std::fs::write(&old, "an earlier log").unwrap();
    let mut cmd = mock_unit(&keys, &["--max-runtime-s", "0.2", "--log"]);
    cmd.arg(&old);
    let out = run_bounded(&mut cmd, Duration::from_secs(60));
    let stderr = text(&out.stderr);
    assert!(
        out.status.code() == Some(1) && stderr.contains("--force") && stderr.contains("old.mcap"),
        "{stderr}"
    );
    assert_eq!(std::fs::read(&old).unwrap(), b"an earlier log");
    let mut cmd = mock_unit(&keys, &["--max-runtime-s", "0.2", "--force", "--log"]);
    cmd.arg(&old);
    let out = run_bounded(&mut cmd, Duration::from_secs(60));
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_finished(&old);
}

#[test]
fn malformed_endpoints_and_injections_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    for (extra, needle) in [
        (&["--connect", "tcp/127.0.0.1"][..], "no port"),
        (&["--connect", "tcp/127.0.0.1:99999"][..], "99999"),
        (&["--connect", "tcp/127.0.0.1:abc"][..], "\"abc\""),
        (&["--listen", "tcp/:7447"][..], "host"),
        (&["--inject", "motor:99@0.1"][..], "joint 99 does not exist"),
        (&["--inject", "emcy:9@0.1"][..], "joints are 0..8"),
        (&["--start-pose", "5000,0,0"][..], "arena"),
        (&["--start-pose", "0,0,100"][..], "yaw"),
    ] {
        let out = run_bounded(
            mock_unit(&keys, &["--max-runtime-s", "0.2"]).args(extra),
            Duration::from_secs(60),
        );
        let stderr = text(&out.stderr);
        assert!(
            matches!(out.status.code(), Some(1 | 2)) && !stderr.contains("panicked"),
            "{extra:?}: {stderr}"
        );
        assert!(
            stderr.contains(extra[1]) && stderr.contains(needle),
            "{extra:?}: {stderr}"
        );
    }
    // The last joint is a joint.
    let out = run_bounded(
        &mut mock_unit(
            &keys,
            &["--max-runtime-s", "0.3", "--inject", "motor:8@0.1"],
        ),
        Duration::from_secs(60),
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
}

/// A unit of a team of two whose config and flags give no endpoint at all could never hear
/// its peer: refused at start, naming the config.
#[test]
fn a_unit_with_no_way_to_reach_its_team_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let shipped = std::fs::read_to_string(repo_file("configs/unit.toml")).unwrap();
    let mut lonely = shipped.replace("connect = [\"tcp/127.0.0.1:7447\"]", "connect = []");
    assert_ne!(lonely, shipped);
    // The same files by absolute path, from a config in another folder.
    for file in [
        "control.toml",
        "gate.toml",
        "sync.toml",
        "tasks.toml",
        "mission.toml",
        "unit_can.toml",
        "../assets/unit.urdf",
        "../assets/policies",
    ] {
        let absolute = repo_file(&format!("configs/{file}"));
        lonely = lonely.replace(
            &format!("\"{file}\""),
            &format!("{:?}", absolute.display().to_string()),
        );
    }
    let config = dir.path().join("lonely.toml");
    std::fs::write(&config, lonely).unwrap();
    let out = run_bounded(
        Command::new(unit_bin())
            .arg("--config")
            .arg(&config)
            .args(["--hal", "mock", "--controller", "scripted", "--keys"])
            .arg(&keys)
            .args(["--max-runtime-s", "0.2"])
            .stdin(Stdio::null()),
        Duration::from_secs(60),
    );
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("lonely.toml") && stderr.contains("could never reach"),
        "{stderr}"
    );
}

/// A `--hal sim` unit whose world never comes.
fn sim_unit_without_world(keys: &Path, log: &Path, extra: &[&str]) -> Command {
    let port = moonhaul_deploy::network::free_loopback_port().unwrap();
    let mut cmd = Command::new(unit_bin());
    cmd.arg("--config")
        .arg(repo_file("configs/unit.toml"))
        .args(["--hal", "sim", "--controller", "scripted", "--keys"])
        .arg(keys)
        .args(["--listen", "tcp/127.0.0.1:0"])
        .args(["--connect", &format!("tcp/127.0.0.1:{port}")])
        .arg("--log")
        .arg(log)
        .args(extra)
        .stdin(Stdio::null());
    cmd
}

#[test]
fn a_sim_unit_without_its_world_keeps_its_runtime_limit_or_fails_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    // --max-runtime-s holds although no world time ever comes.
    let log = dir.path().join("runtime.mcap");
    let out = run_bounded(
        &mut sim_unit_without_world(&keys, &log, &["--max-runtime-s", "1"]),
        Duration::from_secs(60),
    );
    let stderr = text(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("the runtime limit"), "{stderr}");
    assert_finished(&log);
    // Without one, the wait for the world is bounded and fails naming what it waited for.
    let log = dir.path().join("no-world.mcap");
    let out = run_bounded(
        &mut sim_unit_without_world(&keys, &log, &["--world-wait-s", "1"]),
        Duration::from_secs(60),
    );
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("no reading from the simulated world")
            && stderr.contains("moonhaul/moonhaul/sim/0/sensed")
            && stderr.contains("--world-wait-s"),
        "{stderr}"
    );
    assert_finished(&log);
    for bad in ["0", "nan", "1e9"] {
        let out = run_bounded(
            &mut sim_unit_without_world(&keys, &log, &["--world-wait-s", bad]),
            Duration::from_secs(60),
        );
        assert!(
            text(&out.stderr).contains("--world-wait-s"),
            "{bad}: {}",
            text(&out.stderr)
        );
    }
}

/// Whether process `pid` catches SIGTERM (bit 15 of `SigCgt` in /proc/<pid>/status).
fn catches_sigterm(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("SigCgt:"))
                .and_then(|mask| u64::from_str_radix(mask.trim(), 16).ok())
        })
        .is_some_and(|mask| mask & (1 << (15 - 1)) != 0)
}

#[test]
fn a_signal_during_start_up_ends_in_a_hold_with_a_finished_log() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    for sig in ["-TERM", "-INT"] {
        let log = dir.path().join(format!("unit{sig}.mcap"));
        let stderr_path = dir.path().join(format!("unit{sig}.log"));
        let mut cmd = mock_unit(&keys, &["--log"]);
        cmd.arg(&log)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&stderr_path).unwrap());
        let child = cmd.spawn().unwrap();
        // The handlers come first: SIGTERM is caught long before the daemon is up.
        let deadline = Instant::now() + Duration::from_secs(20);
        while !catches_sigterm(child.id()) {
            assert!(Instant::now() < deadline, "no SIGTERM handler within 20 s");
            std::thread::sleep(Duration::from_millis(1));
        }
        let early = !std::fs::read_to_string(&stderr_path)
            .unwrap()
            .contains("unit daemon up");
        Command::new("kill")
            .args([sig, &child.id().to_string()])
            .status()
            .unwrap();
        let out = wait_bounded(child, Duration::from_secs(60));
        let stderr = std::fs::read_to_string(&stderr_path).unwrap();
        assert!(out.status.success(), "{sig}: {stderr}");
        assert!(
            early,
            "{sig}: the handler was installed only after start-up: {stderr}"
        );
        assert!(
            stderr.contains(&format!("SIG{}", &sig[1..])) && stderr.contains("holding"),
            "{sig}: {stderr}"
        );
        assert_finished(&log);
    }
}
