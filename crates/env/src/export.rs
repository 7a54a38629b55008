//! The onboard policy file of [`moonhaul_core::policy`] from a trained actor, whichever trainer
//! made it (`moonhaul-train`'s tch actor, or stock rsl_rl's through the `moonhaul` Python
//! package): the actor's layers (the Gaussian mean; the std is training-only), the actor's
//! observation normalizer with rsl_rl's ε already folded into its std, and the environment's
//! action map and layout. The critic and its normalizer are training-only: the robot never
//! sees the critic's privileged observations.

use std::collections::BTreeMap;
use std::path::Path;

use moonhaul_core::policy::{
    ActionAffine, Activation, Linear, ObsNormalizer, Policy, PolicyMetadata, Tensor,
};
use moonhaul_core::state::Phase;

use crate::config::TrainConfig;
use crate::task::export_identity;
use crate::{provenance, EnvError, VecEnv};

/// rsl_rl's `EmpiricalNormalization` divides by `std + eps` with this ε (its default, and
/// `moonhaul-train`'s normalizer's); the file stores `std + ε`.
pub const NORMALIZER_EPS: f64 = 1e-2;

fn vector(values: &[f64]) -> Tensor {
    Tensor::vector(values.iter().map(|&v| v as f32).collect())
}

/// The phase and metadata of a policy trained on `env` from `config`, whichever trainer made
/// it: `trainer`'s entries (who trained it, seed, iterations, samples) under what the file must
/// say of itself — the task's identity and observation layout, the environment's action map,
/// the config's digest, the source `commit` and the payload file — which `trainer` cannot
/// override.
pub fn policy_provenance(
    config: &TrainConfig,
    env: &dyn VecEnv,
    commit: String,
    payload_file: Option<&Path>,
    mut trainer: BTreeMap<String, String>,
) -> Result<(Phase, BTreeMap<String, String>), EnvError> {
    let (phase, identity) = export_identity(config.run.task);
    trainer.extend(identity);
    trainer.extend(env.policy_metadata());
    trainer.insert("config_sha256".into(), provenance::config_digest(config)?);
    trainer.insert("commit".into(), commit);
    if let Some(path) = payload_file {
        trainer.insert("payload_file".into(), path.display().to_string());
    }
    Ok((phase, trainer))
}

/// A validated [`Policy`] of an ELU actor. `obs_norm` is the normalizer as the file stores it
/// (`None`: identity); `action_scale`/`action_offset` are the environment's action map;
/// `extra` goes into the free-form metadata (the environment's `policy_metadata`, provenance).
pub fn assemble_policy(
    phase: Phase,
    layers: Vec<Linear>,
    obs_norm: Option<ObsNormalizer>,
    action_scale: &[f64],
    action_offset: &[f64],
    extra: BTreeMap<String, String>,
) -> Result<Policy, EnvError> {
    let obs_dim = layers.first().map_or(0, |l| l.weight.shape()[1]);
    let obs_norm = obs_norm.unwrap_or_else(|| ObsNormalizer {
        mean: vector(&vec![0.0; obs_dim]),
        std: vector(&vec![1.0; obs_dim]),
    });
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
