//! The phase rewards of the paper, exactly: r_L (lift), r_T (transport) and r_P (place), with
//! Table II's tolerances and weights from the `[reward]` section of each
//! `configs/train/<phase>.toml`.
//!
//! ```text
//! r_L = −w_h (Δh/h_tol)² − w_ḣ (ḣ/ḣ_tol)² − w_f (σ_f/σ_f,tol) − w_θ (θ/θ_tol)²
//! r_T = −w_p (‖p − p_B‖/p_tol)² − w_v (‖ṗ − v_cmd‖/v_tol)² − w_θ (θ/θ_tol)² − w_h (Δh/h_tol)²
//! r_P = −w_p (‖p − p_B‖/p_tol)² − w_h0 (h/h0_tol)² − w_ḣ (ḣ/ḣ_tol)² − w_θ (θ/θ_tol)²
//! ```
//!
//! Every term is ≤ 0, so the best return is 0. (The paper reports positive plateau rewards —
//! 105.9 for lift — which these equations cannot produce; its training code must add a term
//! the paper does not give. We implement the equations as written.)
//!
//! Choices where the paper is vague:
//! - h is the payload's height above the ground (its lowest point above the terrain under it),
//!   ḣ its vertical velocity, θ its tilt (angle between its z axis and the world's), p and ṗ its
//!   horizontal position and velocity.
//! - σ_f, "the variance of interaction forces across arms", normalized: the variance of the
//!   per-arm grasp force magnitudes divided by the square of the share each arm would carry of
//!   the payload's weight, `Var_i(F_i) / (m g / N)²`. It is dimensionless, 0 for perfectly shared
//!   load, and 1 when the spread of the arms' forces equals one arm's fair share — the natural
//!   reading of σ_f,tol = 1.0 (normalized). The fair share, not the measured mean, normalizes it,
//!   so an unloaded grasp does not divide by zero.

use serde::{Deserialize, Serialize};

use moonhaul_core::config::{positive, FieldError, Validate};

/// Table II: every tolerance and weight (the same table for all phases).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RewardConfig {
    /// h_tol, m (paper: 0.03).
    pub height_tol_m: f64,
    /// ḣ_tol, m/s (paper: 0.10).
    pub vertical_speed_tol_mps: f64,
    /// θ_tol, degrees (paper: 10).
    pub tilt_tol_deg: f64,
    /// p_tol, m (paper: 0.20).
    pub planar_position_tol_m: f64,
    /// v_tol, m/s (paper: 0.05).
    pub planar_speed_tol_mps: f64,
    /// σ_f,tol, normalized (paper: 1.0).
    pub force_variance_tol: f64,
    /// h0_tol, m (paper: 0.02).
    pub final_height_tol_m: f64,
    /// w_h (paper: 1.0).
    pub w_height: f64,
    /// w_ḣ (paper: 0.5).
    pub w_vertical_speed: f64,
    /// w_θ (paper: 0.7).
    pub w_tilt: f64,
    /// w_p (paper: 1.0).
    pub w_planar_position: f64,
    /// w_v (paper: 0.5).
    pub w_planar_speed: f64,
    /// w_f (paper: 0.3).
    pub w_force_variance: f64,
    /// w_h0 (paper: 1.0).
    pub w_final_height: f64,
}

impl Validate for RewardConfig {
    /// Tolerances finite and positive (each divides a term); weights finite and positive, as
    /// the paper requires (w > 0), and at most 100 so no term swamps the rest by accident.
    fn validate(&self) -> Result<(), FieldError> {
        for (field, value, max) in [
            ("height_tol_m", self.height_tol_m, 1.0),
            ("vertical_speed_tol_mps", self.vertical_speed_tol_mps, 10.0),
            ("tilt_tol_deg", self.tilt_tol_deg, 90.0),
            ("planar_position_tol_m", self.planar_position_tol_m, 10.0),
            ("planar_speed_tol_mps", self.planar_speed_tol_mps, 10.0),
            ("force_variance_tol", self.force_variance_tol, 100.0),
            ("final_height_tol_m", self.final_height_tol_m, 1.0),
            ("w_height", self.w_height, 100.0),
            ("w_vertical_speed", self.w_vertical_speed, 100.0),
            ("w_tilt", self.w_tilt, 100.0),
            ("w_planar_position", self.w_planar_position, 100.0),
            ("w_planar_speed", self.w_planar_speed, 100.0),
            ("w_force_variance", self.w_force_variance, 100.0),
            ("w_final_height", self.w_final_height, 100.0),
        ] {
            positive(field, value, max)?;
        }
        Ok(())
    }
}

