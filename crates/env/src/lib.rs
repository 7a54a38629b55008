//! # moonhaul-env
//!
//! The environments moonhaul trains on, without libtorch: what a batched environment offers
//! ([`env`]: the [`VecEnv`] trait, its flat f64 buffers, the actor and critic observation
//! groups, auto-reset), the paper's phase rewards r_L, r_T, r_P ([`reward`]), the lift,
//! transport and place tasks built on them over the simulator's batched worlds
//! ([`phase_env`]), Gymnasium's Pendulum-v1 as a benchmark ([`pendulum`]), and the training
//! config ([`config`]) that [`task::make_env`] turns into the environment of its task.
//!
//! Two trainers drive these environments through the same observation function and action
//! pipeline: `moonhaul-learn` (PPO on libtorch through `tch`, which re-exports these modules
//! under their old paths) and the Python extension of `crates/py` (stock rsl_rl on Python's
//! own torch). That second one is why this crate exists apart: a Python extension must not link
//! a libtorch of its own beside the one `import torch` loaded, so nothing here depends on
//! `tch` (`cargo tree -p moonhaul-env | grep tch` is empty).

pub mod config;
pub mod env;
pub mod error;
pub mod export;
pub mod pendulum;
pub mod phase_env;
pub mod provenance;
pub mod reward;
pub mod task;

pub use env::{PipelineStats, VecEnv, VecStep};
pub use error::EnvError;
pub use phase_env::PhaseVecEnv;
