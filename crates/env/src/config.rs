//! Training configs (`configs/train/*.toml`): every PPO hyperparameter of the paper's Table I
//! plus the run settings, read by core's one loader ([`moonhaul_core::config`]): every key
//! required, so a typo or a forgotten key is an error rather than a silent default, and every
//! number bounded so a run cannot exhaust memory before its first iteration.

use std::path::{Path, PathBuf};

use moonhaul_core::config::{
    self, count, in_range, positive, section, ConfigError, FieldError, Validate,
};
use moonhaul_core::task_config::MAX_EPISODE_S;
use serde::{Deserialize, Serialize};

use crate::reward::RewardConfig;

/// A whole training config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub run: RunConfig,
    pub env: EnvConfig,
    pub policy: PolicyConfig,
    pub ppo: PpoConfig,
    /// Table II's tolerances and weights: required for the phase tasks, absent for benchmark
    /// tasks (which bring their own reward).
    pub reward: Option<RewardConfig>,
    /// The simulated world of the phase tasks; absent for benchmark tasks.
    pub world: Option<WorldConfig>,
    /// Warm start from the scripted expert before PPO (`moonhaul_learn::distill`); absent: PPO
    /// from scratch. Not in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_start: Option<WarmStartConfig>,
    /// A behaviour-cloning term in PPO's loss toward the scripted expert, annealed away
    /// (`moonhaul_learn::kickstart`); needs `[warm_start]` (its expert). Absent: plain PPO. Not
    /// in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kickstart: Option<KickstartConfig>,
}

/// Kickstarting (Schmitt et al., 2018) with a deterministic teacher: during PPO, every visited
/// state is labelled with the scripted expert's action, and `coef(k) · mean‖μ(s) − a*(s)‖²` is
/// added to PPO's loss at iteration k, `coef` falling linearly from `bc_coef` at PPO's first
/// iteration to 0 at `anneal_iterations`, after which PPO runs alone (and the expert is no
/// longer asked). Not in the paper; every value is a training choice.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KickstartConfig {
    /// The term's weight at PPO's first iteration, against PPO's surrogate (order 0.01–0.1)
    /// and the action's squared error in units of the increment step (order 0.01–1).
    pub bc_coef: f64,
    /// PPO iterations over which the weight falls to 0 (counted from PPO's first iteration).
    pub anneal_iterations: usize,
}

impl KickstartConfig {
    fn validate(&self) -> Result<(), FieldError> {
        in_range("bc_coef", self.bc_coef, 0.0, 1e3)?;
        count(
            "anneal_iterations",
            self.anneal_iterations as u64,
            1,
            1_000_000,
        )
    }

    /// The term's weight at PPO iteration `iteration` (0-based, counted from PPO's first).
    pub fn coef(&self, iteration: usize) -> f64 {
        let left = 1.0 - iteration as f64 / self.anneal_iterations as f64;
        self.bc_coef * left.max(0.0)
    }
}

/// The warm start of `moonhaul_learn::distill`: DAgger from the scripted expert, then the critic
/// fitted to the cloned actor's returns before PPO touches either. None of it is in the paper
/// (which trains from scratch); every value here is a training choice, bounded so a config
/// cannot exhaust memory or run forever before PPO's first iteration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WarmStartConfig {
    /// `configs/mission.toml`, relative to this config file: the plan the scripted expert
    /// ([`moonhaul_core::scripted::PhaseScript`]) flies, the same one `moonhaul sim demo` and
    /// the deployed scripted controller fly.
    pub mission: PathBuf,
    /// DAgger rounds (rollout, aggregate, fit).
    pub rounds: usize,
    /// Control steps every world runs per round.
    pub steps_per_round: usize,
    /// Passes over the aggregated buffer per round.
    pub epochs: usize,
    /// Adam steps per epoch (the buffer is split into this many minibatches).
    pub minibatches: usize,
    /// Adam's rate for the actor's fit and the critic's warm-up.
    pub learning_rate: f64,
    /// The aggregated buffer keeps the most recent this many labelled rows.
    pub buffer_rows: usize,
    /// Share of rows the expert drives in the first round; it falls linearly to 0 over the
    /// rounds before the last `student_rounds`.
    pub beta_start: f64,
    /// Of `rounds`, how many end the warm start at β = 0 after the fall: the actor alone, every
    /// state it reaches labelled with the expert's correction (0: the fall reaches 0 in the last
    /// round).
    pub student_rounds: usize,
    /// Std of the Gaussian noise added to every executed DAgger action, in units of the
    /// increment step (the action's own scale); the labels stay the expert's clean actions.
    /// DART's noise injection (Laskey et al. 2017): the rollouts wander off the trajectories of
    /// the expert and the actor, so the fit also sees the corrections from the states next to
    /// them, where the deployed clone's own small errors take it. 0 (absent): plain DAgger.
    #[serde(default)]
    pub action_noise_std: f64,
    /// Rollouts of the cloned actor that fit only the critic before PPO (0: none).
    pub critic_warmup_iterations: usize,
}

