//! `moonhaul log summary` on synthetic mission directories written with the world-log writer:
//! two payloads, two trials each, with known heights and phase timing; an incomplete trial;
//! frames stamped far beyond the mission; logs cut short at many offsets; errors. And on a
//! simulated mission with a fault drill: the summary names the unit that stopped and why.

mod common;

use std::path::Path;

use moonhaul_core::config::repo_file;
use moonhaul_core::state::Phase;
use moonhaul_deploy::mission_log::{read_world_log_contents, LogInputs, UnitLog, WorldLog};
use moonhaul_deploy::record::{TickRecord, WorldFrame};

/// The unit model and configs the test logs attach.
fn inputs() -> LogInputs {
    LogInputs::read(
        &repo_file("assets/unit.urdf"),
        &[repo_file("configs/tasks.toml")],
    )
    .unwrap()
}

/// A world frame of a two-unit team at rest but for the payload.
fn frame(tick: u64, stamp_us: u64, phases: [Option<Phase>; 2], height_m: f64) -> WorldFrame {
    WorldFrame {
        tick,
        stamp_us,
        payload_position_m: [0.0, 0.0, height_m + 0.15],
        payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
        payload_height_m: height_m,
        payload_tilt_deg: 0.3,
        payload_ground_contact: height_m < 0.01,
        base_position_m: vec![[0.0, -0.6, 0.0], [0.0, 0.6, 0.0]],
        base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; 2],
        wheel_position_rad: vec![[0.0; 2]; 2],
        arm_position_rad: vec![[0.0; 7]; 2],
        unit_phase: phases.to_vec(),
        grasp_closed: vec![true; 2],
    }
}

/// Frames every 20 ms: idle 0–1 s, lift 1–11 s (a ramp to `steady_m` over `ramp_s`), transport
/// 11–31 s at `steady_m`, place 31–36 s (down to `settled_m` over 4 s), idle 36–38 s with the
/// grasps open.
fn trial_frames(steady_m: f64, ramp_s: f64, settled_m: f64) -> Vec<WorldFrame> {
    (0..=1900u64)
        .map(|k| {
            let stamp_us = 5_000_000 + k * 20_000;
            let t = (k * 20_000) as f64 * 1e-6;
            let (phase, height) = match k {
                0..50 => (Phase::Idle, 0.0),
                50..550 => (Phase::Lift, (steady_m * (t - 1.0) / ramp_s).min(steady_m)),
                550..1550 => (Phase::Transport, steady_m),
                1550..1800 => (
                    Phase::Place,
                    steady_m - (steady_m - settled_m) * ((t - 31.0) / 4.0).min(1.0),
                ),
                _ => (Phase::Idle, settled_m),
            };
            // Unit 0 is silent on odd ticks: the phase falls back to unit 1's.
            let mut f = frame(
                k,
                stamp_us,
                [(k % 2 == 0).then_some(phase), Some(phase)],
                height,
            );
            f.payload_position_m[0] = 0.1 * t;
            f.base_position_m = vec![[0.1 * t, -0.6, 0.0], [0.1 * t, 0.6, 0.0]];
            // The grippers open once the placement ends.
            f.grasp_closed = vec![k < 1800; 2];
            f
        })
        .collect()
}

fn write_log(path: &Path, frames: &[WorldFrame]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut log = WorldLog::create(path, [0.5, 0.4, 0.3], 2, &inputs()).unwrap();
    for f in frames {
        log.write(f).unwrap();
    }
    log.finish().unwrap();
}

fn write_trial(dir: &Path, steady_m: f64, ramp_s: f64, settled_m: f64) {
    write_log(
        &dir.join("world.mcap"),
        &trial_frames(steady_m, ramp_s, settled_m),
    );
}

fn mission(dir: &Path) {
    write_trial(&dir.join("box/trial-0"), 0.240, 8.0, 0.008);
    write_trial(&dir.join("box/trial-1"), 0.246, 8.4, 0.009);
    write_trial(&dir.join("sledge/trial-0"), 0.270, 6.0, 0.008);
    write_trial(&dir.join("sledge/trial-1"), 0.275, 6.0, 0.008);
}

fn close(v: &serde_json::Value, expected: f64, tol: f64) {
    let got = v.as_f64().unwrap_or_else(|| panic!("{v} is not a number"));
    assert!((got - expected).abs() <= tol, "{got} != {expected} ± {tol}");
}

