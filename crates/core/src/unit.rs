//! One description of a wheel–arm unit, read from its URDF (`assets/unit.urdf`): joint names
//! and order, wheel geometry, the arm chain, limits and mass, and the differential-drive
//! kinematics of the wheel module. The simulator, the clamp's unit model, the HAL's limits and
//! the CAN joint mapping all take a [`UnitSpec`]; nothing else types a unit's geometry.
//!
//! The URDF convention a unit file follows (checked, with errors naming the element):
//! - the root link is the wheel base (`base_link` in ours); its frame is x forward, z up;
//! - the two **wheels** are the `continuous` joints whose parent is the root, with axes along
//!   ±y of the root and collinear (same x and z); the one at +y is the left wheel. A wheel
//!   link's radius is its collision sphere's or cylinder's radius. Wheel velocities are URDF
//!   joint velocities: the spec knows each axis' sign, so either mounting works;
//! - the **arm** is the chain of movable joints from the root to the end-effector link named
//!   [`EE_LINK`], exactly [`ARM_JOINTS`] revolute joints; fixed joints on the way are its mount.
//!
//! Ground frame: on the ground below the root, same axes. Standing on flat ground, the root
//! frame sits [`UnitSpec::base_height_m`] above it (wheel radius less the axle's z in the root).

use std::path::Path;

use nalgebra::{Isometry3, Translation3, Vector3};

use crate::kinematics::{self, Chain, JointLimits, KinematicTree, KinematicsError, MotionKind};
use crate::state::{PlanarPose, PlanarVelocity, ARM_JOINTS, WHEEL_JOINTS};

/// Name of the end-effector link whose pose the clamp watches and the grasp holds.
pub const EE_LINK: &str = "ee";

/// Why a URDF does not describe a wheel–arm unit. Each variant names the element at fault.
#[derive(Debug, thiserror::Error)]
pub enum UnitSpecError {
    #[error(transparent)]
    Urdf(#[from] KinematicsError),
    #[error(
        "expected {WHEEL_JOINTS} wheel joints (continuous joints under root link \"{root}\"), found {found:?}"
    )]
    WheelCount { root: String, found: Vec<String> },
    #[error("wheel joint \"{joint}\": {reason}")]
    Wheel { joint: String, reason: String },
    #[error("the arm chain {root} -> {EE_LINK}: {reason}")]
    Arm { root: String, reason: String },
}

/// A wheel–arm unit as its URDF describes it.
#[derive(Debug, Clone)]
pub struct UnitSpec {
    /// The root link: the wheel base.
    pub base_link: String,
    /// Left, right.
    pub wheel_joints: [String; WHEEL_JOINTS],
    /// Base to tip.
    pub arm_joints: [String; ARM_JOINTS],
    pub wheel_limits: [JointLimits; WHEEL_JOINTS],
    pub arm_limits: [JointLimits; ARM_JOINTS],
    /// Wheel radius, m (from the wheel links' collision geometry).
    pub wheel_radius_m: f64,
    /// Distance between the two wheels' contact points, m.
    pub wheel_track_m: f64,
    /// Height of the root frame above flat ground when standing, m.
    pub base_height_m: f64,
    /// +1 where a positive joint velocity rolls the wheel forward, −1 where its axis is −y.
    wheel_forward_sign: [f64; WHEEL_JOINTS],
    /// Forward kinematics root → [`EE_LINK`], joint values in [`UnitSpec::arm_joints`] order.
    pub arm: Chain,
    /// Sum of all link masses, kg.
    pub mass_kg: f64,
}

/// Distance below which two wheel axle coordinates count as equal, m.
const COLLINEAR_TOLERANCE_M: f64 = 1e-6;
/// Largest angle between a wheel axis and ±y, as its sine.
const AXIS_TOLERANCE: f64 = 1e-6;

impl UnitSpec {
    /// Reads a unit URDF (size- and depth-capped, physically checked) and derives the spec.
    pub fn from_file(path: &Path) -> Result<Self, UnitSpecError> {
        let robot = kinematics::read_urdf(path)?;
        Self::from_robot(&robot)
    }

