//! Missions of real processes over zenoh on loopback, judged from their logs: a simulated
//! mission on the sim-backed drives, a mock-hardware team that is started, carried into
//! transport and then loses a unit to SIGKILL, an operator stop from the console, and drive
//! faults on the emulated CAN bus. Every run must end in a hold, with no panic and readable
//! logs.

mod common;

use common::{keys, unit_bin, Daemon};

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use moonhaul_coord::clamp::{anchor_command, hold_command, interpolate_command};
use moonhaul_coord::message::{FaultKind, StopReason};
use moonhaul_coord::{HoldReason, SyncConfig, UnitModel};
use moonhaul_core::state::Phase;
use moonhaul_core::unit::UnitSpec;
use moonhaul_deploy::mission_log::{read_unit_log, read_world_log};
use moonhaul_deploy::record::TickRecord;

const PERIOD_US: u64 = 20_000;

fn free_port() -> u16 {
    moonhaul_deploy::network::free_loopback_port().unwrap()
}

/// A two-unit mock team on `port`: unit 0 listens, unit 1 connects.
/// One team flies at a time in this binary: each mission test runs two or three processes
/// ticking at 50 Hz with zenoh beside them, and seven teams at once on a 2-core machine once
/// left two teams idle 60 s after an acknowledged `start` (the same tests pass alone and when
/// rerun); a team the machine cannot serve stops, as it must, before the mission a test is about.
fn one_team_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static TEAM: std::sync::Mutex<()> = std::sync::Mutex::new(());
    // A test that failed while holding it poisons nothing the next one needs.
    TEAM.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn mock_team(dir: &Path, keys: &Path, port: u16) -> [Daemon; 2] {
    let listen = format!("tcp/127.0.0.1:{port}");
    let u0 = Daemon::unit(
        dir,
        keys,
        0,
        "mock",
        &["--listen", &listen, "--connect", &listen],
        &[],
    );
    let u1 = Daemon::unit(
        dir,
        keys,
        1,
        "mock",
        &["--connect", &listen, "--listen", "tcp/127.0.0.1:0"],
        &[],
    );
    [u0, u1]
}

fn console(cmd: &str, keys: &Path, port: u16) -> String {
    common::stdout(&console_run(cmd, keys, port, &[]))
}

/// A console run, whatever its outcome.
fn console_run(cmd: &str, keys: &Path, port: u16, extra: &[&str]) -> std::process::Output {
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut args = vec![
        "mission",
        cmd,
        "--keys",
        keys.to_str().unwrap(),
        "--connect",
        &endpoint,
    ];
    args.extend_from_slice(extra);
    common::moonhaul(&args)
}

/// Stdout and stderr of a console run that must fail with our error status (1).
fn console_fails(cmd: &str, keys: &Path, port: u16, extra: &[&str]) -> String {
    let out = console_run(cmd, keys, port, extra);
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    text
}

/// Asks for the team's status until `done` says so (or fails after `timeout`).
fn await_status(keys: &Path, port: u16, timeout: Duration, done: impl Fn(&str) -> bool) -> String {
    let deadline = Instant::now() + timeout;
    loop {
        let status = console("status", keys, port);
        if done(&status) {
            return status;
        }
        assert!(Instant::now() < deadline, "status never matched: {status}");
    }
}

