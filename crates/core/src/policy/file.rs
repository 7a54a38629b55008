//! Reading and writing the safetensors policy file (format in the [module docs](super)).

use std::borrow::Cow;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensorError, View};
use safetensors::SafeTensors;

use super::network::{bias_name, weight_name, ACTION_OFFSET, ACTION_SCALE, OBS_MEAN, OBS_STD};
use super::{ActionAffine, Linear, ObsNormalizer, Policy, PolicyError, PolicyMetadata, Tensor};

impl Policy {
    /// Loads and validates a policy file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, PolicyError> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| PolicyError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Parses and validates the bytes of a policy file: metadata first, then the set of tensor
    /// names, then dtypes; shapes and values are checked by [`Policy::new`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyError> {
        let metadata = PolicyMetadata::from_bytes(bytes)?;
        let file = SafeTensors::deserialize(bytes).map_err(PolicyError::NotSafetensors)?;

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

    /// The policy as the bytes of a policy file.
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
        safetensors::serialize(tensors, Some(self.metadata().to_map()))
            .map_err(PolicyError::Serialize)
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
        other => PolicyError::NotSafetensors(other),
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
