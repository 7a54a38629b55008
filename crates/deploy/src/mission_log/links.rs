//! A unit's links as `/tf` frames: the transform of every URDF joint at one reading's joint
//! values, so Foxglove's 3-D panel moves the whole unit (wheels, arm, gripper), not only its
//! base.

use foxglove::schemas::FrameTransforms;
use foxglove::schemas::{FrameTransform, Quaternion, Timestamp, Vector3};
use moonhaul_core::kinematics::{Joint, KinematicTree};
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::UnitSpec;
use nalgebra::Isometry3;

/// Where a joint's value comes from in a unit's readings.
#[derive(Debug, Clone, Copy)]
enum Source {
    Wheel(usize),
    Arm(usize),
    /// A joint that is not one of the unit's nine (a fixed one, or a movable one the unit has
    /// no encoder for): drawn at 0.
    None,
}

/// The `/tf` transforms of one unit: its root link in a parent frame, then one per URDF joint,
/// every frame named `{prefix}{link}`. Kept as a message that each reading updates in place, so
/// steady-state logging does not allocate.
pub(super) struct UnitFrames {
    joints: Vec<(Joint, Source)>,
    ground_to_base: Isometry3<f64>,
    /// `[parent → root, joint 1, joint 2, …]`.
    message: FrameTransforms,
}

impl UnitFrames {
    /// The frames of a unit of `tree` and `spec` (from the same URDF) under `parent`.
    pub(super) fn new(tree: &KinematicTree, spec: &UnitSpec, parent: &str, prefix: &str) -> Self {
        let source = |name: &str| {
            if let Some(i) = spec.wheel_joints.iter().position(|j| j == name) {
                Source::Wheel(i)
            } else if let Some(i) = spec.arm_joints.iter().position(|j| j == name) {
                Source::Arm(i)
            } else {
                Source::None
            }
        };
        let edge = |parent: String, child: String| FrameTransform {
            timestamp: None,
            parent_frame_id: parent,
            child_frame_id: child,
            translation: None,
            rotation: None,
        };
        let mut transforms = vec![edge(
            parent.to_owned(),
            format!("{prefix}{}", spec.base_link),
        )];
        let mut joints = Vec::with_capacity(tree.joints().len());
        for joint in tree.joints() {
            transforms.push(edge(
                format!("{prefix}{}", joint.parent),
                format!("{prefix}{}", joint.child),
            ));
            joints.push((joint.clone(), source(&joint.name)));
        }
        UnitFrames {
            joints,
            ground_to_base: spec.ground_to_base(),
            message: FrameTransforms { transforms },
        }
    }

    /// The transforms of a unit whose base footprint (the ground point below its root, heading
    /// along its x axis) is `footprint` in the parent frame, at joint positions `wheel_rad` and
    /// `arm_rad` (the unit's order).
    pub(super) fn update(
        &mut self,
        footprint: &Isometry3<f64>,
        wheel_rad: &[f64; WHEEL_JOINTS],
        arm_rad: &[f64; ARM_JOINTS],
        stamp: Timestamp,
    ) -> &FrameTransforms {
        let (root, joints) = self.message.transforms.split_at_mut(1);
        set(&mut root[0], &(footprint * self.ground_to_base), stamp);
        for ((joint, source), out) in self.joints.iter().zip(joints) {
            let q = match *source {
                Source::Wheel(i) => wheel_rad[i],
                Source::Arm(i) => arm_rad[i],
                Source::None => 0.0,
            };
            set(out, &joint.child_in_parent(q), stamp);
        }
        &self.message
    }
}

fn set(out: &mut FrameTransform, pose: &Isometry3<f64>, stamp: Timestamp) {
    let t = pose.translation.vector;
    let q = pose.rotation.coords;
    out.timestamp = Some(stamp);
    out.translation = Some(Vector3 {
        x: t.x,
        y: t.y,
        z: t.z,
    });
    out.rotation = Some(Quaternion {
        x: q.x,
        y: q.y,
        z: q.z,
        w: q.w,
    });
}
