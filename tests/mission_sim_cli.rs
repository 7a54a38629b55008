//! `moonhaul mission sim` as a launcher: what it refuses before any process starts (and why),
//! what it reports when a process fails anyway (the process's own reason), that a trial has a
//! bound, and that a signal to it reaches every process it started and leaves none behind,
//! with every log finished.

mod common;

use common::{run_bounded, wait_bounded};

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use moonhaul_core::config::repo_file;
use moonhaul_deploy::mission_log::{read_unit_log, read_world_log};

const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

fn mission_sim(out: &Path, extra: &[&str]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_moonhaul"));
    cmd.args(["mission", "sim", "--controller", "scripted", "--out"])
        .arg(out)
        .args(extra)
        .env("MOONHAUL_UNIT_BIN", env!("CARGO_BIN_EXE_moonhaul-unit"))
        .current_dir(repo_file(""))
        .stdin(Stdio::null());
    cmd
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn finished(path: &Path) -> bool {
    std::fs::read(path).is_ok_and(|b| b.starts_with(MCAP_MAGIC) && b.ends_with(MCAP_MAGIC))
}

#[test]
fn bad_arguments_keys_and_payloads_are_refused_with_their_reason_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let other_team = dir.path().join("other.keys.toml");
    common::stdout(&common::moonhaul(&[
        "keys",
        "generate",
        "--team",
        "other",
        "--units",
        "2",
        "--out",
        other_team.to_str().unwrap(),
    ]));
    let bad_payload = dir.path().join("crate.urdf");
    std::fs::write(
        &bad_payload,
        "<robot name=\"crate\"><link name=\"oops\"/></robot>",
    )
    .unwrap();
    let other = other_team.to_str().unwrap().to_owned();
    let payload = bad_payload.to_str().unwrap().to_owned();
    for (i, (extra, needles)) in [
        (
            vec!["--max-seconds", "1e300"],
            vec!["--max-seconds", "3600"],
        ),
        (vec!["--max-seconds", "nan"], vec!["--max-seconds"]),
        (vec!["--keys", &other], vec!["--keys", "other"]),
        (vec!["--payload", &payload], vec!["crate.urdf"]),
        (
            vec!["--unit-arg", "5=--realtime"],
            vec!["--unit-arg", "no unit 5", "units 0 to 1"],
        ),
        (
            vec!["--unit-arg", "x=--realtime"],
            vec!["--unit-arg", "\"x\""],
        ),
        (vec!["--unit-arg=--realtime"], vec!["--unit-arg", "I=ARG"]),
        (
            vec!["--seed", "18446744073709551615", "--trials", "2"],
            vec!["--seed", "overflows"],
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let out_dir = dir.path().join(format!("out-{i}"));
        let out = run_bounded(&mut mission_sim(&out_dir, &extra), Duration::from_secs(120));
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{extra:?}: {stderr}");
        for needle in needles {
            assert!(
                stderr.contains(needle),
                "{extra:?}: no {needle:?} in {stderr}"
            );
        }
        // Refused before any process started: no trial folder, no log.
        assert!(
            !out_dir.join("box").exists(),
            "{extra:?}: a trial started: {stderr}"
        );
    }
    // An earlier run's files: only with --force; an input in the way: never.
    let out_dir = dir.path().join("earlier");
    std::fs::create_dir_all(out_dir.join("box/trial-0")).unwrap();
    std::fs::write(out_dir.join("box/trial-0/world.mcap"), "old").unwrap();
    let out = run_bounded(&mut mission_sim(&out_dir, &[]), Duration::from_secs(120));
    let stderr = text(&out.stderr);
    assert!(
        out.status.code() == Some(1) && stderr.contains("world.mcap") && stderr.contains("--force"),
        "{stderr}"
    );
    let keys = out_dir.join("box/trial-0/unit-0.mcap");
    common::stdout(&common::generate_keys(&keys, "2", &[]));
    let keys = keys.to_str().unwrap();
    let out = run_bounded(
        &mut mission_sim(&out_dir, &["--keys", keys, "--force"]),
        Duration::from_secs(120),
    );
    let stderr = text(&out.stderr);
    assert!(
        out.status.code() == Some(1) && stderr.contains("key file") && stderr.contains(keys),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read_to_string(out_dir.join("box/trial-0/world.mcap")).unwrap(),
        "old"
    );
}

#[test]
fn a_failing_unit_is_reported_with_its_own_reason() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    let out = run_bounded(
        &mut mission_sim(
            &out_dir,
            &["--max-seconds", "4", "--unit-arg", "1=--inject=motor:99@1"],
        ),
        Duration::from_secs(300),
    );
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("the unit 1 exited") && stderr.contains("joint 99 does not exist"),
        "{stderr}"
    );
}

