//! Per-tick time of the coordination layer for a team of two: the phase gate with team
//! agreement, then the synchronization clamp, on the shipped unit (assets/unit.urdf); and the
//! cost of sealing and receiving one authenticated peer frame.
//! Prints figures; asserts nothing about time. Run: `cargo bench -p moonhaul-coord`.

use moonhaul_coord::gate::Measurements;
use moonhaul_coord::message::{
    Announcements, Body, Envelope, OperatorCommand, Sender, Transition, UnitTick, PROTOCOL_VERSION,
};
use moonhaul_coord::{
    Clamp, ClampInput, GateConfig, KeyFile, SyncConfig, Team, TeamSettings, UnitModel, Validator,
};
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand, UnitState};
use std::hint::black_box;
use std::time::Instant;

const PERIOD_US: u64 = 20_000;
const TICKS: u32 = 20_000;

fn main() {
    let path = moonhaul_core::config::repo_file("assets/unit.urdf");
    let model = match UnitModel::from_urdf(&path) {
        Ok(model) => model,
        Err(e) => {
            eprintln!("cannot load the unit: {e}");
            std::process::exit(1);
        }
    };
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
    let mut small = previous;
    small[0].arm_position_rad[3] += 0.01;
    // Unit 0's wheels jump to 12 rad/s: just over Δ_w, so t_max is a little below 1.
    let mut slightly = previous;
    slightly[0].wheel_velocity_radps = [12.0, 12.0];
    let mut large = previous;
    large[1].arm_position_rad[1] += 0.3;
    large[0].wheel_velocity_radps = [30.0, 30.0];
    // Unit 0 already drives 0.03 m per period (1.5 Δ_w) and keeps doing so.
    let mut runaway = previous;
    runaway[0].wheel_velocity_radps = [15.0, 15.0];
    let scenarios = [
        (
            "admissible target (t_max = 1, one evaluation)",
            previous,
            small,
        ),
        ("slightly clamped (scan + bisection)", previous, slightly),
        ("strongly clamped (scan + bisection)", previous, large),
        ("nothing admissible: hold after the scan", runaway, runaway),
    ];
    println!("coordination tick for N = 2 (gate + agreement + clamp), {TICKS} ticks each:");
    for (name, previous, target) in scenarios {
        let mut team = running_team();
        let mut peer = peer_state(1_000_000, Phase::Lift);
        let mut clamp = match Clamp::new(model.clone(), &SyncConfig::shipped().unwrap(), 0.02, 2) {
            Ok(clamp) => clamp,
            Err(e) => {
                eprintln!("cannot build the clamp: {e}");
                std::process::exit(1);
            }
        };
        let forces = [30.0, 30.0];
        let measured = Measurements {
            payload_height_m: 0.1,
            goal_distance_m: 2.0,
            wheel_speed_radps: 0.0,
            grasp_force_n: &forces,
        };
        let input = ClampInput {
            sensed: &sensed,
            previous: &previous,
            target: &target,
        };
        let mut issued = [UnitCommand::default(); 2];
        let mut now_us = 1_000_000;
        let mut t_max = f64::NAN;
        let started = Instant::now();
        for _ in 0..TICKS {
            now_us += PERIOD_US;
            (peer.seq, peer.stamp_us) = (now_us, now_us);
            team.receive(&peer);
            let decision = team.tick(now_us, black_box(&measured), None);
            if let Ok(report) = clamp.step(black_box(&input), decision.hold(), &mut issued) {
                t_max = report.t_max;
            }
            black_box(&issued);
        }
        let per_tick_us = started.elapsed().as_secs_f64() * 1e6 / f64::from(TICKS);
        println!(
            "  {name:<54} {per_tick_us:8.2} us/tick  {:>9.0} ticks/s  ({:.4}% of a 20 ms period, t_max {t_max:.4})",
            1e6 / per_tick_us,
            per_tick_us / 200.0,
        );
    }
    frames();
}

