//! A scripted (non-learned) mission: settle, lift to a target height, drive a distance, set the
//! payload down and release. It proves the physics before any learning and drives the
//! stability tests and `moonhaul sim demo`.
//!
//! The arms move their end effectors straight up or down in their own base frames (IK on
//! core's FK, warm-started from the previous command) along a minimum-jerk profile, both by the
//! same amount, so the closed chain is never asked to stretch. The bases follow a reference
//! that moves along +X at a trapezoidal speed profile, each with a unicycle tracking law on
//! its along-track, cross-track and heading errors: driven open-loop, two rigidly coupled
//! bases drift apart within seconds (their wheels slip and load differently) and the grasps
//! would take the strain. Unit 1 faces −X, so it tracks the reference driving backwards.

use moonhaul_core::config::{self, in_range, positive, ConfigError, FieldError, Validate};
use moonhaul_core::se3::rotation_angle;
use moonhaul_core::state::{Phase, PlanarPose, PlanarVelocity, UnitCommand, ARM_JOINTS};
use nalgebra::{Isometry3, Vector3};
use serde::{Deserialize, Serialize};
use std::path::Path;

use crate::ik::{self, IkSettings};
use crate::scene::{Env, EnvState, SceneModel, UNITS};
use crate::task::VelocityProfile;
use crate::SimError;

/// Timing and geometry of the scripted mission: `configs/mission.toml`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MissionPlan {
    /// Time standing still before lifting, s.
    pub settle_s: f64,
    /// Lift of the end effectors, m (the paper's lift targets are 0.3, 0.5 and 0.75 m).
    pub lift_height_m: f64,
    pub lift_duration_s: f64,
    /// Pause after lifting and after driving, s.
    pub hold_s: f64,
    pub distance_m: f64,
    pub speed_mps: f64,
    pub accel_mps2: f64,
    /// Extra time holding the payload aloft after driving (long stability runs), s.
    pub carry_hold_s: f64,
    /// Time to lower the payload to `approach_height_m`, s.
    pub place_duration_s: f64,
    /// Lift at which the fast descent ends and the slow touchdown descent starts, m: enough
    /// to cover arm sag and terrain bumps.
    pub approach_height_m: f64,
    /// Descent speed below `approach_height_m`, m/s (the paper's touchdown speed is 0.03).
    pub touchdown_speed_mps: f64,
    /// How far below the start height the end effectors aim when placing, so the payload
    /// surely touches down on uneven ground, m.
    pub place_press_m: f64,
    /// Time after release until the mission ends, s.
    pub after_release_s: f64,
    /// Placement releases the grasps once the payload has touched the ground this long, s
    /// (or at the end of the placement at the latest).
    pub release_after_contact_s: f64,
    /// Base tracking gains: along-track 1/s, heading 1/s, cross-track rad/(m·s).
    pub along_gain_per_s: f64,
    pub heading_gain_per_s: f64,
    pub cross_gain_per_ms: f64,
}

impl MissionPlan {
    /// Reads and validates a mission plan; errors name the file and the field.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        config::load(path.as_ref())
    }

    /// The shipped `configs/mission.toml` of this source tree (tests and benches).
    pub fn shipped() -> Result<Self, ConfigError> {
        Self::load(config::repo_file("configs/mission.toml"))
    }
}

/// Longest phase or pause of the plan, s: anything longer than ten minutes is a typo.
const MAX_PHASE_S: f64 = 600.0;
/// Longest whole scripted mission, s.
const MAX_MISSION_S: f64 = 1800.0;

impl Validate for MissionPlan {
    fn validate(&self) -> Result<(), FieldError> {
        for (field, value) in [
            ("settle_s", self.settle_s),
            ("hold_s", self.hold_s),
            ("carry_hold_s", self.carry_hold_s),
            ("after_release_s", self.after_release_s),
            ("release_after_contact_s", self.release_after_contact_s),
        ] {
            in_range(field, value, 0.0, MAX_PHASE_S)?;
        }
        positive("lift_height_m", self.lift_height_m, 1.0)?;
        positive("lift_duration_s", self.lift_duration_s, MAX_PHASE_S)?;
        positive("distance_m", self.distance_m, 100.0)?;
        positive("speed_mps", self.speed_mps, 2.0)?;
        positive("accel_mps2", self.accel_mps2, 10.0)?;
        positive("place_duration_s", self.place_duration_s, MAX_PHASE_S)?;
        in_range(
            "approach_height_m",
            self.approach_height_m,
            0.0,
            self.lift_height_m,
        )?;
        positive("touchdown_speed_mps", self.touchdown_speed_mps, 1.0)?;
        in_range("place_press_m", self.place_press_m, 0.0, 0.1)?;
        positive("along_gain_per_s", self.along_gain_per_s, 100.0)?;
        positive("heading_gain_per_s", self.heading_gain_per_s, 100.0)?;
        positive("cross_gain_per_ms", self.cross_gain_per_ms, 100.0)?;
        // Each value may be in range and the mission still last for days: bound the whole.
        let duration_s = self.duration_s();
        if duration_s > MAX_MISSION_S {
            return Err(FieldError::new(
                "distance_m",
                format!(
                    "the plan lasts {duration_s:.0} s (distance / speed, descent / touchdown \
                     speed and every pause), more than {MAX_MISSION_S} s"
                ),
            ));
        }
        Ok(())
    }
}