/// What the rewards measure of the payload at one control step (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PayloadSample {
    /// h, m above the ground.
    pub height_m: f64,
    /// ḣ, m/s.
    pub vertical_speed_mps: f64,
    /// θ, rad.
    pub tilt_rad: f64,
    /// p, horizontal position, m.
    pub planar_position_m: [f64; 2],
    /// ṗ, horizontal velocity, m/s.
    pub planar_velocity_mps: [f64; 2],
}

/// The goals a phase reward is measured against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Goal {
    /// h*, m.
    pub height_m: f64,
    /// p_B, m.
    pub position_m: [f64; 2],
    /// v_cmd, m/s (transport's commanded velocity profile at this step).
    pub velocity_mps: [f64; 2],
}

/// σ_f: the variance of the arms' grasp force magnitudes over the square of each arm's share
/// of the payload weight (see the module docs).
pub fn force_variance(forces_n: &[f64], payload_weight_n: f64) -> f64 {
    let n = forces_n.len() as f64;
    if forces_n.is_empty() || payload_weight_n.is_nan() || payload_weight_n <= 0.0 {
        return 0.0;
    }
    let mean = forces_n.iter().sum::<f64>() / n;
    let variance = forces_n.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / n;
    let share = payload_weight_n / n;
    variance / (share * share)
}

fn square(x: f64) -> f64 {
    x * x
}

fn distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

impl RewardConfig {
    fn tilt_term(&self, s: &PayloadSample) -> f64 {
        -self.w_tilt * square(s.tilt_rad / self.tilt_tol_deg.to_radians())
    }

    fn height_term(&self, s: &PayloadSample, goal: &Goal) -> f64 {
        -self.w_height * square((s.height_m - goal.height_m) / self.height_tol_m)
    }

    fn vertical_speed_term(&self, s: &PayloadSample) -> f64 {
        -self.w_vertical_speed * square(s.vertical_speed_mps / self.vertical_speed_tol_mps)
    }

    fn position_term(&self, s: &PayloadSample, goal: &Goal) -> f64 {
        -self.w_planar_position
            * square(distance(s.planar_position_m, goal.position_m) / self.planar_position_tol_m)
    }

    /// r_L, with σ_f from [`force_variance`].
    pub fn lift(&self, s: &PayloadSample, goal: &Goal, force_variance: f64) -> f64 {
        self.height_term(s, goal) + self.vertical_speed_term(s)
            - self.w_force_variance * (force_variance / self.force_variance_tol)
            + self.tilt_term(s)
    }

    /// r_T.
    pub fn transport(&self, s: &PayloadSample, goal: &Goal) -> f64 {
        self.position_term(s, goal)
            - self.w_planar_speed
                * square(
                    distance(s.planar_velocity_mps, goal.velocity_mps) / self.planar_speed_tol_mps,
                )
            + self.tilt_term(s)
            + self.height_term(s, goal)
    }

