//! # moonhaul-py
//!
//! The native half of the `moonhaul` Python package: `moonhaul._native.Env`, the batched
//! environment of a training config ([`moonhaul_env::task::make_env`], the very function
//! `moonhaul-train` builds its environment with: same observation function, same action
//! pipeline, same rewards). The Python half (`python/moonhaul/`) wraps it as an rsl_rl `VecEnv`
//! with torch tensors.
//!
//! **No libtorch here.** Python's torch is already loaded in the process; this crate depends on
//! `moonhaul-env`, never on `moonhaul-learn`/`tch`. Tensors reach it through the buffer protocol
//! (`tensor.numpy()` of a CPU tensor is a view of the tensor's own memory), so observations,
//! rewards and flags are written in place into the tensors rsl_rl receives: no copy in Python.
//! The environment keeps f64 math; the one conversion, to the f32 of the tensors, happens while
//! writing.
//!
//! **The interpreter's lock is released while the simulator steps** (and resets), so other
//! Python threads run meanwhile; the simulator itself runs on the config's `run.threads`
//! threads or the count given at construction.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Mutex;

use moonhaul_core::policy::{Linear, ObsNormalizer, Policy, Tensor as PolicyTensor};
use moonhaul_env::config::TrainConfig;
use moonhaul_env::export::{assemble_policy, policy_provenance};
use moonhaul_env::{EnvError, VecEnv, VecStep};
use pyo3::buffer::{Element, PyBuffer};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// An environment error as a Python exception: bad input (shapes, configs) is a `ValueError`,
/// the rest (a simulator failure) a `RuntimeError`.
fn py_err(e: EnvError) -> PyErr {
    match e {
        EnvError::Shape { .. }
        | EnvError::Config(_)
        | EnvError::InvalidConfig { .. }
        | EnvError::HandOvers(_)
        | EnvError::Input(_)
        | EnvError::Policy(_)
        | EnvError::NonFinite { .. } => PyValueError::new_err(e.to_string()),
        _ => PyRuntimeError::new_err(e.to_string()),
    }
}

/// What the lock guards: the environment and its reused step buffers.
struct Inner {
    env: Box<dyn VecEnv + Send>,
    out: VecStep,
    actions: Vec<f64>,
}

/// A batch of environments of one training config (see the module docs). Rows are agents: a
/// phase task has two per simulated world (one per unit), so `num_envs` is twice the worlds.
#[pyclass(module = "moonhaul._native", name = "Env", frozen)]
pub struct Env {
    inner: Mutex<Inner>,
    #[pyo3(get)]
    num_envs: usize,
    #[pyo3(get)]
    obs_dim: usize,
    #[pyo3(get)]
    critic_obs_dim: usize,
    #[pyo3(get)]
    action_dim: usize,
    /// Steps after which an episode is cut by its time limit (0: none).
    #[pyo3(get)]
    max_episode_length: u64,
    /// Simulated worlds (phase tasks) or pendulums the batch holds.
    #[pyo3(get)]
    worlds: usize,
    /// Simulator threads.
    #[pyo3(get)]
    threads: usize,
    /// Multiplies every reward written (the config's `ppo.reward_scale` unless given).
    #[pyo3(get)]
    reward_scale: f64,
    /// The training config, as JSON (relative paths resolved as the loader resolved them).
    #[pyo3(get)]
    config_json: String,
    /// The payload URDF every world carries instead of the sim config's payloads, if any.
    payload: Option<PathBuf>,
    /// The loaded config: what an exported policy's provenance digests.
    train: TrainConfig,
}

/// The writable, C-contiguous buffer `obj` of exactly `len` items of `T`, named `what` in errors.
fn buffer<T: Element>(
    obj: &Bound<'_, PyAny>,
    len: usize,
    what: &str,
    writable: bool,
) -> PyResult<PyBuffer<T>> {
    let buf = PyBuffer::<T>::get(obj).map_err(|e| {
        PyValueError::new_err(format!("{what}: {e} (expected a CPU tensor's .numpy())"))
    })?;
    if writable && buf.readonly() {
        return Err(PyValueError::new_err(format!("{what} is read-only")));
    }
    if !buf.is_c_contiguous() {
        return Err(PyValueError::new_err(format!("{what} is not C-contiguous")));
    }
    if buf.item_count() != len {
        return Err(PyValueError::new_err(format!(
            "{what} has {} values, expected {len}",
            buf.item_count()
        )));
    }
    Ok(buf)
}

