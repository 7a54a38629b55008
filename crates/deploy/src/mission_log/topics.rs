//! Topic and frame names of the mission logs.

/// The topic of unit `unit`'s tick records.
pub fn unit_topic(unit: usize) -> String {
    format!("/unit{unit}/tick")
}

/// The topic of the world's ground-truth frames.
pub const WORLD_TOPIC: &str = "/world/frame";
/// The topic of the world's transforms (foxglove `FrameTransforms`).
pub const TF_TOPIC: &str = "/tf";
/// The topic of the 3-D scene (foxglove `SceneUpdate`).
pub const SCENE_TOPIC: &str = "/scene";
/// Frame names in `/tf` and `/scene`.
pub const WORLD_FRAME_ID: &str = "world";
pub const PAYLOAD_FRAME_ID: &str = "payload";

/// The frame of unit `unit`'s wheel base.
pub fn base_frame_id(unit: usize) -> String {
    format!("base{unit}")
}
