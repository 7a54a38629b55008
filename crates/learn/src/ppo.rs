//! The PPO update as rsl_rl's `PPO` does it: per-minibatch KL-adaptive learning rate, clipped
//! surrogate, clipped value loss, entropy bonus, gradient-norm clip, Adam.
//!
//! One deliberate difference: rsl_rl ≥ 4 clips the actor's and the critic's gradient norms
//! separately; we clip their joint norm (actor, critic and std together, as rsl_rl ≤ 3 did with
//! its single `ActorCritic` module), which is what the paper's setup and our spec call for.

use tch::{Kind, Tensor};

use crate::actor_critic::ActorCritic;
use crate::adam::Adam;
use crate::config::{PpoConfig, Schedule};
use crate::gaussian;
use crate::storage::{bootstrap_time_outs, Batch, RolloutStorage, Transition};
use crate::LearnError;

/// An extra loss term of an algorithm built on PPO's update ([`Ppo::update_with`]): given a
/// minibatch and the actor's mean on it (with its gradient), the scalar to add to the loss.
pub type AuxLoss<'a> = &'a mut dyn FnMut(&Batch, &Tensor) -> Tensor;

/// Means over the minibatches of one update.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UpdateStats {
    pub value_loss: f64,
    pub surrogate_loss: f64,
    pub entropy: f64,
    /// KL(old ‖ new) measured before each minibatch step.
    pub kl: f64,
    /// How much of the rollout's return variance the critic explained before the update
    /// ([`RolloutStorage::explained_variance`]).
    pub explained_variance: Option<f64>,
}

/// Time-outs of one step: which envs were truncated and their final critic observations (all
/// the bootstrap `γ V(s_final)` needs).
#[derive(Debug)]
pub struct TimeOuts {
    /// `[K]` Int64 env indices.
    pub env_ids: Tensor,
    /// `[K, C]` raw final critic observations.
    pub final_critic_obs: Tensor,
}

#[derive(Debug)]
pub struct Ppo {
    config: PpoConfig,
    policy: ActorCritic,
    optimizer: Adam,
    storage: RolloutStorage,
}

/// rsl_rl's adaptive rule: shrink the rate by `lr_factor` when KL exceeds twice the target,
/// grow it when KL is positive and below half the target, within `[min_lr, max_lr]`.
pub fn adapt_learning_rate(lr: f64, kl: f64, config: &PpoConfig) -> f64 {
    if kl > config.desired_kl * 2.0 {
        (lr / config.lr_factor).max(config.min_lr)
    } else if kl < config.desired_kl / 2.0 && kl > 0.0 {
        (lr * config.lr_factor).min(config.max_lr)
    } else {
        lr
    }
}

/// Clipped surrogate `mean(max(−A·r, −A·clip(r, 1 ± ε)))` (to minimise).
pub fn surrogate_loss(advantages: &Tensor, ratio: &Tensor, clip: f64) -> Tensor {
    let unclipped = -advantages * ratio;
    let clipped = -advantages * ratio.clamp(1.0 - clip, 1.0 + clip);
    unclipped.maximum(&clipped).mean(Kind::Float)
}

/// Value loss: squared error to the returns, or with `clipped` the pessimistic maximum of it
/// and the error of a value kept within `±clip` of the rollout's value.
pub fn value_loss(
    values: &Tensor,
    old_values: &Tensor,
    returns: &Tensor,
    clip: f64,
    clipped: bool,
) -> Tensor {
    let unclipped = (values - returns).square();
    if !clipped {
        return unclipped.mean(Kind::Float);
    }
    let v_clipped = old_values + (values - old_values).clamp(-clip, clip);
    unclipped
        .maximum(&(v_clipped - returns).square())
        .mean(Kind::Float)
}

/// Keeps freed heap memory in the process instead of handing it back to the kernel.
///
/// libtorch's CPU allocator is plain `malloc`/`free`, and every minibatch allocates and frees
/// activations and gradients of several MB each (`[B, 256]` at B = 24,576 is 25 MB). glibc
/// serves blocks that size with fresh `mmap`s or trims them off the top of the heap when freed,
/// so each was faulted in again page by page: the profile of an update spent ~20 % of its time
/// in the kernel (page faults, zeroing, `munmap`), 2.8 M minor faults per benchmark run. With
/// the largest mmap threshold glibc accepts (32 MiB, which fixes it rather than letting it float)
/// and a trim threshold above the working set, freed blocks are reused from the heap: ~0.1 M
/// faults. The cost is that the process keeps its peak heap (a few hundred MB here) mapped.
/// Process-wide, set once; only on glibc, where `mallopt` is this allocator's own knob.
fn retain_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        static ONCE: std::sync::Once = std::sync::Once::new();
        ONCE.call_once(|| {
            use std::os::raw::c_int;
            extern "C" {
                fn mallopt(param: c_int, value: c_int) -> c_int;
            }
            // <malloc.h>: M_TRIM_THRESHOLD -1, M_MMAP_THRESHOLD -3.
            const M_TRIM_THRESHOLD: c_int = -1;
            const M_MMAP_THRESHOLD: c_int = -3;
            // SAFETY: mallopt only adjusts allocator parameters; any value is valid input (an
            // out-of-range one is refused with 0 and changes nothing).
            unsafe {
                mallopt(M_MMAP_THRESHOLD, 32 << 20);
                mallopt(M_TRIM_THRESHOLD, 1 << 30);
            }
        });
    }
}

