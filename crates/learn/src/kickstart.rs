//! Kickstarting (Schmitt et al., 2018, "Kickstarting Deep Reinforcement Learning") from the
//! scripted expert: PPO ([`crate::ppo`]) with a behaviour-cloning term toward the expert,
//! annealed away. An algorithm of its own beside PPO and DAgger ([`crate::distill`]), built on
//! PPO's update through [`Ppo::update_with`](crate::ppo::Ppo::update_with).
//!
//! Why: a warm-started actor is the expert's clone, and plain PPO from it is free to forget
//! the expert in its first updates, while its advantages are still noisy. With kickstarting,
//! every state the PPO rollout visits is labelled with the expert's raw action
//! ([`VecEnv::expert_actions`], asked once per step before the step, as the stateful expert
//! requires), and each minibatch's loss gains `coef(k) · mean‖μ(s) − a*(s)‖²` over the action
//! components, the same squared error DAgger fits. `coef` falls linearly from `bc_coef` to 0 over
//! `anneal_iterations` PPO iterations ([`KickstartConfig::coef`]): PPO leans on the expert while
//! its critic and advantages settle, then owns the policy. The teacher is deterministic, so the
//! paper's cross-entropy to the teacher's distribution becomes the squared error to its action;
//! the std is left to PPO. Once the weight is 0 the expert is no longer asked.

use tch::{Kind, Tensor};

use crate::config::KickstartConfig;
use crate::distill::AGREEMENT_TOLERANCE;
use crate::env::VecEnv;
use crate::runner::{check_finite, to_tensor};
use crate::storage::Batch;
use crate::LearnError;

/// One kickstarted update's figures (a `metrics.csv` row's `bc_coef`, `bc_loss`,
/// `expert_agreement`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KickstartStats {
    /// The term's weight in this iteration.
    pub coef: f64,
    /// Mean over the update's minibatches of the squared error of the actor's mean to the
    /// expert's labels (before the weight).
    pub bc_loss: f64,
    /// The share of the rollout's rows whose sampled mean was within
    /// [`AGREEMENT_TOLERANCE`] of the expert's action in every component.
    pub expert_agreement: f64,
}

/// The expert's labels of one rollout and the term's schedule.
#[derive(Debug)]
pub struct Kickstart {
    config: KickstartConfig,
    /// `[T·N, A]` f32 labels, step t of env n in row `t·N + n` (the storage's flattening).
    labels: Tensor,
    envs: usize,
    scratch: Vec<f64>,
}

impl Kickstart {
    /// Labels for rollouts of `steps` steps of `envs` rows with `action_dim` actions.
    pub fn new(config: KickstartConfig, steps: usize, envs: usize, action_dim: usize) -> Self {
        Kickstart {
            config,
            labels: Tensor::zeros(
                [(steps * envs) as i64, action_dim as i64],
                (Kind::Float, tch::Device::Cpu),
            ),
            envs,
            scratch: vec![0.0; envs * action_dim],
        }
    }

    /// The term's weight in the update after `iteration` completed PPO iterations (a
    /// resumed run continues the schedule).
    pub fn coef(&self, iteration: usize) -> f64 {
        self.config.coef(iteration)
    }

    /// Asks `env` for the expert's action in every row's current state (before stepping it)
    /// and keeps them as the labels of rollout step `step`.
    pub fn label(&mut self, env: &mut dyn VecEnv, step: usize) -> Result<(), LearnError> {
        env.expert_actions(&mut self.scratch)?;
        check_finite("expert action", &self.scratch)?;
        let rows = to_tensor(&self.scratch, self.envs, self.scratch.len() / self.envs);
        let n = self.envs as i64;
        self.labels.narrow(0, step as i64 * n, n).copy_(&rows);
        Ok(())
    }

    /// The term for [`Ppo::update_with`](crate::ppo::Ppo::update_with) at weight `coef`, and
    /// the figures it gathers while the update runs.
    pub fn term(&self, coef: f64) -> KickstartTerm<'_> {
        KickstartTerm {
            labels: &self.labels,
            coef,
            bc_loss_sum: 0.0,
            agreement_sum: 0.0,
            batches: 0,
        }
    }
}

