//! The CiA 402 master against nine emulated drives on the virtual bus: start-up, mode set-up,
//! enable, command/feedback round trips, disable, fault reset, and every fault the issue lists
//! ending in a reported fault within a bounded (simulated) time.

use std::time::Duration;

use moonhaul_hal::can::cia402::Cia402State;
use moonhaul_hal::can::protocol::NmtCommand;
use moonhaul_hal::can::{
    candump, CanBus, CanError, CanFrame, Cia402Master, RecordingBus, UnitCanConfig, VirtualBus,
};
use moonhaul_hal::{ArmDrive, Drive, HalError, WheelDrive};
use proptest::prelude::*;

const CONFIG: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/unit_can.toml");

fn config() -> UnitCanConfig {
    UnitCanConfig::from_file(CONFIG).unwrap()
}

fn master() -> Cia402Master<VirtualBus> {
    let config = config();
    Cia402Master::new(VirtualBus::for_unit(&config), &config)
}

fn enabled() -> Cia402Master<VirtualBus> {
    let mut master = master();
    master.enable().unwrap();
    master
}

/// Syncs until the master reports a fault; panics if none comes within `max` of bus time.
fn fault_within(master: &mut Cia402Master<VirtualBus>, max: Duration) -> CanError {
    let deadline = master.bus().now() + max;
    while master.bus().now() <= deadline {
        if let Err(err) = master.sync() {
            match err {
                HalError::Can(err) => return err,
                other => panic!("unexpected error {other:?}"),
            }
        }
    }
    panic!("no fault within {max:?}");
}

fn all_enabled(master: &Cia402Master<VirtualBus>) -> bool {
    master
        .drive_states()
        .all(|(_, s)| s == Some(Cia402State::OperationEnabled))
}

#[test]
fn start_up_sets_modes_and_pdo_mappings() {
    let mut master = master();
    master.start_up().unwrap();
    for i in 0..9 {
        let mode = master.sdo_upload(i, 0x6061, 0).unwrap();
        assert_eq!(mode, if i < 2 { 9 } else { 8 }, "axis {i}");
        assert_eq!(
            master.sdo_upload(i, 0x1600, 2).unwrap(),
            if i < 2 { 0x60FF_0020 } else { 0x607A_0020 }
        );
        assert_eq!(master.sdo_upload(i, 0x1A00, 0).unwrap(), 2);
        assert_eq!(master.sdo_upload(i, 0x1017, 0).unwrap(), 100);
    }
    for node in 1..=9 {
        let drive = master.bus().drive(node).unwrap();
        assert_eq!(
            drive.nmt_state(),
            moonhaul_hal::can::protocol::NmtState::Operational
        );
    }
}

#[test]
fn enable_sequence_reaches_operation_enabled_on_all_nine_and_holds_position() {
    let mut master = master();
    for node in 3..=9 {
        master
            .bus_mut()
            .drive_mut(node)
            .unwrap()
            .set_position_rad(0.1 * f64::from(node));
    }
    assert!(matches!(
        master.command_velocity(&[1.0, 1.0]),
        Err(HalError::NotEnabled { .. })
    ));
    master.enable().unwrap();
    assert!(all_enabled(&master));
    // Switch on disabled → ready → switched on → enabled takes a few SYNCs, well in budget.
    assert!(master.stats().cycles <= 5, "{:?}", master.stats());
    for _ in 0..10 {
        master.sync().unwrap();
    }
    let arm = master.read_arm().unwrap();
    for (j, q) in arm.position_rad.iter().enumerate() {
        assert!(
            (q - 0.1 * (j as f64 + 3.0)).abs() < 1e-4,
            "joint {j} moved on enable: {q}"
        );
    }
    master.disable().unwrap();
    assert!(master
        .drive_states()
        .all(|(_, s)| s == Some(Cia402State::ReadyToSwitchOn)));
    assert!(matches!(
        master.command_position(&arm.position_rad),
        Err(HalError::NotEnabled { .. })
    ));
}

