//! The onboard tick does not allocate: a counting global allocator watches this thread while a
//! two-unit team on mock hardware takes in its peer's message and ticks — through Idle, a
//! start, the lift, a drive fault and the stop it causes. (Decoding frames off the network and
//! encoding the log record, outside the tick, do allocate.)

use std::time::Duration;

use moonhaul_coord::message::{
    Body, Envelope, OperatorCommand, RejectCounts, Sender, PROTOCOL_VERSION,
};
use moonhaul_coord::TeamSettings;
use moonhaul_core::config::repo_file;
use moonhaul_core::scripted::MissionPlan;
use moonhaul_core::state::{Phase, PlanarPose};
use moonhaul_deploy::cli_support::load_policies;
use moonhaul_deploy::daemon::mock_hardware;
use moonhaul_deploy::record::TickRecord;
use moonhaul_deploy::tick::{Controller, Onboard, OnboardSettings};
use moonhaul_deploy::unit_config::UnitConfig;
use moonhaul_hal::unit::{FaultInjection, InjectedFault, MockUnit, UnitHardware, UnitReading};

#[path = "../../coord/tests/support/counting_alloc.rs"]
mod counting_alloc;
use counting_alloc::counted;

const PERIOD_US: u64 = 20_000;

fn unit(i: usize, scripted: bool) -> (Onboard, MockUnit) {
    let team = TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: i,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    };
    let pose = PlanarPose {
        x_m: 0.0,
        y_m: if i == 0 { -0.8 } else { 0.8 },
        yaw_rad: if i == 0 { 0.0 } else { std::f64::consts::PI },
    };
    let settings = OnboardSettings::shipped(team, pose).unwrap();
    let config = UnitConfig::from_file(&repo_file("configs/unit.toml")).unwrap();
    let mut hw = mock_hardware(&config, &settings.spec, Duration::from_micros(PERIOD_US)).unwrap();
    hw.activate().unwrap();
    let onboard = Onboard::new(
        settings,
        if scripted {
            Controller::Scripted(MissionPlan::shipped().unwrap())
        } else {
            Controller::Learned(Box::new(
                load_policies(&repo_file("assets/policies")).unwrap(),
            ))
        },
        0,
    )
    .unwrap();
    (onboard, hw)
}

/// The message the unit's last tick produced (cloned outside the counted section).
fn onboard_message(onboard: &mut Onboard) -> Envelope {
    onboard.last_message().clone()
}

#[test]
fn the_tick_does_not_allocate_with_the_policies() {
    tick_without_allocating(false);
}

#[test]
fn the_tick_does_not_allocate_with_the_scripted_controller() {
    tick_without_allocating(true);
}

fn tick_without_allocating(scripted: bool) {
    let mut units = [unit(0, scripted), unit(1, scripted)];
    let mut records = [TickRecord::for_team(2), TickRecord::for_team(2)];
    let mut outbox: [Option<Envelope>; 2] = [None, None];
    let start = Envelope {
        version: PROTOCOL_VERSION,
        team: "moonhaul".into(),
        sender: Sender::Operator,
        seq: 1,
        stamp_us: 0,
        body: Body::Operator(OperatorCommand::Start { mission: 1 }),
    };
    let rejected = RejectCounts::default();
    let mut reading = UnitReading::default();
    let mut lifted = false;
    // Allocations in the tick (with the messages it takes in), and in the mock drives' read
    // and write while no fault is latched (a HAL error carries its joint's name as a String).
    let (mut in_tick, mut in_hardware) = (0, 0);
    for k in 1..=400u64 {
        let now = k * PERIOD_US;
        if k == 300 {
            units[1]
                .1
                .inject(InjectedFault::Motor { joint: 4 })
                .unwrap();
        }
        let inbox = std::mem::take(&mut outbox);
        for (i, (onboard, hw)) in units.iter_mut().enumerate() {
            let healthy = k > 1 && k < 300;
            let mut read = Ok(());
            let n = counted(|| read = hw.read(&mut reading));
            in_hardware += if healthy { n } else { 0 };
            if hw.fault().is_some() {
                onboard.latch_fault(moonhaul_coord::message::FaultKind::Drive, "drive fault");
            }
            let mut output = None;
            in_tick += counted(|| {
                if let Some(m) = &inbox[1 - i] {
                    onboard.receive(m);
                }
                if k == 10 {
                    onboard.receive(&start);
                }
                let out = onboard.tick(
                    now,
                    read.is_ok().then_some(&reading),
                    &rejected,
                    &mut records[i],
                );
                output = Some(out.output);
            });
            outbox[i] = Some(onboard_message(onboard));
            let output = output.unwrap();
            let n = counted(|| {
                let _ = hw.write(&output);
            });
            in_hardware += if healthy { n } else { 0 };
        }
        lifted |= records[0].phase == Phase::Lift && records[0].hold.is_none();
    }
    assert_eq!(in_tick, 0, "allocations in ticks");
    assert_eq!(
        in_hardware, 0,
        "allocations in healthy hardware reads and writes"
    );
    assert!(lifted, "the team flew");
    assert!(records[1].fault.is_some(), "the fault latched");
}
