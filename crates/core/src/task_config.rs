//! `configs/tasks.toml`: the phase tasks' settings — episode lengths, goals, the transport's
//! velocity profile, encoder noise, the action map. Plain configuration in core so that the
//! simulator's tasks (training, evaluation) and the onboard daemon (the mission goals it gives
//! its policies) read the one file through the one type.

use crate::config::{
    self, in_range, interval, positive, section, ConfigError, FieldError, Validate,
};
use crate::observation::PhaseGoal;
use crate::state::Phase;
use crate::state::PlanarPose;
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Encoder noise of the simulated units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sensing {
    pub arm_position_noise_std_rad: f64,
    pub arm_velocity_noise_std_radps: f64,
    pub wheel_velocity_noise_std_radps: f64,
}

/// The increment map of [`crate::action::ActionMap`]: how far one tick's action may move the
/// previous command.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActionSettings {
    /// Largest change of a wheel velocity command per tick, rad/s.
    pub wheel_step_radps: f64,
    /// Largest move of an arm joint position command per tick, rad.
    pub arm_step_rad: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Safety {
    /// Payload tilt that ends an episode, degrees.
    pub max_tilt_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LiftTask {
    pub duration_s: f64,
    /// h* is drawn uniformly from this range, m.
    #[serde(deserialize_with = "crate::config::exact_array")]
    pub goal_height_m: [f64; 2],
    /// Fraction of episodes aiming at the mission's height (`transport.start_height_m`, what
    /// a deployed lift aims at) instead of a drawn h*, 0–1.
    pub mission_goal_fraction: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransportTask {
    pub duration_s: f64,
    /// h*: the payload starts and should stay this high, m.
    pub start_height_m: f64,
    pub distance_m: f64,
    pub speed_mps: f64,
    pub accel_mps2: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaceTask {
    pub duration_s: f64,
    pub start_height_m: f64,
    /// p_B lies within ± this of the start along X, m.
    pub goal_offset_m: f64,
    /// Ground contact this long opens the grasps, s.
    pub release_after_contact_s: f64,
    /// Onboard touchdown: the height of a unit's sensed over its commanded end effector at
    /// which the ground carries the payload, m ([`crate::touchdown`]).
    pub contact_press_m: f64,
    /// Each unit's press is measured from its mean over this first part of the placement, s.
    pub contact_baseline_s: f64,
    /// Time constant of the low-pass filter on that press, s.
    pub contact_filter_s: f64,
    /// Contact counts only while the team's commanded end effectors descend no faster, m/s.
    pub contact_max_descent_mps: f64,
    /// ... and the lift estimate is at most this high above the start's ground, m.
    pub contact_search_height_m: f64,
}

/// The monolithic baseline's mission: lift, transport and place as one episode.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MissionTask {
    /// The payload height at which the reward switches from lift to transport, m (the gate's
    /// h_min).
    pub lift_done_height_m: f64,
}

/// `configs/tasks.toml`: every phase task's settings (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskConfig {
    pub sensing: Sensing,
    pub action: ActionSettings,
    pub safety: Safety,
    pub lift: LiftTask,
    pub transport: TransportTask,
    pub place: PlaceTask,
    pub mission: MissionTask,
}

/// Longest phase episode, s.
pub const MAX_EPISODE_S: f64 = 120.0;

impl Validate for TaskConfig {
    fn validate(&self) -> Result<(), FieldError> {
        section("sensing", || {
            let s = &self.sensing;
            in_range(
                "arm_position_noise_std_rad",
                s.arm_position_noise_std_rad,
                0.0,
                0.1,
            )?;
            in_range(
                "arm_velocity_noise_std_radps",
                s.arm_velocity_noise_std_radps,
                0.0,
                1.0,
            )?;
            in_range(
                "wheel_velocity_noise_std_radps",
                s.wheel_velocity_noise_std_radps,
                0.0,
                1.0,
            )
        })?;
        section("action", || {
            let a = &self.action;
            positive("wheel_step_radps", a.wheel_step_radps, 10.0)?;
            positive("arm_step_rad", a.arm_step_rad, 0.5)
        })?;
        section("safety", || {
            positive("max_tilt_deg", self.safety.max_tilt_deg, 90.0)
        })?;
        section("lift", || {
            positive("duration_s", self.lift.duration_s, MAX_EPISODE_S)?;
            in_range(
                "mission_goal_fraction",
                self.lift.mission_goal_fraction,
                0.0,
                1.0,
            )?;
            interval("goal_height_m", self.lift.goal_height_m, 0.0, 0.75)?;
            // A lift to 0 m is no lift: every drawn goal must raise the payload.
            positive("goal_height_m[0]", self.lift.goal_height_m[0], 0.75)
        })?;
        section("transport", || {
            let t = &self.transport;
            positive("duration_s", t.duration_s, MAX_EPISODE_S)?;
            positive("start_height_m", t.start_height_m, 0.75)?;
            positive("distance_m", t.distance_m, 2.5)?;
            positive("speed_mps", t.speed_mps, 1.0)?;
            positive("accel_mps2", t.accel_mps2, 10.0)?;
            let profile = self.profile();
            if profile.duration_s() > t.duration_s {
                return Err(FieldError::new(
                    "duration_s",
                    format!(
                        "the velocity profile takes {:.1} s, longer than the episode",
                        profile.duration_s()
                    ),
                ));
            }
            Ok(())
        })?;
        section("place", || {
            let p = &self.place;
            positive("duration_s", p.duration_s, MAX_EPISODE_S)?;
            positive("start_height_m", p.start_height_m, 0.75)?;
            in_range("goal_offset_m", p.goal_offset_m, 0.0, 1.0)?;
            in_range(
                "release_after_contact_s",
                p.release_after_contact_s,
                0.0,
                p.duration_s,
            )?;
            // Above the loaded drives' sag and tracking lag (a few mm, tests/drives.rs), far
            // below the clamp's 30 mm.
            positive("contact_press_m", p.contact_press_m, 0.02)?;
            // Up to a second: a slower touchdown signal would hold the payload pressed.
            // Within the episode, and leaving time to place after it.
            positive(
                "contact_baseline_s",
                p.contact_baseline_s,
                p.duration_s / 2.0,
            )?;
            positive("contact_filter_s", p.contact_filter_s, 1.0)?;
            positive("contact_max_descent_mps", p.contact_max_descent_mps, 1.0)?;
            positive(
                "contact_search_height_m",
                p.contact_search_height_m,
                p.start_height_m,
            )
        })?;
        // The monolithic mission switches from lift to transport at this height: every lift
        // goal drawn and the transport's carrying height must reach it, or the mission never
        // leaves its lift.
        section("mission", || {
            let reachable = self.lift.goal_height_m[0].min(self.transport.start_height_m);
            positive(
                "lift_done_height_m",
                self.mission.lift_done_height_m,
                reachable,
            )
            .map_err(|e| {
                FieldError::new(
                    e.field,
                    format!(
                        "{} (at most lift.goal_height_m[0] and transport.start_height_m)",
                        e.reason
                    ),
                )
            })
        })
    }
}

impl TaskConfig {
    /// Reads and validates `configs/tasks.toml`; errors name the file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// The shipped `configs/tasks.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::load(config::repo_file("configs/tasks.toml"))
    }

    /// The transport's velocity profile.
    pub fn profile(&self) -> VelocityProfile {
        let t = &self.transport;
        VelocityProfile {
            distance_m: t.distance_m,
            speed_mps: t.speed_mps,
            accel_mps2: t.accel_mps2,
        }
    }

    /// Episode length of `phase`, s.
    pub fn duration_s(&self, phase: Phase) -> f64 {
        match phase {
            Phase::Lift => self.lift.duration_s,
            Phase::Transport => self.transport.duration_s,
            Phase::Place | Phase::Idle => self.place.duration_s,
        }
    }

    /// A unit's goal in a phase episode — the one definition the training tasks, evaluation and
    /// the onboard tick share: h* = `height_m`, the base `travel_m` along +X from `start` (its
    /// pose when the episode began), v_cmd and the reference point, the transport profile's
    /// speed and distance `phase_s` into a transport (zero speed and the goal in the other
    /// phases), and the phase's progress over its episode length.
    pub fn phase_goal(
        &self,
        phase: Phase,
        height_m: f64,
        start: &PlanarPose,
        travel_m: f64,
        phase_s: f64,
    ) -> PhaseGoal {
        let (speed_mps, along_m) = if phase == Phase::Transport {
            let profile = self.profile();
            (profile.speed_at(phase_s), profile.travelled_at(phase_s))
        } else {
            (0.0, travel_m)
        };
        let progress = (phase_s / self.duration_s(phase)).clamp(0.0, 1.0);
        PhaseGoal {
            height_m,
            base_goal_m: Vector2::new(start.x_m + travel_m, start.y_m),
            velocity_mps: Vector2::new(speed_mps, 0.0),
            reference_m: Vector2::new(start.x_m + along_m, start.y_m),
            progress: if progress.is_finite() { progress } else { 0.0 },
        }
    }

    /// h* and the base travel of `phase` in a mission as the units fly it: lift to (and carry
    /// at) `transport.start_height_m`, carry `transport.distance_m`, set down where the
    /// transport ended.
    pub fn mission_targets(&self, phase: Phase) -> (f64, f64) {
        let t = &self.transport;
        match phase {
            Phase::Idle | Phase::Lift => (t.start_height_m, 0.0),
            Phase::Transport => (t.start_height_m, t.distance_m),
            Phase::Place => (0.0, 0.0),
        }
    }

    /// The lift an episode of `phase` starts at, m.
    pub fn start_lift_m(&self, phase: Phase) -> f64 {
        match phase {
            Phase::Transport => self.transport.start_height_m,
            Phase::Place => self.place.start_height_m,
            Phase::Lift | Phase::Idle => 0.0,
        }
    }
}