/// Which simulator and task settings a phase task trains on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldConfig {
    /// `configs/sim.toml`, relative to this config file.
    pub sim: PathBuf,
    /// `configs/tasks.toml`, relative to this config file.
    pub tasks: PathBuf,
    /// `configs/sync.toml` (the clamp and hold rule the tasks step through), relative to this
    /// config file.
    pub sync: PathBuf,
    /// A hand-over file (`moonhaul sim handovers`), relative to this config file: transport
    /// and place worlds that start where a deployed mission handed over
    /// ([`moonhaul_sim::handover`]). Not in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub handovers: Option<PathBuf>,
    /// The share of worlds that start from a hand-over (the rest start settled), 0 to 1.
    #[serde(default)]
    pub handover_fraction: f64,
    /// Episodes run this long, s, instead of the phase's `duration_s` (`tasks.toml`), which the
    /// actor's phase clock goes on measuring: past it the clock stays at 1. Not in the paper:
    /// a deployed phase ends when the gate says so, not at its training horizon, and an actor
    /// never trained past that horizon meets states there it has never seen. At least the
    /// phase's `duration_s`; absent: the phase's `duration_s`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episode_s: Option<f64>,
}

/// What to train and how the run is driven.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Run name: the default run folder is `runs/<name>`.
    pub name: String,
    pub task: Task,
    /// Seeds libtorch and the environments; with a fixed `threads` the run is reproducible.
    pub seed: u64,
    /// PPO iterations (rollout + update) in total, including resumed ones; 0 with a
    /// `[warm_start]` runs the warm start alone.
    pub iterations: usize,
    /// libtorch intra-op threads, kept explicit so training does not fight the simulator.
    pub threads: usize,
    /// Write a checkpoint every this many iterations (and at the end / on Ctrl-C).
    pub checkpoint_interval: usize,
    /// Run the deterministic evaluation every this many iterations (and at the end).
    pub eval_interval: usize,
    /// Episodes per evaluation (one per evaluation env).
    pub eval_episodes: usize,
}

/// The environments a run trains on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Task {
    /// Gymnasium's Pendulum-v1 ([`crate::pendulum`]).
    Pendulum,
    Lift,
    Transport,
    Place,
    /// The monolithic baseline: one policy for the whole mission ([`moonhaul_sim::task`]).
    Mission,
}

impl Task {
    pub fn name(self) -> &'static str {
        match self {
            Task::Pendulum => "pendulum",
            Task::Lift => "lift",
            Task::Transport => "transport",
            Task::Place => "place",
            Task::Mission => "mission",
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvConfig {
    /// Parallel environments (Table I).
    pub num_envs: usize,
    /// Rollout length per env and iteration (rsl_rl `num_steps_per_env`).
    pub steps_per_env: usize,
}

/// Actor and critic networks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyConfig {
    pub actor_hidden: Vec<usize>,
    pub critic_hidden: Vec<usize>,
    /// Initial Gaussian action std, every dimension.
    pub init_std: f64,
    /// Multiplies the actor's initial output-layer weights and biases: 1 is PyTorch's (and
    /// rsl_rl's) default; a small gain starts the mean action at ≈ 0, the task's offset.
    pub actor_output_gain: f64,
    pub std_type: StdType,
    /// rsl_rl's empirical observation normalization (exported with the policy).
    pub obs_normalization: bool,
}

/// How the learned per-dimension std is parameterised (rsl_rl's `std_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StdType {
    /// The parameter is the std, clamped to `[1e-6, 1e6]` when used (rsl_rl's default).
    Scalar,
    /// The parameter is log std, clamped to `[ln 1e-6, ln 1e6]` and exponentiated.
    Log,
}

