//! The observation contract: what a training task computes from the simulator's sensed
//! readings equals what a unit's daemon computes from its own readings and its peer's state as
//! decoded from the wire (coord's message codec), bit for bit: the sensed fields, the commands
//! (own: what the pipeline issued; the peer's: its published command) and the pipeline's last
//! step (layout 3).

use moonhaul_coord::message::{Announcements, Body, Envelope, Sender, UnitTick, PROTOCOL_VERSION};
use moonhaul_coord::{KeyFile, TeamSettings, Validator};
use moonhaul_core::observation::{field_range, unit_observation, CommandState, ACTOR_OBS_DIM};
use moonhaul_core::state::{Phase, UnitCommand};
use moonhaul_core::unit::UnitSpec;
use moonhaul_sim::task::{PhaseTask, TaskConfig};
use moonhaul_sim::{BatchEnv, SceneModel, SimConfig};

#[test]
fn sim_and_onboard_observations_agree_bit_for_bit() {
    let keys = KeyFile::generate("moonhaul", 2, 1).unwrap();
    let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
    // What a daemon loads: the unit URDF, on its own.
    let spec = UnitSpec::from_file(&scene.config.unit_urdf()).unwrap();
    let task = PhaseTask::new(
        Phase::Transport,
        TaskConfig::shipped().unwrap(),
        moonhaul_coord::SyncConfig::shipped().unwrap(),
        &scene,
    )
    .unwrap();
    let mut batch = BatchEnv::new(scene.clone(), 1, 7, task.env_options(true, None), 1).unwrap();
    let mut rng = PhaseTask::rng(7);
    let mut episode = task
        .begin(&scene, &batch.envs()[0], &batch.states()[0], &mut rng)
        .unwrap();
    let mut slots = [(episode.clone(), rng, [UnitCommand::default(); 2])];
    // Forward, with one arm joint pushed against the chain so the commands lead the joints.
    let forward = [0.3, 0.3, 0.0, 0.4, 0.0, -0.3, 0.0, 0.0, 0.0];
    let mut seen_offset = false;
    for tick in 0..40u64 {
        batch
            .for_each_with(&mut slots, |scene, env, state, (episode, rng, issued)| {
                let delta = task.increment(&forward);
                *issued = episode.commands(&task, &[delta, delta])?;
                env.step(scene, issued);
                env.state_into(scene, state);
                episode.advance(&task, scene, env, state, rng);
                Ok::<_, moonhaul_sim::SimError>(())
            })
            .unwrap();
        episode = slots[0].0.clone();
        let issued = slots[0].2;
        let reports = episode.reports().unwrap();
        for unit in 0..2 {
            let peer = 1 - unit;
            let mut from_sim = [0.0; ACTOR_OBS_DIM];
            episode.observe(&task, &scene, unit, &mut from_sim).unwrap();

            let message = Envelope {
                version: PROTOCOL_VERSION,
                team: "moonhaul".into(),
                sender: Sender::Unit(peer),
                seq: tick + 1,
                stamp_us: tick * 20_000,
                body: Body::Unit(UnitTick {
                    phase: Phase::Transport,
                    // Published at the end of the peer's previous tick: a tick old.
                    state: *episode.published(peer),
                    command: issued[peer],
                    announce: Announcements::default(),
                }),
            };
            let mut validator = Validator::new(
                &TeamSettings {
                    team: "moonhaul".into(),
                    team_size: 2,
                    unit_index: unit,
                    control_period_us: 20_000,
                    peer_staleness_periods: 3,
                },
                &keys,
                moonhaul_coord::message::MessageBounds::shipped().unwrap(),
            )
            .unwrap();
            let frame = keys
                .sealer(Sender::Unit(peer))
                .unwrap()
                .seal(&message)
                .unwrap();
            let received = validator.receive_frame(&frame, tick * 20_000).unwrap();
            let Body::Unit(peer_tick) = received.body else {
                panic!("not a unit message");
            };
            let commands = CommandState {
                own: issued[unit],
                peer: peer_tick.command,
                last_t_max: reports[unit].clamp.t_max,
                last_held: reports[unit].clamp.hold.is_some(),
            };
            let mut onboard = [0.0; ACTOR_OBS_DIM];
            unit_observation(
                &spec,
                episode.reference(unit),
                episode.sensed(unit),
                &peer_tick.state,
                &commands,
                &episode.goal(&task, unit),
                &mut onboard,
            )
            .unwrap();
            let offset = &onboard[field_range("own.arm_command_minus_sensed_rad").unwrap()];
            seen_offset |= offset.iter().any(|v| v.abs() > 1e-3);
            assert_eq!(
                from_sim.map(f64::to_bits),
                onboard.map(f64::to_bits),
                "tick {tick} unit {unit}"
            );
        }
    }
    assert!(
        seen_offset,
        "the commands never led the joints: the test compared zeros"
    );
}