    /// Derives the spec from a parsed URDF.
    pub fn from_robot(robot: &urdf_rs::Robot) -> Result<Self, UnitSpecError> {
        let tree = KinematicTree::from_robot(robot)?;
        let root = tree.root().name.clone();
        let wheel_error = |joint: &str, reason: String| UnitSpecError::Wheel {
            joint: joint.to_owned(),
            reason,
        };

        let wheels: Vec<_> = tree
            .children(&root)?
            .filter(|(joint, _)| {
                joint.motion.as_ref().map(|m| m.kind) == Some(MotionKind::Continuous)
            })
            .map(|(joint, _)| joint.clone())
            .collect();
        let [mut left, mut right] =
            <[_; WHEEL_JOINTS]>::try_from(wheels).map_err(|found| UnitSpecError::WheelCount {
                root: root.clone(),
                found: found.into_iter().map(|j| j.name).collect(),
            })?;
        if left.origin.translation.y < right.origin.translation.y {
            std::mem::swap(&mut left, &mut right);
        }
        let mut wheel_forward_sign = [0.0; WHEEL_JOINTS];
        let mut radii = [0.0; WHEEL_JOINTS];
        let mut wheel_limits = [JointLimits {
            lower: f64::NEG_INFINITY,
            upper: f64::INFINITY,
            effort: 0.0,
            velocity: 0.0,
        }; WHEEL_JOINTS];
        for (i, joint) in [&left, &right].into_iter().enumerate() {
            let motion = joint
                .motion
                .as_ref()
                .ok_or_else(|| wheel_error(&joint.name, "is not movable".into()))?;
            let axis = joint.origin.rotation * motion.axis.into_inner();
            if (axis.x.powi(2) + axis.z.powi(2)).sqrt() > AXIS_TOLERANCE {
                return Err(wheel_error(
                    &joint.name,
                    format!("axis {axis:?} in the root frame is not along ±y"),
                ));
            }
            wheel_forward_sign[i] = axis.y.signum();
            if !motion.limits.known_dynamics() {
                return Err(wheel_error(
                    &joint.name,
                    "has no <limit> effort and velocity; a unit's wheel drives need them".into(),
                ));
            }
            wheel_limits[i] = motion.limits;
            radii[i] = wheel_radius(robot, &joint.child).ok_or_else(|| {
                wheel_error(
                    &joint.name,
                    format!(
                        "child link \"{}\" has no collision sphere or cylinder",
                        joint.child
                    ),
                )
            })?;
        }
        let (pl, pr) = (
            left.origin.translation.vector,
            right.origin.translation.vector,
        );
        if (pl.x - pr.x).abs() > COLLINEAR_TOLERANCE_M
            || (pl.z - pr.z).abs() > COLLINEAR_TOLERANCE_M
        {
            return Err(wheel_error(
                &right.name,
                format!(
                    "axle at {pr:?} is not collinear with \"{}\" at {pl:?}",
                    left.name
                ),
            ));
        }
        if (radii[0] - radii[1]).abs() > COLLINEAR_TOLERANCE_M {
            return Err(wheel_error(
                &right.name,
                format!(
                    "radius {} differs from the left wheel's {}",
                    radii[1], radii[0]
                ),
            ));
        }
        let wheel_track_m = pl.y - pr.y;
        if wheel_track_m <= COLLINEAR_TOLERANCE_M {
            return Err(wheel_error(
                &right.name,
                "both wheels sit at the same y: the track is zero".into(),
            ));
        }

        let arm_error = |reason: String| UnitSpecError::Arm {
            root: root.clone(),
            reason,
        };
        let arm = tree
            .chain(&root, EE_LINK)
            .map_err(|e| arm_error(e.to_string()))?;
        let arm_names: Vec<String> = arm.joint_names().map(str::to_owned).collect();
        let arm_joints = <[String; ARM_JOINTS]>::try_from(arm_names).map_err(|names| {
            arm_error(format!(
                "has {} movable joints {names:?}; a unit's arm has {ARM_JOINTS}",
                names.len()
            ))
        })?;
        for name in &arm_joints {
            let kind = tree
                .joint(name)
                .and_then(|j| j.motion.as_ref())
                .map(|m| m.kind);
            if kind != Some(MotionKind::Revolute) {
                return Err(arm_error(format!("joint \"{name}\" is not revolute")));
            }
        }
        let arm_limits =
            <[JointLimits; ARM_JOINTS]>::try_from(arm.limits().copied().collect::<Vec<_>>())
                .map_err(|_| arm_error("limits do not match its joints".into()))?;
        if let Some((name, _)) = arm_joints
            .iter()
            .zip(&arm_limits)
            .find(|(_, l)| !l.known_dynamics())
        {
            return Err(arm_error(format!(
                "joint \"{name}\" has no <limit> effort or velocity; a unit's arm drives need them"
            )));
        }

        Ok(UnitSpec {
            base_link: root,
            wheel_joints: [left.name.clone(), right.name.clone()],
            arm_joints,
            wheel_limits,
            arm_limits,
            wheel_radius_m: radii[0],
            wheel_track_m,
            base_height_m: radii[0] - pl.z,
            wheel_forward_sign,
            arm,
            mass_kg: tree.total_mass(),
        })
    }

