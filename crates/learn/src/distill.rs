//! The warm start from the scripted expert: DAgger for the actor, then the critic fitted to
//! the cloned actor's returns, before PPO ([`crate::ppo`]) refines both. An algorithm of its
//! own beside PPO, as rsl_rl's `Distillation` is beside its `PPO`. Not in the paper, which trains
//! from scratch: from-scratch PPO does not find the narrow motions the closed kinematic chain
//! of two units holding one payload admits, while the scripted IK expert
//! ([`moonhaul_core::scripted::PhaseScript`]) flies them through the same action pipeline.
//!
//! **DAgger** (Ross, Gordon & Bagnell, 2011). Round k of K rolls `steps_per_round` control
//! steps on every world; each row executes its expert's raw action with probability β_k, else
//! the actor's deterministic mean, and every visited state is labelled with the expert's action
//! ([`VecEnv::expert_actions`]). β falls linearly from `beta_start` in the first round to 0,
//! then stays 0 for the last `student_rounds`: the first rounds show the actor the expert's own
//! states (behaviour cloning), the later ones the states the actor's own mistakes lead to,
//! labelled with the expert's correction, which plain cloning never sees. With
//! `action_noise_std`, every executed action also carries Gaussian noise and the labels stay
//! clean (DART, Laskey et al. 2017): the rounds visit the states around both trajectories too,
//! where a deployed clone's small errors lead, and label the expert's way back. The labelled rows
//! join a buffer of the most recent `buffer_rows`, and the actor's mean is fitted to them by
//! squared error, `epochs` × `minibatches` Adam steps per round. As PPO's rollout does, the
//! actor's observation normalizer learns every visited observation before the fit; the buffer
//! keeps raw observations and normalizes them with the statistics of the round's fit, so rows
//! of early rounds are not fitted through statistics the actor no longer uses. The std is not
//! fitted: PPO starts exploring at the config's `init_std`.
//!
//! **Critic warm-up.** A critic at its random initialisation meeting a cloned actor is the
//! known collapse: its values are noise, so PPO's first advantages are noise too, and the first
//! updates push the actor off the expert before the critic has learnt anything. Before PPO,
//! the actor therefore runs stochastic rollouts (its mean and the config's std, as PPO will)
//! whose GAE returns only the critic is fitted to, with PPO's rollout length, γ, λ, epochs and
//! minibatches. The loss is the plain squared error (not PPO's clipped one: the point is to
//! move the values far from their initialisation fast), and the actor's weights, std and
//! normalizer stay bit for bit as DAgger left them.

use std::time::Instant;

use tch::{Device, Kind, Tensor};

use crate::actor_critic::ActorCritic;
use crate::adam::Adam;
use crate::config::{TrainConfig, WarmStartConfig};
use crate::env::{PipelineStats, VecEnv, VecStep};
use crate::ppo::value_loss;
use crate::runner::{check_finite, step_env, to_f64, to_tensor, EpisodeStats};
use crate::storage::{bootstrap_time_outs, RolloutStorage, Transition};
use crate::LearnError;

/// The actor's mean agrees with the expert where every component is within this of the
/// expert's raw action: a tenth of the increment step the action is scaled by.
pub const AGREEMENT_TOLERANCE: f64 = 0.1;

/// Variable-store prefixes of the actor's and the critic's layers ([`ActorCritic`]).
const ACTOR_VARS: &str = "actor.";
const CRITIC_VARS: &str = "critic.";

/// One warm-start round's figures (a `metrics.csv` row, [`crate::metrics::MetricsRow::warm`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarmStats {
    /// Transitions of this round (all rows).
    pub env_steps: u64,
    /// Mean undiscounted return and length of the episodes that ended in this round, under the
    /// round's acting policy (the expert–actor mix of a DAgger round).
    pub mean_return: Option<f64>,
    pub mean_episode_length: Option<f64>,
    /// Transitions per second of rollout and fit together.
    pub steps_per_s: f64,
    /// What the action pipeline did in the round's rollout (phase tasks).
    pub pipeline: Option<PipelineStats>,
    pub stage: WarmStage,
}

