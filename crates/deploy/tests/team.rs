//! Whole teams of the onboard tick in one process, on mock hardware, with every message sealed
//! and validated exactly as the daemon does (only the zenoh hop is replaced by a queue), and
//! the faults of issue 11 judged from the tick records: a silent peer, a network partition, a
//! NaN sensor, a NaN policy output, a drive fault, an operator stop, forged and replayed
//! messages, another team's unit and a clock offset. Every fault must end in a hold of every
//! unit within the staleness bound, and no command may leave the clamp's hold when held.

use std::time::Duration;

use moonhaul_coord::auth::{KeyFile, Sealer};
use moonhaul_coord::clamp::hold_command;
use moonhaul_coord::message::{
    Body, Envelope, MessageBounds, OperatorCommand, Refusal, Sender, StopReason, Verdict,
    PROTOCOL_VERSION,
};
use moonhaul_coord::{HoldReason, TeamSettings, Validator};
use moonhaul_core::config::repo_file;
use moonhaul_core::scripted::MissionPlan;
use moonhaul_core::state::{Phase, PlanarPose};
use moonhaul_deploy::daemon::mock_hardware;
use moonhaul_deploy::record::TickRecord;
use moonhaul_deploy::tick::{Controller, Onboard, OnboardSettings};
use moonhaul_deploy::unit_config::UnitConfig;
use moonhaul_hal::unit::{FaultInjection, InjectedFault, MockUnit, UnitHardware, UnitReading};

const PERIOD_US: u64 = 20_000;
const BOOT_US: u64 = 1_000_000_000;

struct Unit {
    onboard: Onboard,
    hw: MockUnit,
    validator: Validator,
    sealer: Sealer,
    record: TickRecord,
    /// Added to the team clock (a clock fault).
    clock_offset_us: i64,
    /// This unit's tick records.
    log: Vec<TickRecord>,
    /// A key holder gone wrong: what it does to its message before sealing it.
    tamper: Option<fn(&mut Envelope)>,
}

struct Team {
    units: Vec<Unit>,
    operator: Sealer,
    now_us: u64,
    /// Frames published last tick, by sender index.
    outbox: Vec<Vec<u8>>,
    /// Extra frames delivered to every unit next tick (operator commands, forgeries).
    injected: Vec<Vec<u8>>,
    operator_seq: u64,
}

fn settings(unit: usize) -> TeamSettings {
    TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: unit,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    }
}

/// The formation's start: unit 0 facing +x at y = −0.8 m, unit 1 facing it at y = +0.8 m.
fn start_pose(i: usize) -> PlanarPose {
    PlanarPose {
        x_m: 0.0,
        y_m: if i == 0 { -0.8 } else { 0.8 },
        yaw_rad: if i == 0 { 0.0 } else { std::f64::consts::PI },
    }
}

impl Team {
    fn new() -> Team {
        let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
        let unit_toml = UnitConfig::from_file(&repo_file("configs/unit.toml")).unwrap();
        let units = (0..2)
            .map(|i| {
                let onboard_settings =
                    OnboardSettings::shipped(settings(i), start_pose(i)).unwrap();
                let period = Duration::from_micros(PERIOD_US);
                let mut hw = mock_hardware(&unit_toml, &onboard_settings.spec, period).unwrap();
                hw.activate().unwrap();
                let onboard = Onboard::new(
                    onboard_settings,
                    // The scripted controller: these tests are about the team, not a policy's
                    // skill, and it lifts the mock's cargo past h_min for certain.
                    Controller::Scripted(MissionPlan::shipped().unwrap()),
                    BOOT_US,
                )
                .unwrap();
                Unit {
                    onboard,
                    hw,
                    validator: Validator::new(
                        &settings(i),
                        &keys,
                        MessageBounds::shipped().unwrap(),
                    )
                    .unwrap(),
                    sealer: keys.sealer(Sender::Unit(i)).unwrap(),
                    record: TickRecord::for_team(2),
                    clock_offset_us: 0,
                    log: Vec::new(),
                    tamper: None,
                }
            })
            .collect();
        Team {
            units,
            operator: keys.sealer(Sender::Operator).unwrap(),
            now_us: BOOT_US,
            outbox: vec![Vec::new(); 2],
            injected: Vec::new(),
            operator_seq: BOOT_US,
        }
    }

