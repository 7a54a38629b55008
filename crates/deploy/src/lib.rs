//! # moonhaul-deploy
//!
//! What runs on each robot: the per-unit daemon's settings, and (growing) the control loop,
//! peer transport and mission log.

pub mod unit_config;
