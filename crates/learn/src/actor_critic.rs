//! rsl_rl's actor–critic: two separate ELU MLPs (the actor gives the Gaussian mean, the critic
//! the state value), a learned state-independent per-dimension std, and optional empirical
//! observation normalizers in front of each.
//!
//! The critic is asymmetric (rsl_rl's `critic` observation group): it reads the env's critic
//! observations, which may carry privileged state, while the actor reads only what the robot
//! observes (see [`crate::env`]). Each network therefore has its own normalizer, as rsl_rl's
//! `obs_normalizer` and `critic_obs_normalizer`.

use tch::nn::{self, Module};
use tch::{Device, Tensor};

use crate::config::{PolicyConfig, StdType};
use crate::gaussian;
use crate::mlp::Mlp;
use crate::normalizer::EmpiricalNormalizer;

/// rsl_rl's default std range: keeps σ positive (and log σ finite) whatever the optimizer does.
pub const STD_MIN: f64 = 1e-6;
pub const STD_MAX: f64 = 1e6;

/// Variable-store names of the std parameter, distinct per parameterisation so a checkpoint
/// of the other kind is rejected instead of misread.
fn std_var_name(std_type: StdType) -> &'static str {
    match std_type {
        StdType::Scalar => "std",
        StdType::Log => "log_std",
    }
}

/// What a rollout step records about the policy's decision.
#[derive(Debug)]
pub struct Sample {
    /// `[B, A]` sampled actions.
    pub actions: Tensor,
    /// `[B]` log-probability of `actions`.
    pub log_prob: Tensor,
    /// `[B]` critic values.
    pub values: Tensor,
    /// `[B, A]` Gaussian mean and std (for the KL of the adaptive schedule).
    pub mean: Tensor,
    pub std: Tensor,
}

/// The policy's differentiable view of a minibatch.
#[derive(Debug)]
pub struct Evaluation {
    pub log_prob: Tensor,
    /// Scalar: entropy of the (state-independent) Gaussian.
    pub entropy: Tensor,
    pub values: Tensor,
    pub mean: Tensor,
    /// `[A]`.
    pub std: Tensor,
}

#[derive(Debug)]
pub struct ActorCritic {
    vs: nn::VarStore,
    actor: Mlp,
    critic: Mlp,
    std_param: Tensor,
    std_type: StdType,
    obs_dim: usize,
    critic_obs_dim: usize,
    obs_normalizer: Option<EmpiricalNormalizer>,
    critic_obs_normalizer: Option<EmpiricalNormalizer>,
}

impl ActorCritic {
    /// Fresh networks with PyTorch's default initialisation (the actor's output layer scaled by
    /// `config.actor_output_gain`) and std `config.init_std`: the actor on `obs_dim` inputs,
    /// the critic on `critic_obs_dim`.
    pub fn new(
        obs_dim: usize,
        critic_obs_dim: usize,
        action_dim: usize,
        config: &PolicyConfig,
    ) -> Self {
        let vs = nn::VarStore::new(Device::Cpu);
        let hidden = |h: &[usize]| h.iter().map(|&n| n as i64).collect::<Vec<_>>();
        let (obs, critic_obs, act) = (obs_dim as i64, critic_obs_dim as i64, action_dim as i64);
        let root = vs.root();
        let actor = Mlp::new(&(&root / "actor"), obs, &hidden(&config.actor_hidden), act);
        if let Some(last) = actor.layers().last() {
            // Scaling the output layer makes the initial mean action ≈ 0, i.e. the task's
            // offset: for the phase tasks, the grasp pose rather than a random jerk off it.
            tch::no_grad(|| {
                let _ = last
                    .ws
                    .shallow_clone()
                    .g_mul_scalar_(config.actor_output_gain);
                if let Some(b) = &last.bs {
                    let _ = b.shallow_clone().g_mul_scalar_(config.actor_output_gain);
                }
            });
        }
        let critic_hidden = hidden(&config.critic_hidden);
        let critic = Mlp::new(&(&root / "critic"), critic_obs, &critic_hidden, 1);
        let init = match config.std_type {
            StdType::Scalar => config.init_std,
            StdType::Log => config.init_std.ln(),
        };
        let std_param = root.var(std_var_name(config.std_type), &[act], nn::Init::Const(init));
        let normalizer = |dim| {
            config
                .obs_normalization
                .then(|| EmpiricalNormalizer::new(dim))
        };
        ActorCritic {
            vs,
            actor,
            critic,
            std_param,
            std_type: config.std_type,
            obs_dim,
            critic_obs_dim,
            obs_normalizer: normalizer(obs),
            critic_obs_normalizer: normalizer(critic_obs),
        }
    }

