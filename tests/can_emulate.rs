//! End-to-end tests of `moonhaul can emulate`: the nine emulated drives are started, enabled,
//! moved and disabled, and the recorded candump log holds the whole conversation.

use std::process::Command;

mod common;
use common::*;

use moonhaul_hal::can::candump;

const UNIT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs/unit_can.toml");
const CONFIGS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/configs");

/// The shipped unit config, edited by `edit`, written to `dir/name`; the files it names
/// (control rate, URDF) stay the shipped ones.
fn unit_copy(
    dir: &std::path::Path,
    name: &str,
    edit: impl FnOnce(String) -> String,
) -> std::path::PathBuf {
    let text = std::fs::read_to_string(UNIT).unwrap();
    let text = text
        .lines()
        .map(|line| match line.split_once(" = \"") {
            Some((key @ ("control" | "unit_urdf"), rest)) => {
                format!("{key} = \"{CONFIGS}/{rest}")
            }
            _ => line.to_owned(),
        })
        .collect::<Vec<_>>()
        .join("\n");
    let path = dir.join(name);
    std::fs::write(&path, edit(text)).unwrap();
    path
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
    let bad = unit_copy(dir.path(), "bad_unit.toml", |text| {
        text.replacen("node_id = 2", "node_id = 1", 1)
    });
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

#[test]
fn seconds_out_of_range_are_errors_and_record_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("never.log");
    let log_s = log.to_str().unwrap();
    for seconds in [
        "NaN", "nan", "inf", "-inf", "-1", "0", "-0", "600.001", "1e9", "1e308", "abc", "",
    ] {
        let arg = format!("--seconds={seconds}");
        fails_naming(
            &["can", "emulate", "--unit", UNIT, &arg, "--record", log_s],
            "--seconds",
        );
    }
    // A negative number after a space is the value, not an unknown flag.
    fails_naming(
        &[
            "can",
            "emulate",
            "--unit",
            UNIT,
            "--seconds",
            "-1",
            "--record",
            log_s,
        ],
        "--seconds",
    );
    // Positive but shorter than one 20 ms control cycle.
    let stderr = fails_naming(
        &[
            "can",
            "emulate",
            "--unit",
            UNIT,
            "--seconds",
            "1e-9",
            "--record",
            log_s,
        ],
        "--seconds",
    );
    assert!(stderr.contains("control cycle"), "{stderr}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn a_fast_sync_period_cannot_make_an_unbounded_run() {
    let dir = tempfile::tempdir().unwrap();
    let control = dir.path().join("control.toml");
    std::fs::write(&control, "control_rate_hz = 1000.0\n").unwrap();
    let fast = unit_copy(dir.path(), "fast_unit.toml", |text| {
        let shipped = format!("control = \"{CONFIGS}/control.toml\"");
        assert!(text.contains(&shipped), "{text}");
        text.replacen(&shipped, "control = \"control.toml\"", 1)
    });
    // 600 s at 1 kHz: 600 000 control cycles.
    let stderr = fails_naming(
        &[
            "can",
            "emulate",
            "--unit",
            fast.to_str().unwrap(),
            "--seconds",
            "600",
        ],
        "--seconds",
    );
    assert!(stderr.contains("control cycles"), "{stderr}");
}

#[test]
fn record_refuses_targets_it_cannot_replace_whole() {
    let dir = tempfile::tempdir().unwrap();
    let emulate = |record: &str| {
        vec![
            "can".to_owned(),
            "emulate".into(),
            "--unit".into(),
            UNIT.into(),
            "--seconds".into(),
            "0.1".into(),
            "--record".into(),
            record.to_owned(),
        ]
    };
    let run = |record: &std::path::Path, needle: &str| {
        let args = emulate(record.to_str().unwrap());
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        fails_naming(&args, needle)
    };
    // A folder.
    let folder = dir.path().join("folder");
    std::fs::create_dir(&folder).unwrap();
    run(&folder, "not a regular file");
    assert!(folder.is_dir());
    // A FIFO: opening it would block; replacing it would surprise whoever reads it.
    let fifo = dir.path().join("fifo");
    let made = Command::new("mkfifo").arg(&fifo).status();
    if made.is_ok_and(|s| s.success()) {
        let stderr = run(&fifo, "not a regular file");
        assert!(stderr.contains("fifo"), "{stderr}");
        use std::os::unix::fs::FileTypeExt;
        assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    }
    // A folder that does not exist, and one under a file.
    let missing = dir.path().join("missing").join("unit.log");
    run(&missing, "missing");
    let file = dir.path().join("file");
    std::fs::write(&file, "").unwrap();
    run(&file.join("unit.log"), "is not a folder");
    // A folder that takes no new files (skipped as root, who may write anywhere).
    let locked = dir.path().join("locked");
    std::fs::create_dir(&locked).unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&locked, std::fs::Permissions::from_mode(0o555)).unwrap();
    if std::fs::write(locked.join("probe"), "").is_err() {
        run(&locked.join("unit.log"), "cannot create files");
        assert_eq!(std::fs::read_dir(&locked).unwrap().count(), 0);
    }
    std::fs::set_permissions(&locked, std::fs::Permissions::from_mode(0o755)).unwrap();
    // No file name at all.
    run(std::path::Path::new("/"), "--record");
    // Nothing else was written anywhere (no log, no temporary, no probe).
    for entry in std::fs::read_dir(dir.path()).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        assert!(
            ["fifo", "file", "folder", "locked"].contains(&name.as_str()),
            "left behind: {name}"
        );
    }
    assert_eq!(std::fs::read_dir(&folder).unwrap().count(), 0);
}

#[test]
fn record_never_replaces_the_units_config_and_an_old_log_only_with_force() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config-link.log");
    std::fs::hard_link(UNIT, &config).unwrap();
    let before = std::fs::read(UNIT).unwrap();
    let args = |record: &std::path::Path, force: bool| {
        let mut a = vec![
            "can".to_owned(),
            "emulate".into(),
            "--unit".into(),
            UNIT.into(),
            "--seconds".into(),
            "0.1".into(),
            "--record".into(),
            record.to_str().unwrap().to_owned(),
        ];
        if force {
            a.push("--force".into());
        }
        a
    };
    let run = |a: Vec<String>, needle: &str| {
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        fails_naming(&a, needle)
    };
    let err = run(args(&config, true), "CAN config");
    assert!(err.contains("config-link.log"), "{err}");
    assert_eq!(std::fs::read(UNIT).unwrap(), before);
    let old = dir.path().join("old.log");
    std::fs::write(&old, "old").unwrap();
    run(args(&old, false), "--force");
    assert_eq!(std::fs::read(&old).unwrap(), b"old");
    let a = args(&old, true);
    let a: Vec<&str> = a.iter().map(String::as_str).collect();
    stdout(&moonhaul(&a));
    assert_ne!(std::fs::read(&old).unwrap(), b"old");
}