/// d(X, Y_k) of the paper's eq. (stacked_metric), computed here from the record's own clamp
/// inputs (not by the clamp's code): every unit's commanded image — its sensed base integrated
/// one period under the commanded wheel speeds, the arm's FK on it — against its sensed image.
fn stacked_distance(r: &TickRecord, model: &UnitModel, sync: &SyncConfig) -> f64 {
    let tol = &sync.tolerances;
    let period_s = PERIOD_US as f64 * 1e-6;
    let mut d: f64 = 0.0;
    for (i, (sensed, previous)) in r.team_sensed.iter().zip(&r.team_previous).enumerate() {
        let command = if i == r.unit { r.issued } else { *previous };
        let base =
            model
                .spec()
                .integrate_base(&sensed.base_pose, &command.wheel_velocity_radps, period_s);
        let x = model
            .arm_world_pose(&base, &command.arm_position_rad)
            .unwrap();
        let y = model
            .arm_world_pose(&sensed.base_pose, &sensed.arm.position_rad)
            .unwrap();
        let dt = (x.translation.vector - y.translation.vector).norm();
        let angle = x.rotation.angle_to(&y.rotation);
        let arm = (dt / tol.arm_translation_m).max(angle / tol.arm_rotation_deg.to_radians());
        let dx = (base.x_m - sensed.base_pose.x_m) / tol.base_xy_m[0];
        let dy = (base.y_m - sensed.base_pose.y_m) / tol.base_xy_m[1];
        d = d.max(arm).max(dx.hypot(dy));
    }
    d
}

/// Judges one unit's log: a hold is exactly the hold command; a step is the interpolation
/// T(t_max) of the record's S_k and F_k and lies in V_k by an independent evaluation of d.
fn check_commands(records: &[TickRecord]) {
    assert!(!records.is_empty());
    let spec = UnitSpec::from_file(&moonhaul_core::config::repo_file("assets/unit.urdf")).unwrap();
    let model = UnitModel::new(spec);
    let sync = SyncConfig::shipped().unwrap();
    for r in records {
        assert!((0.0..=1.0).contains(&r.t_max), "{r:?}");
        match r.hold {
            // A hold keeps U_{k-1}'s arm with the wheels stopped; only a tracking stop
            // re-anchors it on the sensed joints.
            Some(_) => {
                let held = hold_command(&r.team_previous[r.unit]);
                let reanchored = r.fault.is_some() && r.issued == anchor_command(&r.sensed);
                assert!(r.issued == held || reanchored, "tick {}: {r:?}", r.tick);
            }
            None => {
                let d = r.distance.expect("a step reports its distance");
                assert!(d.value <= 1.0 + 1e-9, "tick {}: {d:?}", r.tick);
                let s = r.team_previous[r.unit];
                let expected = interpolate_command(&s, &r.target, r.t_max);
                for (a, b) in expected.to_action().iter().zip(r.issued.to_action()) {
                    assert!((a - b).abs() < 1e-9, "tick {}: not T(t_max)", r.tick);
                }
                let ours = stacked_distance(r, &model, &sync);
                assert!(
                    ours <= 1.0 + 1e-6,
                    "tick {}: d = {ours} outside V_k",
                    r.tick
                );
                assert!(
                    (ours - d.value).abs() < 1e-6,
                    "tick {}: {ours} vs {d:?}",
                    r.tick
                );
            }
        }
    }
}