/// PPO hyperparameters (Table I and rsl_rl's algorithm settings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PpoConfig {
    /// Initial learning rate.
    pub learning_rate: f64,
    pub schedule: Schedule,
    /// Target KL of the adaptive schedule.
    pub desired_kl: f64,
    /// The adaptive schedule divides or multiplies the rate by this factor.
    pub lr_factor: f64,
    pub min_lr: f64,
    pub max_lr: f64,
    /// Multiplies the rewards PPO learns from (not the logged returns). Not an rsl_rl
    /// setting: it stands for the reward weights a task would otherwise scale, so the critic's
    /// targets are of order one (Table II's penalties reach −300 per step; the phase configs
    /// use 0.001). The policy gradient is unaffected: advantages are normalized per batch.
    pub reward_scale: f64,
    pub gamma: f64,
    pub lambda: f64,
    /// Clip ratio of the surrogate and of the value loss.
    pub clip: f64,
    pub epochs: usize,
    pub minibatches: usize,
    pub entropy_coef: f64,
    pub value_loss_coef: f64,
    pub clipped_value_loss: bool,
    /// Global gradient-norm clip over actor, critic and std.
    pub max_grad_norm: f64,
}

/// Learning-rate schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Schedule {
    /// rsl_rl's KL-adaptive rate, adjusted every minibatch.
    Adaptive,
    Fixed,
}

impl TrainConfig {
    /// Reads, parses and validates a config file; errors name the file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// Parses and validates config text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &Path) -> Result<Self, ConfigError> {
        config::parse(text, origin)
    }

    /// The config as TOML (the resolved config saved in a run folder).
    pub fn to_toml(&self) -> String {
        // Plain data with string keys: serialization cannot fail.
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Samples per PPO iteration, `num_envs × steps_per_env` (bounded by validation).
    pub fn batch_size(&self) -> usize {
        self.env.num_envs.saturating_mul(self.env.steps_per_env)
    }
}

/// Most samples in one rollout: Table I's largest batch is 4096 × 24 ≈ 98k; 4M samples of an
/// 80-dim observation are already 1.3 GB of f32.
pub const MAX_BATCH_SAMPLES: u64 = 1 << 22;
/// Longest run name, bytes.
const MAX_NAME_BYTES: usize = 64;

impl Validate for TrainConfig {
    fn resolve(&mut self, config_path: &Path) -> Result<(), ConfigError> {
        if let Some(warm) = &mut self.warm_start {
            let resolved = config::resolve(config_path, &warm.mission);
            warm.mission = std::fs::canonicalize(&resolved).unwrap_or(resolved);
        }
        if let Some(world) = &mut self.world {
            // Absolute where they exist, so the resolved config saved in a run folder still
            // names them; a missing file is reported when the world is built.
            let handovers = world.handovers.as_mut();
            for path in [&mut world.sim, &mut world.tasks, &mut world.sync]
                .into_iter()
                .chain(handovers)
            {
                let resolved = config::resolve(config_path, path);
                *path = std::fs::canonicalize(&resolved).unwrap_or(resolved);
            }
        }
        Ok(())
    }