/// Which half of the warm start a round belongs to, and its own figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WarmStage {
    Dagger {
        /// The share of rows the expert drove.
        beta: f64,
        /// Mean squared error of the actor's mean to the labels over the round's fit.
        bc_loss: f64,
        /// The share of the round's rows where the actor's mean agreed with the expert within
        /// [`AGREEMENT_TOLERANCE`] (measured as they were visited, before the fit).
        expert_agreement: f64,
    },
    Critic {
        /// Mean squared error of the values to the returns over the iteration's fit.
        value_loss: f64,
        /// Of the rollout, before the fit ([`RolloutStorage::explained_variance`]).
        explained_variance: Option<f64>,
    },
}

/// The policy must be sized for the env it learns on.
fn check_policy(env: &dyn VecEnv, policy: &ActorCritic) -> Result<(), LearnError> {
    for (what, expected, found) in [
        ("policy observation width", env.obs_dim(), policy.obs_dim()),
        (
            "policy critic observation width",
            env.critic_obs_dim(),
            policy.critic_obs_dim(),
        ),
        ("policy action width", env.action_dim(), policy.action_dim()),
    ] {
        if expected != found {
            return Err(LearnError::Shape {
                what,
                expected,
                found,
            });
        }
    }
    Ok(())
}

/// The aggregated DAgger data: raw observations `[capacity, O]` and expert labels
/// `[capacity, A]`, a ring that keeps the most recent rows.
#[derive(Debug)]
struct LabelBuffer {
    obs: Tensor,
    labels: Tensor,
    len: i64,
    /// Where the next row goes.
    next: i64,
}

impl LabelBuffer {
    fn new(capacity: usize, obs_dim: usize, action_dim: usize) -> Self {
        let zeros = |width: usize| {
            Tensor::zeros(
                [capacity.max(1) as i64, width as i64],
                (Kind::Float, Device::Cpu),
            )
        };
        LabelBuffer {
            obs: zeros(obs_dim),
            labels: zeros(action_dim),
            len: 0,
            next: 0,
        }
    }

    /// Appends `[n, O]` observations and their `[n, A]` labels, overwriting the oldest rows.
    fn push(&mut self, obs: &Tensor, labels: &Tensor) {
        let capacity = self.obs.size()[0];
        let n = obs.size()[0];
        // More rows than fit: only the last `capacity` of them would stay.
        let skip = (n - capacity).max(0);
        let n = n - skip;
        let first = n.min(capacity - self.next);
        for (dst, src) in [(&self.obs, obs), (&self.labels, labels)] {
            let src = src.narrow(0, skip, n);
            dst.narrow(0, self.next, first)
                .copy_(&src.narrow(0, 0, first));
            if n > first {
                dst.narrow(0, 0, n - first)
                    .copy_(&src.narrow(0, first, n - first));
            }
        }
        self.next = (self.next + n) % capacity;
        self.len = (self.len + n).min(capacity);
    }

    /// The rows held, `[len, O]` and `[len, A]` (in no particular order).
    fn rows(&self) -> (Tensor, Tensor) {
        (
            self.obs.narrow(0, 0, self.len),
            self.labels.narrow(0, 0, self.len),
        )
    }
}

/// What a DAgger round executes: per row, the expert's `labels` with probability `beta`, else
/// the actor's `mean`, plus Gaussian noise of std `noise_std` on every component (DART's; the
/// env clips the sum to its action range). The labels the actor is fitted to stay clean.
fn executed_actions(labels: &Tensor, mean: &Tensor, beta: f64, noise_std: f64) -> Tensor {
    let by_expert = Tensor::rand([labels.size()[0], 1], (Kind::Float, Device::Cpu)).lt(beta);
    let actions = labels.where_self(&by_expert, mean);
    if noise_std > 0.0 {
        actions + labels.randn_like() * noise_std
    } else {
        actions
    }
}

/// DAgger's state between rounds: the envs' episodes run on from one round to the next.
#[derive(Debug)]
pub struct Dagger {
    config: WarmStartConfig,
    /// Over the actor's layers alone.
    optimizer: Adam,
    buffer: LabelBuffer,
    /// `[N * O]` the envs' current observations.
    obs: Vec<f64>,
    /// `[N * A]` the experts' labels of them.
    labels: Vec<f64>,
    buf: VecStep,
    round: usize,
}

