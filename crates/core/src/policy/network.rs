//! The policy in memory: validated parameters and the allocation-free forward pass.

use super::{PolicyError, PolicyMetadata};

/// Tensor name of layer `i`'s weight, `[out_i, in_i]`.
pub(super) fn weight_name(layer: usize) -> String {
    format!("actor.{layer}.weight")
}
/// Tensor name of layer `i`'s bias, `[out_i]`.
pub(super) fn bias_name(layer: usize) -> String {
    format!("actor.{layer}.bias")
}
pub(super) const OBS_MEAN: &str = "obs_norm.mean";
pub(super) const OBS_STD: &str = "obs_norm.std";
pub(super) const ACTION_SCALE: &str = "action.scale";
pub(super) const ACTION_OFFSET: &str = "action.offset";

/// Largest |value| of any parameter (weights, biases, normalizer mean and std, action scale
/// and offset). Trained parameters stay within a few hundred; one beyond a million is a
/// corrupt or hostile file, and values near `f32::MAX` overflow the first product of the
/// forward pass, which would latch a unit's fault in flight instead of failing the load.
pub const MAX_PARAMETER_ABS: f32 = 1e6;
/// Smallest normalizer std. The trainer's floor is rsl_rl's ε = 1e-2; a std below 1e-6
/// magnifies an observation's own rounding a million-fold (a denormal like 1e-45 turns every
/// input into infinity).
pub const MIN_OBS_STD: f32 = 1e-6;

/// A dense f32 tensor, row-major: the unit every policy parameter travels in, so a shape
/// error (a transposed weight, say) is caught even when the element count happens to match.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    shape: Vec<usize>,
    data: Vec<f32>,
}

impl Tensor {
    /// A tensor of the given shape; fails if `data.len()` is not the product of `shape`.
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Result<Self, PolicyError> {
        let needed = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        if needed != Some(data.len()) {
            return Err(PolicyError::TensorLength {
                shape,
                len: data.len(),
            });
        }
        Ok(Self { shape, data })
    }

    /// A 1-D tensor.
    pub fn vector(data: Vec<f32>) -> Self {
        Self {
            shape: vec![data.len()],
            data,
        }
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// The values, row-major.
    pub fn data(&self) -> &[f32] {
        &self.data
    }
}

/// One affine layer `y = W x + b`, PyTorch `nn.Linear` layout: `weight` is `[out, in]`,
/// `bias` is `[out]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
}

/// The observation normalizer: the network sees `(obs - mean) / std`.
#[derive(Debug, Clone, PartialEq)]
pub struct ObsNormalizer {
    pub mean: Tensor,
    /// Strictly positive; the exporter folds any epsilon in.
    pub std: Tensor,
}

/// Maps the network output to the action: `offset + scale ⊙ output`.
#[derive(Debug, Clone, PartialEq)]
pub struct ActionAffine {
    pub scale: Tensor,
    pub offset: Tensor,
}

/// A validated phase policy, ready to run. Build it with [`Policy::new`] or load it with
/// [`Policy::from_file`] / [`Policy::from_bytes`]; both go through the same validation.
#[derive(Debug, Clone, PartialEq)]
pub struct Policy {
    metadata: PolicyMetadata,
    layers: Vec<Linear>,
    obs_norm: ObsNormalizer,
    action: ActionAffine,
    /// Widest activation vector (input included): the scratch buffer length.
    width: usize,
}

/// Two ping-pong activation buffers for [`Policy::act`], so inference never allocates.
/// Make one per policy (or per thread) with [`Policy::scratch`] and reuse it every tick.
#[derive(Debug, Clone)]
pub struct PolicyScratch {
    front: Vec<f32>,
    back: Vec<f32>,
}

