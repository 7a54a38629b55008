//! # moonhaul-sim
//!
//! The training and test world: two wheel–arm units rigidly grasping one payload on randomized
//! lunar-analog terrain, in rapier3d.
//!
//! - [`config`]: `configs/sim.toml` — rates, solver settings, motor gains, grasp limits.
//! - [`model`]: URDFs split into rapier bodies; [`ik`]: arm inverse kinematics on core's FK.
//! - [`randomization`] and [`terrain`]: the paper's domain randomization.
//! - [`scene`]: one world ([`scene::Env`]) — formation, multibodies, grasps, readout.
//!
//!   **Payloads** are URDFs: the shipped `assets/payload_{box,bricks,sledge}.urdf`, or any file
//!   [`SceneModel::add_payload_file`] loads as [`PayloadKind::Custom`]. A payload has exactly
//!   one link, named `payload`, with a positive mass and exactly one `<collision>`, a `<box>`
//!   centred on the link frame with its long side along x (size x ≥ size y), and the arms must
//!   reach its grasp; the [`scene`] module docs give the whole convention. Violations are
//!   errors naming the file.
//! - [`handover`]: transport and place episodes that start where a deployed mission handed
//!   over (captured, replayed).
//! - [`batch`]: many worlds stepped in parallel, deterministically.
//! - [`task`]: the lift, transport and place episodes that training and evaluation share.
//! - [`scripted`]: the non-learned lift → transport → place controller; [`accuracy`]: the
//!   configured solver settings against a fine reference.

use std::path::PathBuf;

pub mod accuracy;
pub mod batch;
pub mod config;
pub mod convert;
pub mod handover;
pub use moonhaul_core::ik;
pub mod model;
pub mod randomization;
pub mod scene;
pub mod scripted;
pub mod task;
pub mod terrain;

pub use accuracy::AccuracyReport;
pub use batch::BatchEnv;
pub use config::SimConfig;
pub use randomization::PayloadKind;
pub use scene::{Env, EnvOptions, EnvState, SceneModel};

/// Why the simulator cannot start or continue; each variant names the file, field or body.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Settings(#[from] moonhaul_core::config::ConfigError),
    #[error("invalid simulator config: {0}")]
    Invalid(#[from] moonhaul_core::config::FieldError),
    #[error("config field {field}: {reason}")]
    Config { field: &'static str, reason: String },
    #[error("model {}: {reason}", path.display())]
    Model { path: PathBuf, reason: String },
    #[error("kinematics: {0}")]
    Kinematics(String),
}
