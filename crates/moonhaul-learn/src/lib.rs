//! # moonhaul-learn
//!
//! Training in simulation: phase tasks, PPO on libtorch through `tch`, and export of trained
//! actors to the onboard policy format of [`moonhaul_core::policy`]. This is the only crate in
//! the workspace that links libtorch; nothing that runs onboard depends on it.

pub mod mlp;
