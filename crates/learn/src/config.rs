//! Training configs (`configs/train/*.toml`): every PPO hyperparameter of the paper's Table I
//! plus the run settings, parsed strictly (`deny_unknown_fields`, every key required) so a
//! typo or a forgotten key is an error rather than a silent default.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::LearnError;

/// A whole training config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    pub run: RunConfig,
    pub env: EnvConfig,
    pub policy: PolicyConfig,
    pub ppo: PpoConfig,
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
    /// PPO iterations (rollout + update) in total, including resumed ones.
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
}

impl Task {
    pub fn name(self) -> &'static str {
        match self {
            Task::Pendulum => "pendulum",
            Task::Lift => "lift",
            Task::Transport => "transport",
            Task::Place => "place",
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
    /// targets are of order one; 1.0 for the phase tasks, whose rewards already are.
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
    /// Reads, parses and validates a config file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, LearnError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(LearnError::io(path))?;
        Self::parse(&text).map_err(|e| match e {
            LearnError::ConfigParse { source, .. } => LearnError::ConfigParse {
                path: path.to_path_buf(),
                source,
            },
            other => other,
        })
    }

    /// Parses and validates config text.
    pub fn parse(text: &str) -> Result<Self, LearnError> {
        let config: TrainConfig = toml::from_str(text).map_err(|e| LearnError::ConfigParse {
            path: "<text>".into(),
            source: Box::new(e),
        })?;
        config.validate()?;
        Ok(config)
    }

    /// The config as TOML (the resolved config saved in a run folder).
    pub fn to_toml(&self) -> String {
        // Plain data with string keys: serialization cannot fail.
        toml::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks the ranges serde cannot express.
    pub fn validate(&self) -> Result<(), LearnError> {
        let (run, env, policy, ppo) = (&self.run, &self.env, &self.policy, &self.ppo);
        if run.name.is_empty() || run.name.contains(['/', '\\']) {
            return Err(invalid("run.name", "must be a non-empty file name"));
        }
        for (field, value) in [
            ("run.iterations", run.iterations),
            ("run.threads", run.threads),
            ("run.checkpoint_interval", run.checkpoint_interval),
            ("run.eval_interval", run.eval_interval),
            ("run.eval_episodes", run.eval_episodes),
            ("env.num_envs", env.num_envs),
            ("env.steps_per_env", env.steps_per_env),
            ("ppo.epochs", ppo.epochs),
            ("ppo.minibatches", ppo.minibatches),
        ] {
            if value == 0 {
                return Err(invalid(field, "must be positive"));
            }
        }
        if ppo.minibatches > env.num_envs * env.steps_per_env {
            return Err(invalid(
                "ppo.minibatches",
                "exceeds the batch size num_envs * steps_per_env",
            ));
        }
        for (field, hidden) in [
            ("policy.actor_hidden", &policy.actor_hidden),
            ("policy.critic_hidden", &policy.critic_hidden),
        ] {
            if hidden.contains(&0) {
                return Err(invalid(field, "every hidden size must be positive"));
            }
        }
        let positive = [
            ("policy.init_std", policy.init_std),
            ("ppo.learning_rate", ppo.learning_rate),
            ("ppo.desired_kl", ppo.desired_kl),
            ("ppo.min_lr", ppo.min_lr),
            ("ppo.max_lr", ppo.max_lr),
            ("ppo.clip", ppo.clip),
            ("ppo.reward_scale", ppo.reward_scale),
            ("ppo.max_grad_norm", ppo.max_grad_norm),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(invalid(field, "must be a positive finite number"));
            }
        }
        for (field, value) in [
            ("ppo.entropy_coef", ppo.entropy_coef),
            ("ppo.value_loss_coef", ppo.value_loss_coef),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(invalid(field, "must be a non-negative finite number"));
            }
        }
        if !(ppo.lr_factor.is_finite() && ppo.lr_factor > 1.0) {
            return Err(invalid("ppo.lr_factor", "must be finite and > 1"));
        }
        if ppo.min_lr > ppo.max_lr {
            return Err(invalid("ppo.min_lr", "must not exceed ppo.max_lr"));
        }
        if !(ppo.gamma > 0.0 && ppo.gamma <= 1.0) {
            return Err(invalid("ppo.gamma", "must be in (0, 1]"));
        }
        if !(0.0..=1.0).contains(&ppo.lambda) {
            return Err(invalid("ppo.lambda", "must be in [0, 1]"));
        }
        Ok(())
    }
}

fn invalid(field: &str, reason: &str) -> LearnError {
    LearnError::InvalidConfig {
        field: field.into(),
        reason: reason.into(),
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
    fn phase_configs_hold_table_one() {
        // (lr, gamma, entropy, envs, hidden) per phase; lambda, clip, epochs, minibatches shared.
        type Row = (&'static str, f64, f64, f64, usize, [usize; 3]);
        let table: [Row; 3] = [
            ("lift", 1e-4, 0.98, 0.006, 2048, [256, 128, 64]),
            ("transport", 1e-3, 0.99, 0.005, 4096, [128, 128, 128]),
            ("place", 1e-4, 0.98, 0.006, 2048, [256, 128, 64]),
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
                (1.0, true, 1.0)
            );
            assert_eq!(c.env.num_envs, envs, "{name}");
            assert_eq!(c.policy.actor_hidden, hidden, "{name}");
            assert_eq!(c.policy.critic_hidden, hidden, "{name}");
            assert_eq!(c.policy.init_std, 1.0);
        }
        assert_eq!(repo_config("pendulum").run.task, Task::Pendulum);
    }

    #[test]
    fn resolved_config_round_trips() {
        let c = repo_config("lift");
        assert_eq!(TrainConfig::parse(&c.to_toml()).unwrap(), c);
    }

    #[test]
    fn rejects_unknown_keys_tasks_and_bad_ranges() {
        let text = repo_config("pendulum").to_toml();
        let typo = text.replace("entropy_coef", "entropy_coeff");
        assert!(matches!(
            TrainConfig::parse(&typo),
            Err(LearnError::ConfigParse { .. })
        ));
        let task = text.replace("task = \"pendulum\"", "task = \"cartpole\"");
        assert!(matches!(
            TrainConfig::parse(&task),
            Err(LearnError::ConfigParse { .. })
        ));
        let mut c = repo_config("pendulum");
        c.ppo.gamma = 1.5;
        assert!(
            matches!(c.validate(), Err(LearnError::InvalidConfig { field, .. }) if field == "ppo.gamma")
        );
        let mut c = repo_config("pendulum");
        c.env.num_envs = 0;
        assert!(
            matches!(c.validate(), Err(LearnError::InvalidConfig { field, .. }) if field == "env.num_envs")
        );
    }
}