    pub fn var_store(&self) -> &nn::VarStore {
        &self.vs
    }

    pub fn actor(&self) -> &Mlp {
        &self.actor
    }

    /// Width of the actor's observation.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Width of the critic's observation.
    pub fn critic_obs_dim(&self) -> usize {
        self.critic_obs_dim
    }

    pub fn action_dim(&self) -> usize {
        self.std_param.size()[0] as usize
    }

    /// The actor's normalizer (exported with the policy).
    pub fn obs_normalizer(&self) -> Option<&EmpiricalNormalizer> {
        self.obs_normalizer.as_ref()
    }

    /// The critic's normalizer (training only).
    pub fn critic_obs_normalizer(&self) -> Option<&EmpiricalNormalizer> {
        self.critic_obs_normalizer.as_ref()
    }

    /// Replaces the actor normalizer's statistics (checkpoint resume); `None` if the config has
    /// no normalization.
    pub fn obs_normalizer_mut(&mut self) -> Option<&mut EmpiricalNormalizer> {
        self.obs_normalizer.as_mut()
    }

    /// Replaces the critic normalizer's statistics (checkpoint resume).
    pub fn critic_obs_normalizer_mut(&mut self) -> Option<&mut EmpiricalNormalizer> {
        self.critic_obs_normalizer.as_mut()
    }

    /// `[A]` action std, always in `[STD_MIN, STD_MAX]`.
    pub fn std(&self) -> Tensor {
        match self.std_type {
            StdType::Scalar => self.std_param.clamp(STD_MIN, STD_MAX),
            StdType::Log => self.std_param.clamp(STD_MIN.ln(), STD_MAX.ln()).exp(),
        }
    }

    /// Learns normalizer statistics from raw observations `[B, O]` and critic observations
    /// `[B, C]` (no-op without normalization).
    pub fn update_normalizers(&mut self, obs: &Tensor, critic_obs: &Tensor) {
        if let Some(n) = self.obs_normalizer.as_mut() {
            n.update(obs);
        }
        if let Some(n) = self.critic_obs_normalizer.as_mut() {
            n.update(critic_obs);
        }
    }

    /// Learns the actor normalizer's statistics alone from raw observations `[B, O]`: DAgger
    /// visits states without valuing them ([`crate::distill`]).
    pub fn update_obs_normalizer(&mut self, obs: &Tensor) {
        if let Some(n) = self.obs_normalizer.as_mut() {
            n.update(obs);
        }
    }

    /// Learns the critic normalizer's statistics alone from raw critic observations `[B, C]`:
    /// the critic's warm-up leaves everything the actor computes with as it was.
    pub fn update_critic_obs_normalizer(&mut self, critic_obs: &Tensor) {
        if let Some(n) = self.critic_obs_normalizer.as_mut() {
            n.update(critic_obs);
        }
    }

    /// `[B, A]` Gaussian mean of observations already passed through
    /// [`ActorCritic::normalize_obs`], with gradient (the behaviour-cloning fit).
    pub fn mean_normalized(&self, obs: &Tensor) -> Tensor {
        self.actor.forward(obs)
    }

    /// `[B]` values of critic observations already passed through
    /// [`ActorCritic::normalize_critic_obs`], with gradient (the critic's warm-up).
    pub fn values_normalized(&self, critic_obs: &Tensor) -> Tensor {
        self.critic_forward(critic_obs)
    }