    fn operator(&mut self, command: OperatorCommand) {
        self.operator_seq += 1;
        let envelope = Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender: Sender::Operator,
            seq: self.operator_seq,
            stamp_us: self.now_us,
            body: Body::Operator(command),
        };
        self.injected.push(self.operator.seal(&envelope).unwrap());
    }

    /// One tick of every unit; `deliver(from, to)` says whether unit `from`'s message of the
    /// last tick reaches unit `to`.
    fn tick(&mut self, deliver: impl Fn(usize, usize) -> bool) {
        self.now_us += PERIOD_US;
        let injected = std::mem::take(&mut self.injected);
        let outbox = std::mem::take(&mut self.outbox);
        let mut next = vec![Vec::new(); self.units.len()];
        for (i, u) in self.units.iter_mut().enumerate() {
            let now = self.now_us.saturating_add_signed(u.clock_offset_us);
            let mut reading = UnitReading::default();
            let read = u.hw.read(&mut reading);
            for (from, frame) in outbox.iter().enumerate() {
                if from != i && !frame.is_empty() && deliver(from, i) {
                    match u.validator.receive_frame(frame, now) {
                        Ok(e) => u.onboard.receive(&e),
                        Err(r) => u.onboard.reject(&r),
                    }
                }
            }
            for frame in &injected {
                match u.validator.receive_frame(frame, now) {
                    Ok(e) => u.onboard.receive(&e),
                    Err(r) => u.onboard.reject(&r),
                }
            }
            if u.hw.fault().is_some() {
                u.onboard
                    .latch_fault(moonhaul_coord::message::FaultKind::Drive, "drive fault");
            }
            let out = u.onboard.tick(
                now,
                read.is_ok().then_some(&reading),
                u.validator.counts(),
                &mut u.record,
            );
            let output = out.output;
            let mut message = out.message.clone();
            if let Some(tamper) = u.tamper {
                tamper(&mut message);
            }
            next[i] = u.sealer.seal(&message).unwrap();
            u.validator.set_mission(u.onboard.mission());
            // A rejected write still cycles the mock; the fault latches next tick.
            let _ = u.hw.write(&output);
            u.log.push(u.record.clone());
        }
        self.outbox = next;
    }

    fn run(&mut self, ticks: usize) {
        for _ in 0..ticks {
            self.tick(|_, _| true);
        }
    }

    fn phase(&self, i: usize) -> Phase {
        self.units[i].onboard.phase()
    }

    fn last(&self, i: usize) -> &TickRecord {
        self.units[i].log.last().unwrap()
    }
}

/// A started team, lifting.
fn lifting() -> Team {
    let mut team = Team::new();
    team.run(5);
    team.operator(OperatorCommand::Start { mission: 7 });
    team.run(5);
    assert_eq!((team.phase(0), team.phase(1)), (Phase::Lift, Phase::Lift));
    team.run(20);
    team
}

/// Asserts unit `i` holds now for a safety stop matching `want`, with the hold command.
fn holds_for(team: &Team, i: usize, want: impl Fn(StopReason) -> bool) {
    let r = team.last(i);
    assert_eq!(r.phase, Phase::Idle, "unit {i}: {r:?}");
    match r.hold {
        Some(HoldReason::SafetyStop(reason)) => assert!(want(reason), "unit {i}: {reason:?}"),
        other => panic!("unit {i} is not stopped: {other:?}"),
    }
    assert_eq!(r.issued, hold_command(&r.team_previous[i]), "unit {i}");
}

