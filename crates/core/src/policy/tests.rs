//! Unit tests of the policy runtime: a hand-computed network, file round trips, and one
//! crafted bad file (or bad call) per error variant.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use proptest::prelude::*;
use safetensors::tensor::{Dtype, TensorView};

use super::*;
use crate::input::{InputError, MAX_POLICY_BYTES};
use crate::state::Phase;

/// obs 2 → hidden 2 → action 1, numbers chosen so one hidden unit goes negative through ELU.
fn tiny(obs_clip: Option<f32>) -> Policy {
    let metadata = PolicyMetadata {
        phase: Phase::Lift,
        obs_dim: 2,
        action_dim: 1,
        hidden_sizes: vec![2],
        activation: Activation::Elu,
        obs_clip,
        extra: BTreeMap::from([("created_by".to_owned(), "unit test".to_owned())]),
    };
    let layers = vec![
        Linear {
            weight: Tensor::new(vec![2, 2], vec![1.0, 1.0, 2.0, -0.5]).unwrap(),
            bias: Tensor::vector(vec![0.0, 0.5]),
        },
        Linear {
            weight: Tensor::new(vec![1, 2], vec![2.0, 1.0]).unwrap(),
            bias: Tensor::vector(vec![0.25]),
        },
    ];
    let obs_norm = ObsNormalizer {
        mean: Tensor::vector(vec![1.0, -1.0]),
        std: Tensor::vector(vec![2.0, 0.5]),
    };
    let action = ActionAffine {
        scale: Tensor::vector(vec![0.5]),
        offset: Tensor::vector(vec![0.1]),
    };
    Policy::new(metadata, layers, obs_norm, action).unwrap()
}

fn act_once(policy: &Policy, obs: &[f64]) -> Result<Vec<f64>, PolicyError> {
    let mut action = vec![0.0; policy.action_dim()];
    policy.act(obs, &mut policy.scratch(), &mut action)?;
    Ok(action)
}

#[test]
fn tiny_network_matches_hand_computation() {
    // x0 = ((3-1)/2, (-2+1)/0.5) = (1, -2)
    // h  = ELU(1 - 2 + 0) = e^-1 - 1,  ELU(2 + 1 + 0.5) = 3.5
    // out = 2 (e^-1 - 1) + 3.5 + 0.25;  action = 0.1 + 0.5 out
    let expected = 0.1 + 0.5 * (2.0 * ((-1.0f64).exp() - 1.0) + 3.75);
    let action = act_once(&tiny(None), &[3.0, -2.0]).unwrap();
    assert!(
        (action[0] - expected).abs() < 1e-6,
        "{action:?} vs {expected}"
    );
}

#[test]
fn obs_clip_clamps_normalized_obs() {
    // x0 = (1, -2) clamped to (1, -1.5): h = ELU(-0.5), ELU(2 + 0.75 + 0.5)
    let expected = 0.1 + 0.5 * (2.0 * ((-0.5f64).exp() - 1.0) + 3.25 + 0.25);
    let action = act_once(&tiny(Some(1.5)), &[3.0, -2.0]).unwrap();
    assert!(
        (action[0] - expected).abs() < 1e-6,
        "{action:?} vs {expected}"
    );
}