/// A float32 array (a CPU tensor's `.numpy()`, any layout) as a policy tensor; `what` names it
/// in errors, `rank` is the number of dimensions it must have.
fn policy_tensor(
    py: Python<'_>,
    obj: &Bound<'_, PyAny>,
    what: &str,
    rank: usize,
) -> PyResult<PolicyTensor> {
    let buf = PyBuffer::<f32>::get(obj)
        .map_err(|e| PyValueError::new_err(format!("{what}: {e} (expected a float32 array)")))?;
    if buf.shape().len() != rank {
        return Err(PyValueError::new_err(format!(
            "{what} has shape {:?}, expected {rank} dimensions",
            buf.shape()
        )));
    }
    let data = buf.to_vec(py)?;
    PolicyTensor::new(buf.shape().to_vec(), data)
        .map_err(|e| PyValueError::new_err(format!("{what}: {e}")))
}

/// Writes `src` as f32 into `dst` (checked by [`buffer`] to hold `src.len()` items).
fn write_f32(py: Python<'_>, dst: &PyBuffer<f32>, src: &[f64], scale: f64) -> PyResult<()> {
    let cells = dst
        .as_mut_slice(py)
        .ok_or_else(|| PyValueError::new_err("output buffer is not writable"))?;
    for (cell, &v) in cells.iter().zip(src) {
        cell.set((v * scale) as f32);
    }
    Ok(())
}

fn write_flags(py: Python<'_>, dst: &PyBuffer<u8>, flag: impl Fn(usize) -> bool) -> PyResult<()> {
    let cells = dst
        .as_mut_slice(py)
        .ok_or_else(|| PyValueError::new_err("output buffer is not writable"))?;
    for (i, cell) in cells.iter().enumerate() {
        cell.set(u8::from(flag(i)));
    }
    Ok(())
}

impl Env {
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, Inner>> {
        self.inner
            .lock()
            .map_err(|_| PyRuntimeError::new_err("a previous call panicked inside the environment"))
    }
}

#[pymethods]
impl Env {
    /// `config`: a training config (`configs/train/<task>.toml`). `num_envs`: simulated worlds
    /// (the config's `env.num_envs` unless given; two agent rows each for a phase task).
    /// `threads`: simulator threads (the config's `run.threads` unless given). `payload`: a
    /// payload URDF every world carries. `reward_scale`: the config's `ppo.reward_scale`
    /// unless given.
    #[new]
    #[pyo3(signature = (config, num_envs=None, threads=None, payload=None, reward_scale=None))]
    fn new(
        py: Python<'_>,
        config: PathBuf,
        num_envs: Option<usize>,
        threads: Option<usize>,
        payload: Option<PathBuf>,
        reward_scale: Option<f64>,
    ) -> PyResult<Self> {
        let mut train = TrainConfig::load(&config)
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", config.display())))?;
        if let Some(threads) = threads {
            if threads == 0 {
                return Err(PyValueError::new_err("threads must be at least 1"));
            }
            train.run.threads = threads;
        }
        let worlds = num_envs.unwrap_or(train.env.num_envs);
        if worlds == 0 {
            return Err(PyValueError::new_err("num_envs must be at least 1"));
        }
        let reward_scale = reward_scale.unwrap_or(train.ppo.reward_scale);
        if !reward_scale.is_finite() || reward_scale <= 0.0 {
            return Err(PyValueError::new_err(format!(
                "reward_scale must be positive and finite, got {reward_scale}"
            )));
        }
        let config_json = serde_json::to_string(&train)
            .map_err(|e| PyRuntimeError::new_err(format!("config as JSON: {e}")))?;
        let env = py
            .detach(|| moonhaul_env::task::make_env(&train, worlds, payload.as_deref()))
            .map_err(py_err)?;
        let (n, o, c, a) = (
            env.num_envs(),
            env.obs_dim(),
            env.critic_obs_dim(),
            env.action_dim(),
        );
        Ok(Env {
            num_envs: n,
            obs_dim: o,
            critic_obs_dim: c,
            action_dim: a,
            max_episode_length: env.max_episode_steps().unwrap_or(0),
            worlds,
            threads: train.run.threads,
            reward_scale,
            config_json,
            payload,
            train,
            inner: Mutex::new(Inner {
                out: VecStep::new(n, o, c),
                actions: vec![0.0; n * a],
                env,
            }),
        })
    }

    /// The payload URDF given at construction, if any.
    #[getter]
    fn payload(&self) -> Option<PathBuf> {
        self.payload.clone()
    }