    /// Wheels then arm joints: the order of a unit's nine joints in u⁽ⁱ⁾, the HAL and the CAN
    /// drive list.
    pub fn joint_names(&self) -> impl Iterator<Item = &str> {
        self.wheel_joints
            .iter()
            .chain(&self.arm_joints)
            .map(String::as_str)
    }

    /// The root frame in the ground frame when standing on flat ground.
    pub fn ground_to_base(&self) -> Isometry3<f64> {
        Translation3::from(Vector3::new(0.0, 0.0, self.base_height_m)).into()
    }

    /// Half the wheel track, m.
    pub fn half_track_m(&self) -> f64 {
        self.wheel_track_m / 2.0
    }

    /// Forward speed and yaw rate of the base for wheel joint velocities `[left, right]`
    /// (differential-drive forward kinematics, rolling without slip).
    pub fn base_velocity(&self, wheel_radps: &[f64; WHEEL_JOINTS]) -> PlanarVelocity {
        let [left, right] = self.rim_speeds_mps(wheel_radps);
        PlanarVelocity {
            forward_mps: (left + right) / 2.0,
            yaw_rate_radps: (right - left) / self.wheel_track_m,
        }
    }

    /// Wheel joint velocities `[left, right]` that give a base velocity (the inverse).
    pub fn wheel_velocities(&self, base: &PlanarVelocity) -> [f64; WHEEL_JOINTS] {
        let half = self.half_track_m();
        let rim = [
            base.forward_mps - base.yaw_rate_radps * half,
            base.forward_mps + base.yaw_rate_radps * half,
        ];
        std::array::from_fn(|i| rim[i] * self.wheel_forward_sign[i] / self.wheel_radius_m)
    }

    fn rim_speeds_mps(&self, wheel_radps: &[f64; WHEEL_JOINTS]) -> [f64; WHEEL_JOINTS] {
        std::array::from_fn(|i| wheel_radps[i] * self.wheel_forward_sign[i] * self.wheel_radius_m)
    }

    /// The base pose after holding wheel velocities `[left, right]` for `dt_s` from `pose`:
    /// the exact unicycle arc, whose chord is v·dt·sinc(Δψ/2) along the mean heading.
    pub fn integrate_base(
        &self,
        pose: &PlanarPose,
        wheel_radps: &[f64; WHEEL_JOINTS],
        dt_s: f64,
    ) -> PlanarPose {
        let v = self.base_velocity(wheel_radps);
        let turn_rad = v.yaw_rate_radps * dt_s;
        let half = turn_rad / 2.0;
        // sin(x)/x with its Taylor form near 0, where the quotient loses precision.
        let sinc = if half.abs() < 1e-4 {
            1.0 - half * half / 6.0
        } else {
            half.sin() / half
        };
        let chord_m = v.forward_mps * dt_s * sinc;
        let heading = pose.yaw_rad + half;
        PlanarPose {
            x_m: pose.x_m + chord_m * heading.cos(),
            y_m: pose.y_m + chord_m * heading.sin(),
            yaw_rad: pose.yaw_rad + turn_rad,
        }
    }
}

