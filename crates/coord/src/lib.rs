//! # moonhaul-coord
//!
//! The coordination layer of the paper's Section V that runs every control tick onboard:
//!
//! - [`gate`]: the phase MDP (eq. mode_transition) with measured, debounced events;
//! - [`team`]: agreement of N units on phase changes (a barrier) and the team-wide safety stop;
//! - [`clamp`]: the synchronization clamp that admits the largest safe step toward the policies'
//!   target (eqs. stacked_state … stacked_metric) and names the subsystem that limits it;
//! - [`pipeline`]: the one action pipeline (increment → F_k → clamp → U_k) and the hold rule,
//!   called by training, evaluation and the onboard tick alike;
//! - [`message`]: versioned peer messages, what a receiver checks (authentication, replay
//!   protection, physical bounds) and why;
//! - [`validator`]: the receiving side that runs those checks on every frame;
//! - [`auth`]: the authenticated wire frame (HMAC-SHA256) and the team key file;
//! - [`model`]: the unit kinematics the clamp evaluates (arm FK on a differential-drive base);
//! - [`config`]: `configs/sync.toml`, `configs/gate.toml` and the team settings a daemon
//!   derives from `configs/unit.toml`.
//!
//! Per tick a unit authenticates and validates its frames ([`Validator::receive_frame`]),
//! [`team::Team::receive`]s the accepted messages, calls [`team::Team::tick`] (gate +
//! agreement), runs the active policy when told to, and calls [`clamp::Clamp::step`] with the
//! decision's hold reason. Neither tick call allocates.

pub mod auth;
pub mod clamp;
pub mod config;
pub mod gate;
pub mod message;
pub mod model;
pub mod pipeline;
pub mod team;
pub mod validator;

pub use auth::{KeyFile, Sealer};
pub use clamp::{Clamp, ClampInput, ClampReport, ClampTally, HoldReason};
pub use config::{GateConfig, SyncConfig, TeamError, TeamSettings};
pub use gate::{Measurements, PhaseGate};
pub use message::Envelope;
pub use model::UnitModel;
pub use pipeline::{ActionPipeline, Increment, PipelineInput, PipelineReport};
pub use team::{Decision, Directive, Team};
pub use validator::Validator;
