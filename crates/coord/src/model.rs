//! A wheel–arm unit's kinematics as the clamp needs them: where the arm end effector is in the
//! world for given arm joints and base pose, and where a differential-drive base goes in one
//! control period for given wheel velocities.
//!
//! Frames: the world is Z-up with the ground at z = 0; a base frame sits on the ground between
//! the wheel contact points, x forward, at the base's [`PlanarPose`]; the arm base link is at the
//! configured mount pose in the base frame. Every unit of a team is the same module pair (as in
//! the paper), so one model serves all of them.

use crate::config::{self, ConfigError, UnitModelConfig};
use moonhaul_core::kinematics::{Chain, KinematicTree, KinematicsError};
use moonhaul_core::state::{PlanarPose, PlanarVelocity, UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use std::path::Path;

/// Why a unit model cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("arm URDF: {0}")]
    Kinematics(#[from] KinematicsError),
    #[error("arm chain {base} -> {tip} has {got} movable joints; a unit's arm has {expected}")]
    ArmDof {
        base: String,
        tip: String,
        got: usize,
        expected: usize,
    },
    #[error(transparent)]
    Invalid(#[from] config::InvalidConfig),
}

/// Upper bounds on the change of one unit's task-space image per unit of the interpolation
/// parameter t (see [`UnitModel::image_rate_bounds`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageRates {
    /// Base planar position, m.
    pub base_m: f64,
    /// End-effector position, m.
    pub arm_translation_m: f64,
    /// End-effector orientation, rad.
    pub arm_rotation_rad: f64,
}

/// The kinematics of one wheel–arm unit.
#[derive(Debug, Clone)]
pub struct UnitModel {
    arm: Chain,
    /// [`Chain::reach_bound_m`] of `arm`, computed once.
    arm_reach_m: f64,
    mount: Isometry3<f64>,
    wheel_radius_m: f64,
    wheel_track_m: f64,
}

impl UnitModel {
    /// Reads a unit-model file and the URDF it names (relative to the file's directory).
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let cfg: UnitModelConfig = config::load(path)?;
        let urdf = path.parent().unwrap_or(Path::new(".")).join(&cfg.urdf);
        let model = KinematicTree::from_file(&urdf)
            .map_err(ModelError::from)
            .and_then(|tree| Self::from_tree(&tree, &cfg));
        model.map_err(|source| ConfigError::Model {
            path: path.to_owned(),
            source,
        })
    }

    /// Builds the model from an already loaded arm URDF.
    pub fn from_tree(tree: &KinematicTree, cfg: &UnitModelConfig) -> Result<Self, ModelError> {
        config::Validate::validate(cfg)?;
        let arm = tree.chain(&cfg.arm_base_link, &cfg.arm_tip_link)?;
        if arm.dof() != ARM_JOINTS {
            return Err(ModelError::ArmDof {
                base: cfg.arm_base_link.clone(),
                tip: cfg.arm_tip_link.clone(),
                got: arm.dof(),
                expected: ARM_JOINTS,
            });
        }
        let [x, y, z] = cfg.arm_mount_xyz_m;
        let [roll, pitch, yaw] = cfg.arm_mount_rpy_rad;
        Ok(UnitModel {
            arm_reach_m: arm.reach_bound_m(),
            arm,
            mount: Isometry3::from_parts(
                Translation3::new(x, y, z),
                UnitQuaternion::from_euler_angles(roll, pitch, yaw),
            ),
            wheel_radius_m: cfg.wheel_radius_m,
            wheel_track_m: cfg.wheel_track_m,
        })
    }

    /// Forward speed and yaw rate of the base for wheel velocities `[left, right]`.
    pub fn base_velocity(&self, wheel_radps: &[f64; WHEEL_JOINTS]) -> PlanarVelocity {
        let [left, right] = *wheel_radps;
        PlanarVelocity {
            forward_mps: self.wheel_radius_m * (left + right) / 2.0,
            yaw_rate_radps: self.wheel_radius_m * (right - left) / self.wheel_track_m,
        }
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

    /// Bounds on how fast the task-space image of the interpolated command
    /// T(t) = (1 − t)·`from` + t·`to` moves per unit of t, integrated over `dt_s` from any
    /// sensed base pose.
    ///
    /// With v, ω linear in t, the base end point moves at most T·|Δv| + ½T²·max|v|·|Δω|
    /// (the end point of an arc of length s shifts by at most s²/2 per unit curvature) and
    /// turns T·|Δω|. The end effector adds that turn times its lever (mount offset + arm reach)
    /// and Σⱼ|Δqⱼ|·max(reach, 1) from the arm joints; it rotates at most T·|Δω| + Σⱼ|Δqⱼ|.
    pub fn image_rate_bounds(&self, from: &UnitCommand, to: &UnitCommand, dt_s: f64) -> ImageRates {
        let (v0, v1) = (
            self.base_velocity(&from.wheel_velocity_radps),
            self.base_velocity(&to.wheel_velocity_radps),
        );
        let dv = (v1.forward_mps - v0.forward_mps).abs();
        let dw = (v1.yaw_rate_radps - v0.yaw_rate_radps).abs();
        let v_max = v0.forward_mps.abs().max(v1.forward_mps.abs());
        let base_m = dt_s * dv + 0.5 * dt_s * dt_s * v_max * dw;
        let yaw_rad = dt_s * dw;
        let joints_rad: f64 = from
            .arm_position_rad
            .iter()
            .zip(&to.arm_position_rad)
            .map(|(a, b)| (b - a).abs())
            .sum();
        let lever_m = self.mount.translation.vector.norm() + self.arm_reach_m;
        ImageRates {
            base_m,
            arm_translation_m: base_m + yaw_rad * lever_m + joints_rad * self.arm_reach_m.max(1.0),
            arm_rotation_rad: yaw_rad + joints_rad,
        }
    }

    /// World pose of the arm end effector: base pose · mount · FK(q). Does not allocate.
    pub fn arm_world_pose(
        &self,
        base: &PlanarPose,
        arm_rad: &[f64; ARM_JOINTS],
    ) -> Result<Isometry3<f64>, KinematicsError> {
        let base = Isometry3::from_parts(
            Translation3::new(base.x_m, base.y_m, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), base.yaw_rad),
        );
        Ok(base * self.mount * self.arm.forward(arm_rad)?)
    }

    /// Position limits of the arm joints, base to tip (rad).
    pub fn arm_limits_rad(&self) -> impl ExactSizeIterator<Item = (f64, f64)> + '_ {
        self.arm.limits().map(|l| (l.lower, l.upper))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    /// The test unit: the Franka Panda (panda_link0 → panda_hand) on a plausible wheel module
    /// (r = 0.1 m, track 0.4 m), mounted 0.3 m up and 0.1 m forward.
    pub(crate) fn panda_unit() -> UnitModel {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/panda_unit.toml");
        UnitModel::from_file(&path).unwrap()
    }

    fn pose(x_m: f64, y_m: f64, yaw_rad: f64) -> PlanarPose {
        PlanarPose { x_m, y_m, yaw_rad }
    }

    #[test]
    fn differential_drive_straight_spin_and_arc() {
        let m = panda_unit();
        // 5 rad/s on both wheels: 0.5 m/s straight ahead along the heading.
        let p = m.integrate_base(&pose(1.0, 2.0, FRAC_PI_2), &[5.0, 5.0], 0.02);
        assert!(
            (p.x_m - 1.0).abs() < 1e-15 && (p.y_m - 2.01).abs() < 1e-12 && p.yaw_rad == FRAC_PI_2
        );
        // Opposite wheels: turn on the spot at r·2ω/track = 2.5 rad/s.
        let p = m.integrate_base(&pose(0.0, 0.0, 0.0), &[-5.0, 5.0], 0.02);
        assert!(p.x_m.abs() < 1e-15 && p.y_m.abs() < 1e-15 && (p.yaw_rad - 0.05).abs() < 1e-15);
        // A quarter circle: v = 0.3 m/s, ω = 1 rad/s → radius 0.3 m, ends at (0.3, 0.3).
        let m_v = m.base_velocity(&[1.0, 5.0]);
        assert!((m_v.forward_mps - 0.3).abs() < 1e-15 && (m_v.yaw_rate_radps - 1.0).abs() < 1e-15);
        let p = m.integrate_base(&pose(0.0, 0.0, 0.0), &[1.0, 5.0], FRAC_PI_2);
        assert!(
            (p.x_m - 0.3).abs() < 1e-12 && (p.y_m - 0.3).abs() < 1e-12,
            "{p:?}"
        );
        // The small-angle branch agrees with the exact one at the switch-over.
        let a = m.integrate_base(&pose(0.0, 0.0, 0.3), &[2.0, 2.0 + 1.6e-3], 0.5);
        let b = m.integrate_base(
            &pose(0.0, 0.0, 0.3),
            &[2.0, 2.0 + 1.6e-3 * (1.0 + 1e-9)],
            0.5,
        );
        assert!((a.x_m - b.x_m).abs() < 1e-12 && (a.y_m - b.y_m).abs() < 1e-12);
    }

    #[test]
    fn end_effector_follows_base_and_mount() {
        let m = panda_unit();
        let q = [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8];
        let at_origin = m.arm_world_pose(&pose(0.0, 0.0, 0.0), &q).unwrap();
        let moved = m.arm_world_pose(&pose(1.0, -2.0, FRAC_PI_2), &q).unwrap();
        let expected = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), FRAC_PI_2),
        ) * at_origin;
        assert!((moved.translation.vector - expected.translation.vector).norm() < 1e-12);
        // Mount height 0.3 m plus the Panda's ~0.33 m shoulder: the hand is well above ground.
        assert!(at_origin.translation.z > 0.3, "{at_origin}");
    }

    #[test]
    fn bad_models_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let urdf =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../core/tests/data/panda.urdf");
        let base = format!(
            "urdf = {urdf:?}\narm_base_link = \"panda_link0\"\narm_mount_xyz_m = [0.1, 0.0, 0.3]\n\
             arm_mount_rpy_rad = [0.0, 0.0, 0.0]\nwheel_radius_m = 0.1\n"
        );
        let cases = [
            (
                "arm_tip_link = \"panda_link5\"\nwheel_track_m = 0.4\n",
                "5 movable joints",
            ),
            (
                "arm_tip_link = \"gripper\"\nwheel_track_m = 0.4\n",
                "gripper",
            ),
            (
                "arm_tip_link = \"panda_hand\"\nwheel_track_m = 0.0\n",
                "wheel_track_m",
            ),
            ("arm_tip_link = \"panda_hand\"\n", "wheel_track_m"),
        ];
        for (i, (extra, needle)) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("unit{i}.toml"));
            std::fs::write(&path, format!("{base}{extra}")).unwrap();
            let message = UnitModel::from_file(&path).unwrap_err().to_string();
            assert!(
                message.contains(needle) && message.contains("unit"),
                "{message}"
            );
        }
    }
}