#[test]
fn summary_computes_the_papers_metrics_per_trial_and_payload() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    mission(dir);
    let arg = dir.to_str().unwrap();

    let json_out = common::stdout(&common::moonhaul(&["log", "summary", arg, "--json"]));
    let summary: serde_json::Value = serde_json::from_str(&json_out).unwrap();
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary, written, "summary.json is what --json prints");
    let png = std::fs::read(dir.join("mission_profile.png")).unwrap();
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 5_000,
        "{} bytes",
        png.len()
    );

    let trials = summary["trials"].as_array().unwrap();
    let names: Vec<String> = trials
        .iter()
        .map(|t| format!("{}/{}", t["payload"].as_str().unwrap(), t["trial"]))
        .collect();
    assert_eq!(names, ["sledge/0", "sledge/1", "box/0", "box/1"]);
    let box0 = &trials[2];
    close(&box0["steady_height_mm"], 240.0, 1e-6);
    close(&box0["time_to_95_s"], 7.6, 0.021);
    close(&box0["settled_height_mm"], 8.0, 1e-6);
    close(&box0["lift_s"], 10.0, 1e-9);
    close(&box0["transport_s"], 20.0, 1e-9);
    close(&box0["place_s"], 5.0, 1e-9);
    assert_eq!(box0["completed"], true);
    assert_eq!(box0["settled_after_idle"], true);
    assert!(box0["incomplete"].is_null());
    close(&trials[3]["time_to_95_s"], 7.98, 0.021);

    let payloads = summary["payloads"].as_array().unwrap();
    assert_eq!(payloads.len(), 2);
    let boxes = &payloads[1];
    assert_eq!(boxes["payload"], "box");
    assert_eq!(
        (boxes["trials"].as_u64(), boxes["completed"].as_u64()),
        (Some(2), Some(2))
    );
    close(&boxes["steady_height_mm"]["mean"], 243.0, 1e-6);
    // Sample deviation of 240 and 246: 6 / √2.
    close(&boxes["steady_height_mm"]["std"], 6.0 / 2f64.sqrt(), 1e-6);
    close(&boxes["time_to_95_s"]["mean"], 7.79, 0.021);
    close(&boxes["settled_height_mm"]["mean"], 8.5, 1e-6);
    close(&boxes["settled_height_mm"]["std"], 1.0 / 2f64.sqrt(), 1e-6);
    close(&boxes["paper"]["steady_height_mm"][0], 243.0, 0.0);
    close(&boxes["paper"]["time_to_95_s"][1], 0.76, 0.0);
    let sledge = &payloads[0];
    close(&sledge["steady_height_mm"]["mean"], 272.5, 1e-6);
    close(&sledge["settled_height_mm"]["std"], 0.0, 1e-9);
    close(&sledge["paper"]["mass_kg"], 5.3, 0.0);

    let text = common::stdout(&common::moonhaul(&["log", "summary", arg]));
    for needle in [
        "box/trial-1",
        "box 7.5 kg",
        "243.0 ± 4.2",
        "243.0 ± 5.5",
        "sledge 5.3 kg",
        "272.5 ± 3.5",
        "272.6 ± 3.8",
        "21.02 ± 0.61",
        "8.5 ± 0.7",
        "summary.json",
    ] {
        assert!(text.contains(needle), "no {needle:?} in\n{text}");
    }
}

#[test]
fn summary_flags_an_incomplete_trial() {
    let dir = tempfile::tempdir().unwrap();
    let trial = dir.path().join("bricks/trial-0");
    std::fs::create_dir_all(&trial).unwrap();
    // Lift 0–5 s, then held in transport until the log ends at 15 s.
    let frames: Vec<WorldFrame> = (0..=750u64)
        .map(|k| {
            let phase = if k < 250 {
                Phase::Lift
            } else {
                Phase::Transport
            };
            frame(k, k * 20_000, [Some(phase); 2], 0.2)
        })
        .collect();
    write_log(&trial.join("world.mcap"), &frames);
    let out = common::stdout(&common::moonhaul(&[
        "log",
        "summary",
        dir.path().to_str().unwrap(),
        "--json",
    ]));
    let summary: serde_json::Value = serde_json::from_str(&out).unwrap();
    let t = &summary["trials"][0];
    assert_eq!(t["completed"], false);
    assert_eq!(t["settled_after_idle"], false);
    assert!(t["place_s"].is_null());
    let why = t["incomplete"].as_str().unwrap();
    assert!(why.contains("held in transport"), "{why}");
    assert_eq!(summary["payloads"][0]["completed"], 0);
}