/// Minimum-jerk progress 0 → 1 over τ ∈ [0, 1].
fn min_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

impl MissionPlan {
    /// The base reference's speed profile while driving.
    fn profile(&self) -> VelocityProfile {
        VelocityProfile {
            distance_m: self.distance_m,
            speed_mps: self.speed_mps,
            accel_mps2: self.accel_mps2,
        }
    }

    fn drive_s(&self) -> f64 {
        self.profile().duration_s()
    }

    /// Start times of lift, hold, transport, hold, place, and the release time.
    fn schedule(&self) -> [f64; 6] {
        let lift = self.settle_s;
        let hold1 = lift + self.lift_duration_s;
        let drive = hold1 + self.hold_s;
        let hold2 = drive + self.drive_s();
        let place = hold2 + self.hold_s + self.carry_hold_s;
        let slow_s = (self.approach_height_m + self.place_press_m) / self.touchdown_speed_mps;
        [
            lift,
            hold1,
            drive,
            hold2,
            place,
            place + self.place_duration_s + slow_s,
        ]
    }

    /// Total mission time, s.
    pub fn duration_s(&self) -> f64 {
        self.schedule()[5] + self.after_release_s
    }

    /// Distance the base reference has covered at time `t`, m (the integral of the speed
    /// profile of [`MissionPlan::at`]).
    pub fn travelled_m(&self, t: f64) -> f64 {
        let [_, _, drive, ..] = self.schedule();
        self.profile().travelled_at(t - drive)
    }

    /// Phase, end-effector lift (m) and base ground speed (m/s) at time `t`.
    pub fn at(&self, t: f64) -> (Phase, f64, f64) {
        let [lift, hold1, drive, hold2, place, release] = self.schedule();
        if t < lift {
            (Phase::Idle, 0.0, 0.0)
        } else if t < hold1 {
            (
                Phase::Lift,
                self.lift_height_m * min_jerk((t - lift) / self.lift_duration_s),
                0.0,
            )
        } else if t < drive {
            (Phase::Lift, self.lift_height_m, 0.0)
        } else if t < hold2 {
            (
                Phase::Transport,
                self.lift_height_m,
                self.profile().speed_at(t - drive),
            )
        } else if t < place {
            (Phase::Transport, self.lift_height_m, 0.0)
        } else if t < place + self.place_duration_s {
            let depth = self.lift_height_m - self.approach_height_m;
            let s = min_jerk((t - place) / self.place_duration_s);
            (Phase::Place, self.lift_height_m - depth * s, 0.0)
        } else if t < release {
            let slow = t - place - self.place_duration_s;
            (
                Phase::Place,
                self.approach_height_m - self.touchdown_speed_mps * slow,
                0.0,
            )
        } else {
            (Phase::Idle, -self.place_press_m, 0.0)
        }
    }

    /// When the grasps are released, s.
    pub fn release_s(&self) -> f64 {
        self.schedule()[5]
    }
}

/// Tracks the plan with IK; holds the last arm command so IK is warm-started.
#[derive(Debug, Clone)]
pub struct ScriptedController {
    plan: MissionPlan,
    /// Each unit's end-effector pose in its base frame at the start.
    ee_start: [Isometry3<f64>; UNITS],
    base_start: [PlanarPose; UNITS],
    q_command: [[f64; ARM_JOINTS]; UNITS],
    settings: IkSettings,
}

impl ScriptedController {
    /// Starts from the arms' current positions and end-effector poses.
    pub fn new(plan: MissionPlan, scene: &SceneModel, start: &EnvState) -> Result<Self, SimError> {
        let mut ee_start = [Isometry3::identity(); UNITS];
        let mut q_command = [[0.0; ARM_JOINTS]; UNITS];
        for ((ee, q), unit) in ee_start.iter_mut().zip(&mut q_command).zip(&start.units) {
            *q = unit.state.arm.position_rad;
            *ee = scene
                .arm_chain
                .forward(q)
                .map_err(|e| SimError::Kinematics(e.to_string()))?;
        }
        Ok(ScriptedController {
            plan,
            ee_start,
            base_start: start.units.map(|u| u.state.base_pose),
            q_command,
            settings: IkSettings::default(),
        })
    }

