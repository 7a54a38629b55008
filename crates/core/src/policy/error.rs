//! The one error type of the policy runtime: every way a policy file or an inference call can
//! be wrong has its own variant, so callers (and tests) can tell them apart without parsing
//! messages.

use std::path::PathBuf;

use safetensors::SafeTensorError;

use crate::input::InputError;

/// Why a policy could not be loaded, built, written or evaluated.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// Writing the file failed (its target is not a regular file, the folder is missing, ...).
    #[error("cannot write policy file {}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Reading the file failed: it is missing, not a regular file (a directory, a FIFO, a
    /// device) or larger than [`MAX_POLICY_BYTES`](crate::input::MAX_POLICY_BYTES). The
    /// message names the path.
    #[error(transparent)]
    Input(#[from] InputError),
    /// The bytes are not a well-formed safetensors container (garbage, truncated, bad header,
    /// a tensor whose offsets disagree with its shape or lie outside the file).
    #[error("not a valid safetensors file")]
    NotSafetensors(#[source] SafeTensorError),
    /// The header length in the first 8 bytes exceeds
    /// [`MAX_HEADER_BYTES`](super::MAX_HEADER_BYTES); refused before the header is parsed.
    #[error("safetensors header declares {declared} bytes, more than the {max_bytes} a policy file may have")]
    HeaderTooLarge { declared: u64, max_bytes: u64 },
    /// A tensor's shape has more elements than memory can address (the product of its
    /// dimensions times 4 bytes overflows). safetensors detects this before allocating but
    /// does not say which tensor.
    #[error(
        "a tensor's shape overflows the address space (product of its dimensions × element size)"
    )]
    ShapeOverflow,
    /// [`Policy::to_bytes`](super::Policy::to_bytes) would produce a file the reader refuses.
    #[error(
        "the policy file would be {bytes} bytes, more than the {max_bytes} a policy file may have"
    )]
    TooLarge { bytes: u64, max_bytes: u64 },
    /// Serializing the tensors into a safetensors container failed.
    #[error("cannot serialize policy to safetensors")]
    Serialize(#[source] safetensors::SafeTensorError),
    /// A required `__metadata__` key is absent (a safetensors file without `format` is not a
    /// policy file at all).
    #[error("metadata key `{key}` is missing")]
    MissingMetadata { key: String },
    /// A metadata value is present but unusable.
    #[error("metadata `{key}` = {value:?} is invalid: {reason}")]
    BadMetadata {
        key: String,
        value: String,
        reason: String,
    },
    /// A tensor the metadata calls for is absent.
    #[error("tensor `{name}` is missing")]
    MissingTensor { name: String },
    /// A tensor the metadata does not call for is present (e.g. a layer beyond `hidden_sizes`,
    /// or critic weights exported by mistake).
    #[error("unexpected tensor `{name}` (not part of the format for this metadata)")]
    UnexpectedTensor { name: String },
    /// A tensor is not F32.
    #[error("tensor `{name}` has dtype {dtype}, expected F32")]
    WrongDtype { name: String, dtype: String },
    /// A tensor's shape disagrees with the metadata.
    #[error("tensor `{name}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    /// A [`Tensor`](super::Tensor) was built with a data length that does not fit its shape.
    #[error("tensor data has {len} values, which does not fit shape {shape:?}")]
    TensorLength { shape: Vec<usize>, len: usize },
    /// A parameter is NaN or infinite (flat row-major index).
    #[error("tensor `{name}` has a non-finite value at flat index {index}")]
    NonFinite { name: String, index: usize },
    /// A parameter's magnitude is beyond
    /// [`MAX_PARAMETER_ABS`](super::MAX_PARAMETER_ABS) (flat row-major index).
    #[error(
        "tensor `{name}` has {value:e} at flat index {index}, beyond ±{:e}",
        super::MAX_PARAMETER_ABS
    )]
    ParameterTooLarge {
        name: String,
        index: usize,
        value: f32,
    },
    /// An observation normalizer std entry is below [`MIN_OBS_STD`](super::MIN_OBS_STD)
    /// (zero, negative or vanishingly small).
    #[error(
        "obs_norm.std[{index}] is {value:e}, below the smallest std {:e}",
        super::MIN_OBS_STD
    )]
    StdTooSmall { index: usize, value: f32 },
    /// [`Policy::act`](super::Policy::act) got an observation of the wrong length.
    #[error("observation has {found} values, policy expects {expected}")]
    ObsLength { expected: usize, found: usize },
    /// [`Policy::act`](super::Policy::act) got an action buffer of the wrong length.
    #[error("action buffer has {found} values, policy produces {expected}")]
    ActionLength { expected: usize, found: usize },
    /// The scratch was made for a smaller policy.
    #[error("scratch holds {found} values per buffer, policy needs {needed}")]
    ScratchTooSmall { needed: usize, found: usize },
    /// An observation entry is NaN or infinite (or overflows f32).
    #[error("observation[{index}] is not finite")]
    NonFiniteObs { index: usize },
    /// The network produced a NaN or infinite action entry.
    #[error("action[{index}] came out non-finite")]
    NonFiniteAction { index: usize },
}

impl PolicyError {
    /// A safetensors parse failure, with the failures that have their own variant split out.
    pub(super) fn parse(error: SafeTensorError) -> Self {
        match error {
            SafeTensorError::ValidationOverflow => PolicyError::ShapeOverflow,
            other => PolicyError::NotSafetensors(other),
        }
    }
}