/// Seal (unit 1) and authenticate + decode + validate (unit 0) one unit-state frame.
fn frames() {
    let settings = TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: 0,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    };
    let keys = KeyFile::generate("moonhaul", 2, 1);
    let Ok(bounds) = moonhaul_coord::message::MessageBounds::shipped() else {
        eprintln!("cannot read the shipped unit model for the frame bench");
        std::process::exit(1);
    };
    let (sealer, mut validator) = match keys.map(|keys| {
        let sealer = keys.sealer(Sender::Unit(1));
        (sealer, Validator::new(&settings, &keys, bounds))
    }) {
        Ok((Ok(sealer), Ok(validator))) => (sealer, validator),
        _ => {
            eprintln!("cannot set up the frame bench");
            std::process::exit(1);
        }
    };
    let mut peer = peer_state(1_000_000, Phase::Lift);
    let mut frame = Vec::new();
    let (mut seal_s, mut receive_s, mut accepted) = (0.0, 0.0, 0u32);
    let mut now_us = 1_000_000;
    for _ in 0..TICKS {
        now_us += PERIOD_US;
        (peer.seq, peer.stamp_us) = (now_us, now_us);
        let started = Instant::now();
        if sealer.seal_into(black_box(&peer), &mut frame).is_err() {
            continue;
        }
        seal_s += started.elapsed().as_secs_f64();
        let started = Instant::now();
        accepted += u32::from(validator.receive_frame(black_box(&frame), now_us).is_ok());
        receive_s += started.elapsed().as_secs_f64();
    }
    let n = f64::from(TICKS);
    println!(
        "peer frame ({} bytes): seal {:.2} us, receive (HMAC + JSON + checks) {:.2} us; {accepted} of {TICKS} accepted",
        frame.len(),
        seal_s * 1e6 / n,
        receive_s * 1e6 / n,
    );
}

/// Unit 0 of a two-unit team, already in Lift.
fn running_team() -> Team {
    let settings = TeamSettings {
        team: "moonhaul".into(),
        team_size: 2,
        unit_index: 0,
        control_period_us: PERIOD_US,
        peer_staleness_periods: 3,
    };
    let mut team = match Team::new(settings, &GateConfig::shipped().unwrap()) {
        Ok(team) => team,
        Err(e) => {
            eprintln!("bad team settings: {e}");
            std::process::exit(1);
        }
    };
    let start = Envelope {
        version: PROTOCOL_VERSION,
        team: "moonhaul".into(),
        sender: Sender::Operator,
        seq: 1,
        stamp_us: 1_000_000,
        body: Body::Operator(OperatorCommand::Start { mission: 1 }),
    };
    team.receive(&peer_state(1_000_000, Phase::Idle));
    team.receive(&start);
    let forces = [30.0, 30.0];
    let measured = Measurements {
        payload_height_m: 0.0,
        goal_distance_m: 2.0,
        wheel_speed_radps: 0.0,
        grasp_force_n: &forces,
    };
    team.tick(1_000_000, &measured, None);
    let mut propose = peer_state(1_000_001, Phase::Idle);
    if let Body::Unit(tick) = &mut propose.body {
        tick.announce.propose = Some(Transition {
            mission: 1,
            from: Phase::Idle,
            to: Phase::Lift,
        });
    }
    team.receive(&propose);
    let decision = team.tick(1_000_000, &measured, None);
    assert_eq!(
        decision.phase,
        Phase::Lift,
        "bench setup: the team did not start"
    );
    team
}

fn peer_state(now_us: u64, phase: Phase) -> Envelope {
    Envelope {
        version: PROTOCOL_VERSION,
        team: "moonhaul".into(),
        sender: Sender::Unit(1),
        seq: now_us,
        stamp_us: now_us,
        body: Body::Unit(UnitTick {
            phase,
            state: UnitState::default(),
            command: UnitCommand::default(),
            announce: Announcements::default(),
        }),
    }
}
