//! Export of `moonhaul-train`'s tch actor to the onboard policy file: its tensors as the core's,
//! assembled by [`moonhaul_env::export::assemble_policy`] (shared with the rsl_rl path).

use std::collections::BTreeMap;

use moonhaul_core::policy::{Linear, ObsNormalizer, Policy, Tensor as PolicyTensor};
use moonhaul_core::state::Phase;
use moonhaul_env::export::assemble_policy;
use tch::Tensor;

use crate::actor_critic::ActorCritic;
use crate::LearnError;

fn to_policy_tensor(t: &Tensor) -> Result<PolicyTensor, LearnError> {
    let shape = t.size().iter().map(|&d| d as usize).collect();
    let data: Vec<f32> = Vec::try_from(&t.flatten(0, -1))?;
    Ok(PolicyTensor::new(shape, data)?)
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
    let obs_norm = policy
        .obs_normalizer()
        .map(|n| {
            Ok::<_, LearnError>(ObsNormalizer {
                mean: to_policy_tensor(n.mean())?,
                std: to_policy_tensor(&n.export_std())?,
            })
        })
        .transpose()?;
    Ok(assemble_policy(
        phase,
        layers,
        obs_norm,
        action_scale,
        action_offset,
        extra,
    )?)
}
