//! End-to-end tests of `moonhaul sim demo` and `moonhaul sim bench`, and that every model in
//! `assets/` passes `moonhaul urdf check`.

mod common;
use common::*;

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/sim.toml");
const ASSETS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/assets");

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

/// A 0.5 × 0.3 × 0.2 m, 6 kg payload box, its long side `x` by `y`.
fn payload_urdf(x: f64, y: f64) -> String {
    let (z, m) = (0.2, 6.0 / 12.0);
    format!(
        "<?xml version=\"1.0\"?>\n<robot name=\"crate\"><link name=\"payload\"><inertial>\
         <mass value=\"6\"/><inertia ixx=\"{}\" ixy=\"0\" ixz=\"0\" iyy=\"{}\" iyz=\"0\" \
         izz=\"{}\"/></inertial><collision><geometry><box size=\"{x} {y} {z}\"/></geometry>\
         </collision></link></robot>\n",
        m * (y * y + z * z),
        m * (x * x + z * z),
        m * (x * x + y * y)
    )
}

#[test]
fn demo_carries_a_payload_urdf() {
    let dir = tempfile::tempdir().unwrap();
    let urdf = dir.path().join("crate_small.urdf");
    std::fs::write(&urdf, payload_urdf(0.5, 0.3)).unwrap();
    let out = dir.path().join("run");
    let text = stdout(&moonhaul(&[
        "sim",
        "demo",
        "--payload",
        urdf.to_str().unwrap(),
        "--no-randomization",
        "--out",
        out.to_str().unwrap(),
        "--config",
        CONFIG,
    ]));
    assert!(
        text.starts_with("crate_small (nominal)") && text.contains("broken: false"),
        "{text}"
    );
    assert!(out.join("demo.csv").is_file() && out.join("demo.png").is_file());
}

#[test]
fn demo_refuses_a_bad_payload_urdf_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let out = out.to_str().unwrap();
    let sideways = dir.path().join("sideways.urdf");
    std::fs::write(&sideways, payload_urdf(0.3, 0.5)).unwrap();
    let demo = |payload: &str, needle: &str| {
        let args = [
            "sim",
            "demo",
            "--payload",
            payload,
            "--out",
            out,
            "--config",
            CONFIG,
        ];
        let stderr = fails_naming(&args, payload);
        assert!(stderr.contains(needle), "{stderr}");
    };
    demo(sideways.to_str().unwrap(), "long side");
    demo(
        dir.path().join("absent.urdf").to_str().unwrap(),
        "absent.urdf",
    );
    // A word that is neither a shipped payload nor a path lists the choices.
    demo("crate", "sledge");
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

#[test]
fn bench_rejects_out_of_range_counts_by_name() {
    fn bench<'a>(extra: &[&'a str]) -> Vec<&'a str> {
        let mut args = vec!["sim", "bench", "--json", "--config", CONFIG];
        args.extend_from_slice(extra);
        args
    }
    fails_naming(&bench(&["--steps", "0"]), "--steps");
    fails_naming(&bench(&["--steps", "1000001"]), "--steps");
    fails_naming(&bench(&["--steps", "18446744073709551615"]), "--steps");
    fails_naming(&bench(&["--steps", "-1"]), "--steps");
    fails_naming(&bench(&["--envs", "0"]), "--envs");
    fails_naming(&bench(&["--envs", "4097"]), "--envs");
    fails_naming(&bench(&["--envs", "99999999999999999999"]), "--envs");
    fails_naming(&bench(&["--threads", "100000"]), "--threads");
    // Each in range, together days of work.
    fails_naming(
        &bench(&["--envs", "4096", "--steps", "1000000"]),
        "env steps",
    );
}

#[test]
fn bench_json_with_one_env_reports_finite_rates() {
    let text = stdout(&moonhaul(&[
        "sim",
        "bench",
        "--json",
        "--envs",
        "1",
        "--threads",
        "1",
        "--steps",
        "3",
        "--config",
        CONFIG,
    ]));
    assert_eq!(text.lines().count(), 1, "{text}");
    let value: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    assert_eq!(value["envs"], 1);
    assert_eq!(value["threads"], 1);
    let control = value["control_steps_per_s"].as_f64().unwrap();
    let physics = value["physics_steps_per_s"].as_f64().unwrap();
    assert!(control.is_finite() && control > 0.0, "{text}");
    assert!(physics.is_finite() && physics > control, "{text}");
}

