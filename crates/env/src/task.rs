//! The tasks a config can name, and what each needs: its batched environment and how its
//! exported policy identifies itself.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use moonhaul_core::scripted::MissionPlan;
use moonhaul_core::state::Phase;

use moonhaul_core::observation::{
    layout_fields, LAYOUT_FIELDS_KEY, LAYOUT_VERSION_KEY, OBS_LAYOUT_VERSION,
};
use moonhaul_sim::handover::HandOverFile;
use moonhaul_sim::task::TaskConfig;
use moonhaul_sim::{SceneModel, SimConfig};

use crate::config::{Task, TrainConfig};
use crate::env::VecEnv;
use crate::pendulum::PendulumVecEnv;
use crate::phase_env::{HandOverStarts, PhaseVecEnv};
use crate::EnvError;

/// `num_envs` environments of the config's task: pendulums, or simulated worlds of a phase
/// task (two rows each, one per unit; see [`crate::phase_env`]), with the scripted expert of
/// `[warm_start] mission` where the config has a warm start.
///
/// `payload_file`, a payload URDF (see [`moonhaul_sim::scene`]), replaces the sim config's
/// `randomization.payloads`, so every world carries it and the action map is built around its
/// grasp. It is an argument, not a config field, because configs name payloads only by their
/// shipped names; a run trained on a file needs the same file again to resume or export.
///
/// The env is `Send`, so a caller may step it on a thread of its own (the Python extension
/// steps it with the interpreter's lock released).
pub fn make_env(
    config: &TrainConfig,
    num_envs: usize,
    payload_file: Option<&Path>,
) -> Result<Box<dyn VecEnv + Send>, EnvError> {
    let task = config.run.task;
    let phase = match task {
        Task::Pendulum if payload_file.is_some() => {
            return Err(EnvError::InvalidConfig {
                field: "run.task".into(),
                reason: "the pendulum task carries no payload; a payload file needs a robot task"
                    .into(),
            })
        }
        Task::Pendulum => return Ok(Box::new(PendulumVecEnv::new(num_envs))),
        Task::Lift => Some(Phase::Lift),
        Task::Transport => Some(Phase::Transport),
        Task::Place => Some(Phase::Place),
        Task::Mission => None,
    };
    let missing = |section: &str| EnvError::InvalidConfig {
        field: section.into(),
        reason: format!("the {} task needs it", task.name()),
    };
    let world = config.world.as_ref().ok_or_else(|| missing("world"))?;
    let reward = config.reward.ok_or_else(|| missing("reward"))?;
    let sim = SimConfig::load(&world.sim)?;
    let tasks = TaskConfig::load(&world.tasks)?;
    let sync = moonhaul_coord::SyncConfig::from_file(&world.sync)?;
    let mut scene = SceneModel::new(sim)?;
    if let Some(path) = payload_file {
        let kind = scene.add_payload_file(path)?;
        scene.config.randomization.payloads = vec![kind];
    }
    let starts = match (&world.handovers, phase) {
        (Some(path), Some(phase)) => {
            let handovers = HandOverFile::load(path, phase)?;
            // Checked here, where the file can be named; the replay checks again.
            for (k, h) in handovers.iter().enumerate() {
                h.check(&scene)
                    .map_err(|reason| moonhaul_sim::handover::HandOverFileError {
                        path: path.clone(),
                        reason: format!("hand-over {k} into {phase}: {reason}"),
                    })?;
            }
            HandOverStarts {
                handovers: handovers.into_iter().map(Arc::new).collect(),
                fraction: world.handover_fraction,
            }
        }
        _ => HandOverStarts::default(),
    };
    let episode_s = match (world.episode_s, phase) {
        (Some(episode_s), Some(phase)) if episode_s < tasks.duration_s(phase) => {
            return Err(EnvError::InvalidConfig {
                field: "world.episode_s".into(),
                reason: format!(
                    "{episode_s} s is shorter than the {phase} phase's duration_s ({} s in {}): \
                     the episode would end before its phase clock does",
                    tasks.duration_s(phase),
                    world.tasks.display()
                ),
            })
        }
        (episode_s, _) => episode_s,
    };
    let mut env = PhaseVecEnv::new(
        phase,
        scene,
        (tasks, sync),
        reward,
        config.ppo.gamma,
        num_envs,
        config.run.threads,
    )?
    .with_handover_starts(starts)?;
    if let Some(episode_s) = episode_s {
        env = env.with_episode_s(episode_s);
    }
    // The scripted expert DAgger clones (moonhaul_learn::distill), only where a warm start asks
    // for it.
    if let Some(warm) = &config.warm_start {
        env = env.with_expert(MissionPlan::load(&warm.mission)?);
    }
    Ok(Box::new(env))
}