impl Policy {
    /// Validates and assembles a policy: metadata values, then every tensor's shape against
    /// the metadata, finiteness of every parameter, and `std > 0`.
    ///
    /// `layers` must hold `hidden_sizes.len() + 1` layers; a missing one is reported as
    /// [`PolicyError::MissingTensor`], a surplus one as [`PolicyError::UnexpectedTensor`].
    pub fn new(
        metadata: PolicyMetadata,
        layers: Vec<Linear>,
        obs_norm: ObsNormalizer,
        action: ActionAffine,
    ) -> Result<Self, PolicyError> {
        metadata.validate()?;
        let sizes = metadata.layer_sizes();
        let expected_layers = sizes.len() - 1;
        if layers.len() < expected_layers {
            return Err(PolicyError::MissingTensor {
                name: weight_name(layers.len()),
            });
        }
        if layers.len() > expected_layers {
            return Err(PolicyError::UnexpectedTensor {
                name: weight_name(expected_layers),
            });
        }
        for (i, (layer, io)) in layers.iter().zip(sizes.windows(2)).enumerate() {
            let (inputs, outputs) = (io[0], io[1]);
            check_tensor(&weight_name(i), &layer.weight, &[outputs, inputs])?;
            check_tensor(&bias_name(i), &layer.bias, &[outputs])?;
        }
        check_tensor(OBS_MEAN, &obs_norm.mean, &[metadata.obs_dim])?;
        check_tensor(OBS_STD, &obs_norm.std, &[metadata.obs_dim])?;
        if let Some((index, &value)) = obs_norm
            .std
            .data
            .iter()
            .enumerate()
            .find(|(_, &s)| s < MIN_OBS_STD)
        {
            return Err(PolicyError::StdTooSmall { index, value });
        }
        check_tensor(ACTION_SCALE, &action.scale, &[metadata.action_dim])?;
        check_tensor(ACTION_OFFSET, &action.offset, &[metadata.action_dim])?;

        let width = sizes.iter().copied().max().unwrap_or(0);
        Ok(Self {
            metadata,
            layers,
            obs_norm,
            action,
            width,
        })
    }

    pub fn metadata(&self) -> &PolicyMetadata {
        &self.metadata
    }

    /// The actor layers, input side first.
    pub fn layers(&self) -> &[Linear] {
        &self.layers
    }

    pub fn obs_normalizer(&self) -> &ObsNormalizer {
        &self.obs_norm
    }

    pub fn action_affine(&self) -> &ActionAffine {
        &self.action
    }

    pub fn obs_dim(&self) -> usize {
        self.metadata.obs_dim
    }

    pub fn action_dim(&self) -> usize {
        self.metadata.action_dim
    }