#[test]
fn demo_rejects_an_output_folder_that_cannot_be_one() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("not_a_folder");
    std::fs::write(&file, "keep me").unwrap();
    let under_file = file.join("run");
    for out in [&file, &under_file] {
        let out = out.to_str().unwrap();
        let stderr = fails_naming(
            &[
                "sim",
                "demo",
                "--payload",
                "box",
                "--out",
                out,
                "--config",
                CONFIG,
            ],
            out,
        );
        assert!(stderr.contains("--out"), "{stderr}");
    }
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "keep me");
}

#[test]
fn demo_rejects_a_bad_seed_by_name() {
    for seed in ["-1", "abc", "18446744073709551616", ""] {
        fails_naming(
            &[
                "sim",
                "demo",
                "--payload",
                "box",
                "--seed",
                seed,
                "--out",
                "/tmp/x",
            ],
            "--seed",
        );
    }
}

#[test]
fn bench_replays_a_plan_file_and_names_a_bad_one() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_owned()
    };
    let command = "[0.1, -0.1, -1.13, -1.80, -0.58, 1.28, 0.52, 1.26, -2.67]";
    let good = write(
        "plan.json",
        &format!(r#"{{"commands": [[{command}, {command}], [{command}, {command}]]}}"#),
    );
    let bench = |plan: &str, steps: &str| {
        vec![
            "sim",
            "bench",
            "--json",
            "--envs",
            "1",
            "--threads",
            "1",
            "--steps",
            steps,
            "--config",
            CONFIG,
            "--plan",
        ]
        .into_iter()
        .map(str::to_owned)
        .chain([plan.to_owned()])
        .collect::<Vec<_>>()
    };
    let args = bench(&good, "2");
    let text = stdout(&moonhaul(
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
    ));
    let value: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    assert!(value["control_steps_per_s"].as_f64().unwrap() > 0.0);
    assert!(value["reset_s"].as_f64().unwrap() > 0.0);
    assert!(value["rebuild_s"].as_f64().unwrap() > value["reset_s"].as_f64().unwrap());

    let run = |args: Vec<String>, needle: &str| {
        fails_naming(&args.iter().map(String::as_str).collect::<Vec<_>>(), needle)
    };
    run(bench(&good, "3"), "fewer than --steps 3");
    let short = write(
        "short.json",
        &format!(r#"{{"commands": [[{command}, [1, 2]]]}}"#),
    );
    run(bench(&short, "1"), "short.json");
    let nan = write(
        "nan.json",
        r#"{"commands": [[[0,0,0,0,0,0,0,0,0], [0,0,0,0,0,0,0,0,1e999]]]}"#,
    );
    run(bench(&nan, "1"), "nan.json");
    run(
        bench("/nonexistent/plan.json", "1"),
        "/nonexistent/plan.json",
    );
    // A folder (as a device or a FIFO would be) is refused before anything is read.
    let folder = dir.path().to_str().unwrap().to_owned();
    run(bench(&folder, "1"), "not a regular file");
}

#[test]
fn demo_never_writes_over_an_input_and_an_earlier_run_only_with_force() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    std::fs::create_dir(&out).unwrap();
    // The run's own mission plan, reached through its output name.
    std::fs::hard_link(
        concat!(env!("CARGO_MANIFEST_DIR"), "/configs/mission.toml"),
        out.join("demo.csv"),
    )
    .unwrap();
    let out_s = out.to_str().unwrap();
    let args = [
        "sim",
        "demo",
        "--payload",
        "box",
        "--out",
        out_s,
        "--config",
        CONFIG,
    ];
    let err = fails_naming(&[&args[..], &["--force"]].concat(), "mission plan");
    assert!(
        err.contains("demo.csv") && err.contains("mission.toml"),
        "{err}"
    );
    // An earlier run's file.
    std::fs::remove_file(out.join("demo.csv")).unwrap();
    std::fs::write(out.join("demo.png"), "old").unwrap();
    let err = fails_naming(&args, "--force");
    assert!(err.contains("demo.png"), "{err}");
    assert_eq!(std::fs::read(out.join("demo.png")).unwrap(), b"old");
}