#[test]
fn a_mission_on_mock_hardware_runs_the_phases_in_step() {
    let mut team = Team::new();
    team.run(10);
    // Nothing moves before the operator's start.
    assert!(team
        .units
        .iter()
        .all(|u| u.log.iter().all(|r| r.phase == Phase::Idle)));
    team.operator(OperatorCommand::Start { mission: 1 });
    let mut phases = Vec::new();
    for _ in 0..(40 * 50) {
        team.tick(|_, _| true);
        let now = (team.phase(0), team.phase(1));
        if phases.last() != Some(&now) {
            phases.push(now);
        }
        if phases.len() > 1 && now == (Phase::Idle, Phase::Idle) {
            break;
        }
    }
    // The units never run different phase policies in the same tick.
    for (a, b) in team.units[0].log.iter().zip(&team.units[1].log) {
        let running = |r: &TickRecord| {
            if r.hold.is_none() {
                Some(r.phase)
            } else {
                None
            }
        };
        if let (Some(pa), Some(pb)) = (running(a), running(b)) {
            assert_eq!(pa, pb, "tick {}", a.tick);
        }
    }
    // Mock drives follow their commands exactly and carry no payload: the scripted lift raises
    // the cargo estimate past h_min and the team commits Transport together.
    let visited: Vec<Phase> = phases.iter().map(|p| p.0).collect();
    assert!(visited.contains(&Phase::Transport), "{phases:?}");
    eprintln!("phases on mock hardware: {phases:?}");
    // Every issued command lies in the clamp's admissible set: t_max ∈ [0, 1] and a step only
    // when the distance it reports is within tolerance.
    for r in team.units.iter().flat_map(|u| &u.log) {
        assert!((0.0..=1.0).contains(&r.t_max), "{r:?}");
        if let (None, Some(d)) = (r.hold, r.distance) {
            assert!(d.value <= 1.0 + 1e-9, "{r:?}");
        }
    }
}

#[test]
fn a_silent_peer_stops_the_survivor_within_the_staleness_bound() {
    let mut team = lifting();
    // Unit 1 dies: its message of the last tick is the last to arrive (peers lag one tick, so
    // it is stamped one period before it arrived).
    for k in 1..=3 {
        team.tick(|from, _| from != 1);
        let r = team.last(0);
        if k < 3 {
            assert_ne!(r.phase, Phase::Idle, "tick {k}: {r:?}");
        }
    }
    // Three periods after the last message arrived its stamp is 4 periods old, past the
    // 3-period bound: the survivor holds.
    holds_for(&team, 0, |r| r == StopReason::PeerStale { unit: 1 });
    assert_eq!(team.last(0).peer_age_us[1], Some(4 * PERIOD_US));
}

#[test]
fn a_network_partition_stops_both_sides() {
    let mut team = lifting();
    for _ in 0..5 {
        team.tick(|_, _| false);
    }
    holds_for(&team, 0, |r| matches!(r, StopReason::PeerStale { unit: 1 }));
    holds_for(&team, 1, |r| matches!(r, StopReason::PeerStale { unit: 0 }));
    // Healing the network does not restart the team: a new start is needed.
    team.run(20);
    assert_eq!((team.phase(0), team.phase(1)), (Phase::Idle, Phase::Idle));
}

#[test]
fn a_nan_sensor_stops_the_team_and_is_announced() {
    let mut team = lifting();
    team.units[1]
        .hw
        .inject(InjectedFault::SensorNan { joint: 4 })
        .unwrap();
    team.run(3);
    holds_for(&team, 1, |r| matches!(r, StopReason::Fault(_)));
    holds_for(&team, 0, |r| r == StopReason::PeerStop { unit: 1 });
    assert!(team.last(1).fault.is_some());
}