    /// `[B, A]` Gaussian mean of raw observations `[B, O]`.
    fn actor_mean(&self, obs: &Tensor) -> Tensor {
        self.actor
            .forward(&normalize(self.obs_normalizer.as_ref(), obs))
    }

    /// `[B]` values of raw critic observations `[B, C]`.
    fn critic_value(&self, critic_obs: &Tensor) -> Tensor {
        self.critic_forward(&normalize(self.critic_obs_normalizer.as_ref(), critic_obs))
    }

    /// `[B]` values of normalized critic observations.
    fn critic_forward(&self, normalized: &Tensor) -> Tensor {
        self.critic.forward(normalized).squeeze_dim(-1)
    }

    /// `[B]` critic values of raw critic observations `[B, C]`, without gradient.
    pub fn value(&self, critic_obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.critic_value(critic_obs))
    }

    /// `[B, A]` deterministic action (the Gaussian mean): what evaluation and export run.
    pub fn act_deterministic(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.actor_mean(obs))
    }

    /// Samples actions for a rollout step from raw observations `[B, O]`, valued on the raw
    /// critic observations `[B, C]` of the same rows.
    ///
    /// The log-prob reads the `[A]` std and lets it broadcast, so `σ²` and `ln σ` are computed
    /// on `A` values instead of `B·A` (the same numbers); only the returned `std` is expanded.
    pub fn act(&self, obs: &Tensor, critic_obs: &Tensor) -> Sample {
        tch::no_grad(|| {
            let mean = self.actor_mean(obs);
            let std = self.std();
            let actions = &mean + &std * mean.randn_like();
            let log_prob = gaussian::log_prob(&actions, &mean, &std);
            let values = self.critic_value(critic_obs);
            Sample {
                std: std.expand_as(&mean),
                actions,
                log_prob,
                values,
                mean,
            }
        })
    }

    /// Log-probabilities, entropy and values of a minibatch, with gradient.
    pub fn evaluate(&self, obs: &Tensor, critic_obs: &Tensor, actions: &Tensor) -> Evaluation {
        self.evaluate_normalized(
            &normalize(self.obs_normalizer.as_ref(), obs),
            &normalize(self.critic_obs_normalizer.as_ref(), critic_obs),
            actions,
        )
    }

    /// The actor's normalizer applied to raw observations `[B, O]` (identity without one).
    pub fn normalize_obs(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| normalize(self.obs_normalizer.as_ref(), obs))
    }

    /// The critic's normalizer applied to raw critic observations `[B, C]`.
    pub fn normalize_critic_obs(&self, critic_obs: &Tensor) -> Tensor {
        tch::no_grad(|| normalize(self.critic_obs_normalizer.as_ref(), critic_obs))
    }

    /// [`ActorCritic::evaluate`] on observations already passed through
    /// [`ActorCritic::normalize_obs`] and [`ActorCritic::normalize_critic_obs`]: the PPO update
    /// normalizes the whole rollout once (the statistics are fixed during an update) instead of
    /// every minibatch of every epoch.
    pub fn evaluate_normalized(
        &self,
        obs: &Tensor,
        critic_obs: &Tensor,
        actions: &Tensor,
    ) -> Evaluation {
        let mean = self.actor.forward(obs);
        let std = self.std();
        Evaluation {
            log_prob: gaussian::log_prob(actions, &mean, &std),
            entropy: gaussian::entropy(&std),
            values: self.critic_forward(critic_obs),
            mean,
            std,
        }
    }
}