impl Dagger {
    /// Starts DAgger for `policy` on `env`, which it resets from `seed` (so that every episode
    /// is labelled from its first step, as the expert needs).
    pub fn new(
        config: &WarmStartConfig,
        env: &mut dyn VecEnv,
        policy: &ActorCritic,
        seed: u64,
    ) -> Result<Self, LearnError> {
        check_policy(env, policy)?;
        let (n, o, c, a) = (
            env.num_envs(),
            env.obs_dim(),
            env.critic_obs_dim(),
            env.action_dim(),
        );
        let mut obs = vec![0.0; n * o];
        env.reset(seed, &mut obs, &mut vec![0.0; n * c])?;
        check_finite("environment observation", &obs)?;
        // No larger than all rounds together can fill.
        let capacity = config.buffer_rows.min(
            n.saturating_mul(config.steps_per_round)
                .saturating_mul(config.rounds),
        );
        Ok(Dagger {
            optimizer: Adam::over(policy.var_store(), config.learning_rate, |name| {
                name.starts_with(ACTOR_VARS)
            }),
            buffer: LabelBuffer::new(capacity, o, a),
            obs,
            labels: vec![0.0; n * a],
            buf: VecStep::new(n, o, c),
            round: 0,
            config: config.clone(),
        })
    }

    /// Rounds done.
    pub fn rounds_done(&self) -> usize {
        self.round
    }

    /// One round: the rollout with β of this round, the labels aggregated, the actor's fit.
    pub fn round(
        &mut self,
        env: &mut dyn VecEnv,
        policy: &mut ActorCritic,
    ) -> Result<WarmStats, LearnError> {
        let start = Instant::now();
        let beta = self.config.beta(self.round);
        let (n, o, a) = (env.num_envs(), env.obs_dim(), env.action_dim());
        let mut episodes = EpisodeStats::new(n);
        let mut agreed = 0i64;
        env.take_pipeline_stats();
        for _ in 0..self.config.steps_per_round {
            env.expert_actions(&mut self.labels)?;
            check_finite("expert action", &self.labels)?;
            let obs = to_tensor(&self.obs, n, o);
            let labels = to_tensor(&self.labels, n, a);
            policy.update_obs_normalizer(&obs);
            let mean = policy.act_deterministic(&obs);
            let gap = (&mean - &labels).abs().amax([1], false);
            agreed += gap
                .le(AGREEMENT_TOLERANCE)
                .sum(Kind::Int64)
                .int64_value(&[]);
            let actions = to_f64(&executed_actions(
                &labels,
                &mean,
                beta,
                self.config.action_noise_std,
            ))?;
            check_finite("actor action", &actions)?;
            self.buffer.push(&obs, &labels);
            env.step(&actions, &mut self.buf)?;
            check_finite("environment observation", &self.buf.obs)?;
            episodes.record(&self.buf);
            std::mem::swap(&mut self.obs, &mut self.buf.obs);
        }
        let bc_loss = self.fit(policy)?;
        self.round += 1;
        let samples = (n * self.config.steps_per_round) as u64;
        let (mean_return, mean_episode_length) = episodes.means();
        Ok(WarmStats {
            env_steps: samples,
            mean_return,
            mean_episode_length,
            steps_per_s: samples as f64 / start.elapsed().as_secs_f64(),
            pipeline: env.take_pipeline_stats(),
            stage: WarmStage::Dagger {
                beta,
                bc_loss,
                expert_agreement: agreed as f64 / samples as f64,
            },
        })
    }

    /// Fits the actor's mean to the buffer; the mean loss over the gradient steps.
    fn fit(&mut self, policy: &ActorCritic) -> Result<f64, LearnError> {
        let (obs, targets) = self.buffer.rows();
        // The normalizer is fixed during the fit: every row is normalized once.
        let inputs = policy.normalize_obs(&obs);
        let rows = inputs.size()[0];
        let minibatches = self.config.minibatches as i64;
        let size = rows / minibatches;
        if size == 0 {
            return Err(LearnError::InvalidConfig {
                field: "warm_start.minibatches".into(),
                reason: format!("{minibatches} minibatches of a buffer of {rows} rows"),
            });
        }
        let mut sum = 0.0;
        for _ in 0..self.config.epochs {
            let perm = Tensor::randperm(rows, (Kind::Int64, Device::Cpu));
            for i in 0..minibatches {
                let idx = perm.narrow(0, i * size, size);
                let mean = policy.mean_normalized(&inputs.index_select(0, &idx));
                let loss = (mean - targets.index_select(0, &idx))
                    .square()
                    .mean(Kind::Float);
                self.optimizer.zero_grad();
                loss.backward();
                self.optimizer.step();
                let loss = loss.double_value(&[]);
                if !loss.is_finite() {
                    return Err(LearnError::NonFinite {
                        what: "behaviour-cloning loss".into(),
                    });
                }
                sum += loss;
            }
        }
        Ok(sum / (self.config.epochs as i64 * minibatches) as f64)
    }
}