#[test]
fn commands_and_feedback_round_trip_through_counts() {
    let mut master = enabled();
    let wheels = [1.5, -0.75];
    let arm = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6, 0.7];
    for _ in 0..60 {
        master.command_velocity(&wheels).unwrap();
        master.command_position(&arm).unwrap();
        master.sync().unwrap();
    }
    let w = master.read_wheels().unwrap();
    let a = master.read_arm().unwrap();
    for (got, want) in w.velocity_radps.iter().zip(wheels) {
        assert!((got - want).abs() < 1e-3, "wheels: {:?}", w.velocity_radps);
    }
    for ((got, want), velocity) in a.position_rad.iter().zip(arm).zip(a.velocity_radps) {
        assert!((got - want).abs() < 1e-4, "arm: {:?}", a.position_rad);
        assert!(velocity.abs() < 1e-3);
    }
    // The inverted right wheel turns its motor backwards; the joint still goes the right way.
    let right = master.bus().drive(2).unwrap().position_rad();
    assert!(
        w.position_rad[1] < 0.0 && (right - w.position_rad[1]).abs() < 0.016,
        "{right} {:?}",
        w.position_rad
    );
    assert!(w.stamp == master.bus().now() - Duration::from_millis(20) && a.effort_nm.is_some());
    let err = master.command_position(&[f64::NAN; 7]).unwrap_err();
    assert!(matches!(err, HalError::NonFinite { ref joint, .. } if joint == "arm_joint_1"));
}

#[test]
fn emergency_faults_and_fault_reset_recovers_all_nine() {
    let mut master = enabled();
    master.bus_mut().drive_mut(5).unwrap().raise_fault(0x2310);
    let err = fault_within(&mut master, Duration::from_millis(20));
    assert!(
        matches!(err, CanError::Emergency { ref at, code: 0x2310, .. } if at.node == 5 && at.joint == "arm_joint_3")
    );
    assert!(err.to_string().contains("continuous over-current"), "{err}");
    assert!(matches!(
        master.command_velocity(&[0.0; 2]),
        Err(HalError::Can(_))
    ));
    master.reset_fault().unwrap();
    assert_eq!(master.fault(), None);
    assert_eq!(
        master.bus().drive(5).unwrap().state(),
        Cia402State::SwitchOnDisabled
    );
    master.enable().unwrap();
    assert!(all_enabled(&master));
}

#[test]
fn statusword_fault_without_emcy_is_reported() {
    let mut master = enabled();
    // A silent EMCY (lost frame): the statusword alone must report the fault.
    master.bus_mut().drive_mut(9).unwrap().raise_fault(0x4310);
    master
        .bus_mut()
        .inject(CanFrame::new(0x701, &[0x05]).unwrap()); // unrelated traffic
    let mut drained = std::collections::VecDeque::new();
    master.bus_mut().drive_mut(9).unwrap().drain(&mut drained); // swallow the EMCY
    let err = fault_within(&mut master, Duration::from_millis(20));
    assert!(
        matches!(err, CanError::DriveFault { ref at, .. } if at.node == 9),
        "{err}"
    );
}

#[test]
fn heartbeat_loss_is_reported_within_the_timeout() {
    let mut master = enabled();
    // Heartbeats stop but process data goes on: only the heartbeat supervision can see it.
    master.sdo_download(3, 0x1017, 0, 0, 2).unwrap();
    let config = config();
    let err = fault_within(
        &mut master,
        Duration::from_secs_f64(config.heartbeat_timeout_s + 0.1),
    );
    assert!(
        matches!(err, CanError::HeartbeatLost { ref at, .. } if at.joint == "arm_joint_2"),
        "{err}"
    );
}

#[test]
fn a_silent_drive_is_reported_within_the_feedback_timeout() {
    let mut master = enabled();
    master.bus_mut().drive_mut(1).unwrap().faults.silent = true;
    let err = fault_within(&mut master, Duration::from_millis(150));
    assert!(
        matches!(err, CanError::NoFeedback { ref at, .. } if at.joint == "wheel_left_joint"),
        "{err}"
    );
    // Reset clears the fault, but a drive that stays silent is reported again.
    master.reset_fault().unwrap();
    let err = fault_within(&mut master, Duration::from_millis(150));
    assert!(matches!(err, CanError::NoFeedback { .. }), "{err}");
}

#[test]
fn sdo_abort_is_decoded_and_names_the_drive() {
    let mut master = master();
    master.bus_mut().drive_mut(7).unwrap().faults.sdo_abort = Some((0x6060, 0, 0x0609_0030));
    let err = master.start_up().unwrap_err();
    assert!(
        matches!(err, CanError::SdoAbort { ref at, index: 0x6060, code: 0x0609_0030, .. } if at.node == 7)
    );
    assert!(
        err.to_string().contains("arm_joint_5") && err.to_string().contains("invalid value"),
        "{err}"
    );
}

#[test]
fn sdo_timeout_is_bounded() {
    let mut master = master();
    master.bus_mut().drive_mut(8).unwrap().faults.silent = true;
    let err = master.enable().unwrap_err();
    assert!(
        matches!(err, HalError::Can(CanError::SdoTimeout { ref at, index: 0x1000, .. }) if at.node == 8),
        "{err}"
    );
    assert!(master.bus().now() <= Duration::from_millis(60));
}