#[test]
fn round_trip_through_file_is_identical() {
    let policy = tiny(Some(5.0));
    let dir = std::env::temp_dir().join(format!("moonhaul-policy-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("lift.safetensors");
    policy.write_file(&path).unwrap();
    let loaded = Policy::from_file(&path).unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(loaded, policy);
    assert_eq!(leftovers.len(), 1, "temp file left behind");
    assert_eq!(loaded.metadata().extra["created_by"], "unit test");
    assert_eq!(loaded.param_count(), 2 * 2 + 2 + 2 + 1);
}

#[test]
fn metadata_reads_alone() {
    let bytes = tiny(None).to_bytes().unwrap();
    let metadata = PolicyMetadata::from_bytes(&bytes).unwrap();
    assert_eq!(metadata, *tiny(None).metadata());
    assert_eq!(metadata.layer_sizes(), vec![2, 2, 1]);
}

/// The tiny policy's file split into editable parts: metadata and raw tensors.
struct RawFile {
    metadata: HashMap<String, String>,
    tensors: BTreeMap<String, (Dtype, Vec<usize>, Vec<u8>)>,
}

impl RawFile {
    fn tiny() -> Self {
        let bytes = tiny(None).to_bytes().unwrap();
        let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
        Self {
            metadata: header.metadata().clone().unwrap(),
            tensors: file
                .tensors()
                .into_iter()
                .map(|(name, v)| (name, (v.dtype(), v.shape().to_vec(), v.data().to_vec())))
                .collect(),
        }
    }

    fn set_f32(&mut self, name: &str, index: usize, value: f32) {
        let bytes = &mut self.tensors.get_mut(name).unwrap().2;
        bytes[4 * index..4 * index + 4].copy_from_slice(&value.to_le_bytes());
    }

    fn bytes(&self) -> Vec<u8> {
        let views: Vec<_> = self
            .tensors
            .iter()
            .map(|(name, (dtype, shape, bytes))| {
                (name, TensorView::new(*dtype, shape.clone(), bytes).unwrap())
            })
            .collect();
        safetensors::serialize(views, Some(self.metadata.clone())).unwrap()
    }

    fn load(&self) -> Result<Policy, PolicyError> {
        Policy::from_bytes(&self.bytes())
    }

    fn load_with_metadata(key: &str, value: Option<&str>) -> Result<Policy, PolicyError> {
        let mut raw = Self::tiny();
        match value {
            Some(v) => raw.metadata.insert(key.to_owned(), v.to_owned()),
            None => raw.metadata.remove(key),
        };
        raw.load()
    }
}

#[test]
fn unmodified_raw_file_loads() {
    assert_eq!(RawFile::tiny().load().unwrap(), tiny(None));
}

#[test]
fn missing_tensor() {
    let mut raw = RawFile::tiny();
    raw.tensors.remove("actor.1.bias");
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::MissingTensor { name } if name == "actor.1.bias"),
        "{err}"
    );
}

#[test]
fn extra_layer_is_unexpected() {
    let mut raw = RawFile::tiny();
    let bias = raw.tensors["actor.1.bias"].clone();
    raw.tensors.insert("actor.2.bias".into(), bias);
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::UnexpectedTensor { name } if name == "actor.2.bias"),
        "{err}"
    );
}

#[test]
fn transposed_weight_is_shape_mismatch() {
    let mut raw = RawFile::tiny();
    raw.tensors.get_mut("actor.1.weight").unwrap().1 = vec![2, 1];
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::ShapeMismatch { name, expected, found }
            if name == "actor.1.weight" && expected == &[1, 2] && found == &[2, 1]),
        "{err}"
    );
}

#[test]
fn hidden_sizes_disagreeing_with_tensors_is_shape_mismatch() {
    let err = RawFile::load_with_metadata("hidden_sizes", Some("3")).unwrap_err();
    assert!(
        matches!(&err, PolicyError::ShapeMismatch { name, expected, found }
            if name == "actor.0.weight" && expected == &[3, 2] && found == &[2, 2]),
        "{err}"
    );
}

#[test]
fn nan_weight() {
    let mut raw = RawFile::tiny();
    raw.set_f32("actor.0.weight", 3, f32::NAN);
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::NonFinite { name, index: 3 } if name == "actor.0.weight"),
        "{err}"
    );
}

#[test]
fn zero_negative_or_vanishing_std() {
    for value in [0.0, -1.0, 1e-45, 1e-7] {
        let mut raw = RawFile::tiny();
        raw.set_f32("obs_norm.std", 1, value);
        let err = raw.load().unwrap_err();
        assert!(
            matches!(err, PolicyError::StdTooSmall { index: 1, .. }),
            "{value}: {err}"
        );
    }
    let mut raw = RawFile::tiny();
    raw.set_f32("obs_norm.std", 1, MIN_OBS_STD);
    raw.load().unwrap();
}

#[test]
fn absurd_parameters_of_every_tensor() {
    for name in [
        "actor.0.weight",
        "actor.0.bias",
        "actor.1.weight",
        "obs_norm.mean",
        "obs_norm.std",
        "action.scale",
        "action.offset",
    ] {
        for value in [3e38, -3e38, 2.0 * MAX_PARAMETER_ABS] {
            let mut raw = RawFile::tiny();
            raw.set_f32(name, 0, value);
            let err = raw.load().unwrap_err();
            assert!(
                matches!(&err, PolicyError::ParameterTooLarge { name: n, index: 0, .. } if n == name),
                "{name} = {value}: {err}"
            );
            assert!(err.to_string().contains(name), "{err}");
        }
    }
}