/// A key holder gone wrong, as processes: unit 1 seals, with its genuine key, a second of
/// state messages claiming a base 1e308 m away (`--inject absurd-state@S`). Unit 0 refuses them
/// as out of bounds and holds on a stop that names unit 1, never on a fault of its own; once
/// unit 1 is sane again the stop clears and the next start flies.
#[test]
fn a_key_holder_sending_absurd_states_is_its_own_fault_and_the_team_starts_again() {
    let _one_team = one_team_at_a_time();
    const ABSURD_AT_S: f64 = 6.0;
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = free_port();
    let listen = format!("tcp/127.0.0.1:{port}");
    let mut u0 = Daemon::unit(
        dir.path(),
        &keys,
        0,
        "mock",
        &["--listen", &listen, "--connect", &listen],
        &[],
    );
    let inject = format!("--inject=absurd-state@{ABSURD_AT_S}");
    let mut u1 = Daemon::unit(
        dir.path(),
        &keys,
        1,
        "mock",
        &["--connect", &listen, "--listen", "tcp/127.0.0.1:0"],
        &[&inject],
    );
    await_status(&keys, port, Duration::from_secs(30), |s| {
        !s.contains("not heard")
    });
    console("start", &keys, port);
    await_status(&keys, port, Duration::from_secs(60), |s| {
        s.contains("PeerRejected { unit: 1 }")
    });
    // Sane again: the stop clears, and a new start is acknowledged by both and flies.
    await_status(&keys, port, Duration::from_secs(30), |s| {
        !s.contains("stopped") && s.matches(": idle").count() == 2
    });
    console("start", &keys, port);
    await_status(&keys, port, Duration::from_secs(60), |s| {
        s.matches(": lift").count() == 2 && !s.contains("stopped")
    });
    // Longer than the log's 1 s flush period.
    std::thread::sleep(Duration::from_millis(1500));
    for u in [&mut u0, &mut u1] {
        u.signal("-TERM");
        assert!(u.wait(Duration::from_secs(10)).success());
    }
    let log = read_unit_log(&dir.path().join("unit-0.mcap")).unwrap();
    check_commands(&log);
    let peer_fault = HoldReason::SafetyStop(StopReason::PeerRejected { unit: 1 });
    let stop = log
        .iter()
        .position(|r| r.hold == Some(peer_fault))
        .expect("unit 0 held on unit 1's fault");
    assert!(log.iter().all(|r| r.fault.is_none()), "no fault of its own");
    assert!(
        log[stop].rejected.out_of_bounds > 0,
        "{:?}",
        log[stop].rejected
    );
    assert!(
        log[stop..]
            .iter()
            .any(|r| r.phase == Phase::Lift && r.hold.is_none()),
        "the team lifted again after the stop"
    );
}

#[test]
fn a_mock_team_carries_into_transport_and_a_killed_unit_stops_its_peer() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = free_port();
    let [mut u0, mut u1] = mock_team(dir.path(), &keys, port);
    await_status(&keys, port, Duration::from_secs(30), |s| {
        !s.contains("not heard")
    });
    console("start", &keys, port);
    // The lift on mirror drives takes a few seconds; then the team commits transport together.
    await_status(&keys, port, Duration::from_secs(60), |s| {
        s.matches(": transport").count() == 2
    });
    // Longer than the log's 1 s flush period, so the killed unit's log holds transport.
    std::thread::sleep(Duration::from_millis(1500));
    u1.signal("-KILL");
    u1.wait(Duration::from_secs(5));
    std::thread::sleep(Duration::from_millis(500));
    u0.signal("-TERM");
    assert!(u0.wait(Duration::from_secs(10)).success());
    let log = read_unit_log(&dir.path().join("unit-0.mcap")).unwrap();
    check_commands(&log);
    // The survivor ran transport, then held for its silent peer within the bound: the first
    // stopped tick comes once the peer's newest state is older than 3 periods, i.e. at most one
    // tick (and the sender's one-tick lag) later, plus scheduling jitter of the 50 Hz loop.
    let transport = log
        .iter()
        .position(|r| r.phase == Phase::Transport)
        .unwrap();
    let stop = log[transport..]
        .iter()
        .position(|r| r.hold == Some(HoldReason::SafetyStop(StopReason::PeerStale { unit: 1 })))
        .map(|k| k + transport)
        .expect("the survivor stopped for its peer");
    let age = log[stop].peer_age_us[1].unwrap();
    assert!(
        age > 3 * PERIOD_US && age <= 3 * PERIOD_US + 2 * PERIOD_US,
        "age {age} us"
    );
    assert!(
        log[stop..]
            .iter()
            .all(|r| r.phase == Phase::Idle && r.hold.is_some()),
        "it stays held"
    );
    // The killed unit's log is readable up to (at most a second before) its death.
    let killed = read_unit_log(&dir.path().join("unit-1.mcap")).unwrap();
    assert!(killed.iter().any(|r| r.phase == Phase::Transport));
    check_commands(&killed);
}