    /// Number of network parameters (all weights and biases; normalizer and action affine
    /// are not counted).
    pub fn param_count(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.weight.data.len() + l.bias.data.len())
            .sum()
    }

    /// Activation buffers sized for this policy, to pass to [`Policy::act`].
    pub fn scratch(&self) -> PolicyScratch {
        PolicyScratch {
            front: vec![0.0; self.width],
            back: vec![0.0; self.width],
        }
    }

    /// One forward pass: `action = offset + scale ⊙ MLP(clip((obs - mean) / std))`.
    ///
    /// Computes in f32 like the trainer's tch forward pass (observations are rounded to f32
    /// first) and widens the result to f64. Allocates nothing. Wrong buffer lengths and
    /// non-finite inputs or outputs are errors, never panics; on error `action` is untouched.
    pub fn act(
        &self,
        obs: &[f64],
        scratch: &mut PolicyScratch,
        action: &mut [f64],
    ) -> Result<(), PolicyError> {
        let (obs_dim, action_dim) = (self.metadata.obs_dim, self.metadata.action_dim);
        if obs.len() != obs_dim {
            return Err(PolicyError::ObsLength {
                expected: obs_dim,
                found: obs.len(),
            });
        }
        if action.len() != action_dim {
            return Err(PolicyError::ActionLength {
                expected: action_dim,
                found: action.len(),
            });
        }
        let found = scratch.front.len().min(scratch.back.len());
        if found < self.width {
            return Err(PolicyError::ScratchTooSmall {
                needed: self.width,
                found,
            });
        }

        let (mut x, mut y) = (&mut scratch.front[..], &mut scratch.back[..]);
        let norm = self.obs_norm.mean.data.iter().zip(&self.obs_norm.std.data);
        for (index, ((xi, &o), (&mean, &std))) in x.iter_mut().zip(obs).zip(norm).enumerate() {
            let o = o as f32;
            if !o.is_finite() {
                return Err(PolicyError::NonFiniteObs { index });
            }
            let v = (o - mean) / std;
            *xi = match self.metadata.obs_clip {
                Some(clip) => v.clamp(-clip, clip),
                None => v,
            };
        }

        let last = self.layers.len() - 1;
        let mut inputs = obs_dim;
        for (i, layer) in self.layers.iter().enumerate() {
            let outputs = layer.bias.data.len();
            linear(
                &layer.weight.data,
                &layer.bias.data,
                &x[..inputs],
                &mut y[..outputs],
            );
            if i != last {
                y[..outputs].iter_mut().for_each(|v| *v = elu(*v));
            }
            std::mem::swap(&mut x, &mut y);
            inputs = outputs;
        }

        let out = &mut x[..action_dim];
        let affine = self.action.scale.data.iter().zip(&self.action.offset.data);
        for (index, (v, (&scale, &offset))) in out.iter_mut().zip(affine).enumerate() {
            *v = offset + scale * *v;
            if !v.is_finite() {
                return Err(PolicyError::NonFiniteAction { index });
            }
        }
        for (a, &v) in action.iter_mut().zip(out.iter()) {
            *a = f64::from(v);
        }
        Ok(())
    }
}

/// Shape against the metadata, then finiteness and magnitude ([`MAX_PARAMETER_ABS`]).
fn check_tensor(name: &str, tensor: &Tensor, expected: &[usize]) -> Result<(), PolicyError> {
    if tensor.shape != expected {
        return Err(PolicyError::ShapeMismatch {
            name: name.to_owned(),
            expected: expected.to_vec(),
            found: tensor.shape.clone(),
        });
    }
    if let Some(index) = tensor.data.iter().position(|v| !v.is_finite()) {
        return Err(PolicyError::NonFinite {
            name: name.to_owned(),
            index,
        });
    }
    match tensor
        .data
        .iter()
        .enumerate()
        .find(|(_, v)| v.abs() > MAX_PARAMETER_ABS)
    {
        Some((index, &value)) => Err(PolicyError::ParameterTooLarge {
            name: name.to_owned(),
            index,
            value,
        }),
        None => Ok(()),
    }
}

/// ELU with alpha = 1; `exp_m1` keeps precision near zero, like PyTorch's kernel.
#[inline]
fn elu(v: f32) -> f32 {
    if v > 0.0 {
        v
    } else {
        v.exp_m1()
    }
}

/// `y = W x + b` with `W` row-major `[y.len(), x.len()]`.
#[inline]
fn linear(weight: &[f32], bias: &[f32], x: &[f32], y: &mut [f32]) {
    for ((yr, &b), row) in y.iter_mut().zip(bias).zip(weight.chunks_exact(x.len())) {
        *yr = b + dot(row, x);
    }
}

/// Lanes of independent partial sums in [`dot`]. Float addition is not associative, so the
/// compiler keeps a plain `sum += a * b` loop scalar; splitting it into this many accumulators
/// lets it use SIMD registers (two SSE or one AVX register of f32) and hide add latency.
const LANES: usize = 8;

#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let (chunks_a, chunks_b) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = chunks_a
        .remainder()
        .iter()
        .zip(chunks_b.remainder())
        .map(|(p, q)| p * q)
        .sum();
    let mut acc = [0.0f32; LANES];
    for (ca, cb) in chunks_a.zip(chunks_b) {
        for k in 0..LANES {
            acc[k] += ca[k] * cb[k];
        }
    }
    acc.iter().sum::<f32>() + tail
}
