//! Export of a trained actor to the onboard policy file of [`moonhaul_core::policy`]: the
//! actor's layers (the Gaussian mean; the std is training-only), the actor's observation
//! normalizer with rsl_rl's ε folded into the std, and the env's action map. The critic and its
//! normalizer are training-only: the robot never sees the critic's privileged observations.

use std::collections::BTreeMap;

use moonhaul_core::policy::{
    ActionAffine, Activation, Linear, ObsNormalizer, Policy, PolicyMetadata, Tensor as PolicyTensor,
};
use moonhaul_core::state::Phase;
use tch::Tensor;

use crate::actor_critic::ActorCritic;
use crate::LearnError;

fn to_policy_tensor(t: &Tensor) -> Result<PolicyTensor, LearnError> {
    let shape = t.size().iter().map(|&d| d as usize).collect();
    let data: Vec<f32> = Vec::try_from(&t.flatten(0, -1))?;
    Ok(PolicyTensor::new(shape, data)?)
}

fn vector(values: &[f64]) -> PolicyTensor {
    PolicyTensor::vector(values.iter().map(|&v| v as f32).collect())
}

/// The actor as a validated core [`Policy`]. `action_scale`/`action_offset` are the env's
/// action map; `extra` goes into the free-form metadata.
pub fn export_policy(
    policy: &ActorCritic,
    phase: Phase,
    action_scale: &[f64],
    action_offset: &[f64],
    extra: BTreeMap<String, String>,
) -> Result<Policy, LearnError> {
    let layers = policy
        .actor()
        .layers()
        .iter()
        .map(|l| {
            let bias = l.bs.as_ref().map(to_policy_tensor).transpose()?;
            let bias =
                bias.unwrap_or_else(|| PolicyTensor::vector(vec![0.0; l.ws.size()[0] as usize]));
            Ok(Linear {
                weight: to_policy_tensor(&l.ws)?,
                bias,
            })
        })
        .collect::<Result<Vec<_>, LearnError>>()?;
    let obs_dim = layers.first().map_or(0, |l| l.weight.shape()[1]);
    let obs_norm = match policy.obs_normalizer() {
        Some(n) => ObsNormalizer {
            mean: to_policy_tensor(n.mean())?,
            std: to_policy_tensor(&n.export_std())?,
        },
        None => ObsNormalizer {
            mean: vector(&vec![0.0; obs_dim]),
            std: vector(&vec![1.0; obs_dim]),
        },
    };
    let hidden_sizes = layers
        .iter()
        .take(layers.len().saturating_sub(1))
        .map(|l| l.bias.shape()[0])
        .collect();
    let metadata = PolicyMetadata {
        phase,
        obs_dim,
        action_dim: action_scale.len(),
        hidden_sizes,
        activation: Activation::Elu,
        obs_clip: None,
        extra,
    };
    let action = ActionAffine {
        scale: vector(action_scale),
        offset: vector(action_offset),
    };
    Ok(Policy::new(metadata, layers, obs_norm, action)?)
}