/// One update's behaviour-cloning term ([`Kickstart::term`]).
#[derive(Debug)]
pub struct KickstartTerm<'a> {
    labels: &'a Tensor,
    coef: f64,
    bc_loss_sum: f64,
    agreement_sum: f64,
    batches: usize,
}

impl KickstartTerm<'_> {
    /// `coef · mean((mean − label)²)` on the minibatch's rows.
    pub fn loss(&mut self, batch: &Batch, mean: &Tensor) -> Tensor {
        let labels = self.labels.index_select(0, &batch.rows);
        let bc = (mean - &labels).square().mean(Kind::Float);
        self.bc_loss_sum += bc.double_value(&[]);
        let agree = tch::no_grad(|| {
            (&batch.old_means - &labels)
                .abs()
                .le(AGREEMENT_TOLERANCE)
                .all_dim(1, false)
                .to_kind(Kind::Float)
                .mean(Kind::Float)
                .double_value(&[])
        });
        self.agreement_sum += agree;
        self.batches += 1;
        bc * self.coef
    }

    pub fn stats(&self) -> KickstartStats {
        let n = self.batches.max(1) as f64;
        KickstartStats {
            coef: self.coef,
            bc_loss: self.bc_loss_sum / n,
            expert_agreement: self.agreement_sum / n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(bc_coef: f64, anneal_iterations: usize) -> KickstartConfig {
        KickstartConfig {
            bc_coef,
            anneal_iterations,
        }
    }

    #[test]
    fn the_weight_falls_linearly_to_zero() {
        let k = Kickstart::new(config(0.5, 4), 2, 3, 1);
        let coefs: Vec<f64> = (0..6).map(|i| k.coef(i)).collect();
        assert_eq!(coefs, [0.5, 0.375, 0.25, 0.125, 0.0, 0.0]);
    }

    #[test]
    fn the_term_gathers_the_minibatch_rows_labels() {
        // 2 steps x 2 envs x 1 action; labels 10, 20 (step 0) and 30, 40 (step 1).
        let k = Kickstart::new(config(2.0, 1), 2, 2, 1);
        for (step, values) in [[10.0, 20.0], [30.0, 40.0]].iter().enumerate() {
            k.labels
                .narrow(0, step as i64 * 2, 2)
                .copy_(&Tensor::from_slice(values).view([2, 1]));
        }
        let rows = Tensor::from_slice(&[3i64, 0]);
        let batch = Batch {
            obs: Tensor::zeros([2, 1], (Kind::Float, tch::Device::Cpu)),
            critic_obs: Tensor::zeros([2, 1], (Kind::Float, tch::Device::Cpu)),
            actions: Tensor::zeros([2, 1], (Kind::Float, tch::Device::Cpu)),
            old_values: Tensor::zeros([2], (Kind::Float, tch::Device::Cpu)),
            advantages: Tensor::zeros([2], (Kind::Float, tch::Device::Cpu)),
            returns: Tensor::zeros([2], (Kind::Float, tch::Device::Cpu)),
            old_log_probs: Tensor::zeros([2], (Kind::Float, tch::Device::Cpu)),
            // Row 3's rollout mean agreed with its label (40), row 0's (label 10) did not.
            old_means: Tensor::from_slice(&[40.05f32, 0.0]).view([2, 1]),
            old_stds: Tensor::ones([2, 1], (Kind::Float, tch::Device::Cpu)),
            rows,
        };
        let mean = Tensor::from_slice(&[41.0f32, 8.0]).view([2, 1]);
        let mut term = k.term(2.0);
        let loss = term.loss(&batch, &mean).double_value(&[]);
        // ((41 - 40)^2 + (8 - 10)^2) / 2 = 2.5, times 2.
        assert!((loss - 5.0).abs() < 1e-6, "{loss}");
        let stats = term.stats();
        assert_eq!((stats.coef, stats.expert_agreement), (2.0, 0.5));
        assert!((stats.bc_loss - 2.5).abs() < 1e-6);
    }
}
