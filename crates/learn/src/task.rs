//! The tasks a config can name, and what each needs: its batched environment and how its
//! exported policy identifies itself.

use std::collections::BTreeMap;

use moonhaul_core::state::Phase;

use crate::config::Task;
use crate::env::VecEnv;
use crate::pendulum::PendulumVecEnv;
use crate::LearnError;

/// `num_envs` environments of `task`. The robot phase tasks have no reward, reset or
/// termination in this build and are refused with a clear error.
pub fn make_env(task: Task, num_envs: usize) -> Result<Box<dyn VecEnv>, LearnError> {
    match task {
        Task::Pendulum => Ok(Box::new(PendulumVecEnv::new(num_envs))),
        Task::Lift | Task::Transport | Task::Place => Err(LearnError::TaskUnavailable {
            task: task.name().into(),
            reason: "this build defines no reward, reset or termination for the phase tasks; \
                     only `pendulum` can be trained"
                .into(),
        }),
    }
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
    };
    (
        phase,
        BTreeMap::from([("task".to_string(), name.to_string())]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phase_tasks_are_a_clear_error() {
        for task in [Task::Lift, Task::Transport, Task::Place] {
            let err = make_env(task, 4).err().expect("unavailable");
            assert!(
                matches!(&err, LearnError::TaskUnavailable { task: t, .. } if t == task.name())
            );
            assert!(err.to_string().contains("not available"));
        }
        assert_eq!(
            make_env(Task::Pendulum, 4).map(|e| e.num_envs()).ok(),
            Some(4)
        );
    }
}