#[test]
fn an_operator_stop_from_the_console_holds_the_team() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = free_port();
    let mut team = mock_team(dir.path(), &keys, port);
    await_status(&keys, port, Duration::from_secs(30), |s| {
        !s.contains("not heard")
    });
    console("start", &keys, port);
    await_status(&keys, port, Duration::from_secs(30), |s| {
        s.matches(": lift").count() + s.matches(": transport").count() == 2
    });
    let stopped = console("stop", &keys, port);
    assert!(
        stopped.contains("unit 0: acknowledged") && stopped.contains("unit 1: acknowledged"),
        "{stopped}"
    );
    assert!(stopped.contains("stop of mission"), "{stopped}");
    std::thread::sleep(Duration::from_millis(300));
    for d in &mut team {
        d.signal("-INT");
        assert!(d.wait(Duration::from_secs(10)).success());
    }
    for i in 0..2 {
        let log = read_unit_log(&dir.path().join(format!("unit-{i}.mcap"))).unwrap();
        check_commands(&log);
        let stop = log
            .iter()
            .position(|r| r.hold == Some(HoldReason::SafetyStop(StopReason::Operator)))
            .expect("the operator stop reached the unit");
        assert!(log[..stop]
            .iter()
            .any(|r| r.phase == Phase::Lift && r.hold.is_none()));
        assert!(log[stop..].iter().all(|r| r.phase == Phase::Idle));
    }
}

#[test]
fn drive_faults_on_the_emulated_can_bus_latch_a_stop() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = free_port();
    for (k, fault) in ["motor:3@0.5", "emcy:0@0.5", "heartbeat:8@0.5"]
        .iter()
        .enumerate()
    {
        let listen = format!("tcp/127.0.0.1:{port}");
        let sub = dir.path().join(format!("case{k}"));
        std::fs::create_dir_all(&sub).unwrap();
        let mut d = Daemon::unit(
            &sub,
            &keys,
            0,
            "can-emulated",
            &["--listen", &listen],
            &["--inject", fault, "--max-runtime-s", "1.5"],
        );
        assert!(d.wait(Duration::from_secs(30)).success(), "{fault}");
        let log = read_unit_log(&sub.join("unit-0.mcap")).unwrap();
        check_commands(&log);
        let last = log.last().unwrap();
        assert_eq!(
            last.hold,
            Some(HoldReason::SafetyStop(StopReason::Fault(FaultKind::Drive))),
            "{fault}: {last:?}"
        );
        assert!(last.fault.is_some(), "{fault}");
        // Before the fault the unit held only for its absent peer.
        assert!(log[0].fault.is_none(), "{fault}");
    }
}

#[test]
fn a_simulated_mission_runs_as_separate_processes_and_logs_ground_truth() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mission");
    let output = Command::new(env!("CARGO_BIN_EXE_moonhaul"))
        .args(["mission", "sim", "--payload", "box", "--trials", "1"])
        // The world's clock runs from its own start, in lockstep faster than the wall: on a
        // loaded machine the console's start can come seconds of world time late.
        .args(["--controller", "scripted", "--max-seconds", "10", "--out"])
        .arg(&out)
        .env("MOONHAUL_UNIT_BIN", unit_bin())
        .current_dir(moonhaul_core::config::repo_file(""))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains("243.0"),
        "the paper's figure beside ours: {stdout}"
    );
    let trial = out.join("box/trial-0");
    let world = read_world_log(&trial.join("world.mcap")).unwrap();
    assert!(world.len() >= 250, "{} frames", world.len());
    assert!(world
        .iter()
        .any(|f| f.unit_phase.contains(&Some(Phase::Lift))));
    for i in 0..2 {
        let log = read_unit_log(&trial.join(format!("unit-{i}.mcap"))).unwrap();
        check_commands(&log);
        assert!(log
            .iter()
            .any(|r| r.phase == Phase::Lift && r.hold.is_none()));
        // Nothing forged, garbled or replayed on the lockstep world; at most a message that
        // arrived too late on a machine loaded by the other tests.
        let c = log.last().unwrap().rejected;
        assert_eq!(c.total(), c.stale + c.from_future, "unit {i}: {c:?}");
        assert!(c.stale <= 3, "unit {i}: {c:?}");
    }
    assert!(out.join("mission_profile.png").is_file());
    // The summary pools the clamp's figures from the unit logs.
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["trials"][0]["controller"], "scripted", "{summary}");
    let clamp = &summary["trials"][0]["clamp"];
    assert!(clamp["policy_ticks"].as_u64().unwrap() > 0, "{clamp}");
    assert!(
        (0.0..=1.0).contains(&clamp["mean_t_max"].as_f64().unwrap()),
        "{clamp}"
    );
}

