//! `moonhaul log ros2` against ROS 2 tooling moonhaul did not write: a simulated mission's logs
//! become a rosbag2 bag that PyPI's `rosbags` (its rosbag2 reader, CDR codec and Jazzy type
//! store) reads back with every tick, name and stamp of the logs (`tests/ros2/check_bag.py`);
//! damaged input and outputs over an input are refused by name.

mod common;

use std::path::Path;
use std::process::Command;

use common::{fails_naming, moonhaul, ros2_python, stdout};
use moonhaul_deploy::mission_log::{read_unit_log, read_world_log};

fn mission(out: &Path) {
    let out = out.to_str().unwrap();
    stdout(&moonhaul(&[
        "mission",
        "sim",
        "--controller",
        "scripted",
        "--payload",
        "box",
        "--trials",
        "1",
        "--out",
        out,
    ]));
}

/// What the logs of `trial` hold, by moonhaul's own log reader, for the Python check.
fn expected(trial: &Path) -> serde_json::Value {
    let mut units = serde_json::Map::new();
    for i in 0..2 {
        let records = read_unit_log(&trial.join(format!("unit-{i}.mcap"))).unwrap();
        let stamps: Vec<u64> = records.iter().map(|r| r.stamp_us).collect();
        units.insert(format!("unit_{i}"), stamps.into());
    }
    let payload: Vec<serde_json::Value> = read_world_log(&trial.join("world.mcap"))
        .unwrap()
        .iter()
        .map(|f| {
            let [x, y, z] = f.payload_position_m;
            serde_json::json!([f.stamp_us, x, y, z])
        })
        .collect();
    serde_json::json!({ "units": units, "payload": payload })
}

#[test]
fn a_simulated_missions_bag_reads_back_in_rosbags_with_every_tick() {
    let Some(python) = ros2_python("a_simulated_missions_bag_reads_back_in_rosbags") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let missions = dir.path().join("mission");
    mission(&missions);
    let bag = dir.path().join("bag");
    let text = stdout(&moonhaul(&[
        "log",
        "ros2",
        missions.to_str().unwrap(),
        "--out",
        bag.to_str().unwrap(),
    ]));
    assert!(text.contains("joint_states of unit_0"), "{text}");
    let trial_bag = bag.join("box").join("trial-0");
    assert!(trial_bag.join("metadata.yaml").is_file());
    assert!(trial_bag.join("trial-0_0.mcap").is_file());
    let expected_path = dir.path().join("expected.json");
    let trial = missions.join("box").join("trial-0");
    std::fs::write(&expected_path, expected(&trial).to_string()).unwrap();
    let check = Command::new(&python)
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/ros2/check_bag.py"
        ))
        .arg(&trial_bag)
        .arg(&expected_path)
        .output()
        .unwrap();
    let report = String::from_utf8_lossy(&check.stdout);
    assert!(
        check.status.success(),
        "{report}\n{}",
        String::from_utf8_lossy(&check.stderr)
    );
    assert!(report.contains("bag ok"), "{report}");

    // A single unit log, and a trial folder, convert too, each to one bag.
    let one = dir.path().join("one");
    stdout(&moonhaul(&[
        "log",
        "ros2",
        trial.join("unit-1.mcap").to_str().unwrap(),
        "--out",
        one.to_str().unwrap(),
    ]));
    assert!(one.join("one_0.mcap").is_file());

    // An existing output is kept without --force, and never one holding the input.
    fails_naming(
        &[
            "log",
            "ros2",
            trial.to_str().unwrap(),
            "--out",
            bag.to_str().unwrap(),
        ],
        "pass --force",
    );
    fails_naming(
        &[
            "log",
            "ros2",
            trial.to_str().unwrap(),
            "--out",
            missions.to_str().unwrap(),
            "--force",
        ],
        "refusing to write over an input",
    );
    assert!(trial.join("world.mcap").is_file());
    stdout(&moonhaul(&[
        "log",
        "ros2",
        trial.to_str().unwrap(),
        "--out",
        bag.to_str().unwrap(),
        "--force",
    ]));
    assert!(bag.join("bag_0.mcap").is_file() && !bag.join("box").exists());
}

#[test]
fn damaged_logs_are_refused_naming_the_file_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("unit-0.mcap");
    std::fs::write(&garbage, b"\x89MCAP0\r\nthis is not a record stream at all").unwrap();
    let out = dir.path().join("bag");
    let err = fails_naming(
        &[
            "log",
            "ros2",
            garbage.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        garbage.to_str().unwrap(),
    );
    assert!(err.contains("record"), "{err}");
    assert!(!out.exists());
    // Nothing half-written beside it either.
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");

    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    fails_naming(
        &[
            "log",
            "ros2",
            empty.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        empty.to_str().unwrap(),
    );
}
