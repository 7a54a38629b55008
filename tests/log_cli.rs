//! `moonhaul log summary` on a synthetic mission directory written with the world-log writer:
//! two payloads, two trials each, with known heights and phase timing.

mod common;

use std::path::Path;

use moonhaul_core::state::Phase;
use moonhaul_deploy::mission_log::WorldLog;
use moonhaul_deploy::record::WorldFrame;

/// Frames every 20 ms: idle 0–1 s, lift 1–11 s (a ramp to `steady_m` over `ramp_s`), transport
/// 11–31 s at `steady_m`, place 31–36 s (down to `settled_m` over 4 s), idle 36–38 s with the
/// grasps open.
fn write_trial(dir: &Path, steady_m: f64, ramp_s: f64, settled_m: f64) {
    std::fs::create_dir_all(dir).unwrap();
    let mut log = WorldLog::create(&dir.join("world.mcap"), [0.5, 0.4, 0.3], 2).unwrap();
    for k in 0..=1900u64 {
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
        log.write(&WorldFrame {
            tick: k,
            stamp_us,
            payload_position_m: [0.1 * t, 0.0, height + 0.15],
            payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            payload_height_m: height,
            payload_tilt_deg: 0.3,
            payload_ground_contact: height < 0.01,
            base_position_m: vec![[0.1 * t, -0.6, 0.1], [0.1 * t, 0.6, 0.1]],
            base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; 2],
            // Unit 0 is silent on odd ticks: the phase falls back to unit 1's.
            unit_phase: vec![(k % 2 == 0).then_some(phase), Some(phase)],
            // The grippers open once the placement ends.
            grasp_closed: vec![k < 1800; 2],
        })
        .unwrap();
    }
    log.finish().unwrap();
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
    let mut log = WorldLog::create(&trial.join("world.mcap"), [0.5, 0.4, 0.3], 2).unwrap();
    // Lift 0–5 s, then held in transport until the log ends at 15 s.
    for k in 0..=750u64 {
        let phase = if k < 250 {
            Phase::Lift
        } else {
            Phase::Transport
        };
        log.write(&WorldFrame {
            tick: k,
            stamp_us: k * 20_000,
            payload_position_m: [0.0, 0.0, 0.3],
            payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            payload_height_m: 0.2,
            payload_tilt_deg: 0.0,
            payload_ground_contact: false,
            base_position_m: vec![[0.0; 3]; 2],
            base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; 2],
            unit_phase: vec![Some(phase); 2],
            // The grippers open once the placement ends.
            grasp_closed: vec![k < 1800; 2],
        })
        .unwrap();
    }
    log.finish().unwrap();
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
    WorldLog::create(&missing, [0.5, 0.4, 0.3], 2)
        .unwrap()
        .finish()
        .unwrap();
    let e = common::fails_naming(&["log", "summary", arg], missing.to_str().unwrap());
    assert!(e.contains("empty log"), "{e}");

    // A trial in which no unit ever lifted.
    let mut log = WorldLog::create(&missing, [0.5, 0.4, 0.3], 2).unwrap();
    for k in 0..10 {
        log.write(&WorldFrame {
            tick: k,
            stamp_us: k * 20_000,
            payload_position_m: [0.0; 3],
            payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            payload_height_m: 0.0,
            payload_tilt_deg: 0.0,
            payload_ground_contact: true,
            base_position_m: vec![[0.0; 3]; 2],
            base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; 2],
            unit_phase: vec![Some(Phase::Idle); 2],
            // The grippers open once the placement ends.
            grasp_closed: vec![k < 1800; 2],
        })
        .unwrap();
    }
    log.finish().unwrap();
    let e = common::fails_naming(&["log", "summary", arg], missing.to_str().unwrap());
    assert!(e.contains("lift"), "{e}");

    // Not a mission directory.
    let empty = tempfile::tempdir().unwrap();
    common::fails_naming(
        &["log", "summary", empty.path().to_str().unwrap()],
        "holds no trials",
    );
}
