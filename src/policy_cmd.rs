//! `moonhaul policy`: tools for onboard policy files (safetensors, format in
//! `moonhaul_core::policy`).

use std::path::PathBuf;

use anyhow::Context;
use moonhaul_core::policy::{Policy, FORMAT_NAME, FORMAT_VERSION};
use serde_json::json;

#[derive(clap::Subcommand)]
pub enum PolicyCommand {
    /// Validate a policy file and print its metadata and a summary of its parameters.
    Inspect {
        /// The policy file (safetensors).
        file: PathBuf,
        /// Print one JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: PolicyCommand) -> anyhow::Result<()> {
    match cmd {
        PolicyCommand::Inspect { file, json } => {
            // A full load, not just the header: inspect doubles as the check that a file
            // will run onboard.
            let policy = Policy::from_file(&file)
                .with_context(|| format!("cannot inspect {}", file.display()))?;
            if json {
                outln!("{}", inspect_json(&file, &policy))
            } else {
                outln!("{}", inspect_text(&file, &policy).trim_end())
            }
        }
    }
}

fn inspect_json(file: &std::path::Path, policy: &Policy) -> serde_json::Value {
    let meta = policy.metadata();
    let norm = policy.obs_normalizer();
    let action = policy.action_affine();
    let range = |v: &[f32]| {
        let (min, max) = min_max(v);
        json!({ "min": json_f32(min), "max": json_f32(max) })
    };
    let list = |v: &[f32]| v.iter().copied().map(json_f32).collect::<Vec<_>>();
    json!({
        "file": file.display().to_string(),
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "phase": meta.phase.name(),
        "obs_dim": meta.obs_dim,
        "action_dim": meta.action_dim,
        "hidden_sizes": meta.hidden_sizes,
        "activation": meta.activation.name(),
        "obs_clip": meta.obs_clip.map(json_f32),
        "param_count": policy.param_count(),
        "obs_norm": { "mean": range(norm.mean.data()), "std": range(norm.std.data()) },
        "action": { "scale": list(action.scale.data()), "offset": list(action.offset.data()) },
        "extra": meta.extra,
    })
}

fn inspect_text(file: &std::path::Path, policy: &Policy) -> String {
    let meta = policy.metadata();
    let norm = policy.obs_normalizer();
    let action = policy.action_affine();
    let sizes: Vec<String> = meta.layer_sizes().iter().map(usize::to_string).collect();
    let range = |v: &[f32]| {
        let (min, max) = min_max(v);
        format!("min {min}, max {max}")
    };
    let mut rows = vec![
        ("file".to_owned(), file.display().to_string()),
        ("format".into(), format!("{FORMAT_NAME} v{FORMAT_VERSION}")),
        ("phase".into(), meta.phase.name().to_owned()),
        ("obs_dim".into(), meta.obs_dim.to_string()),
        ("action_dim".into(), meta.action_dim.to_string()),
        ("hidden_sizes".into(), format!("{:?}", meta.hidden_sizes)),
        ("layers".into(), sizes.join(" -> ")),
        ("activation".into(), meta.activation.name().to_owned()),
        (
            "obs_clip".into(),
            meta.obs_clip.map_or("none".to_owned(), |c| c.to_string()),
        ),
        ("parameters".into(), policy.param_count().to_string()),
        ("obs_norm.mean".into(), range(norm.mean.data())),
        ("obs_norm.std".into(), range(norm.std.data())),
        ("action.scale".into(), format!("{:?}", action.scale.data())),
        (
            "action.offset".into(),
            format!("{:?}", action.offset.data()),
        ),
    ];
    rows.extend(
        meta.extra
            .iter()
            .map(|(k, v)| (format!("extra.{k}"), v.clone())),
    );
    let width = rows.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    rows.iter()
        .map(|(k, v)| format!("{k:<width$}  {v}\n"))
        .collect()
}

/// An f32 as the JSON number with its shortest decimal spelling (`0.59`, not the f64 widening
/// `0.5899999737739563`); both read back as the same f32.
fn json_f32(v: f32) -> serde_json::Value {
    v.to_string()
        .parse::<f64>()
        .map_or(serde_json::Value::Null, serde_json::Value::from)
}

/// Smallest and largest value; a validated policy has no empty or non-finite tensor.
fn min_max(values: &[f32]) -> (f32, f32) {
    values
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        })
}