#[test]
fn summary_errors_name_the_file_at_fault() {
    // A trial folder without its world log.
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("box/trial-0")).unwrap();
    let missing = dir.path().join("box/trial-0/world.mcap");
    let arg = dir.path().to_str().unwrap();
    common::fails_naming(&["log", "summary", arg], missing.to_str().unwrap());

    // A world log with no frames.
    write_log(&missing, &[]);
    let e = common::fails_naming(&["log", "summary", arg], missing.to_str().unwrap());
    assert!(e.contains("empty log"), "{e}");

    // A trial in which no unit ever lifted.
    let idle: Vec<WorldFrame> = (0..10)
        .map(|k| frame(k, k * 20_000, [Some(Phase::Idle); 2], 0.0))
        .collect();
    write_log(&missing, &idle);
    let e = common::fails_naming(&["log", "summary", arg], missing.to_str().unwrap());
    assert!(e.contains("lift"), "{e}");

    // Not a mission directory.
    let empty = tempfile::tempdir().unwrap();
    common::fails_naming(
        &["log", "summary", empty.path().to_str().unwrap()],
        "holds no trials",
    );
}

/// Unit `unit`'s log at `path`: one tick record per world frame of `trial_frames` (every 10th),
/// at full steps, written with the daemon's writer; `bend` changes the records first.
fn write_unit_log(path: &Path, unit: usize, bend: impl FnOnce(&mut [TickRecord])) {
    let mut records: Vec<TickRecord> = trial_frames(0.24, 8.0, 0.008)
        .iter()
        .step_by(10)
        .enumerate()
        .map(|(k, f)| {
            let mut r = TickRecord::for_team(2);
            r.unit = unit;
            r.tick = k as u64 + 1;
            r.stamp_us = f.stamp_us;
            r.phase = f.unit_phase[1].unwrap();
            r.t_max = 1.0;
            r
        })
        .collect();
    bend(&mut records);
    let mut log = UnitLog::create(path, unit, &inputs()).unwrap();
    for r in &records {
        log.write(r).unwrap();
    }
    log.finish().unwrap();
}

/// Every class of unit log the summary cannot use — missing beside its team's other logs,
/// damaged, of the wrong kind, another unit's, holding an impossible value, beyond the team —
/// is named with what is wrong, and the trial is still summarized from its ground truth.
#[test]
fn unit_logs_that_cannot_be_used_are_named_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let trial = dir.path().join("box/trial-0");
    write_trial(&trial, 0.240, 8.0, 0.008);
    let unread = |dir: &Path| -> Vec<String> {
        let summary = summary_json(dir);
        let trial = &summary["trials"][0];
        assert_eq!(trial["completed"], true, "{trial}");
        trial["unread"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n.as_str().unwrap().to_owned())
            .collect()
    };
    // Ground truth alone: no unit log expected.
    assert_eq!(unread(dir.path()), Vec::<String>::new());
    let [u0, u1] = [trial.join("unit-0.mcap"), trial.join("unit-1.mcap")];
    write_unit_log(&u0, 0, |_| {});
    write_unit_log(&u1, 1, |_| {});
    assert_eq!(unread(dir.path()), Vec::<String>::new());

    type Damage<'a> = Box<dyn Fn() + 'a>;
    let cases: Vec<(&str, Damage)> = vec![
        (
            "unit-0.mcap is missing",
            Box::new(|| std::fs::remove_file(&u0).unwrap()),
        ),
        (
            "is not a valid MCAP mission log",
            Box::new(|| std::fs::write(&u0, b"\x89MCAP0\r\n garbage that is not a log").unwrap()),
        ),
        (
            "is not a unit log",
            Box::new(|| {
                std::fs::copy(trial.join("world.mcap"), &u0)
                    .map(|_| ())
                    .unwrap()
            }),
        ),
        (
            "is unit 1's, not unit 0's",
            Box::new(|| std::fs::copy(&u1, &u0).map(|_| ()).unwrap()),
        ),
        (
            "t_max 1e300 is outside [0, 1]",
            Box::new(|| write_unit_log(&u0, 0, |r| r[40].t_max = 1e300)),
        ),
        (
            "stamped before the record before",
            Box::new(|| write_unit_log(&u0, 0, |r| r[40].stamp_us = 0)),
        ),
    ];
    for (named, damage) in cases {
        damage();
        let notes = unread(dir.path());
        assert_eq!(notes.len(), 1, "{named}: {notes:?}");
        assert!(
            notes[0].contains(named)
                && notes[0].contains("unit-0.mcap")
                && notes[0].contains("left out of the clamp figures"),
            "{named}: {notes:?}"
        );
        write_unit_log(&u0, 0, |_| {});
    }
    // A log of a unit the team does not have.
    write_unit_log(&trial.join("unit-2.mcap"), 2, |_| {});
    let notes = unread(dir.path());
    assert!(
        notes.len() == 1
            && notes[0].contains("unit-2.mcap is not read")
            && notes[0].contains("2 units"),
        "{notes:?}"
    );
    // The text output says it too, below the table.
    let text = common::stdout(&common::moonhaul(&[
        "log",
        "summary",
        dir.path().to_str().unwrap(),
    ]));
    assert!(text.contains("unit-2.mcap is not read"), "{text}");
}

