//! The world's log: ground truth, and the transforms and scene that draw it in 3-D.

use std::path::Path;
use std::sync::Arc;

use foxglove::schemas::{FrameTransform, FrameTransforms, SceneUpdate};
use foxglove::{Channel, RawChannel};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::file::{log_time_ns, LogFile};
use super::inputs::LogInputs;
use super::links::UnitFrames;
use super::scene::{payload_scene, quaternion, timestamp, vector};
use super::schema::world_schema;
use super::topics::{
    truth_frame_prefix, PAYLOAD_FRAME_ID, SCENE_TOPIC, TF_TOPIC, WORLD_FRAME_ID, WORLD_TOPIC,
};
use super::LogError;
use crate::record::WorldFrame;

/// The payload cube is re-sent this often (log time, µs) so Foxglove draws it wherever a replay
/// is started or seeked to, not only after the first message.
const SCENE_REPUBLISH_US: u64 = 1_000_000;

/// The world's mission log: ground truth on `/world/frame`; `/tf` (`world` → `payload`, and
/// per unit `world` → `truth/unit{i}/base_link` and every URDF joint at the true joint
/// positions) and `/scene` for 3-D.
pub struct WorldLog {
    file: LogFile,
    frames: Arc<RawChannel>,
    tf: Channel<FrameTransforms>,
    scene: Channel<SceneUpdate>,
    payload_size_m: [f64; 3],
    /// One per unit of the team.
    links: Vec<UnitFrames>,
    /// Log time of the last scene update, µs (`None`: none sent yet).
    scene_sent_us: Option<u64>,
    buf: Vec<u8>,
}

impl WorldLog {
    /// Creates (or replaces) the world log at `path` for a payload of `payload_size_m` (the
    /// box that Foxglove draws, centered on the payload pose) carried by `units` units of the
    /// model of `inputs`, attaching its files.
    pub fn create(
        path: &Path,
        payload_size_m: [f64; 3],
        units: usize,
        inputs: &LogInputs,
    ) -> Result<WorldLog, LogError> {
        let size = payload_size_m.map(|s| format!("{s}"));
        let file = LogFile::create(
            path,
            &[
                ("units", units.to_string()),
                ("payload_size_m", size.join(",")),
            ],
            inputs,
        )?;
        let frames = file.json_channel(WORLD_TOPIC, "moonhaul.WorldFrame", &world_schema())?;
        let tf = file.context.channel_builder(TF_TOPIC).build();
        let scene = file.context.channel_builder(SCENE_TOPIC).build();
        let links = (0..units)
            .map(|i| {
                UnitFrames::new(
                    &inputs.tree,
                    &inputs.spec,
                    WORLD_FRAME_ID,
                    &truth_frame_prefix(i),
                )
            })
            .collect();
        Ok(WorldLog {
            file,
            frames,
            tf,
            scene,
            payload_size_m,
            links,
            scene_sent_us: None,
            buf: Vec::with_capacity(1024),
        })
    }

    /// Logs one world step at its `stamp_us`: the frame, its transforms and, the first time and
    /// every second after, the payload cube. Refuses a frame whose per-unit vectors do not
    /// match the team size the log was created for.
    pub fn write(&mut self, f: &WorldFrame) -> Result<(), LogError> {
        self.file.check()?;
        let units = self.links.len();
        let lengths = [
            f.base_position_m.len(),
            f.base_orientation_xyzw.len(),
            f.wheel_position_rad.len(),
            f.arm_position_rad.len(),
            f.unit_phase.len(),
        ];
        if lengths.iter().any(|&n| n != units) {
            return Err(LogError::FrameShape {
                path: self.file.path.clone(),
                tick: f.tick,
                bases: lengths[0],
                orientations: lengths[1],
                wheels: lengths[2],
                arms: lengths[3],
                phases: lengths[4],
                units,
            });
        }
        self.file.start_records(f.stamp_us)?;
        self.file
            .log_json(&self.frames, f, f.stamp_us, &mut self.buf)?;
        let log_time_ns = log_time_ns(f.stamp_us);
        let stamp = timestamp(f.stamp_us);
        let payload = FrameTransforms {
            transforms: vec![FrameTransform {
                timestamp: Some(stamp),
                parent_frame_id: WORLD_FRAME_ID.to_owned(),
                child_frame_id: PAYLOAD_FRAME_ID.to_owned(),
                translation: Some(vector(&f.payload_position_m)),
                rotation: Some(quaternion(&f.payload_orientation_xyzw)),
            }],
        };
        self.tf.log_with_time(&payload, log_time_ns);
        for (i, links) in self.links.iter_mut().enumerate() {
            let [x, y, z] = f.base_position_m[i];
            let [qx, qy, qz, qw] = f.base_orientation_xyzw[i];
            let footprint = Isometry3::from_parts(
                Translation3::new(x, y, z),
                UnitQuaternion::new_normalize(Quaternion::new(qw, qx, qy, qz)),
            );
            let tf = links.update(
                &footprint,
                &f.wheel_position_rad[i],
                &f.arm_position_rad[i],
                stamp,
            );
            self.tf.log_with_time(tf, log_time_ns);
        }
        let due = match self.scene_sent_us {
            None => true,
            Some(sent) => f.stamp_us < sent || f.stamp_us - sent >= SCENE_REPUBLISH_US,
        };
        if due {
            self.scene
                .log_with_time(&payload_scene(self.payload_size_m, stamp), log_time_ns);
            self.scene_sent_us = Some(f.stamp_us);
        }
        Ok(())
    }

    /// Finishes the open chunk and flushes the file now.
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.file.flush()
    }

    /// Writes the summary and footer, flushes and syncs the file.
    pub fn finish(self) -> Result<(), LogError> {
        self.file.finish()
    }
}
