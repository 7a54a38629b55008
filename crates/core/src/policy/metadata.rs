//! The `__metadata__` string map of a policy file, parsed into [`PolicyMetadata`].

use std::collections::{BTreeMap, HashMap};

use safetensors::SafeTensors;

use super::PolicyError;
use crate::input::MAX_POLICY_BYTES;
use crate::state::Phase;

/// Value of the `format` key: marks a safetensors file as a moonhaul policy.
pub const FORMAT_NAME: &str = "moonhaul-policy";
/// The format version this build reads and writes (`format_version` key).
pub const FORMAT_VERSION: u32 = 1;

/// Largest safetensors header (the JSON between the 8-byte length and the tensor data) a
/// policy file may declare, bytes. A real one is ~1 kB; the cap is checked on the length
/// field, before the header is parsed, so a hostile header cannot make the JSON parser
/// allocate much (safetensors alone allows 100 MB).
pub const MAX_HEADER_BYTES: u64 = 1 << 20;
/// Most hidden layers `hidden_sizes` may list (the paper's networks have 3); checked before
/// the list is parsed.
pub const MAX_HIDDEN_LAYERS: usize = 64;
/// Most f32 values a policy may have — weights, biases, normalizer and action map together:
/// what a file of [`MAX_POLICY_BYTES`] can hold. Every width (`obs_dim`, `action_dim`, each
/// hidden size) and the network's total are checked against it from the metadata alone,
/// before anything is allocated for the network or a caller sizes buffers from the metadata.
pub const MAX_VALUES: usize = (MAX_POLICY_BYTES / 4) as usize;

/// Longest metadata value echoed in an error message, characters.
const MAX_ECHOED_CHARS: usize = 64;

const KEY_FORMAT: &str = "format";
const KEY_FORMAT_VERSION: &str = "format_version";
const KEY_PHASE: &str = "phase";
const KEY_OBS_DIM: &str = "obs_dim";
const KEY_ACTION_DIM: &str = "action_dim";
const KEY_HIDDEN_SIZES: &str = "hidden_sizes";
const KEY_ACTIVATION: &str = "activation";
const KEY_OBS_CLIP: &str = "obs_clip";

/// Smallest `obs_clip`, in normalized units (standard deviations): a clip below one cuts off
/// most of the observations the normalizer was fitted to, and a tiny one (1e-45) makes the
/// network blind to its inputs. rsl_rl clips at 5 to 100.
pub const MIN_OBS_CLIP: f32 = 1.0;
/// Keys with a typed meaning; everything else lands in [`PolicyMetadata::extra`].
const RESERVED_KEYS: [&str; 8] = [
    KEY_FORMAT,
    KEY_FORMAT_VERSION,
    KEY_PHASE,
    KEY_OBS_DIM,
    KEY_ACTION_DIM,
    KEY_HIDDEN_SIZES,
    KEY_ACTIVATION,
    KEY_OBS_CLIP,
];

/// The nonlinearity between hidden layers. Only ELU (alpha = 1, the paper's choice) exists;
/// the key is in the format so a future activation is a metadata change, not a new format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `x` for `x > 0`, `exp(x) - 1` otherwise.
    Elu,
}

impl Activation {
    /// The metadata spelling.
    pub fn name(self) -> &'static str {
        match self {
            Activation::Elu => "elu",
        }
    }
}

/// Everything a policy file says about itself besides the numbers in its tensors.
///
/// Read it alone with [`PolicyMetadata::from_bytes`] (no tensor is decoded or checked), or as
/// part of a full load with [`Policy::from_bytes`](super::Policy::from_bytes).
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyMetadata {
    /// The phase this policy drives; never [`Phase::Idle`].
    pub phase: Phase,
    /// Length of the observation vector.
    pub obs_dim: usize,
    /// Length of the action vector.
    pub action_dim: usize,
    /// Widths of the hidden layers, input side first (empty: a single linear layer).
    pub hidden_sizes: Vec<usize>,
    /// Nonlinearity after every hidden layer.
    pub activation: Activation,
    /// If set, normalized observations are clamped to `±obs_clip`.
    pub obs_clip: Option<f32>,
    /// Free-form keys (`created_by`, `train_run`, `env_steps`, ...), kept verbatim.
    pub extra: BTreeMap<String, String>,
}

