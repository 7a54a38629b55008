//! End-to-end tests of `moonhaul sim demo` and `moonhaul sim bench`, and that every model in
//! `assets/` passes `moonhaul urdf check`.

use std::process::{Command, Output};

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/sim.toml");
const ASSETS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/assets");

fn moonhaul(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moonhaul"))
        .args(args)
        .output()
        .unwrap()
}

fn stdout(output: &Output) -> String {
    assert!(
        output.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).unwrap()
}

#[test]
fn demo_writes_the_mission_csv_and_png() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let out_s = out.to_str().unwrap();
    let text = stdout(&moonhaul(&[
        "sim",
        "demo",
        "--payload",
        "box",
        "--no-randomization",
        "--out",
        out_s,
        "--config",
        CONFIG,
    ]));
    assert!(text.contains("broken: false"), "{text}");
    let csv = std::fs::read_to_string(out.join("demo.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    for column in [
        "t_s",
        "phase",
        "payload_height_m",
        "payload_tilt_deg",
        "payload_speed_mps",
        "grasp_force_1_n",
        "grasp_force_2_n",
    ] {
        assert!(header.contains(&column), "missing {column}");
    }
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let height = header
        .iter()
        .position(|c| *c == "payload_height_m")
        .unwrap();
    let max_height = rows
        .iter()
        .map(|r| r[height].parse::<f64>().unwrap())
        .fold(0.0, f64::max);
    assert!(max_height > 0.25, "payload never lifted: {max_height}");
    for phase in ["lift", "transport", "place", "idle"] {
        assert!(rows.iter().any(|r| r[1] == phase), "no {phase} rows");
    }
    let png = std::fs::read(out.join("demo.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    // Written atomically: no temporary files left behind.
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 2);
}

#[test]
fn demo_rejects_an_unknown_payload_by_name() {
    let output = moonhaul(&["sim", "demo", "--payload", "piano", "--out", "/tmp/x"]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("piano"));
}

#[test]
fn bench_json_prints_one_line_with_the_rates() {
    let text = stdout(&moonhaul(&[
        "sim",
        "bench",
        "--json",
        "--envs",
        "2",
        "--threads",
        "2",
        "--steps",
        "10",
        "--config",
        CONFIG,
    ]));
    let value: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    assert_eq!(value["envs"], 2);
    assert_eq!(value["threads"], 2);
    let control = value["control_steps_per_s"].as_f64().unwrap();
    let physics = value["physics_steps_per_s"].as_f64().unwrap();
    assert!(control > 0.0 && (physics / control - 4.0).abs() < 1e-9);
}

#[test]
fn every_asset_passes_urdf_check() {
    for entry in std::fs::read_dir(ASSETS).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "urdf") {
            stdout(&moonhaul(&["urdf", "check", path.to_str().unwrap()]));
        }
    }
}