fn normalize(normalizer: Option<&EmpiricalNormalizer>, x: &Tensor) -> Tensor {
    match normalizer {
        Some(n) => n.normalize(x),
        None => x.shallow_clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    fn config(std_type: StdType) -> PolicyConfig {
        PolicyConfig {
            actor_hidden: vec![8],
            critic_hidden: vec![8, 8],
            init_std: 1.0,
            actor_output_gain: 1.0,
            std_type,
            obs_normalization: true,
        }
    }

    #[test]
    fn std_starts_at_init_and_stays_positive() {
        for std_type in [StdType::Scalar, StdType::Log] {
            let ac = ActorCritic::new(3, 3, 2, &config(std_type));
            let std: Vec<f32> = Vec::try_from(&ac.std()).unwrap();
            assert_eq!(std, vec![1.0, 1.0]);
            // Drive the raw parameter far negative, as a bad update could.
            tch::no_grad(|| {
                let mut p = ac.std_param.shallow_clone();
                p.copy_(&Tensor::from_slice(&[-5.0f32, -1e9]));
            });
            let std: Vec<f32> = Vec::try_from(&ac.std()).unwrap();
            // exp(ln 1e-6) in f32 may land an ulp below 1e-6.
            assert!(
                std.iter()
                    .all(|&s| s >= 0.99 * STD_MIN as f32 && s.is_finite()),
                "{std:?}"
            );
        }
    }

    #[test]
    fn evaluate_matches_act_and_separates_actor_from_critic() {
        tch::manual_seed(0);
        let ac = ActorCritic::new(3, 3, 2, &config(StdType::Scalar));
        let names: Vec<String> = ac.var_store().variables().into_keys().collect();
        assert!(names.contains(&"actor.1.weight".to_string()));
        assert!(names.contains(&"critic.2.bias".to_string()));
        let obs = Tensor::randn([5, 3], (Kind::Float, Device::Cpu));
        let s = ac.act(&obs, &obs);
        let e = ac.evaluate(&obs, &obs, &s.actions);
        assert!(f64::try_from((e.log_prob - s.log_prob).abs().max()).unwrap() < 1e-6);
        assert!(f64::try_from((e.values - s.values).abs().max()).unwrap() < 1e-6);
        assert_eq!(s.actions.size(), vec![5, 2]);
    }

    #[test]
    fn critic_reads_the_wider_critic_observations() {
        tch::manual_seed(1);
        let opts = (Kind::Float, Device::Cpu);
        let mut ac = ActorCritic::new(3, 4, 2, &config(StdType::Scalar));
        let vars = ac.var_store().variables();
        assert_eq!(vars["actor.0.weight"].size(), [8, 3]);
        assert_eq!(vars["critic.0.weight"].size(), [8, 4]);
        assert_eq!(
            (ac.obs_dim(), ac.critic_obs_dim(), ac.action_dim()),
            (3, 4, 2)
        );

        let obs = Tensor::randn([6, 3], opts);
        let critic_obs = Tensor::randn([6, 4], opts) * 2.0 + 1.0;
        ac.update_normalizers(&obs, &critic_obs);
        let norm = |n: Option<&EmpiricalNormalizer>| n.expect("normalized").mean().copy();
        let (actor_mean, critic_mean) =
            (norm(ac.obs_normalizer()), norm(ac.critic_obs_normalizer()));
        let gap = |a: &Tensor, b: &Tensor| f64::try_from((a - b).abs().max()).unwrap();
        assert!(gap(&actor_mean, &obs.mean_dim(0, false, Kind::Float)) < 1e-6);
        assert!(gap(&critic_mean, &critic_obs.mean_dim(0, false, Kind::Float)) < 1e-6);

        // The privileged column moves the value but not the action.
        let shifted = critic_obs.copy();
        let mut privileged = shifted.narrow(1, 3, 1);
        privileged += 5.0;
        assert_eq!(ac.value(&critic_obs).size(), [6]);
        assert!(gap(&ac.value(&critic_obs), &ac.value(&shifted)) > 1e-4);
        // Judged through `evaluate` on one sampled action, not by reseeding the global RNG
        // around two `act` calls: parallel tests draw from that RNG too.
        let b = ac.act(&obs, &shifted);
        let plain = ac.evaluate(&obs, &critic_obs, &b.actions);
        let privileged = ac.evaluate(&obs, &shifted, &b.actions);
        assert!(gap(&plain.log_prob, &privileged.log_prob) < 1e-6);
        assert!(gap(&plain.values, &privileged.values) > 1e-4);
        assert!(gap(&privileged.values, &b.values) < 1e-6);

        // The critic cannot be fed the actor's narrower observation.
        let narrow = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| ac.value(&obs)));
        assert!(narrow.is_err(), "a [B, obs_dim] input reached the critic");
    }
}