/// A trapezoidal speed profile from rest to rest over a distance: accelerate, cruise,
/// decelerate (a triangle when the distance is too short to reach the cruise speed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityProfile {
    pub distance_m: f64,
    pub speed_mps: f64,
    pub accel_mps2: f64,
}

impl VelocityProfile {
    /// The peak speed actually reached, m/s.
    fn peak_mps(&self) -> f64 {
        self.speed_mps
            .min((self.distance_m * self.accel_mps2).sqrt())
    }

    /// Time from start to stop, s.
    pub fn duration_s(&self) -> f64 {
        let v = self.peak_mps();
        self.distance_m / v + v / self.accel_mps2
    }

    /// Commanded speed at `t_s` after the start, m/s.
    pub fn speed_at(&self, t_s: f64) -> f64 {
        let (v, a, end) = (self.peak_mps(), self.accel_mps2, self.duration_s());
        if t_s <= 0.0 || t_s >= end {
            0.0
        } else {
            (a * t_s).min(v).min(a * (end - t_s))
        }
    }

    /// Distance covered by `t_s`, m (the integral of [`Self::speed_at`]).
    pub fn travelled_at(&self, t_s: f64) -> f64 {
        let (v, a, end) = (self.peak_mps(), self.accel_mps2, self.duration_s());
        let ramp = v / a;
        let t = t_s.clamp(0.0, end);
        let up = 0.5 * a * t.min(ramp).powi(2);
        let cruise = v * (t.min(end - ramp) - ramp).max(0.0);
        let down = if t > end - ramp {
            let d = t - (end - ramp);
            v * d - 0.5 * a * d * d
        } else {
            0.0
        };
        up + cruise + down
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_profile_starts_and_ends_at_rest_and_covers_the_distance() {
        let p = TaskConfig::shipped().unwrap().profile();
        assert!((p.duration_s() - 11.0).abs() < 1e-12, "{}", p.duration_s());
        assert_eq!(p.speed_at(0.0), 0.0);
        assert!((p.speed_at(0.5) - 0.1).abs() < 1e-12);
        assert!((p.speed_at(5.0) - 0.2).abs() < 1e-12);
        assert_eq!(p.speed_at(p.duration_s()), 0.0);
        assert!((p.travelled_at(p.duration_s()) - 2.0).abs() < 1e-12);
        let dt = 1e-4;
        let numeric: f64 = (0..(7.3 / dt) as usize)
            .map(|k| p.speed_at((k as f64 + 0.5) * dt) * dt)
            .sum();
        assert!((p.travelled_at(7.3) - numeric).abs() < 1e-6);
        let triangle = VelocityProfile {
            distance_m: 0.1,
            speed_mps: 1.0,
            accel_mps2: 1.0,
        };
        assert!((triangle.travelled_at(triangle.duration_s()) - 0.1).abs() < 1e-12);
    }

    #[test]
    fn bad_task_settings_name_their_field() {
        let path = config::repo_file("configs/tasks.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        for (from, to, field) in [
            (
                "max_tilt_deg = 45.0",
                "max_tilt_deg = 0.0",
                "safety.max_tilt_deg",
            ),
            (
                "goal_height_m = [0.3, 0.75]",
                "goal_height_m = [0.75, 0.3]",
                "lift.goal_height_m",
            ),
            (
                "distance_m = 2.0",
                "distance_m = 9.0",
                "transport.distance_m",
            ),
            (
                "speed_mps = 0.2",
                "speed_mps = 0.01",
                "transport.duration_s",
            ),
            (
                "goal_height_m = [0.3, 0.75]",
                "goal_height_m = [0.0, 0.0]",
                "lift.goal_height_m[0]",
            ),
            (
                "goal_height_m = [0.3, 0.75]",
                "goal_height_m = [0.3, 0.75, 0.9]",
                "lift.goal_height_m",
            ),
            (
                "lift_done_height_m = 0.27",
                "lift_done_height_m = nan",
                "mission.lift_done_height_m",
            ),
            (
                "lift_done_height_m = 0.27",
                "lift_done_height_m = -1.0",
                "mission.lift_done_height_m",
            ),
            (
                "lift_done_height_m = 0.27",
                "lift_done_height_m = 0.0",
                "mission.lift_done_height_m",
            ),
            (
                "lift_done_height_m = 0.27",
                "lift_done_height_m = 100.0",
                "mission.lift_done_height_m",
            ),
            // Cross-field: above the smallest lift goal, the mission would never leave lift.
            (
                "lift_done_height_m = 0.27",
                "lift_done_height_m = 0.31",
                "mission.lift_done_height_m",
            ),
        ] {
            assert!(text.contains(from), "{from}");
            let err = config::parse::<TaskConfig>(&text.replace(from, to), &path).unwrap_err();
            assert_eq!(err.field(), Some(field), "{err}");
        }
    }
}