/// The critic's warm-up between rollouts.
#[derive(Debug)]
pub struct CriticWarmup {
    /// Over the critic's layers alone.
    optimizer: Adam,
    storage: RolloutStorage,
    obs: Tensor,
    critic_obs: Tensor,
    buf: VecStep,
    steps: usize,
    epochs: usize,
    minibatches: usize,
    gamma: f64,
    lambda: f64,
    reward_scale: f64,
    max_grad_norm: f64,
}

impl CriticWarmup {
    /// Starts the warm-up of `policy`'s critic on `env`, reset from `seed`, with PPO's
    /// rollout length, discounting, epochs, minibatches, reward scale and gradient clip from
    /// `config` and Adam at `learning_rate`.
    pub fn new(
        config: &TrainConfig,
        learning_rate: f64,
        env: &mut dyn VecEnv,
        policy: &ActorCritic,
        seed: u64,
    ) -> Result<Self, LearnError> {
        check_policy(env, policy)?;
        let (n, o, c, a) = (
            env.num_envs(),
            env.obs_dim(),
            env.critic_obs_dim(),
            env.action_dim(),
        );
        let (mut obs, mut critic_obs) = (vec![0.0; n * o], vec![0.0; n * c]);
        env.reset(seed, &mut obs, &mut critic_obs)?;
        check_finite("environment observation", &obs)?;
        check_finite("environment critic observation", &critic_obs)?;
        let ppo = &config.ppo;
        Ok(CriticWarmup {
            optimizer: Adam::over(policy.var_store(), learning_rate, |name| {
                name.starts_with(CRITIC_VARS)
            }),
            storage: RolloutStorage::new(config.env.steps_per_env, n, o, c, a),
            obs: to_tensor(&obs, n, o),
            critic_obs: to_tensor(&critic_obs, n, c),
            buf: VecStep::new(n, o, c),
            steps: config.env.steps_per_env,
            epochs: ppo.epochs,
            minibatches: ppo.minibatches,
            gamma: ppo.gamma,
            lambda: ppo.lambda,
            reward_scale: ppo.reward_scale,
            max_grad_norm: ppo.max_grad_norm,
        })
    }

    /// One stochastic rollout of the actor and a fit of the critic to its returns.
    pub fn iterate(
        &mut self,
        env: &mut dyn VecEnv,
        policy: &mut ActorCritic,
    ) -> Result<WarmStats, LearnError> {
        let start = Instant::now();
        let n = env.num_envs();
        let mut episodes = EpisodeStats::new(n);
        env.take_pipeline_stats();
        for _ in 0..self.steps {
            let sample = policy.act(&self.obs, &self.critic_obs);
            let answer = step_env(env, &mut self.buf, &sample.actions, self.reward_scale)?;
            episodes.record(&self.buf);
            let mut rewards = answer.rewards.shallow_clone();
            if let Some(t) = &answer.time_outs {
                let final_values = policy.value(&t.final_critic_obs);
                rewards = bootstrap_time_outs(&rewards, &t.env_ids, &final_values, self.gamma);
            }
            policy.update_critic_obs_normalizer(&answer.next_critic_obs);
            self.storage.add(&Transition {
                obs: &self.obs,
                critic_obs: &self.critic_obs,
                actions: &sample.actions,
                rewards: &rewards,
                dones: &answer.dones,
                values: &sample.values,
                log_probs: &sample.log_prob,
                means: &sample.mean,
                stds: &sample.std,
            });
            self.obs = answer.next_obs;
            self.critic_obs = answer.next_critic_obs;
        }
        let last_values = policy.value(&self.critic_obs);
        self.storage
            .compute_returns(&last_values, self.gamma, self.lambda);
        let explained_variance = self.storage.explained_variance();
        let policy = &*policy;
        let batches =
            self.storage
                .minibatches_with(self.minibatches, self.epochs, |obs, critic_obs| {
                    (obs.shallow_clone(), policy.normalize_critic_obs(critic_obs))
                });
        let mut sum = 0.0;
        for batch in batches {
            let values = policy.values_normalized(&batch.critic_obs);
            let loss = value_loss(&values, &batch.old_values, &batch.returns, 0.0, false);
            self.optimizer.zero_grad();
            loss.backward();
            self.optimizer.clip_grad_norm(self.max_grad_norm);
            self.optimizer.step();
            let loss = loss.double_value(&[]);
            if !loss.is_finite() {
                return Err(LearnError::NonFinite {
                    what: "critic warm-up value loss".into(),
                });
            }
            sum += loss;
        }
        let samples = (n * self.steps) as u64;
        let (mean_return, mean_episode_length) = episodes.means();
        Ok(WarmStats {
            env_steps: samples,
            mean_return,
            mean_episode_length,
            steps_per_s: samples as f64 / start.elapsed().as_secs_f64(),
            pipeline: env.take_pipeline_stats(),
            stage: WarmStage::Critic {
                value_loss: sum / (self.epochs * self.minibatches) as f64,
                explained_variance,
            },
        })
    }
}