    /// The commands at time `t_s` for the current `state`, and their phase.
    pub fn command(
        &mut self,
        scene: &SceneModel,
        t_s: f64,
        state: &EnvState,
    ) -> Result<(Phase, [UnitCommand; UNITS]), SimError> {
        let (phase, lift_m, speed_mps) = self.plan.at(t_s);
        let travelled_m = self.plan.travelled_m(t_s);
        let mut commands = [UnitCommand::default(); UNITS];
        for (i, command) in commands.iter_mut().enumerate() {
            let mut target = self.ee_start[i];
            target.translation.vector += Vector3::new(0.0, 0.0, lift_m);
            self.q_command[i] = ik::solve(
                &scene.arm_chain,
                &target,
                &self.q_command[i],
                &self.settings,
            )?;
            // Bases steer only while transporting; otherwise their wheels hold still.
            let wheels = if phase == Phase::Transport {
                self.track(
                    scene,
                    i,
                    &state.units[i].state.base_pose,
                    travelled_m,
                    speed_mps,
                )
            } else {
                [0.0; 2]
            };
            *command = UnitCommand {
                wheel_velocity_radps: wheels,
                arm_position_rad: self.q_command[i],
            };
        }
        Ok((phase, commands))
    }

    /// Wheel speeds (left, right) that steer unit `i` onto its reference: its start pose moved
    /// `travelled_m` along +X at `speed_mps`.
    fn track(
        &self,
        scene: &SceneModel,
        i: usize,
        pose: &PlanarPose,
        travelled_m: f64,
        speed_mps: f64,
    ) -> [f64; 2] {
        let start = &self.base_start[i];
        let (dx, dy) = (start.x_m + travelled_m - pose.x_m, start.y_m - pose.y_m);
        let (sin, cos) = pose.yaw_rad.sin_cos();
        let along = dx * cos + dy * sin;
        let cross = -dx * sin + dy * cos;
        let heading = (start.yaw_rad - pose.yaw_rad + std::f64::consts::PI)
            .rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        // The reference moves along +X; in the base's own frame that is ±forward.
        let forward_ref = speed_mps * cos.signum();
        let p = &self.plan;
        // Corrections are capped at the cruise speed, so a base that slipped behind catches
        // up at most at twice the speed instead of spinning its wheels.
        let cap = p.speed_mps;
        let v = forward_ref + (p.along_gain_per_s * along).clamp(-cap, cap);
        let yaw_rate = (p.heading_gain_per_s * heading
            + p.cross_gain_per_ms * cross * if forward_ref < 0.0 { -1.0 } else { 1.0 })
        .clamp(
            -cap / scene.spec.half_track_m(),
            cap / scene.spec.half_track_m(),
        );
        scene.spec.wheel_velocities(&PlanarVelocity {
            forward_mps: v,
            yaw_rate_radps: yaw_rate,
        })
    }
}

/// Extremes of a mission, for the stability checks.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MissionSummary {
    pub duration_s: f64,
    /// Highest payload height while grasped, m.
    pub max_height_m: f64,
    /// Largest payload tilt while grasped, rad.
    pub max_tilt_rad: f64,
    /// Largest grasp force and torque seen, N and N·m.
    pub max_grasp_force_n: f64,
    pub max_grasp_torque_nm: f64,
    /// Largest drift of an end effector from its grasp point on the payload, m and rad.
    pub max_grasp_drift_m: f64,
    pub max_grasp_drift_rad: f64,
    /// Payload vertical speed at first ground contact during placement, m/s (≤ 0 = down).
    pub touchdown_speed_mps: f64,
    /// Planar distance the payload travelled, m.
    pub travel_m: f64,
    pub final_height_m: f64,
    pub grasp_broken: bool,
    /// Whether every readout was finite.
    pub finite: bool,
}

