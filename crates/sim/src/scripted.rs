//! The simulator's scripted mission: [`MissionPlan`] (core) scheduled in time, tracked with IK
//! on the simulator's readout. It proves the physics before any learning and drives the
//! stability tests and `moonhaul sim demo`; see [`moonhaul_core::scripted`] for the plan, the
//! tracking law, and the same controller as a controller of the deployed stack.

use moonhaul_core::se3::rotation_angle;
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand, ARM_JOINTS};
use nalgebra::{Isometry3, Vector3};

use crate::ik::{self, IkSettings};
use crate::scene::{Env, EnvState, SceneModel, UNITS};
use crate::SimError;

pub use moonhaul_core::scripted::MissionPlan;

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
            )
            .map_err(|e| SimError::Kinematics(e.to_string()))?;
            // Bases steer only while transporting; otherwise their wheels hold still.
            let wheels = if phase == Phase::Transport {
                self.plan.track(
                    &scene.spec,
                    &self.base_start[i],
                    &state.units[i].state.base_pose,
                    travelled_m,
                    speed_mps,
                    self.plan.speed_mps,
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