#[test]
fn dropping_out_of_operation_enabled_is_a_fault_and_not_silently_undone() {
    let mut master = enabled();
    master.bus_mut().drive_mut(4).unwrap().drop_out();
    let err = fault_within(&mut master, Duration::from_millis(20));
    assert!(
        matches!(err, CanError::LeftOperationEnabled { ref at, state: Cia402State::SwitchOnDisabled } if at.node == 4),
        "{err}"
    );
    for _ in 0..10 {
        let _ = master.sync();
    }
    assert_ne!(
        master.bus().drive(4).unwrap().state(),
        Cia402State::OperationEnabled
    );
    assert_eq!(
        master.bus().drive(5).unwrap().state(),
        Cia402State::OperationEnabled
    );
    master.reset_fault().unwrap();
    master.enable().unwrap();
    assert!(all_enabled(&master));
}

#[test]
fn malformed_truncated_and_foreign_frames_are_reported() {
    let cases: [(u16, &[u8], &str); 6] = [
        (0x181, &[0x37, 0x02, 0x00], "wheel_left_joint"), // truncated TPDO1
        (0x282, &[0; 8], "wheel_right_joint"),            // TPDO2 of the wrong length
        (0x083, &[0x10], "arm_joint_1"),                  // truncated EMCY
        (0x704, &[0x33], "arm_joint_2"),                  // bad NMT state
        (0x72A, &[0x05], "0x72A"),                        // unknown node 42
        (0x000, &[0x01, 0x00], "0x000"),                  // another master
    ];
    let mut master = enabled();
    for (id, data, named) in cases {
        master.bus_mut().inject(CanFrame::new(id, data).unwrap());
        let err = fault_within(&mut master, Duration::from_millis(20));
        assert!(err.to_string().contains(named), "{id:03X}: {err}");
        master.reset_fault().unwrap();
        master.enable().unwrap();
    }
}

#[test]
fn a_rebooted_drive_is_reported() {
    let mut master = enabled();
    master.nmt(NmtCommand::ResetNode, 6).unwrap();
    let err = fault_within(&mut master, Duration::from_millis(20));
    assert!(
        matches!(err, CanError::Rebooted { ref at } if at.node == 6),
        "{err}"
    );
}

#[test]
fn recorded_logs_parse_back_and_replay_into_fresh_drives() {
    let config = config();
    let bus = RecordingBus::new(
        VirtualBus::for_unit(&config),
        Duration::from_secs(1_700_000_000),
    );
    let mut master = Cia402Master::new(bus, &config);
    master.enable().unwrap();
    for k in 0..25 {
        master
            .command_velocity(&[0.04 * f64::from(k), 0.5])
            .unwrap();
        master.command_position(&[0.01 * f64::from(k); 7]).unwrap();
        master.sync().unwrap();
    }
    master.shut_down().unwrap();
    let log = master.bus().log().to_vec();

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unit.log");
    candump::write_file(&path, &log).unwrap();
    let parsed = candump::parse(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert_eq!(parsed, log);

    let mut fresh = VirtualBus::for_unit(&config);
    let answers = candump::replay(&parsed, &mut fresh).unwrap();
    let from_drives = |entries: &[candump::LogEntry]| -> Vec<CanFrame> {
        entries
            .iter()
            .filter(|e| !moonhaul_hal::can::protocol::from_master(e.frame.id()))
            .map(|e| e.frame)
            .collect()
    };
    assert!(answers.len() > 500);
    assert_eq!(from_drives(&answers), from_drives(&parsed));
    let replayed = fresh.drive(3).unwrap().position_rad();
    let original = master.bus().inner().drive(3).unwrap().position_rad();
    assert_eq!(replayed, original);
}

#[test]
fn the_master_is_a_drive_trait_object() {
    let mut master = enabled();
    let arm: &mut dyn ArmDrive = &mut master;
    arm.command_position(&[0.0; 7]).unwrap();
    arm.sync().unwrap();
    assert!(arm.read_arm().is_ok());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Whatever arrives on the bus, the master reports or ignores it, never panics or hangs.
    #[test]
    fn arbitrary_frames_never_panic_the_master(frames in proptest::collection::vec(
        (0u16..=0x7FF, proptest::collection::vec(any::<u8>(), 0..=8)), 1..8)) {
        let mut master = enabled();
        for (id, data) in frames {
            master.bus_mut().inject(CanFrame::new(id, &data).unwrap());
        }
        let start = master.bus().now();
        for _ in 0..3 {
            let _ = master.sync();
        }
        prop_assert!(master.bus().now() - start <= Duration::from_millis(60));
    }
}
