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