impl Ppo {
    /// A learner whose rollout storage holds `steps` steps of `envs` rows, as wide as the
    /// policy's observations and actions.
    pub fn new(policy: ActorCritic, config: PpoConfig, steps: usize, envs: usize) -> Self {
        retain_freed_memory();
        let optimizer = Adam::new(policy.var_store(), config.learning_rate);
        let storage = RolloutStorage::new(
            steps,
            envs,
            policy.obs_dim(),
            policy.critic_obs_dim(),
            policy.action_dim(),
        );
        Ppo {
            config,
            policy,
            optimizer,
            storage,
        }
    }

    pub fn policy(&self) -> &ActorCritic {
        &self.policy
    }

    pub fn policy_mut(&mut self) -> &mut ActorCritic {
        &mut self.policy
    }

    pub fn optimizer(&self) -> &Adam {
        &self.optimizer
    }

    pub fn optimizer_mut(&mut self) -> &mut Adam {
        &mut self.optimizer
    }

    pub fn learning_rate(&self) -> f64 {
        self.optimizer.lr()
    }

    pub fn storage(&self) -> &RolloutStorage {
        &self.storage
    }

    /// One rollout step: samples actions `[N, A]` for raw observations `[N, O]` (valued on
    /// the critic observations `[N, C]`), lets `env` answer them, bootstraps time-outs with
    /// `γ V(s_final)` on their final critic observations, updates the normalizers with the new
    /// observations (rsl_rl's order) and stores the transition.
    pub fn act_and_store(
        &mut self,
        obs: &Tensor,
        critic_obs: &Tensor,
        next: impl FnOnce(&Tensor) -> Result<EnvAnswer, LearnError>,
    ) -> Result<EnvAnswer, LearnError> {
        let sample = self.policy.act(obs, critic_obs);
        let answer = next(&sample.actions)?;
        let mut rewards = answer.rewards.shallow_clone();
        if let Some(t) = &answer.time_outs {
            let final_values = self.policy.value(&t.final_critic_obs);
            rewards = bootstrap_time_outs(&rewards, &t.env_ids, &final_values, self.config.gamma);
        }
        self.policy
            .update_normalizers(&answer.next_obs, &answer.next_critic_obs);
        self.storage.add(&Transition {
            obs,
            critic_obs,
            actions: &sample.actions,
            rewards: &rewards,
            dones: &answer.dones,
            values: &sample.values,
            log_probs: &sample.log_prob,
            means: &sample.mean,
            stds: &sample.std,
        });
        Ok(answer)
    }

    /// GAE on the stored rollout, bootstrapped from the critic observations `[N, C]` after
    /// its last step, then `epochs × minibatches` gradient steps.
    pub fn update(&mut self, last_critic_obs: &Tensor) -> Result<UpdateStats, LearnError> {
        self.update_with(last_critic_obs, None)
    }