    /// Reseeds every env from `seed`, starts new episodes and writes the first observations
    /// into `obs` (f32, `num_envs * obs_dim`) and `critic_obs` (f32, `num_envs * critic_obs_dim`).
    fn reset(
        &self,
        py: Python<'_>,
        seed: u64,
        obs: &Bound<'_, PyAny>,
        critic_obs: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let obs = buffer::<f32>(obs, self.num_envs * self.obs_dim, "obs", true)?;
        let critic = buffer::<f32>(
            critic_obs,
            self.num_envs * self.critic_obs_dim,
            "critic_obs",
            true,
        )?;
        let mut guard = self.lock()?;
        let inner = &mut *guard;
        py.detach(|| {
            inner
                .env
                .reset(seed, &mut inner.out.obs, &mut inner.out.critic_obs)
        })
        .map_err(py_err)?;
        write_f32(py, &obs, &inner.out.obs, 1.0)?;
        write_f32(py, &critic, &inner.out.critic_obs, 1.0)
    }

    /// Advances every env by one control step with `actions` (f32, `num_envs * action_dim`)
    /// and writes, for each row: the observation after the step (after the auto-reset of an
    /// episode that ended) into `obs` and `critic_obs`, the reward times `reward_scale` into
    /// `rewards` (f32), `dones` (u8: the episode ended, by termination or time limit) and
    /// `time_outs` (u8: it was cut by the time limit and not terminated, rsl_rl's bootstrap
    /// flag). The simulator steps with the interpreter's lock released.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &self,
        py: Python<'_>,
        actions: &Bound<'_, PyAny>,
        obs: &Bound<'_, PyAny>,
        critic_obs: &Bound<'_, PyAny>,
        rewards: &Bound<'_, PyAny>,
        dones: &Bound<'_, PyAny>,
        time_outs: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let n = self.num_envs;
        let actions = buffer::<f32>(actions, n * self.action_dim, "actions", false)?;
        let obs = buffer::<f32>(obs, n * self.obs_dim, "obs", true)?;
        let critic = buffer::<f32>(critic_obs, n * self.critic_obs_dim, "critic_obs", true)?;
        let rewards = buffer::<f32>(rewards, n, "rewards", true)?;
        let dones = buffer::<u8>(dones, n, "dones", true)?;
        let time_outs = buffer::<u8>(time_outs, n, "time_outs", true)?;
        let mut guard = self.lock()?;
        let inner = &mut *guard;
        let cells = actions
            .as_slice(py)
            .ok_or_else(|| PyValueError::new_err("actions cannot be read"))?;
        for (a, cell) in inner.actions.iter_mut().zip(cells) {
            *a = f64::from(cell.get());
        }
        if let Some(i) = inner.actions.iter().position(|a| !a.is_finite()) {
            return Err(PyValueError::new_err(format!("actions[{i}] is not finite")));
        }
        py.detach(|| inner.env.step(&inner.actions, &mut inner.out))
            .map_err(py_err)?;
        let out = &inner.out;
        write_f32(py, &obs, &out.obs, 1.0)?;
        write_f32(py, &critic, &out.critic_obs, 1.0)?;
        write_f32(py, &rewards, &out.rewards, self.reward_scale)?;
        write_flags(py, &dones, |i| out.terminated[i] || out.truncated[i])?;
        write_flags(py, &time_outs, |i| out.truncated[i] && !out.terminated[i])
    }

    /// What the action pipeline did since the last call (clamp and grasp figures, the ones eval
    /// reports), or `None` for an env without the pipeline (the pendulum).
    fn take_pipeline_stats<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(stats) = self.lock()?.env.take_pipeline_stats() else {
            return Ok(None);
        };
        let d = PyDict::new(py);
        let c = &stats.clamp;
        d.set_item("ticks", c.ticks)?;
        d.set_item("t_max_sum", c.t_max_sum)?;
        d.set_item("clamped", c.clamped)?;
        d.set_item("holds", c.holds)?;
        d.set_item("no_step", c.no_step)?;
        d.set_item("grasp_force_sum_n", stats.grasp_force_sum_n)?;
        d.set_item("grasp_force_peak_n", stats.grasp_force_peak_n)?;
        Ok(Some(d))
    }

    /// The action map's per-dimension scale (`action_dim` values): a policy's raw output `a`
    /// commands `offset + scale * a`. An exported policy folds it into its output layer.
    fn action_scale(&self) -> PyResult<Vec<f64>> {
        Ok(self.lock()?.env.action_scale())
    }

    /// The action map's per-dimension offset (`action_dim` values).
    fn action_offset(&self) -> PyResult<Vec<f64>> {
        Ok(self.lock()?.env.action_offset())
    }

    /// Metadata an exported policy must carry to run as trained (the action map's version).
    fn policy_metadata(&self) -> PyResult<Vec<(String, String)>> {
        Ok(self.lock()?.env.policy_metadata())
    }

    /// Writes an ELU actor trained on this environment as moonhaul's onboard policy file at
    /// `path` (atomically: a reader sees the old file or the new one), the file `moonhaul-unit`
    /// and `moonhaul eval` fly. `weights[i]` (`[out, in]`) and `biases[i]` (`[out]`) are the
    /// layers in order, float32; `obs_mean`/`obs_std` the actor's normalizer with its ε already
    /// added to the std (both or neither: identity). The file records the task's identity and
    /// observation layout, the action map, the config's digest and the source commit, and
    /// `extra` (the trainer's provenance: who trained it, seed, iteration); `extra` cannot
    /// override those. The file is validated (shapes chain, values finite) before it is
    /// written.
    #[pyo3(signature = (path, weights, biases, obs_mean=None, obs_std=None, extra=None))]
    #[allow(clippy::too_many_arguments)]
    fn export_policy(
        &self,
        py: Python<'_>,
        path: PathBuf,
        weights: Vec<Bound<'_, PyAny>>,
        biases: Vec<Bound<'_, PyAny>>,
        obs_mean: Option<Bound<'_, PyAny>>,
        obs_std: Option<Bound<'_, PyAny>>,
        extra: Option<BTreeMap<String, String>>,
    ) -> PyResult<()> {
        if weights.len() != biases.len() || weights.is_empty() {
            return Err(PyValueError::new_err(format!(
                "{} weights and {} biases: expected one of each per layer, at least one layer",
                weights.len(),
                biases.len()
            )));
        }
        let layers = weights
            .iter()
            .zip(&biases)
            .enumerate()
            .map(|(i, (w, b))| {
                Ok(Linear {
                    weight: policy_tensor(py, w, &format!("weights[{i}]"), 2)?,
                    bias: policy_tensor(py, b, &format!("biases[{i}]"), 1)?,
                })
            })
            .collect::<PyResult<Vec<_>>>()?;
        let obs_norm = match (obs_mean, obs_std) {
            (Some(mean), Some(std)) => Some(ObsNormalizer {
                mean: policy_tensor(py, &mean, "obs_mean", 1)?,
                std: policy_tensor(py, &std, "obs_std", 1)?,
            }),
            (None, None) => None,
            _ => {
                return Err(PyValueError::new_err(
                    "obs_mean and obs_std come together (or neither, for no normalizer)",
                ))
            }
        };
        let commit = moonhaul_env::provenance::commit();
        let inner = self.lock()?;
        let env: &dyn moonhaul_env::VecEnv = inner.env.as_ref();
        let (phase, metadata) = policy_provenance(
            &self.train,
            env,
            commit,
            self.payload.as_deref(),
            extra.unwrap_or_default(),
        )
        .map_err(py_err)?;
        let (scale, offset) = (env.action_scale(), env.action_offset());
        drop(inner);
        let policy =
            assemble_policy(phase, layers, obs_norm, &scale, &offset, metadata).map_err(py_err)?;
        policy
            .write_file(&path)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))
    }
}

