//! Topic and frame names of the mission logs.

/// The topic of unit `unit`'s tick records.
pub fn unit_topic(unit: usize) -> String {
    format!("/unit{unit}/tick")
}

/// The topic of the world's ground-truth frames.
pub const WORLD_TOPIC: &str = "/world/frame";
/// The topic of the transforms (foxglove `FrameTransforms`) of every log.
pub const TF_TOPIC: &str = "/tf";
/// The topic of the 3-D scene (foxglove `SceneUpdate`).
pub const SCENE_TOPIC: &str = "/scene";
/// Frame names in `/tf` and `/scene`.
pub const WORLD_FRAME_ID: &str = "world";
pub const PAYLOAD_FRAME_ID: &str = "payload";

/// The prefix of unit `unit`'s link frames in its own log (`unit0/base_link`, …): the links
/// where its encoders and odometry put them.
pub fn unit_frame_prefix(unit: usize) -> String {
    format!("unit{unit}/")
}

/// The prefix of unit `unit`'s link frames in the world log (`truth/unit0/base_link`, …): the
/// simulator's ground truth, apart from the units' own view so both can be opened together.
pub fn truth_frame_prefix(unit: usize) -> String {
    format!("truth/unit{unit}/")
}
