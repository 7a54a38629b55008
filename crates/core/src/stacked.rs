//! The stacked state Y of the team and its ℓ∞ metric d (paper, eqs. stacked_state and
//! stacked_metric).
//!
//! For each unit the clamp watches one arm end-effector pose g ∈ SE(3) and one base planar
//! position p ∈ ℝ². The paper stacks the N = 2 arms first and the bases second; we group them
//! per unit instead (each unit publishes its own pair), which changes nothing in d because d is
//! the maximum over all 2N subsystems.

use crate::se3::{interpolate_pose, planar_distance, pose_distance};
use nalgebra::{Isometry3, Vector2};
use serde::{Deserialize, Serialize};

/// Per-subsystem tolerances of the clamp (`[tolerances]` of `configs/sync.toml`); each
/// subsystem's distance reaches 1 at its tolerance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncTolerances {
    /// d_max: arm end-effector translation tolerance, m (paper: 0.03).
    pub arm_translation_m: f64,
    /// θ_max: arm end-effector rotation tolerance, degrees (paper: 5).
    pub arm_rotation_deg: f64,
    /// Δ_w: per-axis tolerance of a base's planar position, m (paper: [0.02, 0.02]).
    #[serde(deserialize_with = "crate::config::exact_array")]
    pub base_xy_m: [f64; 2],
}

impl crate::config::Validate for SyncTolerances {
    /// Every tolerance finite and positive, and no wider than makes sense for robots that
    /// share one rigid payload (1 m, 180°).
    fn validate(&self) -> Result<(), crate::config::FieldError> {
        use crate::config::positive;
        positive("arm_translation_m", self.arm_translation_m, 1.0)?;
        positive("arm_rotation_deg", self.arm_rotation_deg, 180.0)?;
        positive("base_xy_m[0]", self.base_xy_m[0], 1.0)?;
        positive("base_xy_m[1]", self.base_xy_m[1], 1.0)
    }
}

/// One unit's share of the stacked state.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct UnitPoses {
    /// Arm end-effector pose in the shared world frame.
    pub arm: Isometry3<f64>,
    /// Wheel-base planar position (x, y) in the shared world frame, m.
    pub base_xy_m: Vector2<f64>,
}

impl UnitPoses {
    /// One unit's two terms of d: (arm d_SE, base wheel metric), each 1 at its tolerance.
    pub fn distances(&self, other: &UnitPoses, tol: &SyncTolerances) -> (f64, f64) {
        let theta_max_rad = tol.arm_rotation_deg.to_radians();
        let arm = pose_distance(&self.arm, &other.arm, tol.arm_translation_m, theta_max_rad);
        let base = planar_distance(
            &self.base_xy_m,
            &other.base_xy_m,
            &Vector2::from(tol.base_xy_m),
        );
        (arm, base)
    }
}

/// The stacked state of a team of N units; `units[i]` belongs to unit i.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StackedState {
    pub units: Vec<UnitPoses>,
}

/// One of the 2N subsystems the metric takes its maximum over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Subsystem {
    /// The arm of unit `i` (index into [`StackedState::units`]).
    Arm(usize),
    /// The wheel base of unit `i`.
    Base(usize),
}

impl std::fmt::Display for Subsystem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Subsystem::Arm(i) => write!(f, "arm of unit {i}"),
            Subsystem::Base(i) => write!(f, "base of unit {i}"),
        }
    }
}

/// The value of d and the subsystem that attains it (the first one on ties, arms before bases
/// within a unit).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StackedDistance {
    pub value: f64,
    pub binding: Subsystem,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StackedError {
    #[error("stacked states have {left} and {right} units; they must belong to the same team")]
    UnitCountMismatch { left: usize, right: usize },
    #[error("a stacked state needs at least one unit")]
    Empty,
}

impl StackedState {
    /// The paper's d(X, Y): the maximum over every unit's arm d_SE and base wheel metric.
    pub fn distance(
        &self,
        other: &StackedState,
        tol: &SyncTolerances,
    ) -> Result<StackedDistance, StackedError> {
        self.check_same_team(other)?;
        let mut worst = StackedDistance {
            value: f64::NEG_INFINITY,
            binding: Subsystem::Arm(0),
        };
        for (i, (x, y)) in self.units.iter().zip(&other.units).enumerate() {
            let (arm, base) = x.distances(y, tol);
            if arm > worst.value {
                worst = StackedDistance {
                    value: arm,
                    binding: Subsystem::Arm(i),
                };
            }
            if base > worst.value {
                worst = StackedDistance {
                    value: base,
                    binding: Subsystem::Base(i),
                };
            }
        }
        Ok(worst)
    }

    /// Writes the interpolation from `self` (t = 0) to `to` (t = 1) into `out` without
    /// allocating when `out` already has the right number of units: arm poses by
    /// translation lerp and rotation slerp, base positions by lerp.
    pub fn interpolate_into(
        &self,
        to: &StackedState,
        t: f64,
        out: &mut StackedState,
    ) -> Result<(), StackedError> {
        self.check_same_team(to)?;
        out.units.resize(self.units.len(), self.units[0]);
        for ((o, a), b) in out.units.iter_mut().zip(&self.units).zip(&to.units) {
            o.arm = interpolate_pose(&a.arm, &b.arm, t);
            o.base_xy_m = if t <= 0.0 {
                a.base_xy_m
            } else if t >= 1.0 {
                b.base_xy_m
            } else {
                a.base_xy_m.lerp(&b.base_xy_m, t)
            };
        }
        Ok(())
    }