#[test]
fn the_daemon_refuses_bad_arguments_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let config = moonhaul_core::config::repo_file("configs/unit.toml");
    for (extra, needle) in [
        (&["--clock-offset-ms", "NaN"][..], "--clock-offset-ms"),
        (&["--max-runtime-s=-1"][..], "--max-runtime-s"),
        (&["--start-pose", "1,2"][..], "--start-pose"),
        (&["--unit-index", "7"][..], "--unit-index"),
        (&["--inject", "motor@x"][..], "motor@x"),
    ] {
        let out = Command::new(unit_bin())
            .arg("--config")
            .arg(&config)
            .args(["--hal", "mock", "--keys"])
            .arg(&keys)
            .args(extra)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            matches!(out.status.code(), Some(1 | 2)),
            "{extra:?}: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{extra:?}: {stderr}");
        assert!(stderr.contains(needle), "{extra:?}: {stderr}");
    }
}

#[test]
fn a_stop_that_no_unit_hears_fails_naming_the_silent_units() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let text = console_fails(
        "stop",
        &keys,
        free_port(),
        &["--listen-s", "0.3", "--ack-timeout-s", "1"],
    );
    assert!(
        text.contains("unit 0: silent") && text.contains("unit 1: silent"),
        "{text}"
    );
    assert!(text.contains("2 of 2 units did not acknowledge"), "{text}");
    for bad in ["0", "-1", "NaN", "61"] {
        let arg = format!("--ack-timeout-s={bad}");
        let text = console_fails("stop", &keys, free_port(), &[&arg]);
        assert!(text.contains("--ack-timeout-s"), "{text}");
    }
}

#[test]
fn console_starts_are_answered_per_unit_and_refusals_say_why() {
    let _one_team = one_team_at_a_time();
    let dir = tempfile::tempdir().unwrap();
    let keys = keys(dir.path());
    let port = free_port();
    let _team = mock_team(dir.path(), &keys, port);
    await_status(&keys, port, Duration::from_secs(30), |s| {
        !s.contains("not heard")
    });
    // Another key file of the same team name: the units refuse it (at the transport), so the
    // console says so instead of "no unit answered", and nothing starts.
    let other = tempfile::tempdir().unwrap();
    let wrong = self::keys(other.path());
    let text = console_fails("start", &wrong, port, &["--ack-timeout-s", "2"]);
    assert!(
        text.contains("unit 0: rejected: authentication")
            && text.contains("unit 1: rejected: authentication"),
        "{text}"
    );
    let status = console("status", &keys, port);
    assert_eq!(status.matches(": idle").count(), 2, "{status}");
    // The real start: every unit acknowledges it.
    let started = console("start", &keys, port);
    assert!(
        started.contains("unit 0: acknowledged") && started.contains("unit 1: acknowledged"),
        "{started}"
    );
    await_status(&keys, port, Duration::from_secs(30), |s| {
        s.matches(": lift").count() + s.matches(": transport").count() == 2
    });
    // A second start during the mission: refused by both, and the console says why.
    std::thread::sleep(Duration::from_millis(1100));
    let text = console_fails("start", &keys, port, &[]);
    assert!(
        text.contains("unit 0: rejected: already in mission")
            && text.contains("unit 1: rejected: already in mission"),
        "{text}"
    );
    let status = console("status", &keys, port);
    assert_eq!(
        status.matches(": lift").count() + status.matches(": transport").count(),
        2,
        "the mission goes on: {status}"
    );
}
