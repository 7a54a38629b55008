//! # moonhaul-core
//!
//! The math and plain data types every other moonhaul crate shares. Nothing here performs I/O
//! except parsing the files a caller names (URDFs, policy files), and nothing here allocates on
//! the per-tick paths the onboard daemon runs at 50 Hz: the stacked metric, forward kinematics
//! of a prepared chain and the policy MLP forward pass.
//!
//! - [`action`]: the paper's action, a bounded increment on the previous command, and the map
//!   a policy file records.
//! - [`atomic_file`]: whole-or-nothing writes of every file the project produces.
//! - [`overwrite`]: the check every output path passes: never over a run's input, never over
//!   an existing file without `--force`.
//! - [`handover`]: a unit's onboard state when the phase gate hands over, where training
//!   episodes of the next phase begin.
//! - [`config`]: the one loader of every TOML settings file, and its range checks.
//! - [`input`]: size-capped reads of every file that comes from outside.
//! - [`scripted`]: the scripted mission plan, its base tracking law, and the scripted
//!   controller as a controller of the deployed stack.
//! - [`se3`]: the paper's arm pose metric d_SE, the wheel metric, and SE(3) interpolation.
//! - [`seed`]: independent, reproducible random streams from one seed.
//! - [`stacked`]: the stacked state Y of N units (one arm pose and one base position each),
//!   its ℓ∞ metric d and interpolation.
//! - [`state`]: joint and unit state types and the mission [`state::Phase`].
//! - [`ik`]: damped-least-squares inverse kinematics of the 7-joint arm.
//! - [`kinematics`]: URDF kinematic trees, forward kinematics between any two links, limits.
//! - [`unit`]: a wheel–arm unit as its URDF describes it, and differential-drive kinematics.
//! - `plot_font` (feature `plot`): the bundled font of every PNG plot.
//! - [`observation`]: a unit's actor observation o⁽ⁱ⁾, the one function training and the
//!   onboard daemon share, and its recorded layout.
//! - [`touchdown`]: when the ground carries the payload, from the arms' following error.
//! - [`policy`]: the onboard policy runtime (a pure-Rust MLP loaded from safetensors).

pub mod action;
pub mod atomic_file;
pub mod config;
pub mod handover;
pub mod ik;
pub mod input;
pub mod kinematics;
pub mod observation;
pub mod overwrite;
#[cfg(feature = "plot")]
pub mod plot_font;
pub mod policy;
pub mod scripted;
pub mod se3;
pub mod seed;
pub mod stacked;
pub mod state;
pub mod task_config;
pub mod touchdown;
pub mod unit;
