//! A wheel–arm unit's kinematics as the clamp needs them: where the arm end effector is in the
//! world for given arm joints and base pose, and where a differential-drive base goes in one
//! control period for given wheel velocities.
//!
//! Frames: the world is Z-up with the ground at z = 0; a base frame sits on the ground between
//! the wheel contact points, x forward, at the base's [`PlanarPose`]; the arm base link is at the
//! configured mount pose in the base frame. Every unit of a team is the same module pair (as in
//! the paper), so one model serves all of them.

use moonhaul_core::kinematics::KinematicsError;
use moonhaul_core::stacked::UnitPoses;
use moonhaul_core::state::{PlanarPose, UnitCommand, UnitState, ARM_JOINTS};
use moonhaul_core::unit::{UnitSpec, UnitSpecError};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2, Vector3};
use std::path::Path;

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

/// The kinematics of one wheel–arm unit, from its [`UnitSpec`].
#[derive(Debug, Clone)]
pub struct UnitModel {
    spec: UnitSpec,
    /// [`moonhaul_core::kinematics::Chain::reach_bound_m`] of the arm, computed once.
    arm_reach_m: f64,
    /// The root (wheel-base) link in the ground frame.
    mount: Isometry3<f64>,
}

impl UnitModel {
    /// The model of the unit `spec` describes.
    pub fn new(spec: UnitSpec) -> Self {
        UnitModel {
            arm_reach_m: spec.arm.reach_bound_m(),
            mount: spec.ground_to_base(),
            spec,
        }
    }

    /// Reads the unit URDF (`assets/unit.urdf`).
    pub fn from_urdf(path: &Path) -> Result<Self, UnitSpecError> {
        UnitSpec::from_file(path).map(Self::new)
    }

    /// The unit description the model is built on.
    pub fn spec(&self) -> &UnitSpec {
        &self.spec
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
            self.spec.base_velocity(&from.wheel_velocity_radps),
            self.spec.base_velocity(&to.wheel_velocity_radps),
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
        Ok(base * self.mount * self.spec.arm.forward(arm_rad)?)
    }

    /// A unit's part of the sensed stacked state Y_k: its arm pose and base position.
    pub fn sensed_image(&self, s: &UnitState) -> Result<UnitPoses, KinematicsError> {
        Ok(UnitPoses {
            arm: self.arm_world_pose(&s.base_pose, &s.arm.position_rad)?,
            base_xy_m: Vector2::new(s.base_pose.x_m, s.base_pose.y_m),
        })
    }

    /// The task-space image of `command` for a unit sensed at `s`: the base integrated over
    /// `dt_s` under its wheel velocities, the arm by FK on that base.
    pub fn command_image(
        &self,
        s: &UnitState,
        command: &UnitCommand,
        dt_s: f64,
    ) -> Result<UnitPoses, KinematicsError> {
        let base = self
            .spec
            .integrate_base(&s.base_pose, &command.wheel_velocity_radps, dt_s);
        Ok(UnitPoses {
            arm: self.arm_world_pose(&base, &command.arm_position_rad)?,
            base_xy_m: Vector2::new(base.x_m, base.y_m),
        })
    }

    /// Position limits of the arm joints, base to tip (rad).
    pub fn arm_limits_rad(&self) -> impl ExactSizeIterator<Item = (f64, f64)> + '_ {
        self.spec.arm_limits.iter().map(|l| (l.lower, l.upper))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use moonhaul_core::config::repo_file;
    use std::f64::consts::FRAC_PI_2;

    /// The shipped unit (`assets/unit.urdf`): wheel radius 0.1 m, track 0.56 m.
    pub(crate) fn shipped_unit() -> UnitModel {
        UnitModel::from_urdf(&repo_file("assets/unit.urdf")).unwrap()
    }

    fn pose(x_m: f64, y_m: f64, yaw_rad: f64) -> PlanarPose {
        PlanarPose { x_m, y_m, yaw_rad }
    }

    #[test]
    fn differential_drive_straight_spin_and_arc() {
        let m = shipped_unit();
        let (r, track) = (m.spec().wheel_radius_m, m.spec().wheel_track_m);
        // 5 rad/s on both wheels: 5r m/s straight ahead along the heading.
        let p = m
            .spec()
            .integrate_base(&pose(1.0, 2.0, FRAC_PI_2), &[5.0, 5.0], 0.02);
        assert!(
            (p.x_m - 1.0).abs() < 1e-15
                && (p.y_m - (2.0 + 0.1 * r)).abs() < 1e-12
                && p.yaw_rad == FRAC_PI_2
        );
        // Opposite wheels: turn on the spot at r·2ω/track.
        let p = m
            .spec()
            .integrate_base(&pose(0.0, 0.0, 0.0), &[-5.0, 5.0], 0.02);
        let turn = r * 10.0 / track * 0.02;
        assert!(p.x_m.abs() < 1e-15 && p.y_m.abs() < 1e-15 && (p.yaw_rad - turn).abs() < 1e-15);
        // A quarter circle ends at (R, R) for turning radius R = v/ω.
        let v = m.spec().base_velocity(&[1.0, 5.0]);
        assert!((v.forward_mps - 3.0 * r).abs() < 1e-15);
        assert!((v.yaw_rate_radps - 4.0 * r / track).abs() < 1e-15);
        let radius = v.forward_mps / v.yaw_rate_radps;
        let p = m.spec().integrate_base(
            &pose(0.0, 0.0, 0.0),
            &[1.0, 5.0],
            FRAC_PI_2 / v.yaw_rate_radps,
        );
        assert!(
            (p.x_m - radius).abs() < 1e-12 && (p.y_m - radius).abs() < 1e-12,
            "{p:?}"
        );
        // The small-angle branch agrees with the exact one at the switch-over.
        let a = m
            .spec()
            .integrate_base(&pose(0.0, 0.0, 0.3), &[2.0, 2.0 + 1.6e-3], 0.5);
        let b = m.spec().integrate_base(
            &pose(0.0, 0.0, 0.3),
            &[2.0, 2.0 + 1.6e-3 * (1.0 + 1e-9)],
            0.5,
        );
        assert!((a.x_m - b.x_m).abs() < 1e-12 && (a.y_m - b.y_m).abs() < 1e-12);
    }

    #[test]
    fn end_effector_follows_base_and_mount() {
        let m = shipped_unit();
        let q = [0.0, -0.5, 0.0, -2.0, 0.0, 1.5, 0.8];
        let at_origin = m.arm_world_pose(&pose(0.0, 0.0, 0.0), &q).unwrap();
        let moved = m.arm_world_pose(&pose(1.0, -2.0, FRAC_PI_2), &q).unwrap();
        let expected = Isometry3::from_parts(
            Translation3::new(1.0, -2.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), FRAC_PI_2),
        ) * at_origin;
        assert!((moved.translation.vector - expected.translation.vector).norm() < 1e-12);
        // The ground frame: FK from the root plus the root's height above the ground.
        let from_root = m.spec().arm.forward(&q).unwrap();
        assert!(
            (at_origin.translation.z - from_root.translation.z - m.spec().base_height_m).abs()
                < 1e-12
        );
    }
}
