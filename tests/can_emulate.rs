//! End-to-end tests of `moonhaul can emulate`: the nine emulated drives are started, enabled,
//! moved and disabled, and the recorded candump log holds the whole conversation.

use std::process::{Command, Output};

use moonhaul_hal::can::candump;

const UNIT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/unit_can.toml");

fn moonhaul(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moonhaul"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn emulate_enables_nine_drives_and_records_a_parsable_log() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("unit.log");
    let out = moonhaul(&[
        "can",
        "emulate",
        "--unit",
        UNIT,
        "--seconds",
        "1",
        "--record",
        log.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("9 drives, 9 enabled"), "{stdout}");
    assert!(stdout.contains("arm_joint_7"), "{stdout}");

    let entries = candump::parse(&std::fs::read_to_string(&log).unwrap()).unwrap();
    assert!(
        stdout.contains(&format!("frames: {} ", entries.len())),
        "{stdout}"
    );
    let count = |id: u16, first: Option<u8>| {
        entries
            .iter()
            .filter(|e| {
                e.frame.id() == id && first.is_none_or(|b| e.frame.data().first() == Some(&b))
            })
            .count()
    };
    assert_eq!(count(0x000, Some(0x82)), 1, "NMT reset communication");
    assert_eq!(count(0x000, Some(0x01)), 1, "NMT start");
    assert_eq!(count(0x000, Some(0x02)), 1, "NMT stop");
    assert!(count(0x080, None) >= 50, "SYNC every period");
    // Mode of operation written to every drive: 9 (CSV) for wheels, 8 (CSP) for the arm.
    for node in 1..=9u16 {
        let mode = if node <= 2 { 9 } else { 8 };
        assert!(entries.iter().any(|e| e.frame.id() == 0x600 + node
            && e.frame.data() == [0x2F, 0x60, 0x60, 0, mode, 0, 0, 0]));
        assert!(count(0x180 + node, None) >= 50, "TPDO1 of node {node}");
    }
    assert!(entries.iter().all(|e| e.interface == "can0"));
    assert!(entries.windows(2).all(|w| w[0].time <= w[1].time));
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "no partial file left"
    );
}

#[test]
fn help_documents_every_argument() {
    let out = moonhaul(&["can", "emulate", "--help"]);
    let help = String::from_utf8(out.stdout).unwrap();
    for arg in ["--unit", "--seconds", "--record", "candump"] {
        assert!(help.contains(arg), "{help}");
    }
}

#[test]
fn a_bad_config_is_named_with_its_field() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad_unit.toml");
    let text = std::fs::read_to_string(UNIT)
        .unwrap()
        .replacen("node_id = 2", "node_id = 1", 1);
    std::fs::write(&bad, text).unwrap();
    let log = dir.path().join("never.log");
    let out = moonhaul(&[
        "can",
        "emulate",
        "--unit",
        bad.to_str().unwrap(),
        "--record",
        log.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(
        stderr.contains("bad_unit.toml") && stderr.contains("wheels[1].node_id"),
        "{stderr}"
    );
    assert!(!log.exists());
    let out = moonhaul(&["can", "emulate", "--unit", UNIT, "--seconds", "-1"]);
    assert!(!out.status.success());
}
