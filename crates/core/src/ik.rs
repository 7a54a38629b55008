//! Damped-least-squares inverse kinematics of a 7-DOF arm chain, on core's forward kinematics.
//!
//! Used wherever arm joint positions are needed for an end-effector pose: the simulator's grasp
//! configuration at reset, and the scripted controller's lift and lowering (in the simulator
//! and onboard). Allocation-free, so the onboard tick can run it. The Jacobian is
//! taken by central differences of [`Chain::forward`]; at 7 joints that is 14 FK calls per
//! iteration, microseconds, and it cannot disagree with the FK it inverts.

use nalgebra::{Isometry3, SMatrix, SVector, Vector6};

use crate::kinematics::{Chain, KinematicsError};
use crate::state::ARM_JOINTS;

/// Why IK found no solution.
#[derive(Debug, thiserror::Error)]
pub enum IkError {
    #[error("IK needs a {ARM_JOINTS}-joint chain, got {0}")]
    ChainDof(usize),
    #[error("IK: singular damped system")]
    Singular,
    #[error("IK did not reach target {target_m:?} within {iterations} iterations")]
    NotReached {
        target_m: [f64; 3],
        iterations: usize,
        /// The last iterate: within the joint limits, as close as the solver got (a target
        /// beyond the limits ends here).
        best_q: [f64; ARM_JOINTS],
    },
    #[error(transparent)]
    Kinematics(#[from] KinematicsError),
}

/// Convergence and step settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSettings {
    /// Stop when the position error is below this, m…
    pub tolerance_m: f64,
    /// …and the orientation error below this, rad.
    pub tolerance_rad: f64,
    pub max_iterations: usize,
    /// Levenberg damping λ: keeps steps bounded near singularities.
    pub damping: f64,
    /// Gain of the null-space pull toward mid-range: the seventh joint's freedom keeps the
    /// arm away from its limits, so a tracked path does not stall against one.
    pub centering_gain: f64,
}

impl Default for IkSettings {
    fn default() -> Self {
        IkSettings {
            tolerance_m: 1e-6,
            tolerance_rad: 1e-6,
            max_iterations: 200,
            damping: 0.05,
            centering_gain: 0.05,
        }
    }
}

/// Task error (m and rad combined) above which the null-space centering acts.
const CENTERING_ERROR: f64 = 1e-4;

/// Pose error `[Δp; rotation vector]` from `current` to `target`, both in the chain base frame.
fn pose_error(current: &Isometry3<f64>, target: &Isometry3<f64>) -> Vector6<f64> {
    let dp = target.translation.vector - current.translation.vector;
    let dr = (target.rotation * current.rotation.inverse()).scaled_axis();
    Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
}

fn forward(chain: &Chain, q: &[f64; ARM_JOINTS]) -> Result<Isometry3<f64>, IkError> {
    Ok(chain.forward(q)?)
}

/// One damped-least-squares step plus the null-space pull toward mid-range.
fn damped_step(
    jacobian: &SMatrix<f64, 6, ARM_JOINTS>,
    e: &Vector6<f64>,
    q: &[f64; ARM_JOINTS],
    limits: &[(f64, f64); ARM_JOINTS],
    settings: &IkSettings,
) -> Result<SVector<f64, ARM_JOINTS>, IkError> {
    let jjt = jacobian * jacobian.transpose()
        + SMatrix::<f64, 6, 6>::identity() * settings.damping.powi(2);
    let Some(c) = jjt.cholesky() else {
        return Err(IkError::Singular);
    };
    let pinv = jacobian.transpose() * c.solve(&SMatrix::<f64, 6, 6>::identity());
    // Only while far from the target: the damped projector leaks a little of the pull into
    // the task, which would keep the last iterations from converging.
    let far = e.norm() > CENTERING_ERROR;
    let centering = SVector::<f64, ARM_JOINTS>::from_fn(|j, _| {
        let (lo, hi) = limits[j];
        if far && lo.is_finite() && hi.is_finite() {
            settings.centering_gain * (0.5 * (lo + hi) - q[j]) / (hi - lo).powi(2)
        } else {
            0.0
        }
    });
    let null = SMatrix::<f64, ARM_JOINTS, ARM_JOINTS>::identity() - pinv * jacobian;
    Ok(pinv * e + null * centering)
}

/// Joint positions that put the chain's tip at `target`, starting from `seed`, within the
/// chain's position limits.
pub fn solve(
    chain: &Chain,
    target: &Isometry3<f64>,
    seed: &[f64; ARM_JOINTS],
    settings: &IkSettings,
) -> Result<[f64; ARM_JOINTS], IkError> {
    if chain.dof() != ARM_JOINTS {
        return Err(IkError::ChainDof(chain.dof()));
    }
    let mut limits = [(0.0, 0.0); ARM_JOINTS];
    for (l, j) in limits.iter_mut().zip(chain.limits()) {
        *l = (j.lower, j.upper);
    }
    let mut q = *seed;
    for _ in 0..settings.max_iterations {
        let e = pose_error(&forward(chain, &q)?, target);
        if e.fixed_rows::<3>(0).norm() < settings.tolerance_m
            && e.fixed_rows::<3>(3).norm() < settings.tolerance_rad
        {
            return Ok(q);
        }
        let mut jacobian = SMatrix::<f64, 6, ARM_JOINTS>::zeros();
        const H: f64 = 1e-6;
        for j in 0..ARM_JOINTS {
            let (mut plus, mut minus) = (q, q);
            plus[j] += H;
            minus[j] -= H;
            let (fp, fm) = (forward(chain, &plus)?, forward(chain, &minus)?);
            // d(error)/dq = -d(pose)/dq; measure both against the same target.
            let column = (pose_error(&fm, target) - pose_error(&fp, target)) / (2.0 * H);
            jacobian.set_column(j, &column);
        }
        // Joints pinned at a limit that the step would push further are taken out of the
        // Jacobian, so the other six joints make up for them instead of the solve stalling.
        let mut step = SVector::<f64, ARM_JOINTS>::zeros();
        for _ in 0..ARM_JOINTS {
            step = damped_step(&jacobian, &e, &q, &limits, settings)?;
            let mut pinned = false;
            for (j, (lo, hi)) in limits.iter().enumerate() {
                let at_limit = (q[j] <= *lo && step[j] < 0.0) || (q[j] >= *hi && step[j] > 0.0);
                if at_limit && jacobian.column(j).norm() > 0.0 {
                    jacobian.column_mut(j).fill(0.0);
                    pinned = true;
                }
            }
            if !pinned {
                break;
            }
        }
        for (j, (lo, hi)) in limits.iter().enumerate() {
            q[j] = (q[j] + step[j]).clamp(*lo, *hi);
        }
    }
    let t = target.translation.vector;
    Err(IkError::NotReached {
        target_m: [t.x, t.y, t.z],
        iterations: settings.max_iterations,
        best_q: q,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::KinematicTree;

    #[test]
    fn recovers_a_reachable_pose_from_a_nearby_seed() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/unit.urdf");
        let chain = KinematicTree::from_file(path)
            .unwrap()
            .chain("base_link", "ee")
            .unwrap();
        let truth = [0.3, 0.5, -0.2, -1.2, 0.1, 0.8, 0.2];
        let target = chain.forward(&truth).unwrap();
        let seed = truth.map(|q| q + 0.15);
        let q = solve(&chain, &target, &seed, &IkSettings::default()).unwrap();
        let got = chain.forward(&q).unwrap();
        assert!((got.translation.vector - target.translation.vector).norm() < 1e-6);
        assert!(got.rotation.angle_to(&target.rotation) < 1e-6);
    }
}
