//! Reading and writing the safetensors policy file (format in the [module docs](super)).

use std::borrow::Cow;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensorError, View};
use safetensors::SafeTensors;

use super::metadata::check_header_len;
use super::network::{bias_name, weight_name, ACTION_OFFSET, ACTION_SCALE, OBS_MEAN, OBS_STD};
use super::{ActionAffine, Linear, ObsNormalizer, Policy, PolicyError, PolicyMetadata, Tensor};
use crate::input::{read_capped, MAX_POLICY_BYTES};

impl Policy {
    /// Loads and validates a policy file. Anything but a regular file of at most
    /// [`MAX_POLICY_BYTES`] is refused before it is read ([`PolicyError::Input`]).
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, PolicyError> {
        let bytes = read_capped(path.as_ref(), MAX_POLICY_BYTES)?;
        Self::from_bytes(&bytes)
    }

    /// Parses and validates the bytes of a policy file: metadata first, then the set of tensor
    /// names, then dtypes; shapes and values are checked by [`Policy::new`].
    ///
    /// Nothing is allocated from a size the file declares before that size is bounded: the
    /// header length by [`MAX_HEADER_BYTES`](super::MAX_HEADER_BYTES), the metadata's widths
    /// and layer count by [`PolicyMetadata::from_bytes`]. safetensors itself checks that every
    /// shape's byte size is computed without overflow ([`PolicyError::ShapeOverflow`]) and
    /// equals the tensor's data offsets, which are contiguous and end exactly at the end of
    /// the buffer — so every tensor's data lies inside the file; it does not bound the header
    /// below 100 MB, the metadata values, or a shape with a zero dimension beside a huge one
    /// (caught as [`PolicyError::ShapeMismatch`] against the bounded metadata).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyError> {
        let metadata = PolicyMetadata::from_bytes(bytes)?;
        let file = SafeTensors::deserialize(bytes).map_err(PolicyError::parse)?;

        let layer_count = metadata.hidden_sizes.len() + 1;
        let mut expected: Vec<String> = (0..layer_count)
            .flat_map(|i| [weight_name(i), bias_name(i)])
            .collect();
        expected.extend([OBS_MEAN, OBS_STD, ACTION_SCALE, ACTION_OFFSET].map(String::from));
        let mut names = file.names();
        names.sort_unstable();
        if let Some(name) = names.iter().find(|n| !expected.iter().any(|e| e == *n)) {
            return Err(PolicyError::UnexpectedTensor {
                name: (*name).to_owned(),
            });
        }

        let layers = (0..layer_count)
            .map(|i| {
                Ok(Linear {
                    weight: read_tensor(&file, &weight_name(i))?,
                    bias: read_tensor(&file, &bias_name(i))?,
                })
            })
            .collect::<Result<_, PolicyError>>()?;
        let obs_norm = ObsNormalizer {
            mean: read_tensor(&file, OBS_MEAN)?,
            std: read_tensor(&file, OBS_STD)?,
        };
        let action = ActionAffine {
            scale: read_tensor(&file, ACTION_SCALE)?,
            offset: read_tensor(&file, ACTION_OFFSET)?,
        };
        Self::new(metadata, layers, obs_norm, action)
    }

    /// The policy as the bytes of a policy file. A file the reader would refuse (over
    /// [`MAX_POLICY_BYTES`], or a header over [`MAX_HEADER_BYTES`](super::MAX_HEADER_BYTES)
    /// from huge free-form metadata) is an error here rather than there.
    pub fn to_bytes(&self) -> Result<Vec<u8>, PolicyError> {
        let mut tensors: Vec<(String, F32View<'_>)> = Vec::new();
        for (i, layer) in self.layers().iter().enumerate() {
            tensors.push((weight_name(i), F32View(&layer.weight)));
            tensors.push((bias_name(i), F32View(&layer.bias)));
        }
        let (norm, action) = (self.obs_normalizer(), self.action_affine());
        tensors.push((OBS_MEAN.into(), F32View(&norm.mean)));
        tensors.push((OBS_STD.into(), F32View(&norm.std)));
        tensors.push((ACTION_SCALE.into(), F32View(&action.scale)));
        tensors.push((ACTION_OFFSET.into(), F32View(&action.offset)));
        let bytes = safetensors::serialize(tensors, Some(self.metadata().to_map()))
            .map_err(PolicyError::Serialize)?;
        check_header_len(&bytes)?;
        let len = bytes.len() as u64;
        if len > MAX_POLICY_BYTES {
            return Err(PolicyError::TooLarge {
                bytes: len,
                max_bytes: MAX_POLICY_BYTES,
            });
        }
        Ok(bytes)
    }

    /// Writes the policy file atomically ([`crate::atomic_file`]): a reader, or a robot booting
    /// after a crash, sees the old file or the new one, never a torn one.
    pub fn write_file(&self, path: impl AsRef<Path>) -> Result<(), PolicyError> {
        let path = path.as_ref();
        let bytes = self.to_bytes()?;
        crate::atomic_file::write(path, &bytes).map_err(|source| PolicyError::Io {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// Decodes one F32 tensor (little-endian on disk, whatever the host byte order).
fn read_tensor(file: &SafeTensors<'_>, name: &str) -> Result<Tensor, PolicyError> {
    let view = file.tensor(name).map_err(|e| match e {
        SafeTensorError::TensorNotFound(_) => PolicyError::MissingTensor {
            name: name.to_owned(),
        },
        other => PolicyError::parse(other),
    })?;
    if view.dtype() != Dtype::F32 {
        return Err(PolicyError::WrongDtype {
            name: name.to_owned(),
            dtype: view.dtype().to_string(),
        });
    }
    let data = view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Tensor::new(view.shape().to_vec(), data)
}

/// Serializes a [`Tensor`] as F32 little-endian for `safetensors::serialize`.
struct F32View<'a>(&'a Tensor);

impl View for F32View<'_> {
    fn dtype(&self) -> Dtype {
        Dtype::F32
    }

    fn shape(&self) -> &[usize] {
        self.0.shape()
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Owned(self.0.data().iter().flat_map(|v| v.to_le_bytes()).collect())
    }

    fn data_len(&self) -> usize {
        self.0.data().len() * 4
    }
}