/// The random streams of the warm start's two halves, apart from PPO's
/// ([`crate::runner::iteration_seed`] counts up from 0, evaluation takes the last).
fn warm_seed(seed: u64, half: u64) -> u64 {
    moonhaul_core::seed::stream_seed(seed, u64::MAX - 1 - half)
}

/// The whole warm start of `config` (which must have one) on `env`: DAgger's rounds, then the
/// critic's warm-up iterations, calling `on_round` with each round's figures and the policy
/// after it. Before every round, `stop()` may end it early. Returns whether it ran to the end.
pub fn warm_start(
    config: &TrainConfig,
    env: &mut dyn VecEnv,
    policy: &mut ActorCritic,
    stop: impl Fn() -> bool,
    mut on_round: impl FnMut(&WarmStats, &ActorCritic) -> Result<(), LearnError>,
) -> Result<bool, LearnError> {
    let warm = config
        .warm_start
        .as_ref()
        .ok_or_else(|| LearnError::InvalidConfig {
            field: "warm_start".into(),
            reason: "the config has no [warm_start] section".into(),
        })?;
    let mut dagger = Dagger::new(warm, env, policy, warm_seed(config.run.seed, 0))?;
    for _ in 0..warm.rounds {
        if stop() {
            return Ok(false);
        }
        let stats = dagger.round(env, policy)?;
        on_round(&stats, policy)?;
    }
    if warm.critic_warmup_iterations == 0 {
        return Ok(true);
    }
    let seed = warm_seed(config.run.seed, 1);
    let mut critic = CriticWarmup::new(config, warm.learning_rate, env, policy, seed)?;
    for _ in 0..warm.critic_warmup_iterations {
        if stop() {
            return Ok(false);
        }
        let stats = critic.iterate(env, policy)?;
        on_round(&stats, policy)?;
    }
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pendulum::PendulumVecEnv;

    fn values(t: &Tensor) -> Vec<f32> {
        Vec::try_from(&t.flatten(0, -1)).unwrap()
    }

    #[test]
    fn executed_actions_mix_expert_and_actor_and_add_noise_to_both() {
        tch::manual_seed(3);
        let rows = 20_000;
        let labels = Tensor::ones([rows, 2], (Kind::Float, Device::Cpu));
        let mean = -Tensor::ones([rows, 2], (Kind::Float, Device::Cpu));
        // Noise-free: each row is exactly one of the two, the expert's on about β of them.
        let clean = executed_actions(&labels, &mean, 0.25, 0.0);
        let by_expert = clean.eq(1.0).all_dim(1, false);
        assert!(
            by_expert
                .logical_or(&clean.eq(-1.0).all_dim(1, false))
                .all()
                .int64_value(&[])
                == 1
        );
        let share = by_expert
            .to_kind(Kind::Float)
            .mean(Kind::Float)
            .double_value(&[]);
        assert!((share - 0.25).abs() < 0.02, "{share}");
        // With noise: centred on the mix, with the asked-for spread on every component.
        for beta in [0.0, 1.0] {
            let noisy = executed_actions(&labels, &mean, beta, 0.3);
            let centre = if beta == 1.0 { &labels } else { &mean };
            let noise = noisy - centre;
            let (m, sd) = (
                noise.mean(Kind::Float).double_value(&[]),
                noise.std(true).double_value(&[]),
            );
            assert!(
                m.abs() < 0.01 && (sd - 0.3).abs() < 0.01,
                "beta {beta}: {m} {sd}"
            );
        }
        // The inputs, the buffer's labels among them, are not touched.
        assert!(labels.eq(1.0).all().int64_value(&[]) == 1);
    }

    #[test]
    fn the_buffer_keeps_the_most_recent_rows() {
        let mut buffer = LabelBuffer::new(5, 1, 2);
        let rows = |from: i64, n: i64| {
            let ids = Tensor::arange_start(from, from + n, (Kind::Float, Device::Cpu));
            (ids.view([n, 1]), Tensor::stack(&[&ids, &(-&ids)], 1))
        };
        let held = |buffer: &LabelBuffer| {
            let (obs, labels) = buffer.rows();
            let mut ids = values(&obs);
            // Each label travels with its observation.
            assert_eq!(values(&labels.select(1, 0)), ids);
            assert_eq!(values(&(-labels.select(1, 1))), ids);
            ids.sort_by(f32::total_cmp);
            ids
        };
        let (obs, labels) = rows(0, 3);
        buffer.push(&obs, &labels);
        assert_eq!(held(&buffer), [0.0, 1.0, 2.0]);
        // Wraps around: rows 0 and 1 go.
        let (obs, labels) = rows(3, 4);
        buffer.push(&obs, &labels);
        assert_eq!(held(&buffer), [2.0, 3.0, 4.0, 5.0, 6.0]);
        // A push larger than the buffer keeps its own last rows.
        let (obs, labels) = rows(10, 7);
        buffer.push(&obs, &labels);
        assert_eq!(held(&buffer), [12.0, 13.0, 14.0, 15.0, 16.0]);
    }

    #[test]
    fn the_critic_warmup_leaves_the_actor_bit_identical() {
        tch::manual_seed(5);
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../configs/train/pendulum.toml"
        );
        let mut config = TrainConfig::load(path).unwrap();
        config.env.steps_per_env = 50;
        let mut env = PendulumVecEnv::new(8);
        let mut policy = ActorCritic::new(3, 3, 1, &config.policy);
        // A normalizer with statistics of its own, as DAgger leaves it.
        policy.update_obs_normalizer(&(Tensor::randn([32, 3], (Kind::Float, Device::Cpu)) * 2.0));
        let snapshot = |policy: &ActorCritic, prefix: &str| -> Vec<(String, Tensor)> {
            let mut vars: Vec<(String, Tensor)> = policy
                .var_store()
                .variables()
                .into_iter()
                .filter(|(name, _)| name.starts_with(prefix))
                .map(|(name, t)| (name, t.copy()))
                .collect();
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            vars
        };
        let norm = |policy: &ActorCritic| {
            let n = policy.obs_normalizer().unwrap();
            (n.mean().copy(), n.var().copy(), n.count())
        };
        // Everything but the critic's layers: the actor's and the std.
        let not_critic = |policy: &ActorCritic| {
            let mut vars = snapshot(policy, "");
            vars.retain(|(name, _)| !name.starts_with(CRITIC_VARS));
            vars
        };
        let (actor, critic, actor_norm) = (
            not_critic(&policy),
            snapshot(&policy, CRITIC_VARS),
            norm(&policy),
        );
        assert!(actor.iter().any(|(n, _)| n.starts_with(ACTOR_VARS)));
        assert!(actor.iter().any(|(n, _)| n == "std"));
        let mut warmup = CriticWarmup::new(&config, 1e-3, &mut env, &policy, 9).unwrap();
        let mut figures = Vec::new();
        for _ in 0..3 {
            let stats = warmup.iterate(&mut env, &mut policy).unwrap();
            assert_eq!(stats.env_steps, 8 * 50);
            figures.push(stats.stage);
        }
        println!("{figures:?}");
        for stage in &figures {
            let WarmStage::Critic {
                value_loss,
                explained_variance,
            } = *stage
            else {
                panic!("{stage:?}");
            };
            assert!(value_loss.is_finite() && explained_variance.is_some_and(f64::is_finite));
        }
        for ((name, before), (_, after)) in actor.iter().zip(&not_critic(&policy)) {
            assert!(before.equal(after), "{name} moved");
        }
        let (mean, var, count) = norm(&policy);
        assert!(mean.equal(&actor_norm.0) && var.equal(&actor_norm.1));
        assert_eq!(count, actor_norm.2);
        // The critic did learn: its layers moved and its normalizer saw the rollouts.
        let moved = critic
            .iter()
            .zip(&snapshot(&policy, CRITIC_VARS))
            .all(|((_, before), (_, after))| !before.equal(after));
        assert!(moved, "a critic layer did not move");
        assert_eq!(policy.critic_obs_normalizer().unwrap().count(), 3 * 8 * 50);
    }
}