    /// r_P.
    pub fn place(&self, s: &PayloadSample, goal: &Goal) -> f64 {
        self.position_term(s, goal)
            - self.w_final_height * square(s.height_m / self.final_height_tol_m)
            + self.vertical_speed_term(s)
            + self.tilt_term(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::TrainConfig;

    fn table_two() -> RewardConfig {
        let path = moonhaul_core::config::repo_file("configs/train/lift.toml");
        TrainConfig::load(path).unwrap().reward.unwrap()
    }

    fn close(a: f64, b: f64) {
        assert!((a - b).abs() < 1e-12, "{a} vs {b}");
    }

    const GOAL: Goal = Goal {
        height_m: 0.3,
        position_m: [2.0, 0.0],
        velocity_mps: [0.2, 0.0],
    };

    #[test]
    fn every_phase_config_holds_table_two() {
        for phase in ["lift", "transport", "place"] {
            let path = moonhaul_core::config::repo_file(&format!("configs/train/{phase}.toml"));
            let r = TrainConfig::load(path).unwrap().reward.unwrap();
            assert_eq!(r, table_two(), "{phase}");
        }
        let r = table_two();
        assert_eq!(
            [
                r.height_tol_m,
                r.vertical_speed_tol_mps,
                r.tilt_tol_deg,
                r.planar_position_tol_m,
                r.planar_speed_tol_mps,
                r.force_variance_tol,
                r.final_height_tol_m
            ],
            [0.03, 0.10, 10.0, 0.20, 0.05, 1.0, 0.02]
        );
        assert_eq!(
            [
                r.w_height,
                r.w_vertical_speed,
                r.w_tilt,
                r.w_planar_position,
                r.w_planar_speed,
                r.w_force_variance,
                r.w_final_height
            ],
            [1.0, 0.5, 0.7, 1.0, 0.5, 0.3, 1.0]
        );
    }

    #[test]
    fn each_term_matches_a_hand_computation() {
        let r = table_two();
        // At the goal, at rest, level, evenly loaded: every reward is exactly 0.
        let at_goal = PayloadSample {
            height_m: 0.3,
            vertical_speed_mps: 0.0,
            tilt_rad: 0.0,
            planar_position_m: [2.0, 0.0],
            planar_velocity_mps: [0.2, 0.0],
        };
        close(r.lift(&at_goal, &GOAL, 0.0), 0.0);
        close(r.transport(&at_goal, &GOAL), 0.0);
        // One tolerance off in one quantity costs exactly that term's weight.
        let tol = |f: &dyn Fn(&mut PayloadSample)| {
            let mut s = at_goal;
            f(&mut s);
            s
        };
        let high = tol(&|s| s.height_m += 0.03);
        close(r.lift(&high, &GOAL, 0.0), -1.0);
        close(r.transport(&high, &GOAL), -1.0);
        let rising = tol(&|s| s.vertical_speed_mps = -0.1);
        close(r.lift(&rising, &GOAL, 0.0), -0.5);
        let tilted = tol(&|s| s.tilt_rad = 10f64.to_radians());
        close(r.lift(&tilted, &GOAL, 0.0), -0.7);
        close(r.transport(&tilted, &GOAL), -0.7);
        close(r.lift(&at_goal, &GOAL, 1.0), -0.3);
        // Transport: 0.2 m off the goal on a diagonal, 0.05 m/s off the command.
        let off = tol(&|s| {
            s.planar_position_m = [2.0 - 0.12, 0.16];
            s.planar_velocity_mps = [0.2 + 0.03, -0.04];
        });
        close(r.transport(&off, &GOAL), -1.0 - 0.5);
        // Place: resting on the ground at p_B costs nothing; 2 cm up costs w_h0.
        let down = tol(&|s| s.height_m = 0.0);
        close(r.place(&down, &GOAL), 0.0);
        close(r.place(&tol(&|s| s.height_m = 0.02), &GOAL), -1.0);
        // Two tolerances in height: quadratic, four times the weight.
        close(r.lift(&tol(&|s| s.height_m = 0.36), &GOAL, 0.0), -4.0);
    }

    #[test]
    fn force_variance_is_normalized_by_the_fair_share() {
        // 100 N payload on two arms: 50 N each is balanced.
        close(force_variance(&[50.0, 50.0], 100.0), 0.0);
        // 100 N and 0 N: variance 2500 N², share 50 N → 1.
        close(force_variance(&[100.0, 0.0], 100.0), 1.0);
        close(force_variance(&[75.0, 25.0], 100.0), 0.25);
        close(force_variance(&[], 100.0), 0.0);
        close(force_variance(&[10.0, 0.0], 0.0), 0.0);
    }
}
