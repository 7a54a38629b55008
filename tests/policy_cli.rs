//! `moonhaul policy inspect` on files written by the core policy writer.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use moonhaul_core::policy::{
    ActionAffine, Activation, Linear, ObsNormalizer, Policy, PolicyMetadata, Tensor,
};
use moonhaul_core::state::Phase;

/// A 3 → 4 → 2 place policy with a clip and one free-form metadata key.
fn small_policy() -> Policy {
    let metadata = PolicyMetadata {
        phase: Phase::Place,
        obs_dim: 3,
        action_dim: 2,
        hidden_sizes: vec![4],
        activation: Activation::Elu,
        obs_clip: Some(5.0),
        extra: BTreeMap::from([("train_run".to_owned(), "place-2024-07".to_owned())]),
    };
    let layers = vec![
        Linear {
            weight: Tensor::new(vec![4, 3], (0..12).map(|i| i as f32 * 0.1).collect()).unwrap(),
            bias: Tensor::vector(vec![0.0; 4]),
        },
        Linear {
            weight: Tensor::new(vec![2, 4], vec![0.5; 8]).unwrap(),
            bias: Tensor::vector(vec![0.1, -0.1]),
        },
    ];
    let obs_norm = ObsNormalizer {
        mean: Tensor::vector(vec![-1.0, 0.0, 2.5]),
        std: Tensor::vector(vec![0.5, 1.0, 3.0]),
    };
    let action = ActionAffine {
        scale: Tensor::vector(vec![2.0, 0.25]),
        offset: Tensor::vector(vec![0.0, 1.0]),
    };
    Policy::new(metadata, layers, obs_norm, action).unwrap()
}

fn inspect(args: &[&str], file: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moonhaul"))
        .args(["policy", "inspect"])
        .args(args)
        .arg(file)
        .output()
        .unwrap()
}

#[test]
fn inspect_prints_metadata_as_text() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("place.safetensors");
    small_policy().write_file(&file).unwrap();

    let out = inspect(&[], &file);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    for expected in [
        "moonhaul-policy v1",
        "place",
        "3 -> 4 -> 2",
        "elu",
        "obs_clip         5",
        "parameters       26",
        "obs_norm.mean    min -1, max 2.5",
        "obs_norm.std     min 0.5, max 3",
        "action.scale     [2.0, 0.25]",
        "action.offset    [0.0, 1.0]",
        "extra.train_run  place-2024-07",
    ] {
        assert!(text.contains(expected), "missing {expected:?} in\n{text}");
    }
}

#[test]
fn inspect_json_is_one_object() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("place.safetensors");
    small_policy().write_file(&file).unwrap();

    let out = inspect(&["--json"], &file);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let value: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(value["format"], "moonhaul-policy");
    assert_eq!(value["format_version"], 1);
    assert_eq!(value["phase"], "place");
    assert_eq!(value["obs_dim"], 3);
    assert_eq!(value["action_dim"], 2);
    assert_eq!(value["hidden_sizes"], serde_json::json!([4]));
    assert_eq!(value["activation"], "elu");
    assert_eq!(value["obs_clip"], 5.0);
    assert_eq!(value["param_count"], 26);
    assert_eq!(value["obs_norm"]["mean"]["min"], -1.0);
    assert_eq!(value["obs_norm"]["std"]["max"], 3.0);
    assert_eq!(value["action"]["scale"], serde_json::json!([2.0, 0.25]));
    assert_eq!(value["extra"]["train_run"], "place-2024-07");
}

#[test]
fn corrupted_files_fail_naming_file_and_problem() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = small_policy().to_bytes().unwrap();

    let truncated = dir.path().join("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() - 3]).unwrap();

    // Same length, so still a valid safetensors container, but an idle policy is invalid.
    let idle = dir.path().join("idle.safetensors");
    let mut idle_bytes = bytes.clone();
    let at = idle_bytes
        .windows(7)
        .position(|w| w == b"\"place\"")
        .unwrap();
    idle_bytes[at..at + 7].copy_from_slice(b"\"idle\" ");
    std::fs::write(&idle, idle_bytes).unwrap();

    let missing = dir.path().join("missing.safetensors");

    for (file, problem) in [
        (&truncated, "not a valid safetensors file"),
        (&idle, "the idle phase runs no policy"),
        (&missing, "No such file"),
    ] {
        let out = inspect(&[], file);
        assert!(!out.status.success());
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(stderr.contains(&file.display().to_string()), "{stderr}");
        assert!(stderr.contains(problem), "{stderr}");
    }
}

/// `bytes` with every f32 `from` in the tensor data replaced by `to` (the header untouched).
fn patch_f32(bytes: &[u8], from: f32, to: f32) -> Vec<u8> {
    let header = 8 + u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut out = bytes.to_vec();
    let mut hits = 0;
    for chunk in out[header..].chunks_exact_mut(4) {
        if chunk == from.to_le_bytes() {
            chunk.copy_from_slice(&to.to_le_bytes());
            hits += 1;
        }
    }
    assert_eq!(hits, 1, "{from} is not one value of the file");
    out
}

/// `bytes` with metadata `key` set to `value` (the header rewritten, its length updated).
fn patch_metadata(bytes: &[u8], key: &str, value: &str) -> Vec<u8> {
    let len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + len]).unwrap();
    header["__metadata__"][key] = value.into();
    let mut text = serde_json::to_vec(&header).unwrap();
    while text.len() % 8 != 0 {
        text.push(b' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&text);
    out.extend_from_slice(&bytes[8 + len..]);
    out
}

#[test]
fn absurd_numbers_fail_inspect_naming_the_tensor_or_key() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = small_policy().to_bytes().unwrap();
    for (name, patched, problem) in [
        // The last normalizer std (3.0), vanishing.
        ("std", patch_f32(&bytes, 3.0, 1e-45), "obs_norm.std[2]"),
        // The first action scale (2.0), near f32::MAX.
        ("weight", patch_f32(&bytes, 2.0, 3e38), "action.scale"),
        (
            "clip",
            patch_metadata(&bytes, "obs_clip", "1e-45"),
            "obs_clip",
        ),
    ] {
        let file = dir.path().join(format!("{name}.safetensors"));
        std::fs::write(&file, patched).unwrap();
        let out = inspect(&[], &file);
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert_eq!(out.status.code(), Some(1), "{name}: {stderr}");
        assert!(
            stderr.contains(&file.display().to_string()) && stderr.contains(problem),
            "{name}: {stderr}"
        );
    }
    // The unpatched file still passes: the patching is what fails it.
    let file = dir.path().join("good.safetensors");
    std::fs::write(&file, patch_metadata(&bytes, "obs_clip", "5")).unwrap();
    assert!(inspect(&[], &file).status.success());
}
