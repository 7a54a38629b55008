//! The batched-environment interface the trainer drives and the simulator's batched envs
//! implement.
//!
//! All buffers are flat, row-major `f64` slices (`env` major): `obs[i * obs_dim + k]` is
//! observation entry `k` of env `i`. The trainer converts to f32 tensors; env math stays f64.
//! A row is one agent: a task may drive several agents per simulated world with one shared
//! policy, so [`VecEnv::num_envs`] counts rows, not worlds.
//!
//! # Asymmetric actor–critic
//!
//! Each row has two observations (rsl_rl's `policy` and `critic` observation groups): `obs`,
//! what the actor and the exported policy see, and `critic_obs`, what the training-only critic
//! sees. The critic may read privileged simulator state the robot cannot measure, since it
//! never runs onboard; an env without such state reports `critic_obs = obs`.
//!
//! # Auto-reset
//!
//! [`VecEnv::step`] resets an env **in the same call** in which its episode ends (the
//! IsaacLab / rsl_rl convention): for such an env, `obs` and `critic_obs` already hold the
//! first observations of the next episode, `terminated` or `truncated` says why the old one
//! ended, and `final_obs` / `final_critic_obs` hold the observations the old episode ended in.
//! The trainer needs `final_critic_obs` to bootstrap time-outs with `γ V(s_final)`: a truncated
//! episode was cut by the clock, not finished, so its value did not drop to zero. Rows of
//! `final_obs` and `final_critic_obs` for envs that did not end are unspecified.

use moonhaul_coord::{ClampReport, ClampTally};

use crate::EnvError;

/// One batched step's outputs, reused across steps (allocate once with [`VecStep::new`]).
#[derive(Debug, Clone, PartialEq)]
pub struct VecStep {
    /// `[num_envs * obs_dim]`: observation after the step (after auto-reset where an episode
    /// ended).
    pub obs: Vec<f64>,
    /// `[num_envs * critic_obs_dim]`: critic observation after the step (after auto-reset).
    pub critic_obs: Vec<f64>,
    /// `[num_envs]`: reward of the transition.
    pub rewards: Vec<f64>,
    /// `[num_envs]`: the episode reached a terminal state (no value beyond it).
    pub terminated: Vec<bool>,
    /// `[num_envs]`: the episode was cut by the time limit (not terminal).
    pub truncated: Vec<bool>,
    /// `[num_envs * obs_dim]`: last observation of each episode that ended this step.
    pub final_obs: Vec<f64>,
    /// `[num_envs * critic_obs_dim]`: last critic observation of each episode that ended this
    /// step.
    pub final_critic_obs: Vec<f64>,
}

impl VecStep {
    pub fn new(num_envs: usize, obs_dim: usize, critic_obs_dim: usize) -> Self {
        VecStep {
            obs: vec![0.0; num_envs * obs_dim],
            critic_obs: vec![0.0; num_envs * critic_obs_dim],
            rewards: vec![0.0; num_envs],
            terminated: vec![false; num_envs],
            truncated: vec![false; num_envs],
            final_obs: vec![0.0; num_envs * obs_dim],
            final_critic_obs: vec![0.0; num_envs * critic_obs_dim],
        }
    }
}

/// A fixed-size batch of agent rows of one task (see the [module docs](self)).
///
/// Actions are the policy's raw outputs; an env maps them to its physical command as
/// `offset + scale ⊙ action` (then applies its own limits). [`VecEnv::action_scale`] and
/// [`VecEnv::action_offset`] report that map so the exported policy emits physical commands.
pub trait VecEnv {
    fn num_envs(&self) -> usize;
    fn obs_dim(&self) -> usize;
    fn action_dim(&self) -> usize;

    /// Width of the critic's (privileged) observation; equal to obs_dim for envs without
    /// privileged state. No default: every env states what its critic sees.
    fn critic_obs_dim(&self) -> usize;

    /// `[action_dim]` scale of the action map (default: identity).
    fn action_scale(&self) -> Vec<f64> {
        vec![1.0; self.action_dim()]
    }

    /// `[action_dim]` offset of the action map (default: none).
    fn action_offset(&self) -> Vec<f64> {
        vec![0.0; self.action_dim()]
    }

    /// Steps after which an episode is cut by its time limit (rsl_rl's `max_episode_length`),
    /// where the task has one; default none.
    fn max_episode_steps(&self) -> Option<u64> {
        None
    }