impl PolicyMetadata {
    /// Parses and validates the metadata of a policy file's bytes without touching its tensors.
    /// Every size it declares is bounded ([`MAX_HEADER_BYTES`], [`MAX_HIDDEN_LAYERS`],
    /// [`MAX_VALUES`]), so a caller may allocate from it.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PolicyError> {
        check_header_len(bytes)?;
        let (_, header) = SafeTensors::read_metadata(bytes).map_err(PolicyError::parse)?;
        let empty = HashMap::new();
        Self::from_map(header.metadata().as_ref().unwrap_or(&empty))
    }

    /// Layer widths from input to output: `[obs_dim, hidden_sizes..., action_dim]`.
    pub fn layer_sizes(&self) -> Vec<usize> {
        let mut sizes = Vec::with_capacity(self.hidden_sizes.len() + 2);
        sizes.push(self.obs_dim);
        sizes.extend_from_slice(&self.hidden_sizes);
        sizes.push(self.action_dim);
        sizes
    }

    pub(super) fn from_map(map: &HashMap<String, String>) -> Result<Self, PolicyError> {
        let get = |key: &str| {
            map.get(key).ok_or_else(|| PolicyError::MissingMetadata {
                key: key.to_owned(),
            })
        };

        let format = get(KEY_FORMAT)?;
        if format != FORMAT_NAME {
            return Err(bad(KEY_FORMAT, format, format!("expected {FORMAT_NAME:?}")));
        }
        let version = get(KEY_FORMAT_VERSION)?;
        if parse_int::<u32>(KEY_FORMAT_VERSION, version)? != FORMAT_VERSION {
            return Err(bad(
                KEY_FORMAT_VERSION,
                version,
                format!("unsupported version (this build reads {FORMAT_VERSION})"),
            ));
        }
        let phase_str = get(KEY_PHASE)?;
        let phase = phase_str
            .parse::<Phase>()
            .map_err(|e| bad(KEY_PHASE, phase_str, e.to_string()))?;
        let hidden_str = get(KEY_HIDDEN_SIZES)?;
        let hidden_count = hidden_str.split(',').count();
        let hidden_sizes = if hidden_str.trim().is_empty() {
            Vec::new()
        } else if hidden_count > MAX_HIDDEN_LAYERS {
            return Err(too_many_layers(hidden_str, hidden_count));
        } else {
            hidden_str
                .split(',')
                .map(|s| {
                    s.trim()
                        .parse()
                        .map_err(|e| bad(KEY_HIDDEN_SIZES, hidden_str, format!("entry {s:?}: {e}")))
                })
                .collect::<Result<_, _>>()?
        };
        let activation_str = get(KEY_ACTIVATION)?;
        let activation = match activation_str.as_str() {
            "elu" => Activation::Elu,
            _ => {
                return Err(bad(
                    KEY_ACTIVATION,
                    activation_str,
                    "unsupported activation (expected elu)".into(),
                ))
            }
        };
        let obs_clip = match map.get(KEY_OBS_CLIP) {
            None => None,
            Some(s) => Some(
                s.trim()
                    .parse::<f32>()
                    .map_err(|e| bad(KEY_OBS_CLIP, s, e.to_string()))?,
            ),
        };
        let metadata = Self {
            phase,
            obs_dim: parse_int(KEY_OBS_DIM, get(KEY_OBS_DIM)?)?,
            action_dim: parse_int(KEY_ACTION_DIM, get(KEY_ACTION_DIM)?)?,
            hidden_sizes,
            activation,
            obs_clip,
            extra: map
                .iter()
                .filter(|(k, _)| !RESERVED_KEYS.contains(&k.as_str()))
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        };
        metadata.validate()?;
        Ok(metadata)
    }

    /// The string map written as `__metadata__`.
    pub(super) fn to_map(&self) -> HashMap<String, String> {
        let hidden: Vec<String> = self.hidden_sizes.iter().map(usize::to_string).collect();
        let mut map: HashMap<String, String> = self.extra.clone().into_iter().collect();
        map.insert(KEY_FORMAT.into(), FORMAT_NAME.into());
        map.insert(KEY_FORMAT_VERSION.into(), FORMAT_VERSION.to_string());
        map.insert(KEY_PHASE.into(), self.phase.name().into());
        map.insert(KEY_OBS_DIM.into(), self.obs_dim.to_string());
        map.insert(KEY_ACTION_DIM.into(), self.action_dim.to_string());
        map.insert(KEY_HIDDEN_SIZES.into(), hidden.join(","));
        map.insert(KEY_ACTIVATION.into(), self.activation.name().into());
        if let Some(clip) = self.obs_clip {
            map.insert(KEY_OBS_CLIP.into(), clip.to_string());
        }
        map
    }

    /// Checks the value constraints the types cannot express. Shared by parsing and by
    /// [`Policy::new`](super::Policy::new), so a hand-built policy obeys the same rules.
    pub(super) fn validate(&self) -> Result<(), PolicyError> {
        if !self.phase.has_policy() {
            return Err(bad(
                KEY_PHASE,
                self.phase.name(),
                "the idle phase runs no policy".into(),
            ));
        }
        for (key, dim) in [
            (KEY_OBS_DIM, self.obs_dim),
            (KEY_ACTION_DIM, self.action_dim),
        ] {
            if dim == 0 {
                return Err(bad(key, "0", "must be positive".into()));
            }
        }
        if self.hidden_sizes.contains(&0) {
            return Err(bad(
                KEY_HIDDEN_SIZES,
                &joined(&self.hidden_sizes),
                "every hidden size must be positive".into(),
            ));
        }
        if self.hidden_sizes.len() > MAX_HIDDEN_LAYERS {
            return Err(too_many_layers(
                &joined(&self.hidden_sizes),
                self.hidden_sizes.len(),
            ));
        }
        for (key, dim) in [
            (KEY_OBS_DIM, self.obs_dim),
            (KEY_ACTION_DIM, self.action_dim),
        ]
        .into_iter()
        .chain(self.hidden_sizes.iter().map(|&h| (KEY_HIDDEN_SIZES, h)))
        {
            if dim > MAX_VALUES {
                let value = if key == KEY_HIDDEN_SIZES {
                    joined(&self.hidden_sizes)
                } else {
                    dim.to_string()
                };
                return Err(bad(
                    key,
                    &value,
                    format!(
                        "width {dim} exceeds {MAX_VALUES}, the most values a policy file may hold"
                    ),
                ));
            }
        }
        let sizes = self.layer_sizes();
        if value_count(&sizes).is_none_or(|n| n > MAX_VALUES) {
            // Name the key that makes the network big: the hidden layers if there are any.
            let (key, value) = if !self.hidden_sizes.is_empty() {
                (KEY_HIDDEN_SIZES, joined(&self.hidden_sizes))
            } else if self.obs_dim >= self.action_dim {
                (KEY_OBS_DIM, self.obs_dim.to_string())
            } else {
                (KEY_ACTION_DIM, self.action_dim.to_string())
            };
            return Err(bad(
                key,
                &value,
                format!(
                    "layer sizes {sizes:?} need more than {MAX_VALUES} values, the most a policy file may hold"
                ),
            ));
        }
        if let Some(clip) = self.obs_clip {
            if !(clip.is_finite() && clip >= MIN_OBS_CLIP) {
                return Err(bad(
                    KEY_OBS_CLIP,
                    &clip.to_string(),
                    format!("must be a finite number >= {MIN_OBS_CLIP} (normalized units)"),
                ));
            }
        }
        if let Some((key, value)) = self
            .extra
            .iter()
            .find(|(k, _)| RESERVED_KEYS.contains(&k.as_str()))
        {
            return Err(bad(
                key,
                value,
                "reserved key, set through its typed field".into(),
            ));
        }
        Ok(())
    }
}

