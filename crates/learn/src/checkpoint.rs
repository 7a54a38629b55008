//! Training checkpoints: everything needed to continue a run — actor, critic and std
//! parameters, Adam's moments, step count and learning rate, the actor's and the critic's
//! observation normalizers, and the run's progress — in one safetensors file, written
//! atomically.
//!
//! Tensors: `model/<var>` (variable-store names such as `actor.0.weight`), `adam/exp_avg/<var>`,
//! `adam/exp_avg_sq/<var>`, and with normalization `obs_norm/mean`, `obs_norm/var` (actor) and
//! `critic_obs_norm/mean`, `critic_obs_norm/var` (critic). Metadata: `format`,
//! `format_version`, `task`, `iteration`, `env_steps`, `learning_rate`, `adam_step`,
//! `obs_norm_count` and `critic_obs_norm_count`.
//!
//! Version 2 added the critic's normalizer (the critic reads its own observations, see
//! [`crate::env`]); version 1 files are refused rather than resumed with a critic normalizer
//! reset to identity.
//!
//! Not stored: libtorch's and the envs' random streams, and the episodes in progress. A resumed
//! run reseeds both from the config seed and the iteration and starts fresh episodes (as rsl_rl
//! does), so it is reproducible but not bit-identical to an uninterrupted run.

use std::collections::HashMap;
use std::path::Path;

use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;
use tch::Tensor;

use crate::config::Task;
use crate::normalizer::EmpiricalNormalizer;
use crate::ppo::Ppo;
use crate::runner::Progress;
use crate::LearnError;

const FORMAT: &str = "moonhaul-checkpoint";
const FORMAT_VERSION: &str = "2";
/// Prefixes of the actor's and the critic's normalizer entries.
const OBS_NORM: &str = "obs_norm";
const CRITIC_OBS_NORM: &str = "critic_obs_norm";

/// Writes `bytes` to `path` whole or not at all ([`moonhaul_core::atomic_file`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), LearnError> {
    moonhaul_core::atomic_file::write(path, bytes).map_err(LearnError::io(path))
}

/// A tensor's shape and little-endian F32 bytes.
type Raw = (Vec<usize>, Vec<u8>);

fn f32_bytes(t: &Tensor) -> Result<Raw, LearnError> {
    let shape = t.size().iter().map(|&d| d as usize).collect();
    let values: Vec<f32> = Vec::try_from(&t.flatten(0, -1))?;
    Ok((shape, values.iter().flat_map(|v| v.to_le_bytes()).collect()))
}

