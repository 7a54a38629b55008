//! Transport training from a captured hand-over: the fixture is the first transport hand-over
//! of `moonhaul sim handovers --payload box --episodes 2 --seed 7` (scripted, deployed stack),
//! recaptured whenever the simulator or the onboard tick changes what a mission does (the
//! replay's check then fails, naming the file). A world of the training batch replays it and
//! starts its episodes there, observed exactly as the simulator's own hand-over start; a
//! config mixing hand-over and settled worlds trains.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use moonhaul_core::observation::ACTOR_OBS_DIM;
use moonhaul_core::state::Phase;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::metrics::MetricsRow;
use moonhaul_learn::task::make_env;
use moonhaul_learn::trainer::{train, TrainOptions};
use moonhaul_sim::handover::HandOverFile;
use moonhaul_sim::task::{PhaseTask, TaskConfig, CRITIC_OBS_DIM};
use moonhaul_sim::{Env, SceneModel, SimConfig};

fn fixture() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/handover_transport_box.json"
    ))
}

fn transport_config(fraction: f64) -> TrainConfig {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../configs/train/transport.toml"
    );
    let mut config = TrainConfig::load(path).unwrap();
    let world = config.world.as_mut().unwrap();
    world.handovers = Some(fixture());
    world.handover_fraction = fraction;
    config
}

#[test]
fn a_batch_world_starts_its_episodes_at_the_captured_handover() {
    let config = transport_config(0.5);
    // Two worlds: the first replays the hand-over, the second starts settled.
    let mut env = make_env(&config, 2, None).unwrap();
    let seed = 3;
    let mut obs = vec![0.0; 4 * ACTOR_OBS_DIM];
    let mut critic = vec![0.0; 4 * CRITIC_OBS_DIM];
    env.reset(seed, &mut obs, &mut critic).unwrap();

    let world = config.world.as_ref().unwrap();
    let scene = SceneModel::new(SimConfig::load(&world.sim).unwrap()).unwrap();
    let tasks = TaskConfig::load(&world.tasks).unwrap();
    let sync = moonhaul_coord::SyncConfig::from_file(&world.sync).unwrap();
    let handover = &HandOverFile::load(&fixture(), Phase::Transport).unwrap()[0];
    let task = PhaseTask::new(Phase::Transport, tasks, sync, &scene).unwrap();
    let mut sim = Env::replay(&scene, handover).unwrap();
    sim.reset();
    let state = sim.state(&scene);
    let mut rng = PhaseTask::rng(moonhaul_sim::batch::env_seed(seed, 0));
    let episode = task
        .begin_handover(&scene, &state, handover, &mut rng)
        .unwrap();
    for i in 0..2 {
        let mut expected = [0.0; ACTOR_OBS_DIM];
        episode.observe(&task, &scene, i, &mut expected).unwrap();
        assert_eq!(&obs[i * ACTOR_OBS_DIM..(i + 1) * ACTOR_OBS_DIM], &expected);
    }
    // The settled world's units start with U = Y: its rows differ from the hand-over's.
    assert_ne!(
        &obs[..ACTOR_OBS_DIM],
        &obs[2 * ACTOR_OBS_DIM..3 * ACTOR_OBS_DIM]
    );
}

#[test]
fn transport_trains_on_a_mix_of_handover_and_settled_starts() {
    let mut config = transport_config(0.5);
    config.env.num_envs = 8;
    config.run.iterations = 2;
    config.run.eval_interval = 2;
    config.run.checkpoint_interval = 2;
    config.run.eval_episodes = 4;
    let dir = tempfile::tempdir().unwrap();
    let options = TrainOptions {
        run_dir: dir.path().join("run"),
        resume: None,
        stop: Arc::new(AtomicBool::new(false)),
        payload_file: None,
    };
    let mut rows = Vec::new();
    train(&config, &options, |row: &MetricsRow| rows.push(*row)).unwrap();
    assert_eq!(rows.len(), 2);
    assert!(rows
        .iter()
        .all(|r| r.mean_t_max.is_some() && r.hold_fraction.is_some()));
    assert!(rows[1].eval_return.is_some_and(f64::is_finite), "{rows:?}");
}

#[test]
fn a_config_names_its_handover_file_or_the_phase_it_lacks() {
    let mut config = transport_config(1.0);
    config.world.as_mut().unwrap().handovers = Some(PathBuf::from("/nonexistent/h.json"));
    let error = make_env(&config, 2, None).err().unwrap().to_string();
    assert!(error.contains("/nonexistent/h.json"), "{error}");

    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../configs/train/place.toml"
    );
    let mut place = TrainConfig::load(path).unwrap();
    let world = place.world.as_mut().unwrap();
    world.handovers = Some(fixture());
    world.handover_fraction = 0.5;
    let error = make_env(&place, 2, None).err().unwrap().to_string();
    assert!(
        error.contains("handover_transport_box.json") && error.contains("into place"),
        "{error}"
    );

    // A capture no mission can have made: a command beyond the joint limits, a non-finite
    // onboard state, too many ticks. Refused by file and capture before any replay.
    let text = std::fs::read_to_string(fixture()).unwrap();
    let file: HandOverFile = serde_json::from_str(&text).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut bent = file.clone();
    bent.handovers[0].commands[10][1].arm_position_rad[3] = 40.0;
    let mut odd = file.clone();
    odd.handovers[0].units[0].last_t_max = 7.0;
    let mut long = file.clone();
    let tick = long.handovers[0].commands[0];
    long.handovers[0].commands = vec![tick; moonhaul_sim::handover::MAX_REPLAY_TICKS + 1];
    for (name, forged, needle) in [
        ("bent", bent, "tick 10: unit 1"),
        ("odd", odd, "unit 0's onboard state"),
        ("long", long, "ticks of commands"),
    ] {
        let path = dir.path().join(format!("{name}.json"));
        std::fs::write(&path, serde_json::to_vec(&forged).unwrap()).unwrap();
        let mut config = transport_config(1.0);
        config.world.as_mut().unwrap().handovers = Some(path);
        let error = make_env(&config, 2, None).err().unwrap().to_string();
        assert!(
            error.contains(&format!("{name}.json"))
                && error.contains("hand-over 0")
                && error.contains(needle),
            "{error}"
        );
    }
}