    fn check_same_team(&self, other: &StackedState) -> Result<(), StackedError> {
        if self.units.len() != other.units.len() {
            return Err(StackedError::UnitCountMismatch {
                left: self.units.len(),
                right: other.units.len(),
            });
        }
        if self.units.is_empty() {
            return Err(StackedError::Empty);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Validate;

    /// The paper's tolerances (the values of `configs/sync.toml`).
    const PAPER: SyncTolerances = SyncTolerances {
        arm_translation_m: 0.03,
        arm_rotation_deg: 5.0,
        base_xy_m: [0.02, 0.02],
    };
    use crate::se3::{planar_distance, pose_distance};
    use nalgebra::{Translation3, Unit, UnitQuaternion, Vector3};
    use proptest::prelude::*;

    fn unit_poses() -> impl Strategy<Value = UnitPoses> {
        (
            prop::array::uniform3(-0.2..0.2f64),
            prop::array::uniform3(-1.0..1.0f64),
            0.0..0.5f64,
            prop::array::uniform2(-0.1..0.1f64),
        )
            .prop_map(|(t, axis, angle, xy)| {
                let axis = Vector3::from(axis) + Vector3::new(1e-3, 0.0, 0.0);
                UnitPoses {
                    arm: Isometry3::from_parts(
                        Translation3::from(Vector3::from(t)),
                        UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), angle),
                    ),
                    base_xy_m: Vector2::from(xy),
                }
            })
    }

    fn team(n: usize) -> impl Strategy<Value = StackedState> {
        prop::collection::vec(unit_poses(), n).prop_map(|units| StackedState { units })
    }

    fn two_teams() -> impl Strategy<Value = (StackedState, StackedState)> {
        (1usize..5).prop_flat_map(|n| (team(n), team(n)))
    }

    #[test]
    fn mismatched_teams_and_bad_tolerances_are_errors() {
        let one = StackedState {
            units: vec![UnitPoses {
                arm: Isometry3::identity(),
                base_xy_m: Vector2::zeros(),
            }],
        };
        let two = StackedState {
            units: vec![one.units[0]; 2],
        };
        let tol = PAPER;
        assert_eq!(
            one.distance(&two, &tol),
            Err(StackedError::UnitCountMismatch { left: 1, right: 2 })
        );
        let empty = StackedState { units: vec![] };
        assert_eq!(empty.distance(&empty, &tol), Err(StackedError::Empty));
        let bad = SyncTolerances {
            base_xy_m: [0.02, 0.0],
            ..tol
        };
        assert_eq!(bad.validate().unwrap_err().field, "base_xy_m[1]");
        assert_eq!(tol.validate(), Ok(()));
    }

    #[test]
    fn binding_subsystem_is_named() {
        let home = UnitPoses {
            arm: Isometry3::identity(),
            base_xy_m: Vector2::zeros(),
        };
        let y = StackedState {
            units: vec![home; 2],
        };
        let mut x = y.clone();
        x.units[1].base_xy_m = Vector2::new(0.03, 0.0);
        x.units[0].arm = Isometry3::translation(0.0, 0.0, 0.015);
        let d = x.distance(&y, &PAPER).unwrap();
        assert_eq!(d.binding, Subsystem::Base(1));
        assert!((d.value - 1.5).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn metric_is_the_max_of_its_parts((x, y) in two_teams()) {
            let tol = PAPER;
            let d = x.distance(&y, &tol).unwrap();
            let delta_w = Vector2::from(tol.base_xy_m);
            let parts: Vec<(Subsystem, f64)> = x.units.iter().zip(&y.units).enumerate().flat_map(|(i, (a, b))| {
                [
                    (Subsystem::Arm(i), pose_distance(&a.arm, &b.arm, tol.arm_translation_m, tol.arm_rotation_deg.to_radians())),
                    (Subsystem::Base(i), planar_distance(&a.base_xy_m, &b.base_xy_m, &delta_w)),
                ]
            }).collect();
            let max = parts.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
            prop_assert_eq!(d.value, max);
            prop_assert!(parts.contains(&(d.binding, d.value)));
        }

        #[test]
        fn metric_symmetric_and_zero_on_self((x, y) in two_teams()) {
            let tol = PAPER;
            prop_assert_eq!(x.distance(&x, &tol).unwrap().value, 0.0);
            let xy = x.distance(&y, &tol).unwrap().value;
            let yx = y.distance(&x, &tol).unwrap().value;
            prop_assert!((xy - yx).abs() <= 1e-9 * xy.max(1.0));
        }

        #[test]
        fn metric_scales_inversely_with_tolerances((x, y) in two_teams(), k in 0.1..10.0f64) {
            let tol = PAPER;
            let scaled = SyncTolerances {
                arm_translation_m: k * tol.arm_translation_m,
                arm_rotation_deg: k * tol.arm_rotation_deg,
                base_xy_m: [k * tol.base_xy_m[0], k * tol.base_xy_m[1]],
            };
            let d = x.distance(&y, &tol).unwrap().value;
            let ds = x.distance(&y, &scaled).unwrap().value;
            prop_assert!((ds * k - d).abs() <= 1e-9 * d.max(1.0));
        }

        #[test]
        fn interpolation_endpoints_exact((x, y) in two_teams(), t in 0.0..1.0f64) {
            let mut out = StackedState { units: Vec::new() };
            x.interpolate_into(&y, 0.0, &mut out).unwrap();
            prop_assert_eq!(&out, &x);
            x.interpolate_into(&y, 1.0, &mut out).unwrap();
            prop_assert_eq!(&out, &y);
            // Every subsystem moves monotonically: at t it is no farther from x than the whole step.
            x.interpolate_into(&y, t, &mut out).unwrap();
            let tol = PAPER;
            let whole = x.distance(&y, &tol).unwrap().value;
            prop_assert!(x.distance(&out, &tol).unwrap().value <= whole * t + 1e-9);
        }
    }
}
