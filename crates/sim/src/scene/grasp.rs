//! Grasp solving: the end-effector pose that grasps a resting payload, and the arm
//! configuration (IK from elbow-up/elbow-down seeds) that reaches it and can follow the lift.

use moonhaul_core::state::ARM_JOINTS;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::SceneModel;
use crate::ik::{self, IkSettings};
use crate::SimError;

/// Highest lift the grasp configuration must allow, m (the paper's largest lift target).
pub const MAX_LIFT_M: f64 = 0.75;
/// Steps in which the grasp configuration is tracked up the lift (5 mm each): small enough
/// that IK follows one branch, as the scripted controller does.
pub const LIFT_CHECKS: usize = 150;

/// The end-effector orientation of a grasp in the base frame: approach (z) along the base's
/// +Y toward the payload, paddle x pointing down.
fn grasp_rotation() -> UnitQuaternion<f64> {
    let x = Vector3::new(0.0, 0.0, -1.0);
    let z = Vector3::new(0.0, 1.0, 0.0);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(
        &[x, z.cross(&x), z],
    )))
}

impl SceneModel {
    /// The end-effector pose in the base frame that grasps a resting payload of these half
    /// extents, raised by `lift_m`.
    pub fn grasp_target(&self, half_extents_m: &Vector3<f64>, lift_m: f64) -> Isometry3<f64> {
        let z = half_extents_m.z - self.spec.base_height_m + lift_m;
        Isometry3::from_parts(
            Translation3::new(0.0, self.config.scene.reach_m, z),
            grasp_rotation(),
        )
    }

    /// IK from a small set of elbow-up/elbow-down seeds. A seed's solution is followed up
    /// the whole lift range (the paper's targets reach [`MAX_LIFT_M`]); the configuration
    /// that lifts farthest, then stays farthest from its joint limits, wins. Returns its path:
    /// entry k is the arm configuration at a lift of k·[`MAX_LIFT_M`]/[`LIFT_CHECKS`].
    pub(super) fn solve_grasp(
        &self,
        half_extents_m: &Vector3<f64>,
    ) -> Result<Vec<[f64; ARM_JOINTS]>, SimError> {
        let limits: Vec<_> = self.arm_chain.limits().copied().collect();
        let margin = |q: &[f64; ARM_JOINTS]| {
            q.iter()
                .zip(&limits)
                .map(|(q, l)| (q - l.lower).min(l.upper - q) / (l.upper - l.lower))
                .fold(f64::INFINITY, f64::min)
        };
        let settings = IkSettings::default();
        let mut best: Option<(usize, f64, Vec<[f64; ARM_JOINTS]>)> = None;
        let h = std::f64::consts::FRAC_PI_2;
        for seed in (0..16).map(|k| {
            let s = |bit: usize| if k & (1 << bit) == 0 { 1.0 } else { -1.0 };
            [h * s(0), 0.6 * s(1), 0.0, 1.4 * s(2), 0.0, 0.8 * s(3), 0.0]
        }) {
            let Ok(q0) = ik::solve(
                &self.arm_chain,
                &self.grasp_target(half_extents_m, 0.0),
                &seed,
                &settings,
            ) else {
                continue;
            };
            let (mut q, mut reached, mut worst) = (q0, 0, margin(&q0));
            let mut path = vec![q0];
            for k in 1..=LIFT_CHECKS {
                let lift = MAX_LIFT_M * k as f64 / LIFT_CHECKS as f64;
                match ik::solve(
                    &self.arm_chain,
                    &self.grasp_target(half_extents_m, lift),
                    &q,
                    &settings,
                ) {
                    Ok(next) => {
                        (q, reached, worst) = (next, k, worst.min(margin(&next)));
                        path.push(next);
                    }
                    Err(_) => break,
                }
            }
            if best
                .as_ref()
                .is_none_or(|(r, m, _)| (reached, worst) > (*r, *m))
            {
                best = Some((reached, worst, path));
            }
        }
        best.map(|(_, _, path)| path).ok_or_else(|| {
            SimError::Kinematics(format!(
                "no arm configuration reaches the grasp at {:?}",
                self.grasp_target(half_extents_m, 0.0)
                    .translation
                    .vector
                    .as_slice()
            ))
        })
    }
}
