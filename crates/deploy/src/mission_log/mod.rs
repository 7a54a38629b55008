//! Mission logs as MCAP, written through the Foxglove SDK so a mission replays in Foxglove
//! (3-D included, `assets/foxglove/mission_layout.json` lays it out), and read back — truncated
//! ones too — by `moonhaul log summary` and the tests.
//!
//! Two kinds of log:
//!
//! - [`UnitLog`], one per unit: topic `/unit{i}/tick`, one [`TickRecord`] per control tick as
//!   JSON (with a JSON schema, so Foxglove lists and plots its fields); `/tf` as foxglove
//!   `FrameTransforms`: `world` → `unit{i}/base_link` by the unit's odometry, then every URDF
//!   joint at its sensed position (`unit{i}/arm_link_3`, …).
//! - [`WorldLog`], one per simulated world: topic `/world/frame`, one [`WorldFrame`] per world
//!   step as JSON (the ground truth, like the paper's OptiTrack); `/tf`: `world` → `payload`,
//!   and the units' links at their true poses and joint positions (`truth/unit{i}/…`); and
//!   `/scene`, a foxglove `SceneUpdate` drawing the payload as a cube locked to the `payload`
//!   frame.
//!
//! Every log carries the files it was recorded with as MCAP attachments ([`LogInputs`]: the
//! unit URDF, then the configs, then a learned unit's policy files), and `moonhaul` metadata
//! (unit index and what flew it, `controller`; team size, payload size).
//!
//! The log time of every message is the record's `stamp_us` (the team's clock, the world's time
//! in a simulated mission), not the wall clock, so logs of one mission line up in Foxglove.
//!
//! # Chunks, and what a killed process leaves
//!
//! Each log has its own Foxglove [`Context`](foxglove::Context), so two logs in one process
//! never see each other's channels. Records are written in zstd-compressed chunks held in
//! memory until complete (`disable_seeking`: the writer never leaves a placeholder chunk header
//! on disk to patch later). A chunk is finished before it would span more than a second of log
//! time, and a background thread finishes the open chunk and flushes the file every
//! [`FLUSH_PERIOD`] of wall time. A process killed at any moment, or a copy cut short,
//! therefore leaves a valid MCAP prefix — possibly ending in one partly written chunk and
//! without the summary and footer — that loses at most the records of its last second.
//! [`read_unit_log`] and [`read_world_log`] return every message of such a file up to the
//! first incomplete record; [`read_world_log_contents`] also says whether the file was whole.
//!
//! Write errors of the SDK's sink are only logged by the SDK itself (`tracing`); the flush that
//! follows fails on the same file, so an I/O error surfaces here at the latest one flush period
//! later, from the next [`UnitLog::write`] or from `finish`.

#[cfg(doc)]
use crate::record::{TickRecord, WorldFrame};

mod error;
mod file;
mod flusher;
mod inputs;
mod links;
mod read;
mod scene;
mod schema;
mod topics;
mod unit;
mod world;

#[cfg(test)]
mod tests;

use std::time::Duration;

pub use error::LogError;
pub use inputs::LogInputs;
pub(crate) use links::UnitLinks;
pub use read::{
    read_attachments, read_unit_log, read_unit_log_contents, read_world_log,
    read_world_log_contents, LogContents, LogEnd,
};
pub use topics::{
    truth_frame_prefix, unit_frame_prefix, unit_topic, PAYLOAD_FRAME_ID, SCENE_TOPIC, TF_TOPIC,
    WORLD_FRAME_ID, WORLD_TOPIC,
};
pub use unit::UnitLog;
pub use world::WorldLog;

/// How often the open chunk is finished and the file flushed: what a killed process may lose.
pub const FLUSH_PERIOD: Duration = Duration::from_secs(1);

/// Largest log file read, bytes (2 GiB): compressed, many hours of a unit, far beyond a
/// mission; a larger file is refused before anything is read (every message is decoded into
/// memory).
pub const MAX_LOG_BYTES: u64 = 2 << 30;