#[test]
fn a_motor_fault_stops_the_team() {
    let mut team = lifting();
    team.units[0]
        .hw
        .inject(InjectedFault::Motor { joint: 3 })
        .unwrap();
    team.run(4);
    holds_for(&team, 0, |r| matches!(r, StopReason::Fault(_)));
    holds_for(&team, 1, |r| r == StopReason::PeerStop { unit: 0 });
}

#[test]
fn an_operator_stop_wins_even_replayed_but_never_stops_a_later_mission() {
    let mut team = lifting();
    team.operator(OperatorCommand::Stop { mission: Some(7) });
    let stop = team.injected[0].clone();
    team.run(1);
    holds_for(&team, 0, |r| r == StopReason::Operator);
    holds_for(&team, 1, |r| r == StopReason::Operator);
    // The team stays in Idle after the stop; a replay within the mission stops it again
    // (stopping is always safe).
    team.run(5);
    assert_eq!((team.phase(0), team.phase(1)), (Phase::Idle, Phase::Idle));
    team.injected.push(stop.clone());
    team.run(1);
    holds_for(&team, 0, |r| r == StopReason::Operator);
    // Restart, then replay the old stop much later: it names mission 7, so mission 8 goes on.
    team.operator(OperatorCommand::Start { mission: 8 });
    team.run(30);
    assert_eq!(team.phase(0), Phase::Lift);
    let before = team.last(0).rejected.wrong_mission;
    team.injected.push(stop);
    team.run(3);
    assert_eq!((team.phase(0), team.phase(1)), (Phase::Lift, Phase::Lift));
    assert!(team.last(0).rejected.wrong_mission > before);
    // Each unit answers it, by sequence number, as a stop for the wrong mission.
    let moonhaul_coord::message::Body::Unit(tick) = &team.units[0].onboard.last_message().body
    else {
        unreachable!()
    };
    assert_eq!(tick.announce.mission, Some(8));
    assert!(
        matches!(
            tick.announce.operator.map(|a| a.verdict),
            Some(Verdict::Rejected(Refusal::WrongMission {
                got: 7,
                current: 8
            }))
        ),
        "{:?}",
        tick.announce.operator
    );
    // The stop for mission 8 stops it.
    team.operator(OperatorCommand::Stop { mission: Some(8) });
    team.run(1);
    holds_for(&team, 0, |r| r == StopReason::Operator);
}

/// A key holder whose messages carry absurd finite values (the x = 1e308): the
/// receiver refuses them by name, holds for that peer once its last good state is stale, never
/// latches a fault of its own, and its team runs the next mission once the peer is good again.
#[test]
fn a_key_holder_with_absurd_values_is_a_named_peer_fault_that_clears() {
    let mut team = lifting();
    team.units[1].tamper = Some(|e| {
        if let Body::Unit(tick) = &mut e.body {
            tick.state.base_pose.x_m = 1e308;
        }
    });
    team.run(10);
    holds_for(&team, 0, |r| r == StopReason::PeerRejected { unit: 1 });
    // Its peer hears the announced stop and stops too, for unit 0's reason.
    holds_for(&team, 1, |r| r == StopReason::PeerStop { unit: 0 });
    for u in &team.units {
        assert_eq!(u.onboard.fault(), None, "unit {}", u.onboard.unit());
        assert!(u.log.iter().all(|r| r.fault.is_none()));
    }
    assert!(
        team.last(0).rejected.out_of_bounds >= 8,
        "{:?}",
        team.last(0).rejected
    );
    // The peer is good again: the stop clears (an Idle hold, no safety stop) ...
    team.units[1].tamper = None;
    team.run(5);
    for i in 0..2 {
        assert_eq!(team.last(i).hold, Some(HoldReason::Idle), "unit {i}");
    }
    // ... and the next start runs: the team lifts and moves again.
    team.operator(OperatorCommand::Start { mission: 9 });
    team.run(30);
    assert_eq!((team.phase(0), team.phase(1)), (Phase::Lift, Phase::Lift));
    let log = &team.units[0].log;
    let recent = &log[log.len() - 20..];
    assert!(recent
        .iter()
        .any(|r| r.hold.is_none() && r.issued != r.team_previous[0]));
    assert_eq!(team.units[0].onboard.fault(), None);
}

