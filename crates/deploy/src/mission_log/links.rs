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

/// A unit's links at its readings: its root on the ground below it, and each URDF joint's
/// child in its parent at the joint's value. Shared by the logs' `/tf` and the ROS 2 topics.
pub(crate) struct UnitLinks {
    joints: Vec<(Joint, Source)>,
    ground_to_base: Isometry3<f64>,
    base_link: String,
}

impl UnitLinks {
    /// The links of a unit of `tree` and `spec` (from the same URDF).
    pub(crate) fn new(tree: &KinematicTree, spec: &UnitSpec) -> Self {
        let source = |name: &str| {
            if let Some(i) = spec.wheel_joints.iter().position(|j| j == name) {
                Source::Wheel(i)
            } else if let Some(i) = spec.arm_joints.iter().position(|j| j == name) {
                Source::Arm(i)
            } else {
                Source::None
            }
        };
        UnitLinks {
            joints: tree
                .joints()
                .iter()
                .map(|j| (j.clone(), source(&j.name)))
                .collect(),
            ground_to_base: spec.ground_to_base(),
            base_link: spec.base_link.clone(),
        }
    }

    /// The unit's root link (its URDF base link).
    pub(crate) fn base_link(&self) -> &str {
        &self.base_link
    }

    /// The URDF joints, in the tree's order.
    pub(crate) fn joints(&self) -> impl ExactSizeIterator<Item = &Joint> {
        self.joints.iter().map(|(j, _)| j)
    }

    /// The root link in the parent frame of a unit whose base footprint (the ground point
    /// below its root, heading along its x axis) is `footprint` there.
    pub(crate) fn root(&self, footprint: &Isometry3<f64>) -> Isometry3<f64> {
        footprint * self.ground_to_base
    }

    /// Each joint's child link in its parent link at joint positions `wheel_rad` and `arm_rad`
    /// (the unit's order), in the order of [`Self::joints`].
    pub(crate) fn poses<'a>(
        &'a self,
        wheel_rad: &'a [f64; WHEEL_JOINTS],
        arm_rad: &'a [f64; ARM_JOINTS],
    ) -> impl ExactSizeIterator<Item = Isometry3<f64>> + 'a {
        self.joints.iter().map(|(joint, source)| {
            let q = match *source {
                Source::Wheel(i) => wheel_rad[i],
                Source::Arm(i) => arm_rad[i],
                Source::None => 0.0,
            };
            joint.child_in_parent(q)
        })
    }
}

/// The `/tf` transforms of one unit: its root link in a parent frame, then one per URDF joint,
/// every frame named `{prefix}{link}`. Kept as a message that each reading updates in place, so
/// steady-state logging does not allocate.
pub(super) struct UnitFrames {
    links: UnitLinks,
    /// `[parent → root, joint 1, joint 2, …]`.
    message: FrameTransforms,
}

impl UnitFrames {
    /// The frames of a unit of `tree` and `spec` (from the same URDF) under `parent`.
    pub(super) fn new(tree: &KinematicTree, spec: &UnitSpec, parent: &str, prefix: &str) -> Self {
        let links = UnitLinks::new(tree, spec);
        let edge = |parent: String, child: String| FrameTransform {
            timestamp: None,
            parent_frame_id: parent,
            child_frame_id: child,
            translation: None,
            rotation: None,
        };
        let mut transforms = vec![edge(
            parent.to_owned(),
            format!("{prefix}{}", links.base_link()),
        )];
        for joint in links.joints() {
            transforms.push(edge(
                format!("{prefix}{}", joint.parent),
                format!("{prefix}{}", joint.child),
            ));
        }
        UnitFrames {
            links,
            message: FrameTransforms { transforms },
        }
    }

    /// The transforms of a unit whose base footprint is `footprint` in the parent frame, at
    /// joint positions `wheel_rad` and `arm_rad` (the unit's order).
    pub(super) fn update(
        &mut self,
        footprint: &Isometry3<f64>,
        wheel_rad: &[f64; WHEEL_JOINTS],
        arm_rad: &[f64; ARM_JOINTS],
        stamp: Timestamp,
    ) -> &FrameTransforms {
        let (root, joints) = self.message.transforms.split_at_mut(1);
        set(&mut root[0], &self.links.root(footprint), stamp);
        for (pose, out) in self.links.poses(wheel_rad, arm_rad).zip(joints) {
            set(out, &pose, stamp);
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