#[test]
fn wrong_dtype() {
    let mut raw = RawFile::tiny();
    raw.tensors
        .insert("obs_norm.mean".into(), (Dtype::F64, vec![2], vec![0; 16]));
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::WrongDtype { name, dtype } if name == "obs_norm.mean" && dtype == "F64"),
        "{err}"
    );
}

#[test]
fn bad_metadata_values() {
    for (key, value) in [
        ("format", "pytorch"),
        ("format_version", "2"),
        ("format_version", "one"),
        ("phase", "idle"),
        ("phase", "fly"),
        ("obs_dim", "two"),
        ("action_dim", "0"),
        ("hidden_sizes", "2,,2"),
        ("activation", "relu"),
        ("obs_clip", "-1"),
        ("obs_clip", "inf"),
        ("obs_clip", "0.5"),
        ("obs_clip", "0.000001"),
    ] {
        let err = RawFile::load_with_metadata(key, Some(value)).unwrap_err();
        assert!(
            matches!(&err, PolicyError::BadMetadata { key: k, value: v, .. } if k == key && v == value),
            "{key}={value}: {err}"
        );
    }
}

#[test]
fn a_vanishing_obs_clip_is_refused() {
    let err = RawFile::load_with_metadata("obs_clip", Some("1e-45")).unwrap_err();
    assert!(
        matches!(&err, PolicyError::BadMetadata { key, .. } if key == "obs_clip"),
        "{err}"
    );
    RawFile::load_with_metadata("obs_clip", Some("1")).unwrap();
}

#[test]
fn missing_metadata_key() {
    for key in [
        "format",
        "format_version",
        "phase",
        "obs_dim",
        "action_dim",
        "hidden_sizes",
        "activation",
    ] {
        let err = RawFile::load_with_metadata(key, None).unwrap_err();
        assert!(
            matches!(&err, PolicyError::MissingMetadata { key: k } if k == key),
            "{key}: {err}"
        );
    }
}

#[test]
fn garbage_and_truncated_bytes_are_not_safetensors() {
    let bytes = tiny(None).to_bytes().unwrap();
    for bad in [
        &bytes[..bytes.len() - 1],
        &bytes[..5],
        b"definitely not a policy".as_slice(),
    ] {
        let err = Policy::from_bytes(bad).unwrap_err();
        assert!(matches!(err, PolicyError::NotSafetensors(_)), "{err}");
    }
}

#[test]
fn missing_file_is_input_error_with_path() {
    let err = Policy::from_file("/nonexistent/lift.safetensors").unwrap_err();
    assert!(
        matches!(&err, PolicyError::Input(InputError::Io { path, .. }) if path.ends_with("lift.safetensors")),
        "{err}"
    );
    assert!(
        err.to_string().contains("/nonexistent/lift.safetensors"),
        "{err}"
    );
}

#[test]
fn non_regular_file_is_refused_unread() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("lift.safetensors");
    let status = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(status.success());
    // A FIFO would block a plain read forever; a directory or device is no policy either.
    for path in [fifo.as_path(), dir.path(), Path::new("/dev/zero")] {
        let err = Policy::from_file(path).unwrap_err();
        assert!(
            matches!(&err, PolicyError::Input(InputError::NotAFile { path: p }) if p == path),
            "{}: {err}",
            path.display()
        );
        assert!(
            err.to_string().contains(&path.display().to_string()),
            "{err}"
        );
    }
}

#[test]
fn oversized_file_is_refused_unread() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lift.safetensors");
    // Sparse: takes no disk space, and is never read.
    std::fs::File::create(&path)
        .unwrap()
        .set_len(MAX_POLICY_BYTES + 1)
        .unwrap();
    let err = Policy::from_file(&path).unwrap_err();
    assert!(
        matches!(&err, PolicyError::Input(InputError::TooLarge { max_bytes, .. }) if *max_bytes == MAX_POLICY_BYTES),
        "{err}"
    );
}

/// A safetensors container written by hand, so the header can say what the library's
/// serializer would refuse to write.
fn hand_made(header: &str, data: &[u8]) -> Vec<u8> {
    let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend_from_slice(data);
    bytes
}