/// The processes whose parent is `pid` (from /proc).
fn children(pid: u32) -> Vec<u32> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(child) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{child}/stat")) else {
            continue;
        };
        // pid (comm) state ppid ...; comm may hold spaces, so read after its ')'.
        let ppid = stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if ppid == Some(pid) {
            found.push(child);
        }
    }
    found
}

/// Whether `pid` is still a process (a zombie counts as gone: it runs nothing).
fn alive(pid: u32) -> bool {
    std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|stat| {
        stat.rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X")
    })
}

#[test]
fn sigterm_mid_trial_reaches_every_process_and_leaves_finished_logs() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    let trial = out_dir.join("box/trial-0");
    // A trial that lasts its 60 s for certain: on the wall clock (lockstep runs faster than
    // real time), with a team that holds (a clock drill) instead of ending its mission early.
    let child = mission_sim(
        &out_dir,
        &[
            "--max-seconds",
            "60",
            "--realtime",
            "--unit-arg",
            "0=--clock-offset-ms=1000",
        ],
    )
    .stdout(Stdio::piped())
    .stderr(Stdio::piped())
    .spawn()
    .unwrap();
    let pid = child.id();
    // Mid-trial: the world and both units are up and the units have been logging a while.
    let deadline = Instant::now() + Duration::from_secs(180);
    let started: Vec<u32> = loop {
        let procs = children(pid);
        let logging = (0..2).all(|i| {
            std::fs::metadata(trial.join(format!("unit-{i}.mcap"))).is_ok_and(|m| m.len() > 0)
        });
        if procs.len() == 3 && logging {
            break procs;
        }
        assert!(
            Instant::now() < deadline,
            "the trial did not get going within 180 s ({} children)",
            procs.len()
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    std::thread::sleep(Duration::from_secs(2));
    Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status()
        .unwrap();
    let out = wait_bounded(child, Duration::from_secs(60));
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("interrupted by SIGTERM"), "{stderr}");
    for p in &started {
        assert!(!alive(*p), "process {p} outlived mission sim: {stderr}");
    }
    let world = trial.join("world.mcap");
    assert!(finished(&world), "world.mcap not finished: {stderr}");
    assert!(!read_world_log(&world).unwrap().is_empty());
    for i in 0..2 {
        let log: PathBuf = trial.join(format!("unit-{i}.mcap"));
        assert!(finished(&log), "unit-{i}.mcap not finished: {stderr}");
        assert!(!read_unit_log(&log).unwrap().is_empty(), "unit {i}");
        // Each unit took the signal passed on and held.
        let unit_log = std::fs::read_to_string(trial.join(format!("unit-{i}.log"))).unwrap();
        assert!(
            unit_log.contains("SIGTERM") && unit_log.contains("holding"),
            "unit {i}: {unit_log}"
        );
    }
}

#[test]
fn a_clock_drill_on_the_lockstep_world_stays_within_its_trial() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    let started = Instant::now();
    let out = run_bounded(
        &mut mission_sim(
            &out_dir,
            &[
                "--max-seconds",
                "4",
                "--unit-arg",
                "0=--clock-offset-ms=1000",
            ],
        ),
        Duration::from_secs(600),
    );
    let stderr = text(&out.stderr);
    // Each unit sees its peer as stale (a second behind, or ahead) and holds: the team never
    // starts, which the summary says. The world's 4 s end the trial as they would without
    // the drill, not after a second's peer wait on each of its 200 ticks (the issue saw it
    // pass 180 s), and the units are stopped, not left to find their world gone.
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("the mission never started"), "{stderr}");
    assert!(!stderr.contains("fell silent"), "{stderr}");
    let wall = started.elapsed();
    eprintln!("a 4 s trial with a 1 s clock offset took {wall:?}");
    assert!(wall < Duration::from_secs(150), "{wall:?}: {stderr}");
    let trial = out_dir.join("box/trial-0");
    for name in ["world.mcap", "unit-0.mcap", "unit-1.mcap"] {
        assert!(finished(&trial.join(name)), "{name}");
    }
}