/// Runs the scripted mission on `env`, calling `tick` with every control-step readout.
pub fn run_mission(
    scene: &SceneModel,
    env: &mut Env,
    plan: MissionPlan,
    mut tick: impl FnMut(Phase, &EnvState),
) -> Result<MissionSummary, SimError> {
    let mut state = env.state(scene);
    let start = state;
    let grasp_start: Vec<Isometry3<f64>> = start
        .units
        .iter()
        .map(|u| start.payload.pose.inverse() * u.ee_pose)
        .collect();
    let mut controller = ScriptedController::new(plan, scene, &state)?;
    let mut summary = MissionSummary {
        finite: true,
        ..Default::default()
    };
    let mut released = false;
    let mut touched_down = false;
    let mut contact_s = 0.0;
    let t0 = state.time_s;
    while state.time_s - t0 < plan.duration_s() {
        let t = state.time_s - t0;
        if !released && (t >= plan.release_s() || contact_s >= plan.release_after_contact_s) {
            env.release_grasps();
            released = true;
        }
        let (phase, commands) = controller.command(scene, t, &state)?;
        env.step(scene, &commands);
        env.state_into(scene, &mut state);
        summary.finite &= state.is_finite();
        if !summary.finite {
            break;
        }
        let p = &state.payload;
        if !released {
            summary.max_height_m = summary.max_height_m.max(p.height_m);
            summary.max_tilt_rad = summary.max_tilt_rad.max(p.tilt_rad);
            for (u, g0) in state.units.iter().zip(&grasp_start) {
                let g = p.pose.inverse() * u.ee_pose;
                summary.max_grasp_force_n = summary.max_grasp_force_n.max(u.grasp.force_n);
                summary.max_grasp_torque_nm = summary.max_grasp_torque_nm.max(u.grasp.torque_nm);
                summary.max_grasp_drift_m = summary
                    .max_grasp_drift_m
                    .max((g.translation.vector - g0.translation.vector).norm());
                summary.max_grasp_drift_rad = summary
                    .max_grasp_drift_rad
                    .max(rotation_angle(&g.rotation, &g0.rotation));
            }
        }
        if phase == Phase::Place && p.ground_contact {
            if !touched_down {
                touched_down = true;
                summary.touchdown_speed_mps = p.linvel_mps.z;
            }
            contact_s += 1.0 / scene.config.control_hz;
        }
        tick(phase, &state);
    }
    summary.duration_s = state.time_s - t0;
    summary.travel_m = (state.payload.pose.translation.vector.xy()
        - start.payload.pose.translation.vector.xy())
    .norm();
    summary.final_height_m = state.payload.height_m;
    summary.grasp_broken = state.grasp_broken;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_plans_are_named_by_file_and_field() {
        let path = config::repo_file("configs/mission.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let cases = [
            ("speed_mps = 0.2", "speed_mps = 0.0", "speed_mps"),
            ("speed_mps = 0.2", "speed_mps = 1e-6", "distance_m"),
            ("distance_m = 2.0", "distance_m = -2.0", "distance_m"),
            (
                "lift_height_m = 0.3",
                "lift_height_m = nan",
                "lift_height_m",
            ),
            ("hold_s = 1.0", "hold_s = 1e9", "hold_s"),
            (
                "approach_height_m = 0.04",
                "approach_height_m = 0.5",
                "approach_height_m",
            ),
            (
                "settle_s = 1.0",
                "settle_s = 1.0\nsettle_time = 2.0",
                "settle_time",
            ),
        ];
        for (from, to, field) in cases {
            assert!(text.contains(from), "{from}");
            let err = config::parse::<MissionPlan>(&text.replace(from, to), &path).unwrap_err();
            let message = err.to_string();
            assert!(
                message.contains(field) && message.contains("mission.toml"),
                "{field}: {message}"
            );
        }
    }

    #[test]
    fn the_plan_lifts_drives_the_distance_and_comes_back_down() {
        let plan = MissionPlan::shipped().unwrap();
        let dt = 0.02;
        let steps = (plan.duration_s() / dt) as usize;
        let distance: f64 = (0..steps).map(|k| plan.at(k as f64 * dt).2 * dt).sum();
        assert!((distance - plan.distance_m).abs() < 0.01, "{distance}");
        let (phase, lift, _) = plan.at(plan.schedule()[1] + 0.1);
        assert_eq!((phase, lift), (Phase::Lift, plan.lift_height_m));
        assert_eq!(plan.at(plan.duration_s()).1, -plan.place_press_m);
        assert_eq!(min_jerk(0.5), 0.5);
        assert!((plan.travelled_m(plan.duration_s()) - plan.distance_m).abs() < 1e-9);
        let mid = plan.schedule()[2] + plan.drive_s() / 2.0;
        let numeric: f64 = (0..100_000)
            .map(|k| plan.at(k as f64 * mid / 1e5).2 * mid / 1e5)
            .sum();
        assert!((plan.travelled_m(mid) - numeric).abs() < 1e-3);
    }
}
