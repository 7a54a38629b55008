//! # moonhaul-deploy
//!
//! What runs on each robot: the per-unit daemon's settings.

pub mod unit_config;