    /// [`Ppo::update`] with an extra term in every minibatch's loss: `aux(batch, mean)` gets
    /// the minibatch and the actor's mean on it (with its gradient) and returns a scalar to
    /// add. How an algorithm built on PPO's update adds its own objective
    /// ([`crate::kickstart`]) without a flag in PPO.
    pub fn update_with(
        &mut self,
        last_critic_obs: &Tensor,
        mut aux: Option<AuxLoss<'_>>,
    ) -> Result<UpdateStats, LearnError> {
        let last_values = self.policy.value(last_critic_obs);
        let c = &self.config;
        self.storage
            .compute_returns(&last_values, c.gamma, c.lambda);
        let explained_variance = self.storage.explained_variance();
        let mut sums = [0.0f64; 4];
        let mut lr = self.optimizer.lr();
        let count = (c.minibatches * c.epochs) as f64;
        let policy = &self.policy;
        let batches = self
            .storage
            .minibatches_with(c.minibatches, c.epochs, |obs, critic_obs| {
                (
                    policy.normalize_obs(obs),
                    policy.normalize_critic_obs(critic_obs),
                )
            });
        for batch in batches {
            let e = self
                .policy
                .evaluate_normalized(&batch.obs, &batch.critic_obs, &batch.actions);
            let kl = tch::no_grad(|| {
                gaussian::kl(
                    &batch.old_means,
                    &batch.old_stds,
                    &e.mean.detach(),
                    &e.std.detach(),
                )
                .mean(Kind::Float)
                .double_value(&[])
            });
            if c.schedule == Schedule::Adaptive {
                lr = adapt_learning_rate(lr, kl, c);
                self.optimizer.set_lr(lr);
            }
            let ratio = (&e.log_prob - &batch.old_log_probs).exp();
            let surrogate = surrogate_loss(&batch.advantages, &ratio, c.clip);
            let value = value_loss(
                &e.values,
                &batch.old_values,
                &batch.returns,
                c.clip,
                c.clipped_value_loss,
            );
            let mut loss = &surrogate + &value * c.value_loss_coef - &e.entropy * c.entropy_coef;
            if let Some(aux) = aux.as_mut() {
                loss += aux(&batch, &e.mean);
            }
            self.optimizer.zero_grad();
            loss.backward();
            self.optimizer.clip_grad_norm(c.max_grad_norm);
            self.optimizer.step();
            let stats = [
                value.double_value(&[]),
                surrogate.double_value(&[]),
                e.entropy.double_value(&[]),
                kl,
            ];
            if let Some(bad) = stats.iter().position(|v| !v.is_finite()) {
                let what = ["value loss", "surrogate loss", "entropy", "KL"][bad];
                return Err(LearnError::NonFinite { what: what.into() });
            }
            sums.iter_mut().zip(stats).for_each(|(s, v)| *s += v);
        }
        Ok(UpdateStats {
            value_loss: sums[0] / count,
            surrogate_loss: sums[1] / count,
            entropy: sums[2] / count,
            kl: sums[3] / count,
            explained_variance,
        })
    }
}

/// What the environment returned for one step, as tensors.
#[derive(Debug)]
pub struct EnvAnswer {
    /// `[N, O]` observations after the step (after auto-reset).
    pub next_obs: Tensor,
    /// `[N, C]` critic observations after the step (after auto-reset).
    pub next_critic_obs: Tensor,
    pub rewards: Tensor,
    /// `[N]` 1.0 where an episode ended.
    pub dones: Tensor,
    pub time_outs: Option<TimeOuts>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrainConfig;

    fn ppo_config() -> PpoConfig {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml");
        TrainConfig::load(path).unwrap().ppo
    }

    #[test]
    fn adaptive_rate_follows_rsl_rl() {
        let c = ppo_config();
        let lr = 1e-3;
        assert!((adapt_learning_rate(lr, 0.03, &c) - lr / 1.5).abs() < 1e-15);
        assert!((adapt_learning_rate(lr, 0.001, &c) - lr * 1.5).abs() < 1e-15);
        assert_eq!(adapt_learning_rate(lr, 0.01, &c), lr);
        assert_eq!(
            adapt_learning_rate(lr, 0.02, &c),
            lr,
            "exactly 2x target is not above it"
        );
        assert_eq!(
            adapt_learning_rate(lr, 0.0, &c),
            lr,
            "zero KL leaves the rate"
        );
        assert_eq!(adapt_learning_rate(1.2e-5, 1.0, &c), 1e-5);
        assert_eq!(adapt_learning_rate(9e-3, 1e-4, &c), 1e-2);
    }

    #[test]
    fn surrogate_clips_in_the_pessimistic_direction() {
        let adv = Tensor::from_slice(&[1.0f32, 1.0, -1.0, -1.0]);
        let ratio = Tensor::from_slice(&[1.5f32, 0.5, 1.5, 0.5]);
        // A>0, r=1.5: clipped gain 1.2 -> -1.2; A>0, r=0.5: unclipped -0.5;
        // A<0, r=1.5: unclipped 1.5; A<0, r=0.5: clipped 0.8. Mean = 0.15.
        let l = surrogate_loss(&adv, &ratio, 0.2).double_value(&[]);
        assert!((l - 0.15).abs() < 1e-6, "{l}");
    }

    #[test]
    fn value_loss_clips_around_the_old_value() {
        let old = Tensor::from_slice(&[0.0f32, 0.0]);
        let new = Tensor::from_slice(&[1.0f32, 0.1]);
        let ret = Tensor::from_slice(&[2.0f32, 0.0]);
        // Sample 0: unclipped (1-2)^2 = 1, clipped (0.2-2)^2 = 3.24 -> 3.24.
        // Sample 1: unclipped 0.01, clipped 0.01 -> 0.01. Mean 1.625.
        let l = value_loss(&new, &old, &ret, 0.2, true).double_value(&[]);
        assert!((l - 1.625).abs() < 1e-6, "{l}");
        let l = value_loss(&new, &old, &ret, 0.2, false).double_value(&[]);
        assert!((l - 0.505).abs() < 1e-6, "{l}");
    }
}
