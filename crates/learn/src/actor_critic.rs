//! rsl_rl's actor–critic: two separate ELU MLPs (the actor gives the Gaussian mean, the critic
//! the state value), a learned state-independent per-dimension std, and an optional shared
//! empirical observation normalizer in front of both.

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
    normalizer: Option<EmpiricalNormalizer>,
}

impl ActorCritic {
    /// Fresh networks with PyTorch's default initialisation and std `config.init_std`.
    pub fn new(obs_dim: usize, action_dim: usize, config: &PolicyConfig) -> Self {
        let vs = nn::VarStore::new(Device::Cpu);
        let hidden = |h: &[usize]| h.iter().map(|&n| n as i64).collect::<Vec<_>>();
        let (obs, act) = (obs_dim as i64, action_dim as i64);
        let root = vs.root();
        let actor = Mlp::new(&(&root / "actor"), obs, &hidden(&config.actor_hidden), act);
        let critic = Mlp::new(&(&root / "critic"), obs, &hidden(&config.critic_hidden), 1);
        let init = match config.std_type {
            StdType::Scalar => config.init_std,
            StdType::Log => config.init_std.ln(),
        };
        let std_param = root.var(std_var_name(config.std_type), &[act], nn::Init::Const(init));
        let normalizer = config
            .obs_normalization
            .then(|| EmpiricalNormalizer::new(obs));
        ActorCritic {
            vs,
            actor,
            critic,
            std_param,
            std_type: config.std_type,
            normalizer,
        }
    }

    pub fn var_store(&self) -> &nn::VarStore {
        &self.vs
    }

    pub fn actor(&self) -> &Mlp {
        &self.actor
    }

    pub fn normalizer(&self) -> Option<&EmpiricalNormalizer> {
        self.normalizer.as_ref()
    }

    /// Replaces the normalizer statistics (checkpoint resume); `None` if the config has no
    /// normalizer.
    pub fn normalizer_mut(&mut self) -> Option<&mut EmpiricalNormalizer> {
        self.normalizer.as_mut()
    }

    /// `[A]` action std, always in `[STD_MIN, STD_MAX]`.
    pub fn std(&self) -> Tensor {
        match self.std_type {
            StdType::Scalar => self.std_param.clamp(STD_MIN, STD_MAX),
            StdType::Log => self.std_param.clamp(STD_MIN.ln(), STD_MAX.ln()).exp(),
        }
    }

    /// Learns normalizer statistics from raw observations `[B, O]` (no-op without one).
    pub fn update_normalizer(&mut self, obs: &Tensor) {
        if let Some(n) = self.normalizer.as_mut() {
            n.update(obs);
        }
    }

    fn normalize(&self, obs: &Tensor) -> Tensor {
        match &self.normalizer {
            Some(n) => n.normalize(obs),
            None => obs.shallow_clone(),
        }
    }

    /// `[B]` critic values of raw observations, without gradient.
    pub fn value(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.critic.forward(&self.normalize(obs)).squeeze_dim(-1))
    }

    /// `[B, A]` deterministic action (the Gaussian mean): what evaluation and export run.
    pub fn act_deterministic(&self, obs: &Tensor) -> Tensor {
        tch::no_grad(|| self.actor.forward(&self.normalize(obs)))
    }

    /// Samples actions for a rollout step from raw observations `[B, O]`.
    pub fn act(&self, obs: &Tensor) -> Sample {
        tch::no_grad(|| {
            let x = self.normalize(obs);
            let mean = self.actor.forward(&x);
            let std = self.std().expand_as(&mean);
            let actions = &mean + &std * mean.randn_like();
            let log_prob = gaussian::log_prob(&actions, &mean, &std);
            let values = self.critic.forward(&x).squeeze_dim(-1);
            Sample {
                actions,
                log_prob,
                values,
                mean,
                std,
            }
        })
    }

    /// Log-probabilities, entropy and values of a minibatch, with gradient.
    pub fn evaluate(&self, obs: &Tensor, actions: &Tensor) -> Evaluation {
        let x = self.normalize(obs);
        let mean = self.actor.forward(&x);
        let std = self.std();
        Evaluation {
            log_prob: gaussian::log_prob(actions, &mean, &std),
            entropy: gaussian::entropy(&std),
            values: self.critic.forward(&x).squeeze_dim(-1),
            mean,
            std,
        }
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
            std_type,
            obs_normalization: true,
        }
    }

    #[test]
    fn std_starts_at_init_and_stays_positive() {
        for std_type in [StdType::Scalar, StdType::Log] {
            let ac = ActorCritic::new(3, 2, &config(std_type));
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
        let ac = ActorCritic::new(3, 2, &config(StdType::Scalar));
        let names: Vec<String> = ac.var_store().variables().into_keys().collect();
        assert!(names.contains(&"actor.1.weight".to_string()));
        assert!(names.contains(&"critic.2.bias".to_string()));
        let obs = Tensor::randn([5, 3], (Kind::Float, Device::Cpu));
        let s = ac.act(&obs);
        let e = ac.evaluate(&obs, &s.actions);
        assert!(f64::try_from((e.log_prob - s.log_prob).abs().max()).unwrap() < 1e-6);
        assert!(f64::try_from((e.values - s.values).abs().max()).unwrap() < 1e-6);
        assert_eq!(s.actions.size(), vec![5, 2]);
    }
}
