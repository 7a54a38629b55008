//! # moonhaul-learn
//!
//! Training in simulation: PPO on libtorch through `tch`, faithful to rsl_rl (the PPO the paper
//! used), and export of trained actors to the onboard policy format of
//! [`moonhaul_core::policy`]. This is the only crate in the workspace that links libtorch;
//! nothing that runs onboard depends on it.
//!
//! The environments it trains on live in `moonhaul-env`, which has no libtorch, so that the
//! Python extension can drive the same tasks under Python's own torch; this crate re-exports
//! its modules ([`config`], [`env`], [`pendulum`], [`phase_env`], [`reward`], [`task`]) under
//! the paths they always had here.
//!
//! The split follows rsl_rl: [`env`] (what a batched environment offers), [`storage`] (rollout
//! buffer and GAE), [`ppo`] (the update), [`runner`] (rollout/update loop and evaluation),
//! [`trainer`] (the run folder: config, metrics, plots, checkpoints, export). [`reward`] holds
//! the paper's phase rewards r_L, r_T, r_P with Table II's tolerances and weights, and
//! [`phase_env`] the lift, transport and place tasks built on them. [`distill`] is the warm
//! start from the scripted expert (DAgger, then the critic), an algorithm of its own beside
//! [`ppo`] that a config's `[warm_start]` runs before PPO's first iteration.

pub mod actor_critic;
pub mod adam;
pub mod checkpoint;
pub mod distill;
pub mod error;
pub mod export;
pub mod gaussian;
pub mod kickstart;
pub mod metrics;
pub mod mlp;
pub mod normalizer;
pub mod plot;
pub mod ppo;
pub mod runner;
pub mod storage;
pub mod trainer;

pub use error::LearnError;
pub use moonhaul_env::{config, env, pendulum, phase_env, provenance, reward, task, EnvError};