/// The tiny policy's metadata as a JSON object, for [`hand_made`] headers.
fn tiny_metadata_json() -> String {
    let metadata = RawFile::tiny().metadata;
    let pairs: Vec<String> = metadata
        .iter()
        .map(|(k, v)| format!("{k:?}:{v:?}"))
        .collect();
    format!("{{{}}}", pairs.join(","))
}

#[test]
fn overflowing_shape_is_refused_before_allocating() {
    // 2^62 × 8 elements overflows usize: safetensors' own check, surfaced as its own variant.
    let header = format!(
        r#"{{"__metadata__":{},"actor.0.weight":{{"dtype":"F32","shape":[4611686018427387904,8],"data_offsets":[0,0]}}}}"#,
        tiny_metadata_json()
    );
    for result in [
        Policy::from_bytes(&hand_made(&header, &[])).map(|_| ()),
        PolicyMetadata::from_bytes(&hand_made(&header, &[])).map(|_| ()),
    ] {
        let err = result.unwrap_err();
        assert!(matches!(err, PolicyError::ShapeOverflow), "{err}");
    }
}

#[test]
fn huge_shape_without_its_data_is_not_safetensors() {
    // 10^12 floats declared, none present: safetensors checks offsets against shape and file.
    let header = format!(
        r#"{{"__metadata__":{},"obs_norm.mean":{{"dtype":"F32","shape":[1000000000000],"data_offsets":[0,8]}}}}"#,
        tiny_metadata_json()
    );
    let err = Policy::from_bytes(&hand_made(&header, &[0; 8])).unwrap_err();
    assert!(matches!(err, PolicyError::NotSafetensors(_)), "{err}");
}

#[test]
fn huge_dimension_beside_a_zero_is_shape_mismatch() {
    // [0, 10^18] holds no element, so safetensors accepts it; the metadata check names it.
    let mut raw = RawFile::tiny();
    raw.tensors.insert(
        "actor.0.weight".into(),
        (Dtype::F32, vec![0, 1_000_000_000_000_000_000], vec![]),
    );
    let err = raw.load().unwrap_err();
    assert!(
        matches!(&err, PolicyError::ShapeMismatch { name, found, .. }
            if name == "actor.0.weight" && found == &[0, 1_000_000_000_000_000_000]),
        "{err}"
    );
}

#[test]
fn oversized_header_is_refused_before_parsing() {
    // A header of 1 MiB + 1 byte (whitespace after an empty object: valid JSON).
    let mut header = String::from("{}");
    header.extend(std::iter::repeat_n(' ', MAX_HEADER_BYTES as usize - 1));
    let bytes = hand_made(&header, &[]);
    for result in [
        Policy::from_bytes(&bytes).map(|_| ()),
        PolicyMetadata::from_bytes(&bytes).map(|_| ()),
    ] {
        let err = result.unwrap_err();
        assert!(
            matches!(err, PolicyError::HeaderTooLarge { declared, .. } if declared == MAX_HEADER_BYTES + 1),
            "{err}"
        );
    }
    // The writer refuses what the reader would: here, huge free-form metadata.
    let mut policy_metadata = tiny(None).metadata().clone();
    policy_metadata
        .extra
        .insert("notes".into(), "x".repeat(MAX_HEADER_BYTES as usize));
    let good = tiny(None);
    let big = Policy::new(
        policy_metadata,
        good.layers().to_vec(),
        good.obs_normalizer().clone(),
        good.action_affine().clone(),
    )
    .unwrap();
    let err = big.to_bytes().unwrap_err();
    assert!(matches!(err, PolicyError::HeaderTooLarge { .. }), "{err}");
}

#[test]
fn huge_declared_dims_are_refused_from_metadata_alone() {
    let huge = "1000000000000"; // 10^12: would be 4 TB of floats
    let many_layers = vec!["1"; MAX_HIDDEN_LAYERS + 1].join(",");
    let wide = format!("{MAX_VALUES},1"); // fits alone, not with its neighbours
    for (key, value) in [
        ("obs_dim", huge),
        ("action_dim", huge),
        ("hidden_sizes", huge),
        ("hidden_sizes", "64,1000000000000,64"),
        ("hidden_sizes", "4000000,4000000"), // each fine, 1.6e13 weights together
        ("hidden_sizes", wide.as_str()),
        ("hidden_sizes", many_layers.as_str()),
        ("obs_dim", "18446744073709551615"), // usize::MAX on 64-bit
    ] {
        let mut raw = RawFile::tiny();
        raw.metadata.insert(key.to_owned(), value.to_owned());
        let bytes = raw.bytes();
        // Refused by the metadata reader alone, so a caller sizing buffers from it is safe...
        for result in [
            PolicyMetadata::from_bytes(&bytes).map(|_| ()),
            Policy::from_bytes(&bytes).map(|_| ()),
        ] {
            let err = result.unwrap_err();
            assert!(
                matches!(&err, PolicyError::BadMetadata { key: k, .. } if k == key),
                "{key}={value}: {err}"
            );
        }
    }
    // ...and the message never echoes a megabyte of metadata.
    let long = vec!["1"; 100_000].join(",");
    let err = RawFile::load_with_metadata("hidden_sizes", Some(&long)).unwrap_err();
    assert!(err.to_string().len() < 400, "{err}");
    assert!(err.to_string().contains("100000 hidden layers"), "{err}");
}

