//! A unit's log: one tick record per control tick, and the unit's links where its own
//! encoders and odometry put them.

use std::path::Path;
use std::sync::Arc;

use foxglove::schemas::FrameTransforms;
use foxglove::{Channel, RawChannel};
use nalgebra::{Isometry3, Vector3};

use super::file::{log_time_ns, LogFile};
use super::inputs::LogInputs;
use super::links::UnitFrames;
use super::scene::timestamp;
use super::schema::tick_schema;
use super::topics::{unit_frame_prefix, unit_topic, TF_TOPIC, WORLD_FRAME_ID};
use super::LogError;
use crate::record::TickRecord;

/// One unit's mission log: `/unit{i}/tick`, one [`TickRecord`] per control tick, and `/tf`:
/// `world` → `unit{i}/base_link` by odometry, then every URDF joint at the sensed positions.
pub struct UnitLog {
    file: LogFile,
    ticks: Arc<RawChannel>,
    tf: Channel<FrameTransforms>,
    links: UnitFrames,
    /// The encoded record, reused so steady-state logging allocates little.
    buf: Vec<u8>,
}

impl UnitLog {
    /// Creates (or replaces) the log of unit `unit` at `path`, drawing with the model of
    /// `inputs` and attaching its files.
    pub fn create(path: &Path, unit: usize, inputs: &LogInputs) -> Result<UnitLog, LogError> {
        let mut metadata = vec![("unit", unit.to_string())];
        if let Some(controller) = inputs.controller {
            metadata.push(("controller", controller.to_owned()));
        }
        let file = LogFile::create(path, &metadata, inputs)?;
        let ticks = file.json_channel(&unit_topic(unit), "moonhaul.TickRecord", &tick_schema())?;
        let tf = file.context.channel_builder(TF_TOPIC).build();
        let links = UnitFrames::new(
            &inputs.tree,
            &inputs.spec,
            WORLD_FRAME_ID,
            &unit_frame_prefix(unit),
        );
        Ok(UnitLog {
            file,
            ticks,
            tf,
            links,
            buf: Vec::with_capacity(4096),
        })
    }

    /// Logs one tick at its `stamp_us`. Fails if a flush of an earlier record failed.
    pub fn write(&mut self, r: &TickRecord) -> Result<(), LogError> {
        self.file.check()?;
        self.file.start_records(r.stamp_us)?;
        self.file
            .log_json(&self.ticks, r, r.stamp_us, &mut self.buf)?;
        let pose = &r.sensed.base_pose;
        let footprint = Isometry3::new(
            Vector3::new(pose.x_m, pose.y_m, 0.0),
            Vector3::z() * pose.yaw_rad,
        );
        let tf = self.links.update(
            &footprint,
            &r.sensed.wheels.position_rad,
            &r.sensed.arm.position_rad,
            timestamp(r.stamp_us),
        );
        self.tf.log_with_time(tf, log_time_ns(r.stamp_us));
        Ok(())
    }

    /// Finishes the open chunk and flushes the file now (the background flush does it every
    /// [`FLUSH_PERIOD`](super::FLUSH_PERIOD) anyway).
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.file.flush()
    }

    /// Writes the summary and footer, flushes and syncs the file.
    pub fn finish(self) -> Result<(), LogError> {
        self.file.finish()
    }
}