    /// Metadata the exported policy must carry for a runtime to run it as trained (the phase
    /// tasks' action map and its version); default none.
    fn policy_metadata(&self) -> Vec<(String, String)> {
        Vec::new()
    }

    /// Reseeds every env's randomness from `seed` (same seed, same initial states) and starts
    /// new episodes; writes the first observations into `obs` (`[num_envs * obs_dim]`) and
    /// `critic_obs` (`[num_envs * critic_obs_dim]`).
    fn reset(&mut self, seed: u64, obs: &mut [f64], critic_obs: &mut [f64])
        -> Result<(), EnvError>;

    /// Starts a new episode in env `index` alone, drawing from its current random stream;
    /// writes its first observations into `obs` (`[obs_dim]`) and `critic_obs`
    /// (`[critic_obs_dim]`).
    fn reset_env(
        &mut self,
        index: usize,
        obs: &mut [f64],
        critic_obs: &mut [f64],
    ) -> Result<(), EnvError>;

    /// Advances every env by one control step with `actions` (`[num_envs * action_dim]`),
    /// auto-resetting finished episodes as described in the [module docs](self).
    fn step(&mut self, actions: &[f64], out: &mut VecStep) -> Result<(), EnvError>;

    /// Writes every row's expert raw action for the current state into `actions`
    /// (`[num_envs * action_dim]`, the policy's action space): the labels DAgger
    /// (`moonhaul_learn::distill`) clones. An expert may be stateful (the phase tasks' scripted
    /// expert is), so ask once per step, before [`VecEnv::step`], from the first step of the
    /// episodes on; a second call before the next step gives the same labels. Default: an
    /// error, the task has no expert.
    fn expert_actions(&mut self, actions: &mut [f64]) -> Result<(), EnvError> {
        let _ = actions;
        Err(EnvError::NoExpert {
            reason: format!("{} has no scripted expert", std::any::type_name::<Self>()),
        })
    }

    /// The physics' share of the step time since the last call, s, for envs that simulate
    /// (`None`: no simulator to separate from the task, as Pendulum's closed form).
    fn take_physics_s(&mut self) -> Option<f64> {
        None
    }

    /// What the action pipeline did since the last call, for envs that step through it
    /// (`None`: no pipeline, as Pendulum).
    fn take_pipeline_stats(&mut self) -> Option<PipelineStats> {
        None
    }
}

/// What the onboard action pipeline (increment → clamp → drives) did over some unit ticks: the
/// clamp figures the learned mission is judged by ([`ClampTally`], the one eval and the log
/// summary use) and the grasp force that shows whether a policy lifts by squeezing. Sums, so
/// batches and steps add up.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PipelineStats {
    /// One tick per unit per world step.
    pub clamp: ClampTally,
    /// Sum over the unit ticks of the grasp force magnitude, N.
    pub grasp_force_sum_n: f64,
    /// Largest grasp force magnitude seen, N.
    pub grasp_force_peak_n: f64,
}

impl PipelineStats {
    /// Adds one unit tick: what its clamp issued and its grasp's force magnitude.
    pub fn record(&mut self, clamp: &ClampReport, grasp_force_n: f64) {
        self.clamp.record(clamp.t_max, clamp.hold);
        self.grasp_force_sum_n += grasp_force_n;
        self.grasp_force_peak_n = self.grasp_force_peak_n.max(grasp_force_n);
    }

    pub fn merge(&mut self, other: &PipelineStats) {
        self.clamp.merge(&other.clamp);
        self.grasp_force_sum_n += other.grasp_force_sum_n;
        self.grasp_force_peak_n = self.grasp_force_peak_n.max(other.grasp_force_peak_n);
    }

    pub fn mean_grasp_force_n(&self) -> Option<f64> {
        (self.clamp.ticks > 0).then(|| self.grasp_force_sum_n / self.clamp.ticks as f64)
    }

    pub fn peak_grasp_force_n(&self) -> Option<f64> {
        (self.clamp.ticks > 0).then_some(self.grasp_force_peak_n)
    }
}

/// Checks a flat batch's length: shared by every [`VecEnv`] implementation.
pub fn check_len(what: &'static str, data: &[f64], expected: usize) -> Result<(), EnvError> {
    if data.len() == expected {
        Ok(())
    } else {
        Err(EnvError::Shape {
            what,
            expected,
            found: data.len(),
        })
    }
}