/// Saves the learner's state and `progress` to `path` (atomically).
pub fn save(path: &Path, ppo: &Ppo, progress: Progress, task: Task) -> Result<(), LearnError> {
    let mut entries: Vec<(String, Raw)> = Vec::new();
    for (name, var) in ppo.policy().var_store().variables() {
        entries.push((format!("model/{name}"), f32_bytes(&var)?));
    }
    for (name, m, v) in ppo.optimizer().moments() {
        entries.push((format!("adam/exp_avg/{name}"), f32_bytes(m)?));
        entries.push((format!("adam/exp_avg_sq/{name}"), f32_bytes(v)?));
    }
    let mut metadata = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("format_version".into(), FORMAT_VERSION.into()),
        ("task".into(), task.name().into()),
        ("iteration".into(), progress.iteration.to_string()),
        ("env_steps".into(), progress.env_steps.to_string()),
        ("learning_rate".into(), ppo.learning_rate().to_string()),
        ("adam_step".into(), ppo.optimizer().step_count().to_string()),
    ]);
    let policy = ppo.policy();
    let normalizers = [
        (OBS_NORM, policy.obs_normalizer()),
        (CRITIC_OBS_NORM, policy.critic_obs_normalizer()),
    ];
    for (prefix, norm) in normalizers {
        if let Some(norm) = norm {
            entries.push((format!("{prefix}/mean"), f32_bytes(norm.mean())?));
            entries.push((format!("{prefix}/var"), f32_bytes(norm.var())?));
            metadata.insert(format!("{prefix}_count"), norm.count().to_string());
        }
    }
    let views = entries
        .iter()
        .map(|(name, (shape, bytes))| {
            Ok((
                name.as_str(),
                TensorView::new(Dtype::F32, shape.clone(), bytes)?,
            ))
        })
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>();
    let bytes = views
        .and_then(|v| safetensors::serialize(v, Some(metadata)))
        .map_err(|e| LearnError::Checkpoint {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
    write_atomic(path, &bytes)
}

/// Restores a checkpoint written by [`save`] into `ppo` (built from the same config) and
/// returns the progress to continue from. Every mismatch names the tensor or key at fault.
pub fn load(path: &Path, ppo: &mut Ppo, task: Task) -> Result<Progress, LearnError> {
    let bad = |reason: String| LearnError::Checkpoint {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = moonhaul_core::input::read_capped(path, moonhaul_core::input::MAX_CHECKPOINT_BYTES)
        .map_err(|e| bad(e.to_string()))?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| bad(e.to_string()))?;
    let (_, header) = SafeTensors::read_metadata(&bytes).map_err(|e| bad(e.to_string()))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let get = |key: &str| {
        meta.get(key)
            .ok_or_else(|| bad(format!("metadata `{key}` missing")))
    };
    fn parse<T: std::str::FromStr>(key: &str, value: &str) -> Result<T, String> {
        value
            .parse()
            .map_err(|_| format!("metadata `{key}` = {value:?} is not a number"))
    }
    if get("format")? != FORMAT {
        return Err(bad(format!("not a {FORMAT} file")));
    }
    let version = get("format_version")?;
    if version != FORMAT_VERSION {
        return Err(bad(format!(
            "format_version {version:?}, this build reads only version {FORMAT_VERSION} \
             (version 2 added the critic's observation normalizer)"
        )));
    }
    if get("task")? != task.name() {
        return Err(bad(format!(
            "trained task `{}`, config task `{}`",
            get("task")?,
            task.name()
        )));
    }
    let num = |key: &str| get(key).and_then(|v| parse::<u64>(key, v).map_err(bad));
    let progress = Progress {
        iteration: num("iteration")? as usize,
        env_steps: num("env_steps")?,
    };
    let adam_step = num("adam_step")? as i64;
    let lr = get("learning_rate").and_then(|v| parse::<f64>("learning_rate", v).map_err(bad))?;
    if !(lr.is_finite() && lr > 0.0) {
        return Err(bad(format!("learning_rate {lr} is not positive")));
    }

    let read = |name: &str, shape: &[i64]| -> Result<Tensor, LearnError> {
        let view = file
            .tensor(name)
            .map_err(|_| bad(format!("tensor `{name}` missing")))?;
        let found: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
        if view.dtype() != Dtype::F32 || found != shape {
            return Err(bad(format!(
                "tensor `{name}` is {:?} {found:?}, expected F32 {shape:?}",
                view.dtype()
            )));
        }
        let values: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        if values.iter().any(|v| !v.is_finite()) {
            return Err(bad(format!("tensor `{name}` has non-finite values")));
        }
        Ok(Tensor::from_slice(&values).view(shape))
    };

    let variables = ppo.policy().var_store().variables();
    let saved_model = file
        .names()
        .iter()
        .filter(|n| n.starts_with("model/"))
        .count();
    if saved_model != variables.len() {
        return Err(bad(format!(
            "{saved_model} model tensors, the config's networks have {}",
            variables.len()
        )));
    }
    let mut restored = Vec::with_capacity(variables.len());
    for (name, var) in &variables {
        restored.push((
            var.shallow_clone(),
            read(&format!("model/{name}"), &var.size())?,
        ));
    }
    let mut moments = HashMap::new();
    for (name, var) in &variables {
        let m = read(&format!("adam/exp_avg/{name}"), &var.size())?;
        let v = read(&format!("adam/exp_avg_sq/{name}"), &var.size())?;
        moments.insert(name.clone(), (m, v));
    }
    let read_normalizer = |prefix: &str,
                           current: Option<&EmpiricalNormalizer>|
     -> Result<Option<EmpiricalNormalizer>, LearnError> {
        let count_key = format!("{prefix}_count");
        match (current, meta.get(&count_key)) {
            (Some(norm), Some(count)) => {
                let dim = norm.mean().size();
                let count = parse::<i64>(&count_key, count).map_err(bad)?;
                Ok(Some(EmpiricalNormalizer::from_parts(
                    read(&format!("{prefix}/mean"), &dim)?,
                    read(&format!("{prefix}/var"), &dim)?,
                    count,
                )))
            }
            (None, None) => Ok(None),
            (has, _) => {
                let side = if has.is_some() {
                    "config uses"
                } else {
                    "checkpoint has"
                };
                Err(bad(format!(
                    "`{prefix}` normalizer mismatch: only the {side} one"
                )))
            }
        }
    };
    let policy = ppo.policy();
    let obs_norm = read_normalizer(OBS_NORM, policy.obs_normalizer())?;
    let critic_obs_norm = read_normalizer(CRITIC_OBS_NORM, policy.critic_obs_normalizer())?;

    // Everything validated: now mutate.
    tch::no_grad(|| {
        for (mut var, value) in restored {
            var.copy_(&value);
        }
    });
    ppo.optimizer_mut()
        .restore(adam_step, |name| moments.remove(name))
        .map_err(bad)?;
    ppo.optimizer_mut().set_lr(lr);
    let policy = ppo.policy_mut();
    if let (Some(n), Some(saved)) = (policy.obs_normalizer_mut(), obs_norm) {
        *n = saved;
    }
    if let (Some(n), Some(saved)) = (policy.critic_obs_normalizer_mut(), critic_obs_norm) {
        *n = saved;
    }
    Ok(progress)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::actor_critic::ActorCritic;
    use crate::config::TrainConfig;
    use tch::{Device, Kind};

    /// A learner whose critic reads one more input than its actor, normalizers fed distinct
    /// data.
    fn ppo() -> Ppo {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../configs/train/pendulum.toml"
        );
        let config = TrainConfig::load(path).unwrap();
        assert!(config.policy.obs_normalization);
        let mut ppo = Ppo::new(ActorCritic::new(3, 4, 1, &config.policy), config.ppo, 2, 2);
        let opts = (Kind::Float, Device::Cpu);
        ppo.policy_mut().update_normalizers(
            &Tensor::randn([5, 3], opts),
            &(Tensor::randn([7, 4], opts) * 3.0 - 2.0),
        );
        ppo
    }

    /// Rewrites the checkpoint at `path` keeping only the entries `keep` accepts, with
    /// `format_version` set to `version`.
    fn rewrite(path: &Path, keep: impl Fn(&str) -> bool, version: &str) {
        let bytes = std::fs::read(path).unwrap();
        let file = SafeTensors::deserialize(&bytes).unwrap();
        let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
        let mut meta = header.metadata().clone().unwrap();
        meta.retain(|k, _| keep(k));
        meta.insert("format_version".into(), version.into());
        let views: Vec<_> = file
            .tensors()
            .into_iter()
            .filter(|(name, _)| keep(name))
            .collect();
        std::fs::write(path, safetensors::serialize(views, Some(meta)).unwrap()).unwrap();
    }

    #[test]
    fn both_normalizers_round_trip() {
        tch::manual_seed(5);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ckpt.safetensors");
        let saved = ppo();
        let progress = Progress {
            iteration: 3,
            env_steps: 12,
        };
        save(&path, &saved, progress, Task::Pendulum).unwrap();
        let mut loaded = ppo();
        assert_eq!(load(&path, &mut loaded, Task::Pendulum).unwrap(), progress);
        let pairs = [
            (
                saved.policy().obs_normalizer(),
                loaded.policy().obs_normalizer(),
            ),
            (
                saved.policy().critic_obs_normalizer(),
                loaded.policy().critic_obs_normalizer(),
            ),
        ];
        for (a, b) in pairs {
            let (a, b) = (a.unwrap(), b.unwrap());
            assert_eq!(a.count(), b.count());
            assert!(a.mean().equal(b.mean()) && a.var().equal(b.var()));
        }
        let critic = loaded.policy().critic_obs_normalizer().unwrap();
        assert_eq!((critic.mean().size(), critic.count()), (vec![4], 7));
    }

    #[test]
    fn checkpoints_without_the_critic_normalizer_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ckpt.safetensors");
        let old_layout = |name: &str| !name.starts_with(CRITIC_OBS_NORM);

        save(&path, &ppo(), Progress::default(), Task::Pendulum).unwrap();
        rewrite(&path, old_layout, "1");
        let err = load(&path, &mut ppo(), Task::Pendulum).unwrap_err();
        assert!(err.to_string().contains("format_version \"1\""), "{err}");

        // Even labelled as the current version, the missing normalizer is named.
        save(&path, &ppo(), Progress::default(), Task::Pendulum).unwrap();
        rewrite(&path, old_layout, FORMAT_VERSION);
        let err = load(&path, &mut ppo(), Task::Pendulum).unwrap_err();
        assert!(
            err.to_string().contains("`critic_obs_norm` normalizer"),
            "{err}"
        );
    }
}