    fn validate(&self) -> Result<(), FieldError> {
        let (run, env, policy, ppo) = (&self.run, &self.env, &self.policy, &self.ppo);
        section("run", || {
            let name_ok = (1..=MAX_NAME_BYTES).contains(&run.name.len())
                && run.name != "."
                && run.name != ".."
                && run
                    .name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b));
            if !name_ok {
                return Err(FieldError::new(
                    "name",
                    format!(
                        "{:?} must be a plain folder name: 1 to {MAX_NAME_BYTES} ASCII letters, \
                         digits, '_', '-' or '.', not \".\" or \"..\"",
                        run.name
                    ),
                ));
            }
            // 0: the warm start alone (its cloned expert is the run's policy).
            let least = u64::from(self.warm_start.is_none());
            count("iterations", run.iterations as u64, least, 1_000_000)?;
            count("threads", run.threads as u64, 1, 256)?;
            count(
                "checkpoint_interval",
                run.checkpoint_interval as u64,
                1,
                1_000_000,
            )?;
            count("eval_interval", run.eval_interval as u64, 1, 1_000_000)?;
            count("eval_episodes", run.eval_episodes as u64, 1, 100_000)
        })?;
        section("env", || {
            count("num_envs", env.num_envs as u64, 1, 65_536)?;
            count("steps_per_env", env.steps_per_env as u64, 1, 10_000)?;
            let samples = (env.num_envs as u64).saturating_mul(env.steps_per_env as u64);
            if samples > MAX_BATCH_SAMPLES {
                return Err(FieldError::new(
                    "steps_per_env",
                    format!(
                        "num_envs × steps_per_env = {samples} samples per iteration exceeds \
                         {MAX_BATCH_SAMPLES}"
                    ),
                ));
            }
            Ok(())
        })?;
        section("policy", || {
            for (field, hidden) in [
                ("actor_hidden", &policy.actor_hidden),
                ("critic_hidden", &policy.critic_hidden),
            ] {
                count(field, hidden.len() as u64, 1, 16)?;
                for (i, &width) in hidden.iter().enumerate() {
                    count(&format!("{field}[{i}]"), width as u64, 1, 4096)?;
                }
            }
            positive("init_std", policy.init_std, 100.0)?;
            positive("actor_output_gain", policy.actor_output_gain, 1.0)
        })?;
        match (self.run.task, &self.reward) {
            (Task::Pendulum, Some(_)) => {
                return Err(FieldError::new(
                    "reward",
                    "the pendulum task brings its own reward; remove [reward]",
                ))
            }
            (Task::Pendulum, None) => {}
            (task, None) => {
                return Err(FieldError::new(
                    "reward",
                    format!(
                        "the {} task needs a [reward] section (Table II)",
                        task.name()
                    ),
                ))
            }
            (_, Some(reward)) => section("reward", || reward.validate())?,
        }
        match (self.run.task, &self.world) {
            (Task::Pendulum, Some(_)) => {
                return Err(FieldError::new(
                    "world",
                    "the pendulum task has no simulated world; remove [world]",
                ))
            }
            (Task::Pendulum, None) => {}
            (task, Some(world)) => section("world", || {
                in_range("handover_fraction", world.handover_fraction, 0.0, 1.0)?;
                let starts = world.handover_fraction > 0.0;
                if starts && !matches!(task, Task::Transport | Task::Place) {
                    return Err(FieldError::new(
                        "handover_fraction",
                        format!(
                            "the {} task has no hand-over: only transport and place start \
                             where a deployed mission handed over",
                            task.name()
                        ),
                    ));
                }
                if starts != world.handovers.is_some() {
                    return Err(FieldError::new(
                        "handovers",
                        "a hand-over file and a positive handover_fraction go together",
                    ));
                }
                if let Some(episode_s) = world.episode_s {
                    if task == Task::Mission {
                        return Err(FieldError::new(
                            "episode_s",
                            "the mission task has no phase clock to run past; remove episode_s",
                        ));
                    }
                    positive("episode_s", episode_s, MAX_EPISODE_S)?;
                }
                Ok(())
            })?,
            (task, None) => {
                return Err(FieldError::new(
                    "world",
                    format!(
                        "the {} task needs a [world] section naming sim.toml and tasks.toml",
                        task.name()
                    ),
                ))
            }
        }
        section("ppo", || {
            positive("learning_rate", ppo.learning_rate, 1.0)?;
            positive("desired_kl", ppo.desired_kl, 1.0)?;
            in_range("lr_factor", ppo.lr_factor, 1.0 + f64::EPSILON, 100.0)?;
            positive("min_lr", ppo.min_lr, 1.0)?;
            positive("max_lr", ppo.max_lr, 1.0)?;
            if ppo.min_lr > ppo.max_lr {
                return Err(FieldError::new("min_lr", "must not exceed ppo.max_lr"));
            }
            // The adaptive schedule keeps the rate in [min_lr, max_lr]; it must start there.
            if ppo.schedule == Schedule::Adaptive
                && !(ppo.min_lr..=ppo.max_lr).contains(&ppo.learning_rate)
            {
                return Err(FieldError::new(
                    "learning_rate",
                    format!(
                        "{:?} must lie in [min_lr, max_lr] = [{:?}, {:?}] for the adaptive \
                         schedule",
                        ppo.learning_rate, ppo.min_lr, ppo.max_lr
                    ),
                ));
            }
            positive("reward_scale", ppo.reward_scale, 1e6)?;
            positive("gamma", ppo.gamma, 1.0)?;
            in_range("lambda", ppo.lambda, 0.0, 1.0)?;
            positive("clip", ppo.clip, 10.0)?;
            count("epochs", ppo.epochs as u64, 1, 100)?;
            count(
                "minibatches",
                ppo.minibatches as u64,
                1,
                self.batch_size() as u64,
            )?;
            in_range("entropy_coef", ppo.entropy_coef, 0.0, 10.0)?;
            in_range("value_loss_coef", ppo.value_loss_coef, 0.0, 100.0)?;
            positive("max_grad_norm", ppo.max_grad_norm, 1e6)
        })?;
        match (&self.warm_start, self.run.task) {
            (None, _) => Ok(()),
            (Some(_), Task::Pendulum) => Err(FieldError::new(
                "warm_start",
                "the pendulum task has no scripted expert to warm-start from; remove [warm_start]",
            )),
            (Some(warm), _) => section("warm_start", || warm.validate(self.env.num_envs)),
        }?;
        match (&self.kickstart, &self.warm_start) {
            (None, _) => Ok(()),
            (Some(_), None) => Err(FieldError::new(
                "kickstart",
                "kickstarting labels states with [warm_start]'s scripted expert; add [warm_start]",
            )),
            (Some(k), Some(_)) => section("kickstart", || k.validate()),
        }
    }
}