#[test]
fn forged_replayed_and_foreign_messages_are_rejected_and_counted() {
    let mut team = lifting();
    let before = team.units[0].log.len();
    // A forger without the key: a stop, a start with the largest mission, and a unit message
    // with the largest sequence number, all under a key of its own.
    let forger = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let mut envelope = Envelope {
        version: PROTOCOL_VERSION,
        team: "moonhaul".into(),
        sender: Sender::Operator,
        seq: u64::MAX,
        stamp_us: team.now_us,
        body: Body::Operator(OperatorCommand::Start { mission: u32::MAX }),
    };
    let forged_start = forger
        .sealer(Sender::Operator)
        .unwrap()
        .seal(&envelope)
        .unwrap();
    envelope.body = Body::Operator(OperatorCommand::Stop { mission: None });
    let forged_stop = forger
        .sealer(Sender::Operator)
        .unwrap()
        .seal(&envelope)
        .unwrap();
    team.injected.push(forged_start);
    team.injected.push(forged_stop);
    // A replay of a real message of unit 1.
    let replay = team.outbox[1].clone();
    team.tick(|_, _| true);
    team.injected.push(replay);
    // Another team's unit, with that team's valid key.
    let other = KeyFile::generate("rivals", 2, 1).unwrap();
    let foreign = Envelope {
        version: PROTOCOL_VERSION,
        team: "rivals".into(),
        sender: Sender::Unit(1),
        seq: u64::MAX / 2,
        stamp_us: team.now_us,
        body: Body::Operator(OperatorCommand::Stop { mission: None }),
    };
    if let Ok(frame) = other.sealer(Sender::Unit(1)).unwrap().seal(&foreign) {
        team.injected.push(frame);
    }
    team.run(10);
    // Nothing of it had an effect: the mission goes on (in step), and the real operator is
    // still obeyed.
    assert_eq!(team.phase(0), team.phase(1));
    assert_ne!(team.phase(0), Phase::Idle);
    assert!(team.units.iter().all(|u| u.log[before..]
        .iter()
        .all(|r| !matches!(r.hold, Some(HoldReason::SafetyStop(_))))));
    let counts = team.last(0).rejected;
    assert!(counts.bad_mac >= 2, "{counts:?}");
    assert!(counts.duplicate + counts.reordered >= 1, "{counts:?}");
    assert!(counts.total() >= 4, "{counts:?}");
    team.operator(OperatorCommand::Stop { mission: Some(7) });
    team.run(1);
    holds_for(&team, 0, |r| r == StopReason::Operator);
}

#[test]
fn a_clock_offset_beyond_the_bound_stops_the_team() {
    let mut team = lifting();
    // Unit 1's clock jumps 200 ms ahead: its messages are from the future for unit 0, and unit
    // 0's are stale for it.
    team.units[1].clock_offset_us = 200_000;
    team.run(6);
    holds_for(&team, 0, |r| matches!(r, StopReason::PeerStale { unit: 1 }));
    holds_for(&team, 1, |r| {
        matches!(
            r,
            StopReason::PeerStale { unit: 0 } | StopReason::PeerStop { unit: 0 }
        )
    });
    assert!(team.last(0).rejected.from_future > 0);
}

#[test]
fn a_nan_policy_output_is_a_fault_that_stops_the_team() {
    let mut team = lifting();
    team.units[0].onboard.inject_policy_nan();
    team.run(3);
    holds_for(&team, 0, |r| matches!(r, StopReason::Fault(_)));
    holds_for(&team, 1, |r| r == StopReason::PeerStop { unit: 0 });
}