#[test]
fn hand_built_policy_obeys_the_same_bounds() {
    let good = tiny(None);
    let mut metadata = good.metadata().clone();
    metadata.hidden_sizes = vec![1; MAX_HIDDEN_LAYERS + 1];
    let err = Policy::new(
        metadata,
        good.layers().to_vec(),
        good.obs_normalizer().clone(),
        good.action_affine().clone(),
    )
    .unwrap_err();
    assert!(
        matches!(&err, PolicyError::BadMetadata { key, .. } if key == "hidden_sizes"),
        "{err}"
    );
}

#[test]
fn new_rejects_wrong_layer_count_and_reserved_extra_keys() {
    let good = tiny(None);
    let parts = || (good.metadata().clone(), good.layers().to_vec());
    let (norm, action) = (good.obs_normalizer().clone(), good.action_affine().clone());

    let (metadata, mut layers) = parts();
    layers.pop();
    let err = Policy::new(metadata, layers, norm.clone(), action.clone()).unwrap_err();
    assert!(
        matches!(&err, PolicyError::MissingTensor { name } if name == "actor.1.weight"),
        "{err}"
    );

    let (metadata, mut layers) = parts();
    layers.push(layers[1].clone());
    let err = Policy::new(metadata, layers, norm.clone(), action.clone()).unwrap_err();
    assert!(
        matches!(&err, PolicyError::UnexpectedTensor { name } if name == "actor.2.weight"),
        "{err}"
    );

    let (mut metadata, layers) = parts();
    metadata.extra.insert("phase".into(), "place".into());
    let err = Policy::new(metadata, layers, norm, action).unwrap_err();
    assert!(
        matches!(&err, PolicyError::BadMetadata { key, .. } if key == "phase"),
        "{err}"
    );
}

#[test]
fn tensor_length_must_fit_shape() {
    let err = Tensor::new(vec![2, 3], vec![0.0; 5]).unwrap_err();
    assert!(
        matches!(err, PolicyError::TensorLength { len: 5, .. }),
        "{err}"
    );
}

#[test]
fn act_rejects_bad_buffers_and_inputs() {
    let policy = tiny(None);
    let mut scratch = policy.scratch();
    let mut action = [7.0];
    let err = policy.act(&[1.0], &mut scratch, &mut action).unwrap_err();
    assert!(
        matches!(
            err,
            PolicyError::ObsLength {
                expected: 2,
                found: 1
            }
        ),
        "{err}"
    );
    let err = policy.act(&[1.0, 2.0], &mut scratch, &mut []).unwrap_err();
    assert!(
        matches!(
            err,
            PolicyError::ActionLength {
                expected: 1,
                found: 0
            }
        ),
        "{err}"
    );
    for bad in [f64::NAN, f64::INFINITY, 1e300] {
        let err = policy
            .act(&[1.0, bad], &mut scratch, &mut action)
            .unwrap_err();
        assert!(
            matches!(err, PolicyError::NonFiniteObs { index: 1 }),
            "{err}"
        );
    }
    let mut small = random_policy(&[1, 1], 1, None).scratch();
    let err = policy
        .act(&[1.0, 2.0], &mut small, &mut action)
        .unwrap_err();
    assert!(
        matches!(
            err,
            PolicyError::ScratchTooSmall {
                needed: 2,
                found: 1
            }
        ),
        "{err}"
    );
    assert_eq!(action, [7.0], "action written on error");
}