/// A world log holding a value no mission can have (here a height of 1e300 m, which once
/// averaged to `inf`) is an error naming the file, the frame and the field; a world log whose
/// frames carry no unit's phase says that, not that the mission never started.
#[test]
fn impossible_world_logs_are_errors_naming_the_file_frame_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("box/trial-0/world.mcap");
    let arg = dir.path().to_str().unwrap();
    let mut frames = trial_frames(0.240, 8.0, 0.008);
    frames[900].payload_height_m = 1e300;
    write_log(&log, &frames);
    let e = common::fails_naming(&["log", "summary", arg], log.to_str().unwrap());
    assert!(
        e.contains("frame 901 (tick 900")
            && e.contains("payload_height_m 1e300")
            && !e.contains("inf"),
        "{e}"
    );

    let silent: Vec<WorldFrame> = trial_frames(0.240, 8.0, 0.008)
        .into_iter()
        .map(|mut f| {
            f.unit_phase = vec![None, None];
            f
        })
        .collect();
    write_log(&log, &silent);
    let e = common::fails_naming(&["log", "summary", arg], log.to_str().unwrap());
    assert!(
        e.contains("carries a unit's phase") && !e.contains("never started"),
        "{e}"
    );
}

fn summary_json(dir: &Path) -> serde_json::Value {
    let out = common::stdout(&common::moonhaul(&[
        "log",
        "summary",
        dir.to_str().unwrap(),
        "--json",
    ]));
    serde_json::from_str(&out).unwrap()
}

#[test]
fn frames_stamped_beyond_the_mission_are_left_out_and_named() {
    let dir = tempfile::tempdir().unwrap();
    let mut frames = trial_frames(0.240, 8.0, 0.008);
    let whole = frames.clone();
    // A stamp decades ahead in the middle, and a last frame at the end of the clock: the grid
    // of the profile would walk to them.
    frames[700].stamp_us = 1 << 60;
    let mut last = frames.last().unwrap().clone();
    last.tick += 1;
    last.stamp_us = u64::MAX;
    frames.push(last);
    write_log(&dir.path().join("box/trial-0/world.mcap"), &frames);
    write_log(&dir.path().join("box/trial-1/world.mcap"), &whole);
    let summary = summary_json(dir.path());
    let [cut, clean] = [&summary["trials"][0], &summary["trials"][1]];
    for key in [
        "steady_height_mm",
        "time_to_95_s",
        "settled_height_mm",
        "duration_s",
    ] {
        close(&cut[key], clean[key].as_f64().unwrap(), 1e-9);
    }
    assert_eq!(cut["completed"], true);
    let unread = cut["unread"].as_array().unwrap();
    assert_eq!(unread.len(), 1, "{unread:?}");
    let note = unread[0].as_str().unwrap();
    assert!(
        note.contains("2 frames")
            && note.contains("beyond the mission's span")
            && note.contains("tick 700"),
        "{note}"
    );
    assert!(clean["unread"].as_array().unwrap().is_empty());
    let png = std::fs::metadata(dir.path().join("mission_profile.png")).unwrap();
    assert!(png.len() > 5_000);
}