/// Most warm-start rounds and critic warm-up iterations: far beyond what a warm start needs
/// (tens), short of a run that never reaches PPO.
const MAX_WARM_ITERATIONS: u64 = 10_000;

impl WarmStartConfig {
    /// `worlds` is `env.num_envs`: every task gives at least one row per world, so a round
    /// adds at least `worlds × steps_per_round` rows to the buffer.
    fn validate(&self, worlds: usize) -> Result<(), FieldError> {
        count("rounds", self.rounds as u64, 1, MAX_WARM_ITERATIONS)?;
        // A round's rollout and fit are bounded as PPO's are (`env.steps_per_env`, `ppo.epochs`).
        count("steps_per_round", self.steps_per_round as u64, 1, 10_000)?;
        count("epochs", self.epochs as u64, 1, 100)?;
        // The buffer is held as f32 tensors of observations and labels: the rollout's bound.
        count("buffer_rows", self.buffer_rows as u64, 1, MAX_BATCH_SAMPLES)?;
        // Every minibatch of the first round's fit must hold at least one row.
        let first_round = (worlds as u64)
            .saturating_mul(self.steps_per_round as u64)
            .min(self.buffer_rows as u64);
        count("minibatches", self.minibatches as u64, 1, first_round)?;
        // As `ppo.learning_rate`; β is a probability.
        positive("learning_rate", self.learning_rate, 1.0)?;
        in_range("beta_start", self.beta_start, 0.0, 1.0)?;
        // Beyond one step's std the executed increments are mostly the clip's, not the labels'.
        in_range("action_noise_std", self.action_noise_std, 0.0, 1.0)?;
        // At least one round shows the actor the expert's own states at `beta_start`.
        count(
            "student_rounds",
            self.student_rounds as u64,
            0,
            self.rounds as u64 - 1,
        )?;
        count(
            "critic_warmup_iterations",
            self.critic_warmup_iterations as u64,
            0,
            MAX_WARM_ITERATIONS,
        )
    }