#[test]
fn overflowing_output_is_non_finite_action() {
    // Parameters are bounded, observations only finite: a huge one overflows the network.
    let policy = tiny(None);
    let err = act_once(&policy, &[3e38, -2.0]).unwrap_err();
    assert!(
        matches!(err, PolicyError::NonFiniteAction { index: 0 }),
        "{err}"
    );
}

/// A random policy of the given layer sizes (deterministic in `seed`).
fn random_policy(sizes: &[usize], seed: u64, obs_clip: Option<f32>) -> Policy {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let mut vector =
        |n: usize, lo: f32| Tensor::vector((0..n).map(|_| lo + next().abs()).collect());
    let (obs_dim, action_dim) = (sizes[0], sizes[sizes.len() - 1]);
    let obs_norm = ObsNormalizer {
        mean: vector(obs_dim, -0.5),
        std: vector(obs_dim, 0.1),
    };
    let action = ActionAffine {
        scale: vector(action_dim, 0.1),
        offset: vector(action_dim, -0.5),
    };
    let layers = sizes
        .windows(2)
        .map(|io| Linear {
            weight: Tensor::new(
                vec![io[1], io[0]],
                (0..io[0] * io[1]).map(|_| next()).collect(),
            )
            .unwrap(),
            bias: Tensor::vector((0..io[1]).map(|_| 0.1 * next()).collect()),
        })
        .collect();
    let metadata = PolicyMetadata {
        phase: Phase::Transport,
        obs_dim,
        action_dim,
        hidden_sizes: sizes[1..sizes.len() - 1].to_vec(),
        activation: Activation::Elu,
        obs_clip,
        extra: BTreeMap::new(),
    };
    Policy::new(metadata, layers, obs_norm, action).unwrap()
}

/// The forward pass written the obvious way, in f64, as an independent reference.
fn reference_act(policy: &Policy, obs: &[f64]) -> Vec<f64> {
    let norm = policy.obs_normalizer();
    let mut x: Vec<f64> = obs
        .iter()
        .zip(norm.mean.data().iter().zip(norm.std.data()))
        .map(|(&o, (&m, &s))| {
            let v = (f64::from(o as f32) - f64::from(m)) / f64::from(s);
            policy
                .metadata()
                .obs_clip
                .map_or(v, |c| v.clamp(-f64::from(c), f64::from(c)))
        })
        .collect();
    for (i, layer) in policy.layers().iter().enumerate() {
        let inputs = x.len();
        x = (0..layer.bias.data().len())
            .map(|r| {
                let row = &layer.weight.data()[r * inputs..(r + 1) * inputs];
                let v = f64::from(layer.bias.data()[r])
                    + row
                        .iter()
                        .zip(&x)
                        .map(|(&w, &xi)| f64::from(w) * xi)
                        .sum::<f64>();
                if i + 1 < policy.layers().len() && v <= 0.0 {
                    v.exp_m1()
                } else {
                    v
                }
            })
            .collect();
    }
    let affine = policy.action_affine();
    x.iter()
        .zip(affine.scale.data().iter().zip(affine.offset.data()))
        .map(|(&v, (&s, &o))| f64::from(o) + f64::from(s) * v)
        .collect()
}

proptest! {
    #[test]
    fn act_matches_reference_and_survives_round_trip(
        sizes in proptest::collection::vec(1usize..40, 2..5),
        seed in any::<u64>(),
        obs_seed in any::<u64>(),
        clip in proptest::option::of(MIN_OBS_CLIP..4.0),
    ) {
        let policy = random_policy(&sizes, seed, clip);
        let obs: Vec<f64> = (0..sizes[0])
            .map(|i| ((obs_seed >> (i % 60)) & 0xff) as f64 / 64.0 - 2.0)
            .collect();
        let mut action = vec![0.0; policy.action_dim()];
        let mut scratch = policy.scratch();
        policy.act(&obs, &mut scratch, &mut action).unwrap();
        for (a, r) in action.iter().zip(reference_act(&policy, &obs)) {
            prop_assert!((a - r).abs() <= 1e-4 * (1.0 + r.abs()), "{a} vs {r}");
        }
        // Scratch reuse gives the same answer; a file round trip gives the same policy.
        let mut again = vec![0.0; policy.action_dim()];
        policy.act(&obs, &mut scratch, &mut again).unwrap();
        prop_assert_eq!(&again, &action);
        prop_assert_eq!(Policy::from_bytes(&policy.to_bytes().unwrap()).unwrap(), policy);
    }
}