/// The radius of a link's first collision sphere or cylinder.
fn wheel_radius(robot: &urdf_rs::Robot, link: &str) -> Option<f64> {
    let link = robot.links.iter().find(|l| l.name == link)?;
    link.collision.iter().find_map(|c| match c.geometry {
        urdf_rs::Geometry::Sphere { radius } | urdf_rs::Geometry::Cylinder { radius, .. } => {
            Some(radius)
        }
        _ => None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped() -> UnitSpec {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/unit.urdf");
        UnitSpec::from_file(&path).unwrap()
    }

    #[test]
    fn reads_the_shipped_unit() {
        let spec = shipped();
        assert_eq!(spec.base_link, "base_link");
        assert_eq!(spec.wheel_joints, ["wheel_left_joint", "wheel_right_joint"]);
        let arm: Vec<String> = (1..=7).map(|i| format!("arm_joint_{i}")).collect();
        assert_eq!(spec.arm_joints.to_vec(), arm);
        assert_eq!(spec.joint_names().count(), 9);
        assert!((spec.wheel_radius_m - 0.1).abs() < 1e-12);
        assert!((spec.wheel_track_m - 0.56).abs() < 1e-12);
        assert!((spec.base_height_m - 0.1).abs() < 1e-12);
        assert!(spec.arm_limits.iter().all(|l| l.lower < l.upper));
        assert!(spec.mass_kg > 40.0);
    }

    #[test]
    fn diff_drive_inverse_undoes_forward() {
        let spec = shipped();
        for (v, w) in [(0.2, 0.0), (0.0, 0.5), (-0.1, 0.3), (0.15, -0.7)] {
            let base = PlanarVelocity {
                forward_mps: v,
                yaw_rate_radps: w,
            };
            let wheels = spec.wheel_velocities(&base);
            let back = spec.base_velocity(&wheels);
            assert!((back.forward_mps - v).abs() < 1e-12);
            assert!((back.yaw_rate_radps - w).abs() < 1e-12);
        }
        // Equal positive wheel speeds drive straight ahead at ω·r; right faster turns left.
        let ahead = spec.base_velocity(&[2.0, 2.0]);
        assert!((ahead.forward_mps - 0.2).abs() < 1e-12 && ahead.yaw_rate_radps == 0.0);
        assert!(spec.base_velocity(&[1.0, 2.0]).yaw_rate_radps > 0.0);
        // A quarter circle: ends at (R, R) for turning radius R, heading +90°.
        let w = [1.0, 2.0];
        let v = spec.base_velocity(&w);
        let quarter_s = std::f64::consts::FRAC_PI_2 / v.yaw_rate_radps;
        let end = spec.integrate_base(&PlanarPose::default(), &w, quarter_s);
        let radius = v.forward_mps / v.yaw_rate_radps;
        assert!((end.x_m - radius).abs() < 1e-9 && (end.y_m - radius).abs() < 1e-9);
    }

    fn unit_urdf() -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/unit.urdf");
        std::fs::read_to_string(path).unwrap()
    }

    fn spec_error(urdf: &str) -> String {
        let robot = kinematics::parse_urdf(urdf).unwrap();
        UnitSpec::from_robot(&robot).unwrap_err().to_string()
    }

    #[test]
    fn units_that_break_the_convention_are_named() {
        let urdf = unit_urdf();
        // A flipped right wheel axis is a mounting, not an error: forward stays forward.
        let flipped = urdf.replacen(
            "<origin xyz=\"0 -0.28 0\" rpy=\"0 0 0\"/>\n    <axis xyz=\"0 1 0\"/>",
            "<origin xyz=\"0 -0.28 0\" rpy=\"0 0 0\"/>\n    <axis xyz=\"0 -1 0\"/>",
            1,
        );
        assert_ne!(flipped, urdf);
        let spec = UnitSpec::from_robot(&kinematics::parse_urdf(&flipped).unwrap()).unwrap();
        let wheels = spec.wheel_velocities(&PlanarVelocity {
            forward_mps: 0.2,
            yaw_rate_radps: 0.0,
        });
        assert!(wheels[0] > 0.0 && wheels[1] < 0.0);

        let tilted = urdf.replacen("<axis xyz=\"0 1 0\"/>", "<axis xyz=\"1 0 0\"/>", 1);
        assert!(spec_error(&tilted).contains("wheel_left_joint"));
        let raised = urdf.replacen("xyz=\"0 -0.28 0\"", "xyz=\"0 -0.28 0.01\"", 1);
        assert!(spec_error(&raised).contains("collinear"));
        let one_wheel = urdf.replacen(
            "name=\"wheel_right_joint\" type=\"continuous\"",
            "name=\"wheel_right_joint\" type=\"fixed\"",
            1,
        );
        assert!(spec_error(&one_wheel).contains("wheel_left_joint"));
        let short_arm = urdf.replacen(
            "name=\"arm_joint_7\" type=\"revolute\"",
            "name=\"arm_joint_7\" type=\"fixed\"",
            1,
        );
        assert!(spec_error(&short_arm).contains("6 movable joints"));
        let no_ee = urdf.replace("\"ee\"", "\"tool\"");
        assert!(spec_error(&no_ee).contains("ee"));
        // A wheel joint without `<limit>` is a valid URDF, but its drive needs the limits.
        let wheel_limit = "<limit lower=\"0\" upper=\"0\" effort=\"40\" velocity=\"10\"/>";
        let unlimited = urdf.replacen(wheel_limit, "", 1);
        assert_ne!(unlimited, urdf);
        let e = spec_error(&unlimited);
        assert!(
            e.contains("wheel_left_joint") && e.contains("<limit>"),
            "{e}"
        );
    }
}
