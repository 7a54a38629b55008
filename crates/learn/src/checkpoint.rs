//! Training checkpoints: everything needed to continue a run — actor, critic and std
//! parameters, Adam's moments, step count and learning rate, the observation normalizer, and
//! the run's progress — in one safetensors file, written atomically.
//!
//! Tensors: `model/<var>` (variable-store names such as `actor.0.weight`), `adam/exp_avg/<var>`,
//! `adam/exp_avg_sq/<var>`, and with a normalizer `obs_norm/mean`, `obs_norm/var`. Metadata:
//! `format`, `format_version`, `task`, `iteration`, `env_steps`, `learning_rate`,
//! `adam_step` and `obs_norm_count`.
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
const FORMAT_VERSION: &str = "1";

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
    if let Some(norm) = ppo.policy().normalizer() {
        entries.push(("obs_norm/mean".into(), f32_bytes(norm.mean())?));
        entries.push(("obs_norm/var".into(), f32_bytes(norm.var())?));
        metadata.insert("obs_norm_count".into(), norm.count().to_string());
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
    if get("format")? != FORMAT || get("format_version")? != FORMAT_VERSION {
        return Err(bad(format!("not a {FORMAT} version {FORMAT_VERSION} file")));
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
    let normalizer = match (ppo.policy().normalizer(), meta.get("obs_norm_count")) {
        (Some(norm), Some(count)) => {
            let dim = norm.mean().size();
            let count = parse::<i64>("obs_norm_count", count).map_err(bad)?;
            Some(EmpiricalNormalizer::from_parts(
                read("obs_norm/mean", &dim)?,
                read("obs_norm/var", &dim)?,
                count,
            ))
        }
        (None, None) => None,
        (has, _) => {
            let side = if has.is_some() {
                "config uses"
            } else {
                "checkpoint has"
            };
            return Err(bad(format!(
                "observation normalizer mismatch: only the {side} one"
            )));
        }
    };

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
    if let (Some(n), Some(saved)) = (ppo.policy_mut().normalizer_mut(), normalizer) {
        *n = saved;
    }
    Ok(progress)
}