#[test]
fn a_log_cut_anywhere_summarizes_all_but_its_last_second() {
    let source = tempfile::tempdir().unwrap();
    let full_path = source.path().join("world.mcap");
    let frames = trial_frames(0.240, 8.0, 0.008);
    write_log(&full_path, &frames);
    let bytes = std::fs::read(&full_path).unwrap();
    let last_us = frames.last().unwrap().stamp_us;
    let read = |len: usize| {
        let path = source.path().join("cut.mcap");
        std::fs::write(&path, &bytes[..len]).unwrap();
        read_world_log_contents(&path).unwrap()
    };
    // The longest cut that loses frames ends inside the last chunk.
    let mut in_last_chunk = bytes.len();
    while read(in_last_chunk).records.len() == frames.len() {
        in_last_chunk -= 16;
    }
    let kept = read(in_last_chunk).records;
    let kept_us = kept.last().unwrap().stamp_us;
    assert!(
        kept_us + 1_000_000 >= last_us,
        "a cut in the last chunk kept frames up to {kept_us} µs of {last_us} µs"
    );

    // A mission directory of cuts: a tenth of the file and on, the cut in the last chunk, and
    // one inside the file's header.
    let dir = tempfile::tempdir().unwrap();
    let cuts: Vec<usize> = [0.1, 0.25, 0.5, 0.75, 0.9]
        .iter()
        .map(|f| (bytes.len() as f64 * f) as usize)
        .chain([in_last_chunk, 20])
        .collect();
    for (k, cut) in cuts.iter().enumerate() {
        let path = dir.path().join(format!("box/trial-{k}/world.mcap"));
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &bytes[..*cut]).unwrap();
    }
    let summary = summary_json(dir.path());
    let trials = summary["trials"].as_array().unwrap();
    assert_eq!(trials.len(), cuts.len() - 1, "{summary}");
    let mut last_duration = 0.0;
    for (t, cut) in trials.iter().zip(&cuts) {
        let duration = t["duration_s"].as_f64().unwrap();
        assert!(duration > last_duration, "cut at {cut}: {duration} s");
        last_duration = duration;
        let note = t["unread"][0].as_str().unwrap();
        assert!(
            note.contains("ends without its footer")
                && note.contains(&format!("trial-{}", t["trial"])),
            "{note}"
        );
    }
    // The cut in the last chunk: the whole mission but its last second.
    let whole_s = (last_us - frames[0].stamp_us) as f64 * 1e-6;
    assert!(
        last_duration >= whole_s - 1.0,
        "{last_duration} of {whole_s} s"
    );
    assert_eq!(trials[5]["completed"], true);
    // The cut inside the header: named, with the file.
    let skipped = summary["skipped"].as_array().unwrap();
    assert_eq!(skipped.len(), 1, "{skipped:?}");
    let reason = skipped[0]["reason"].as_str().unwrap();
    assert!(
        reason.contains("trial-6") && reason.contains("empty log"),
        "{reason}"
    );
}

/// A simulated mission (world and unit processes) in which unit 1's controller output turns
/// non-finite (`--unit-arg 1=--inject=policy-nan@2`; sticky, so it trips on the first
/// controller tick after 2 s whenever the start comes): unit 1 latches a policy fault, unit 0
/// stops on its announcement, and the summary says so, by unit, in text and JSON.
#[test]
fn summary_of_a_fault_drill_names_the_unit_and_its_reason() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mission");
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_moonhaul"));
    cmd.args(["mission", "sim", "--payload", "box", "--trials", "1"])
        .args(["--controller", "scripted", "--max-seconds", "10"])
        .args(["--unit-arg", "1=--inject=policy-nan@2", "--out"])
        .arg(&out)
        .env("MOONHAUL_UNIT_BIN", common::unit_bin())
        .current_dir(repo_file(""))
        .stdin(std::process::Stdio::null());
    let output = common::run_bounded(&mut cmd, std::time::Duration::from_secs(400));
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stdout}\n{stderr}");
    let expected = "unit 1 latched a policy fault (non-finite or failed controller output)";
    assert!(stdout.contains(expected), "{stdout}");

    let summary = summary_json(&out);
    let trial = &summary["trials"][0];
    assert_eq!(trial["completed"], false, "{trial}");
    let why = trial["incomplete"].as_str().unwrap();
    assert!(
        why.starts_with("stopped during ") && why.contains(&format!(": {expected}")),
        "{why}"
    );
    assert!(
        why.contains("unit 0 stopped because unit 1 announced a stop"),
        "{why}"
    );
    let stop = &trial["stop"];
    assert_eq!(stop["unit"], 1, "{stop}");
    assert_eq!(stop["cause"]["fault"], "policy", "{stop}");
    assert!(
        ["lift", "transport", "place"].contains(&stop["phase"].as_str().unwrap()),
        "{stop}"
    );
    assert!(
        stop["reason"].as_str().unwrap().contains("policy fault"),
        "{stop}"
    );
    let heard = &stop["units"][0];
    assert_eq!(heard["unit"], 0, "{stop}");
    assert_eq!(heard["cause"]["peer_stop"]["unit"], 1, "{stop}");
}