/// Refuses a header over [`MAX_HEADER_BYTES`] before safetensors parses it. A length the
/// bytes cannot hold (garbage, a truncated file) is left to safetensors, which refuses it
/// without parsing anything ([`PolicyError::NotSafetensors`]).
pub(super) fn check_header_len(bytes: &[u8]) -> Result<(), PolicyError> {
    let present = bytes.len().saturating_sub(8) as u64;
    match bytes.first_chunk::<8>().map(|n| u64::from_le_bytes(*n)) {
        Some(declared) if declared > MAX_HEADER_BYTES && declared <= present => {
            Err(PolicyError::HeaderTooLarge {
                declared,
                max_bytes: MAX_HEADER_BYTES,
            })
        }
        _ => Ok(()),
    }
}

/// Values a network of these layer sizes holds: every layer's weight and bias, plus the
/// normalizer (2 × first) and the action map (2 × last). `None` on overflow.
fn value_count(sizes: &[usize]) -> Option<usize> {
    let (&first, &last) = (sizes.first()?, sizes.last()?);
    sizes
        .windows(2)
        .try_fold(0usize, |n, io| {
            n.checked_add(io[0].checked_mul(io[1])?.checked_add(io[1])?)
        })?
        .checked_add(first.checked_mul(2)?)?
        .checked_add(last.checked_mul(2)?)
}

fn joined(sizes: &[usize]) -> String {
    let parts: Vec<String> = sizes.iter().map(usize::to_string).collect();
    parts.join(",")
}

fn too_many_layers(value: &str, count: usize) -> PolicyError {
    bad(
        KEY_HIDDEN_SIZES,
        value,
        format!("{count} hidden layers, more than the {MAX_HIDDEN_LAYERS} a policy may have"),
    )
}

/// A [`PolicyError::BadMetadata`]; a value longer than [`MAX_ECHOED_CHARS`] is shortened, so
/// a hostile file cannot make an error message megabytes long.
fn bad(key: &str, value: &str, reason: String) -> PolicyError {
    let value = match value.char_indices().nth(MAX_ECHOED_CHARS) {
        Some((end, _)) => format!("{}… ({} bytes)", &value[..end], value.len()),
        None => value.to_owned(),
    };
    PolicyError::BadMetadata {
        key: key.to_owned(),
        value,
        reason,
    }
}

fn parse_int<T>(key: &str, value: &str) -> Result<T, PolicyError>
where
    T: std::str::FromStr<Err = std::num::ParseIntError>,
{
    value
        .trim()
        .parse()
        .map_err(|e: std::num::ParseIntError| bad(key, value, e.to_string()))
}