/// A policy file as the onboard runtime reads and runs it (`moonhaul_core::policy`): the check
/// that an export flies what the trainer's actor computes, without leaving Python.
#[pyclass(module = "moonhaul._native", name = "OnboardPolicy", frozen)]
pub struct OnboardPolicy {
    policy: Policy,
}

#[pymethods]
impl OnboardPolicy {
    /// Reads and validates the policy file at `path` (a `ValueError` naming the file and what
    /// is wrong with it otherwise).
    #[new]
    fn new(path: PathBuf) -> PyResult<Self> {
        Policy::from_file(&path)
            .map(|policy| OnboardPolicy { policy })
            .map_err(|e| PyValueError::new_err(format!("{}: {e}", path.display())))
    }

    /// The file's metadata: `phase`, `obs_dim`, `action_dim` and every free-form entry.
    #[getter]
    fn metadata(&self) -> BTreeMap<String, String> {
        let m = self.policy.metadata();
        let mut out = m.extra.clone();
        out.insert("phase".into(), m.phase.name().into());
        out.insert("obs_dim".into(), m.obs_dim.to_string());
        out.insert("action_dim".into(), m.action_dim.to_string());
        out
    }

    /// The command increment for one observation (`obs_dim` values), as the tick computes it.
    fn act(&self, obs: Vec<f64>) -> PyResult<Vec<f64>> {
        let mut scratch = self.policy.scratch();
        let mut action = vec![0.0; self.policy.action_dim()];
        self.policy
            .act(&obs, &mut scratch, &mut action)
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(action)
    }
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Env>()?;
    m.add_class::<OnboardPolicy>()?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
