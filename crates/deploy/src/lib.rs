//! # moonhaul-deploy
//!
//! What runs on each robot: the per-unit daemon's settings and its mission-log records.

pub mod record;
pub mod unit_config;
