//! The onboard policy runtime: a pure-Rust MLP that runs a phase policy trained elsewhere.
//!
//! Training (tch/libtorch, `moonhaul-learn`) and the robots share nothing but a **policy
//! file**; this module defines that file, loads it with full validation ([`Policy::from_file`]),
//! writes it ([`Policy::write_file`], used by the trainer's exporter) and evaluates it without
//! allocating ([`Policy::act`]).
//!
//! # Policy file format, version 1
//!
//! A [safetensors](https://github.com/huggingface/safetensors) file. Every tensor is dtype
//! `F32`, little-endian, row-major (C order). For `L = hidden_sizes.len() + 1` layers and
//! widths `n_0 = obs_dim`, `n_1..n_{L-1} = hidden_sizes`, `n_L = action_dim`:
//!
//! | tensor | shape | meaning |
//! |---|---|---|
//! | `actor.{i}.weight`, i = 0, …, L−1 | `[n_{i+1}, n_i]` | layer i computes `W x + b` (PyTorch `nn.Linear` layout) |
//! | `actor.{i}.bias`, i = 0, …, L−1 | `[n_{i+1}]` | |
//! | `obs_norm.mean` | `[obs_dim]` | observation normalizer mean |
//! | `obs_norm.std` | `[obs_dim]` | normalizer std, finite and > 0 (the exporter folds any epsilon in) |
//! | `action.scale` | `[action_dim]` | action scale |
//! | `action.offset` | `[action_dim]` | action offset |
//!
//! No other tensor may be present: a layer beyond `hidden_sizes`, critic weights or the policy
//! std in the file are errors ([`PolicyError::UnexpectedTensor`]), because they mean the
//! exporter and this reader disagree about the network, and guessing would run a different
//! network than the one trained.
//!
//! The forward pass, computed in f32:
//!
//! ```text
//! x_0    = (obs - mean) / std                      elementwise; then clamped to ±obs_clip if set
//! x_i+1  = ELU(W_i x_i + b_i)                      i < L-1, ELU(v) = v if v > 0 else exp(v) - 1
//! out    = W_{L-1} x_{L-1} + b_{L-1}               linear output layer: the Gaussian mean
//! action = offset + scale ⊙ out
//! ```
//!
//! The policy's action noise (Gaussian std) is a training-only parameter and is not exported.
//! Observations are rounded to f32 before normalizing and the normalizer divides (it does not
//! multiply by a reciprocal), so the result differs from an f32 tch forward pass only by
//! summation order.
//!
//! `__metadata__` (string → string), all keys required unless marked optional:
//!
//! | key | value |
//! |---|---|
//! | `format` | `moonhaul-policy` |
//! | `format_version` | `1` |
//! | `phase` | `lift`, `transport` or `place` ([`Phase`](crate::state::Phase) names; `idle` runs no policy) |
//! | `obs_dim`, `action_dim` | positive decimal integers |
//! | `hidden_sizes` | comma-separated positive integers, input side first, e.g. `256,128,64`; empty = no hidden layer |
//! | `activation` | `elu` |
//! | `obs_clip` (optional) | finite float >= [`MIN_OBS_CLIP`] (1); absent = no clipping |
//! | any other key | free-form (`created_by`, `train_run`, `env_steps`, ...), preserved verbatim |
//!
//! Every parameter is finite and within ±[`MAX_PARAMETER_ABS`], and every normalizer std at
//! least [`MIN_OBS_STD`]: a file that would overflow the forward pass is refused at load (and
//! by `moonhaul policy inspect`), not found out in flight.
//!
//! Metadata and tensor shapes must agree exactly; every violation has its own
//! [`PolicyError`] variant naming the key or tensor (and expected vs found shape).
//!
//! Limits, checked before anything is allocated from a size the file declares: the file is a
//! regular file of at most [`MAX_POLICY_BYTES`](crate::input::MAX_POLICY_BYTES), its header
//! at most [`MAX_HEADER_BYTES`], `hidden_sizes` at most [`MAX_HIDDEN_LAYERS`] entries, and
//! every width and the network's total at most [`MAX_VALUES`] f32 values (what a file of the
//! maximum size can hold).
//!
//! # Example
//!
//! ```no_run
//! # fn main() -> Result<(), moonhaul_core::policy::PolicyError> {
//! use moonhaul_core::policy::Policy;
//!
//! let policy = Policy::from_file("assets/policies/lift.safetensors")?;
//! let mut scratch = policy.scratch(); // once
//! let obs = vec![0.0; policy.obs_dim()];
//! let mut action = vec![0.0; policy.action_dim()];
//! policy.act(&obs, &mut scratch, &mut action)?; // every tick, no allocation
//! # Ok(())
//! # }
//! ```

mod error;
mod file;
mod metadata;
mod network;

pub use error::PolicyError;
pub use metadata::{
    Activation, PolicyMetadata, FORMAT_NAME, FORMAT_VERSION, MAX_HEADER_BYTES, MAX_HIDDEN_LAYERS,
    MAX_VALUES, MIN_OBS_CLIP,
};
pub use network::{
    ActionAffine, Linear, ObsNormalizer, Policy, PolicyScratch, Tensor, MAX_PARAMETER_ABS,
    MIN_OBS_STD,
};

#[cfg(test)]
mod tests;