    /// β of round `round` (0-based): `beta_start` in the first, falling linearly to 0 in the
    /// last round before the `student_rounds`, 0 in those (a fall of one round keeps
    /// `beta_start`).
    pub fn beta(&self, round: usize) -> f64 {
        let falling = self.rounds.saturating_sub(self.student_rounds).max(1);
        if round >= falling {
            return 0.0;
        }
        if falling == 1 {
            return self.beta_start;
        }
        self.beta_start * (1.0 - round as f64 / (falling - 1) as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn repo_config(name: &str) -> TrainConfig {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/");
        TrainConfig::load(format!("{path}{name}.toml")).unwrap_or_else(|e| panic!("{name}: {e}"))
    }

    #[test]
    fn the_added_terms_variant_is_the_lift_config_with_only_those_weights_on() {
        let (lift, mut variant) = (repo_config("lift"), repo_config("lift_pipeline_terms"));
        let weights = variant.reward.map(|r| (r.w_clamp_step, r.w_squeeze));
        assert_eq!(weights, Some((1.0, 1.0)));
        let paper = lift.reward.map(|r| (r.w_clamp_step, r.w_squeeze));
        assert_eq!(
            paper,
            Some((0.0, 0.0)),
            "the shipped lift reward is the paper's"
        );
        if let Some(r) = &mut variant.reward {
            (r.w_clamp_step, r.w_squeeze) = (0.0, 0.0);
        }
        variant.run.name = lift.run.name.clone();
        assert_eq!(
            variant, lift,
            "the variant drifted from configs/train/lift.toml"
        );
    }

    #[test]
    fn each_warm_variant_is_its_phase_config_with_a_warm_start() {
        for phase in ["lift", "transport", "place"] {
            let (scratch, mut warm) = (repo_config(phase), repo_config(&format!("{phase}_warm")));
            let plan = warm
                .warm_start
                .take()
                .unwrap_or_else(|| panic!("{phase}_warm has no [warm_start]"));
            // The expert's plan is the shipped mission, resolved against the config's folder.
            moonhaul_core::scripted::MissionPlan::load(&plan.mission).unwrap();
            assert_eq!(plan.beta(0), 1.0, "{phase}");
            assert_eq!(plan.beta(plan.rounds - 1), 0.0, "{phase}");
            assert!(warm.run.iterations < scratch.run.iterations, "{phase}");
            // PPO explores around the clone, not as widely as from scratch.
            assert!(warm.policy.init_std < scratch.policy.init_std, "{phase}");
            // Fewer worlds: a DAgger round's rollout costs worlds x steps.
            assert!(warm.env.num_envs <= scratch.env.num_envs, "{phase}");
            (warm.run.name, warm.run.iterations, warm.env.num_envs) = (
                scratch.run.name.clone(),
                scratch.run.iterations,
                scratch.env.num_envs,
            );
            warm.policy.init_std = scratch.policy.init_std;
            assert_eq!(
                warm, scratch,
                "{phase}_warm drifted from configs/train/{phase}.toml"
            );
        }
    }

    #[test]
    fn the_kickstart_variant_is_the_warm_config_with_a_kickstart() {
        let (warm, mut kicked) = (repo_config("lift_warm"), repo_config("lift_kickstart"));
        let kickstart = kicked.kickstart.take().expect("[kickstart]");
        assert!(kickstart.coef(0) > 0.0);
        assert_eq!(kickstart.coef(kickstart.anneal_iterations), 0.0);
        assert!(kickstart.anneal_iterations <= kicked.run.iterations);
        kicked.run.name = warm.run.name.clone();
        assert_eq!(
            kicked, warm,
            "lift_kickstart drifted from configs/train/lift_warm.toml"
        );
    }

    #[test]
    fn kickstart_needs_the_warm_start_s_expert_and_bounded_values() {
        let text = repo_config("lift_kickstart").to_toml();
        let refused = |text: &str, field: &str| {
            let err = TrainConfig::parse(text, Path::new("train.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(field), "{field}: {err}");
        };
        let warm = text.find("[warm_start]").unwrap();
        let kick = text.find("[kickstart]").unwrap();
        let without_warm = if warm < kick {
            format!("{}{}", &text[..warm], &text[kick..])
        } else {
            text[..warm].to_owned()
        };
        refused(&without_warm, "kickstart");
        refused(
            &text.replace("bc_coef = 1.0", "bc_coef = -1.0"),
            "kickstart.bc_coef",
        );
        refused(
            &text.replace("bc_coef = 1.0", "bc_coef = nan"),
            "kickstart.bc_coef",
        );
        refused(
            &text.replace("anneal_iterations = 150", "anneal_iterations = 0"),
            "kickstart.anneal_iterations",
        );
    }

    #[test]
    fn zero_iterations_is_the_warm_start_alone() {
        let zero = |name: &str| {
            let text = repo_config(name).to_toml();
            let edited = text.replacen(
                &format!("iterations = {}", repo_config(name).run.iterations),
                "iterations = 0",
                1,
            );
            assert_ne!(edited, text);
            let path = std::env::temp_dir().join(format!(
                "moonhaul-zero-iterations-{name}-{}.toml",
                std::process::id()
            ));
            std::fs::write(&path, edited).unwrap();
            let loaded = TrainConfig::load(&path);
            std::fs::remove_file(&path).unwrap();
            loaded
        };
        assert_eq!(zero("lift_warm").unwrap().run.iterations, 0);
        let refused = zero("lift").unwrap_err().to_string();
        assert!(refused.contains("run.iterations"), "{refused}");
    }

    #[test]
    fn beta_falls_linearly_to_zero_over_the_rounds() {
        let mut warm = repo_config("lift_warm").warm_start.unwrap();
        (warm.rounds, warm.beta_start, warm.student_rounds) = (5, 0.8, 0);
        let close = |betas: &[f64], expected: &[f64]| {
            betas.len() == expected.len()
                && betas
                    .iter()
                    .zip(expected)
                    .all(|(b, e)| (b - e).abs() < 1e-12)
        };
        let betas: Vec<f64> = (0..5).map(|k| warm.beta(k)).collect();
        assert!(close(&betas, &[0.8, 0.6, 0.4, 0.2, 0.0]), "{betas:?}");
        // Student rounds end the warm start at 0 after a fall over the others.
        (warm.rounds, warm.beta_start, warm.student_rounds) = (6, 0.9, 2);
        let betas: Vec<f64> = (0..6).map(|k| warm.beta(k)).collect();
        assert!(close(&betas, &[0.9, 0.6, 0.3, 0.0, 0.0, 0.0]), "{betas:?}");
        (warm.rounds, warm.student_rounds) = (1, 0);
        assert_eq!(warm.beta(0), 0.9, "a single round keeps beta_start");
    }

    #[test]
    fn bad_warm_start_values_are_refused_by_name() {
        let text = repo_config("lift_warm").to_toml();
        let section = text.find("[warm_start]").expect("serialized");
        // `key = value` set inside [warm_start] (epochs and minibatches are in [ppo] too).
        let set = |key: &str, value: &str| {
            let (before, after) = text.split_at(section);
            let lines: Vec<String> = after
                .lines()
                .map(|l| match l.split_once(" = ") {
                    Some((k, _)) if k == key => format!("{key} = {value}"),
                    _ => l.to_owned(),
                })
                .collect();
            let edited = format!("{before}{}\n", lines.join("\n"));
            assert_ne!(
                edited.trim_end(),
                text.trim_end(),
                "{key} not in [warm_start]"
            );
            edited
        };
        // 256 worlds x 400 steps: at most 102,400 minibatches of one row in the first round.
        let cases = [
            (set("rounds", "0"), "warm_start.rounds"),
            (set("rounds", "10001"), "warm_start.rounds"),
            (set("steps_per_round", "0"), "warm_start.steps_per_round"),
            (set("epochs", "0"), "warm_start.epochs"),
            (set("minibatches", "0"), "warm_start.minibatches"),
            (set("minibatches", "102401"), "warm_start.minibatches"),
            (set("learning_rate", "0.0"), "warm_start.learning_rate"),
            (set("learning_rate", "nan"), "warm_start.learning_rate"),
            (set("buffer_rows", "0"), "warm_start.buffer_rows"),
            (set("buffer_rows", "4194305"), "warm_start.buffer_rows"),
            (set("beta_start", "1.5"), "warm_start.beta_start"),
            (set("beta_start", "-0.1"), "warm_start.beta_start"),
            (
                set("action_noise_std", "-0.1"),
                "warm_start.action_noise_std",
            ),
            (
                set("action_noise_std", "1.5"),
                "warm_start.action_noise_std",
            ),
            (
                set("action_noise_std", "nan"),
                "warm_start.action_noise_std",
            ),
            (set("student_rounds", "8"), "warm_start.student_rounds"),
            (
                set("critic_warmup_iterations", "10001"),
                "warm_start.critic_warmup_iterations",
            ),
            (set("rounds", "-1"), "warm_start.rounds"),
            (set("beta_start", "1.0\nbeta_end = 0.0"), "beta_end"),
            (
                text.replace("critic_warmup_iterations = 20\n", ""),
                "critic_warmup_iterations",
            ),
            // A small buffer bounds the first round's minibatches too.
            (
                set("buffer_rows", "100").replace("minibatches = 32", "minibatches = 101"),
                "warm_start.minibatches",
            ),
        ];
        for (text, field) in cases {
            let err = TrainConfig::parse(&text, Path::new("train.toml")).unwrap_err();
            let message = err.to_string();
            assert!(
                message.contains(field) && message.contains("train.toml"),
                "{field}: {message}"
            );
        }
        // What the bounds admit parses.
        for (key, value) in [("critic_warmup_iterations", "0"), ("beta_start", "0.0")] {
            TrainConfig::parse(&set(key, value), Path::new("train.toml")).unwrap();
        }
        // The pendulum has no expert.
        let pendulum = repo_config("pendulum").to_toml();
        let with_warm = format!("{pendulum}\n{}", &text[section..]);
        let err = TrainConfig::parse(&with_warm, Path::new("train.toml")).unwrap_err();
        assert_eq!(err.field(), Some("warm_start"), "{err}");
    }

    #[test]
    fn phase_configs_hold_table_one() {
        // (lr, gamma, entropy, envs, hidden) per phase; lambda, clip, epochs, minibatches shared.
        // Env counts are this machine's compute choice (worlds of two units), in the paper's
        // proportions: Table I has 2048 / 4096 / 2048.
        type Row = (&'static str, f64, f64, f64, usize, [usize; 3]);
        let table: [Row; 3] = [
            ("lift", 1e-4, 0.98, 0.006, 256, [256, 128, 64]),
            ("transport", 1e-3, 0.99, 0.005, 512, [128, 128, 128]),
            ("place", 1e-4, 0.98, 0.006, 256, [256, 128, 64]),
        ];
        for (name, lr, gamma, entropy, envs, hidden) in table {
            let c = repo_config(name);
            assert_eq!(c.run.task.name(), name);
            let p = &c.ppo;
            assert_eq!(
                (p.learning_rate, p.gamma, p.entropy_coef),
                (lr, gamma, entropy),
                "{name}"
            );
            assert_eq!(
                (p.lambda, p.clip, p.epochs, p.minibatches),
                (0.95, 0.2, 5, 4),
                "{name}"
            );
            assert_eq!(p.schedule, Schedule::Adaptive);
            assert_eq!(
                (p.desired_kl, p.lr_factor, p.min_lr, p.max_lr),
                (0.01, 1.5, 1e-5, 1e-2)
            );
            assert_eq!(
                (p.max_grad_norm, p.clipped_value_loss, p.reward_scale),
                (1.0, true, 0.001)
            );
            assert_eq!(c.env.num_envs, envs, "{name}");
            assert_eq!(c.policy.actor_hidden, hidden, "{name}");
            assert_eq!(c.policy.critic_hidden, hidden, "{name}");
            assert_eq!((c.policy.init_std, c.policy.actor_output_gain), (0.5, 0.01));
        }
        assert_eq!(repo_config("pendulum").run.task, Task::Pendulum);
    }

    #[test]
    fn episode_s_is_refused_by_name_out_of_range_or_without_a_phase_clock() {
        let with = |name: &str, value: &str| {
            let text = repo_config(name).to_toml();
            let edited = text.replacen("[world]\n", &format!("[world]\nepisode_s = {value}\n"), 1);
            assert_ne!(edited, text);
            TrainConfig::parse(&edited, Path::new("train.toml"))
        };
        assert_eq!(
            with("place", "12.0").unwrap().world.unwrap().episode_s,
            Some(12.0)
        );
        for (name, value) in [
            ("place", "0.0"),
            ("place", "-1.0"),
            ("place", "nan"),
            ("place", "121.0"),
            ("mission", "12.0"),
        ] {
            let err = with(name, value).unwrap_err().to_string();
            assert!(err.contains("world.episode_s"), "{name} {value}: {err}");
        }
    }

    #[test]
    fn resolved_config_round_trips() {
        let c = repo_config("lift");
        assert_eq!(
            TrainConfig::parse(&c.to_toml(), Path::new("resolved.toml")).unwrap(),
            c
        );
    }

    #[test]
    fn rejects_unknown_keys_tasks_and_bad_ranges() {
        let text = repo_config("pendulum").to_toml();
        let cases = [
            (
                text.replace("entropy_coef", "entropy_coeff"),
                "entropy_coeff",
            ),
            (
                text.replace("task = \"pendulum\"", "task = \"cartpole\""),
                "run.task",
            ),
            (text.replace("gamma = 0.98", "gamma = 1.5"), "ppo.gamma"),
            (
                text.replace("learning_rate = 0.001", "learning_rate = 0.5"),
                "ppo.learning_rate",
            ),
            (
                text.replace("num_envs = ", "num_envs = 0 #"),
                "env.num_envs",
            ),
            (
                text.replace("num_envs = ", "num_envs = 65536 #")
                    .replace("steps_per_env = ", "steps_per_env = 10000 #"),
                "env.steps_per_env",
            ),
            (
                text.replace("name = \"pendulum\"", "name = \"../escape\""),
                "run.name",
            ),
            (
                text.replace("name = \"pendulum\"", "name = \"..\""),
                "run.name",
            ),
            (
                text.replace("epochs = ", "epochs = 18446744073709551615 #"),
                "ppo.epochs",
            ),
        ];
        let lift = repo_config("lift").to_toml();
        let without_reward = lift[..lift.find("[reward]").unwrap()].to_owned();
        let table = &lift[lift.find("[reward]").unwrap()..];
        let cases = cases.into_iter().chain([
            (without_reward, "reward"),
            (format!("{text}\n{table}"), "reward"),
            (
                lift.replace("tilt_tol_deg = 10.0", "tilt_tol_deg = 0.0"),
                "reward.tilt_tol_deg",
            ),
        ]);
        for (text, field) in cases {
            let err = TrainConfig::parse(&text, Path::new("train.toml")).unwrap_err();
            let message = err.to_string();
            assert!(
                message.contains(field) && message.contains("train.toml"),
                "{field}: {message}"
            );
        }
    }
}
