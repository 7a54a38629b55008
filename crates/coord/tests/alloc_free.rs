//! The per-tick path (agreement + gate + clamp for N = 2) does not allocate: a counting global
//! allocator watches this thread while ticks run through every clamp outcome.

use moonhaul_coord::gate::Measurements;
use moonhaul_coord::message::{
    Announcements, Body, Envelope, OperatorCommand, Sender, Transition, UnitTick, PROTOCOL_VERSION,
};
use moonhaul_coord::{
    Clamp, ClampInput, Directive, GateConfig, SyncConfig, Team, TeamSettings, UnitModel,
};
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand, UnitState};
mod support {
    pub mod counting_alloc;
}
use support::counting_alloc::counted;

const PERIOD_US: u64 = 20_000;

fn peer(stamp_us: u64, phase: Phase, propose: Option<Transition>) -> Envelope {
    Envelope {
        version: PROTOCOL_VERSION,
        team: "moonhaul".into(),
        sender: Sender::Unit(1),
        seq: stamp_us,
        stamp_us,
        body: Body::Unit(UnitTick {
            phase,
            state: UnitState::default(),
            command: UnitCommand::default(),
            announce: Announcements {
                propose,
                ..Announcements::default()
            },
        }),
    }
}

#[test]
fn gate_agreement_and_clamp_do_not_allocate_per_tick() {
    let path = moonhaul_core::config::repo_file("assets/unit.urdf");
    let model = UnitModel::from_urdf(&path).unwrap();
    let settings = TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: 0,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    };
    let mut team = Team::new(settings, &GateConfig::shipped().unwrap()).unwrap();
    let mut clamp = Clamp::new(model, &SyncConfig::shipped().unwrap(), 0.02, 2).unwrap();
    let home = [0.0, -0.4, 0.0, -2.0, 0.0, 1.6, 0.8];
    let mut sensed = [UnitState::default(); 2];
    for (i, s) in sensed.iter_mut().enumerate() {
        s.arm.position_rad = home;
        s.base_pose = PlanarPose {
            x_m: 0.0,
            y_m: 1.2 * i as f64,
            yaw_rad: 0.0,
        };
    }
    let previous = [UnitCommand {
        wheel_velocity_radps: [2.0, 2.0],
        arm_position_rad: home,
    }; 2];
    let mut clamped = previous;
    clamped[1].arm_position_rad[1] += 0.3;
    // Unit 0 already drives 0.03 m per period (1.5 Δ_w) and keeps doing so: nothing admissible.
    let mut runaway = previous;
    runaway[0].wheel_velocity_radps = [15.0, 15.0];
    let cases = [
        (previous, previous),
        (previous, clamped),
        (runaway, runaway),
    ];
    let forces = [30.0, 30.0];

    // Messages are built outside the watched region (decoding allocates; it is not per-tick
    // coordination work), then fed in.
    let start = Envelope {
        sender: Sender::Operator,
        body: Body::Operator(OperatorCommand::Start { mission: 1 }),
        ..peer(0, Phase::Idle, None)
    };
    let lift = Transition {
        mission: 1,
        from: Phase::Idle,
        to: Phase::Lift,
    };
    let transport = Transition {
        mission: 1,
        from: Phase::Lift,
        to: Phase::Transport,
    };
    let script: Vec<(Envelope, f64)> = (1..=300u64)
        .map(|k| {
            let now = k * PERIOD_US;
            // Idle, then Lift with the payload rising, then the peer proposes Transport.
            let (phase, propose) = match k {
                ..=20 => (Phase::Idle, (k > 10).then_some(lift)),
                21..=64 => (Phase::Lift, None),
                _ => (Phase::Lift, Some(transport)),
            };
            (peer(now, phase, propose), if k > 60 { 0.3 } else { 0.0 })
        })
        .collect();

    let mut issued = [UnitCommand::default(); 2];
    let mut outcomes = [0u32; 4];
    let allocations = counted(|| {
        for (k, (message, height)) in script.iter().enumerate() {
            let now = message.stamp_us;
            if k == 10 {
                team.receive(&start);
            }
            team.receive(message);
            let measured = Measurements {
                payload_height_m: *height,
                goal_distance_m: 1.0,
                wheel_speed_radps: 0.0,
                grasp_force_n: &forces,
            };
            let decision = team.tick(now, &measured, None);
            let (previous, target) = &cases[k % 3];
            let input = ClampInput {
                sensed: &sensed,
                previous,
                target,
            };
            let report = clamp.step(&input, decision.hold(), &mut issued).unwrap();
            let slot = match (decision.directive, report.hold) {
                (Directive::Run(_), None) if report.t_max == 1.0 => 0,
                (Directive::Run(_), None) => 1,
                (Directive::Run(_), Some(_)) => 2,
                (Directive::Hold(_), _) => 3,
            };
            outcomes[slot] += 1;
        }
    });
    assert_eq!(allocations, 0, "{allocations} allocations in 300 ticks");
    // Every path ran: full steps, clamped steps, no admissible step, requested holds.
    assert!(outcomes.iter().all(|&n| n > 0), "{outcomes:?}");
    assert_eq!(team.phase(), Phase::Transport);
}
