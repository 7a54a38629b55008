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
//! Two terms are **not in the paper** (issue 18), each off at weight 0, which is the paper's
//! reward (the shipped phase configs): `−w_clamp_step · mean_i(1 − t_max,i)`, what the clamp cut
//! of each unit's increment this tick (0 when both full steps were issued, 1 on a hold), and
//! `−w_squeeze · ((|F₁| + |F₂|)/(m g) − 1)₊`, the grasp force beyond what carrying the payload
//! needs — an internal squeeze that σ_f cannot see, since it penalizes only the arms'
//! *difference*. See [`RewardConfig::pipeline_terms`].
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

use moonhaul_core::config::{in_range, positive, FieldError, Validate};

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
    /// Not in the paper: weight of the clamp-step term (module docs); 0 = the paper's reward.
    pub w_clamp_step: f64,
    /// Not in the paper: weight of the squeeze term (module docs); 0 = the paper's reward.
    pub w_squeeze: f64,
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
        for (field, value) in [
            ("w_clamp_step", self.w_clamp_step),
            ("w_squeeze", self.w_squeeze),
        ] {
            in_range(field, value, 0.0, 100.0)?;
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

    /// The two terms not in the paper (module docs), ≤ 0: `t_max` of each unit's issued step
    /// this tick, `grasp_forces_n` the grasps' force magnitudes (both 0 once released) and
    /// `payload_weight_n` = m g.
    pub fn pipeline_terms(
        &self,
        t_max: &[f64],
        grasp_forces_n: &[f64],
        payload_weight_n: f64,
    ) -> f64 {
        let cut = if t_max.is_empty() {
            0.0
        } else {
            t_max.iter().map(|t| 1.0 - t.clamp(0.0, 1.0)).sum::<f64>() / t_max.len() as f64
        };
        let squeeze = if payload_weight_n > 0.0 {
            (grasp_forces_n.iter().sum::<f64>() / payload_weight_n - 1.0).max(0.0)
        } else {
            0.0
        };
        -self.w_clamp_step * cut - self.w_squeeze * squeeze
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

    #[test]
    fn the_terms_not_in_the_paper_are_off_as_shipped_and_measure_cut_and_squeeze() {
        let shipped = table_two();
        close(
            shipped.pipeline_terms(&[0.0, 0.5], &[300.0, 300.0], 100.0),
            0.0,
        );
        let on = RewardConfig {
            w_clamp_step: 2.0,
            w_squeeze: 0.5,
            ..shipped
        };
        // Full steps and exactly the weight carried: nothing to pay.
        close(on.pipeline_terms(&[1.0, 1.0], &[60.0, 40.0], 100.0), 0.0);
        // One hold (cut 1) and one half step: mean cut 0.75; forces 1.5x the weight: 0.5 over.
        close(
            on.pipeline_terms(&[0.0, 0.5], &[90.0, 60.0], 100.0),
            -2.0 * 0.75 - 0.5 * 0.5,
        );
        // Carrying less than the weight (payload on the ground) is no squeeze.
        close(on.pipeline_terms(&[1.0, 1.0], &[10.0, 10.0], 100.0), 0.0);
        let bad = RewardConfig {
            w_squeeze: -1.0,
            ..shipped
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("w_squeeze"));
    }
}