/// The phase recorded in an exported policy, and a `task` metadata entry.
///
/// The policy format (version 1) requires a phase. A benchmark task has none, so its policy
/// is labelled `lift` — the first phase, never used for a robot mission by a 3-input policy,
/// whose observation size the runtime checks — and the `task` key says what it really is.
pub fn export_identity(task: Task) -> (Phase, BTreeMap<String, String>) {
    let (phase, name) = match task {
        Task::Pendulum => (Phase::Lift, "pendulum-v1"),
        Task::Lift => (Phase::Lift, "lift"),
        Task::Transport => (Phase::Transport, "transport"),
        Task::Place => (Phase::Place, "place"),
        // Like the benchmark, the baseline has no phase of its own; `task` says what it is.
        Task::Mission => (Phase::Lift, "mission"),
    };
    let mut extra = BTreeMap::from([("task".to_string(), name.to_string())]);
    if task != Task::Pendulum {
        // The onboard runtime refuses a policy whose observation layout is not its own.
        extra.insert(LAYOUT_VERSION_KEY.into(), OBS_LAYOUT_VERSION.to_string());
        extra.insert(LAYOUT_FIELDS_KEY.into(), layout_fields());
    }
    (phase, extra)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_task_builds_its_env() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/");
        for (name, rows) in [
            ("pendulum", 3),
            ("lift", 6),
            ("transport", 6),
            ("place", 6),
            ("mission", 6),
        ] {
            let mut config = TrainConfig::load(format!("{dir}{name}.toml")).unwrap();
            // The hand-over file is made by `moonhaul sim handovers` (train-all does): settled
            // starts here; tests/handover_starts.rs trains from a captured fixture.
            if let Some(world) = &mut config.world {
                world.handovers = None;
                world.handover_fraction = 0.0;
            }
            let env = make_env(&config, 3, None).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(env.num_envs(), rows, "{name}");
            assert!(env.max_episode_steps().is_some_and(|n| n > 0), "{name}");
        }
    }

    #[test]
    fn episode_s_runs_episodes_past_the_phase_clock_and_never_short_of_it() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/");
        let mut config = TrainConfig::load(format!("{dir}place.toml")).unwrap();
        let world = config.world.as_mut().unwrap();
        (world.handovers, world.handover_fraction) = (None, 0.0);
        let steps = |config: &TrainConfig| make_env(config, 1, None).map(|e| e.max_episode_steps());
        // tasks.toml: an 8 s placement at 50 Hz.
        assert_eq!(steps(&config).unwrap(), Some(400));
        config.world.as_mut().unwrap().episode_s = Some(12.0);
        assert_eq!(steps(&config).unwrap(), Some(600));
        config.world.as_mut().unwrap().episode_s = Some(5.0);
        let err = steps(&config).err().unwrap().to_string();
        assert!(
            err.contains("world.episode_s") && err.contains("tasks.toml"),
            "{err}"
        );
    }

    #[test]
    fn a_payload_file_replaces_the_training_payloads() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../");
        let config =
            |name: &str| TrainConfig::load(format!("{dir}configs/train/{name}.toml")).unwrap();
        let lift = config("lift");
        let sledge = Path::new(dir).join("assets/payload_sledge.urdf");
        make_env(&lift, 1, Some(&sledge)).unwrap();
        let unit = Path::new(dir).join("assets/unit.urdf");
        let err = make_env(&lift, 1, Some(&unit)).err().unwrap().to_string();
        assert!(err.contains("unit.urdf"), "{err}");
        assert!(make_env(&config("pendulum"), 1, Some(&sledge)).is_err());
    }
}
