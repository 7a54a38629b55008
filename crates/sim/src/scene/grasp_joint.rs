//! The grasps at run time: fixed joints made at reset, measured every substep, broken on
//! overload or released on placement.

use rapier3d::prelude::*;

use super::{Env, SceneModel};
use crate::convert::to_pose;

/// One grasp's state.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GraspState {
    /// Whether the fixed joint exists.
    pub attached: bool,
    /// Magnitude of the joint's force at the last substep, N.
    pub force_n: f64,
    /// Magnitude of the joint's torque at the last substep, N·m.
    pub torque_nm: f64,
}

impl Env {
    /// Makes each grasp a fixed joint at the current end-effector–payload pose.
    pub(super) fn attach_grasps(&mut self, scene: &SceneModel) {
        let payload_pose = *self.world.bodies[self.payload].position();
        for (i, unit) in self.units.iter().enumerate() {
            let ee = unit.bodies[scene.ee_body];
            let ee_world = *self.world.bodies[ee].position() * to_pose(&scene.ee_offset);
            let joint = FixedJointBuilder::new()
                .local_frame1(to_pose(&scene.ee_offset))
                .local_frame2(payload_pose.inverse() * ee_world);
            self.grasps[i] = Some(self.world.insert_impulse_joint(ee, self.payload, joint));
            self.grasp_state[i] = GraspState {
                attached: true,
                ..Default::default()
            };
        }
    }

    /// Releases both grasps (placement).
    pub fn release_grasps(&mut self) {
        for unit in 0..self.grasps.len() {
            self.release_grasp(unit);
        }
    }

    /// Releases unit `unit`'s grasp (its gripper opened); a no-op when it holds nothing or
    /// there is no such unit.
    pub fn release_grasp(&mut self, unit: usize) {
        if let Some(h) = self.grasps.get_mut(unit).and_then(Option::take) {
            self.world.remove_impulse_joint(h);
        }
        if let Some(state) = self.grasp_state.get_mut(unit) {
            *state = GraspState::default();
        }
    }

    /// Reads each grasp's wrench from its joint impulses and breaks overloaded grasps.
    pub(super) fn update_grasps(&mut self, scene: &SceneModel) {
        let p = &self.world.integration_parameters;
        // rapier writes back the impulse of the last substep.
        let substep_dt = (p.dt / p.num_solver_iterations as f32) as f64;
        let limits = &scene.config.grasp;
        for (grasp, state) in self.grasps.iter_mut().zip(&mut self.grasp_state) {
            let Some(h) = *grasp else { continue };
            let Some(joint) = self.world.impulse_joints.get(h) else {
                continue;
            };
            let imp = joint.impulses;
            let norm = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
            state.force_n = norm(&imp[..3]) / substep_dt;
            state.torque_nm = norm(&imp[3..]) / substep_dt;
            if state.force_n > limits.break_force_n || state.torque_nm > limits.break_torque_nm {
                self.world.remove_impulse_joint(h);
                *grasp = None;
                // A broken grasp holds nothing: the wrist reads no load from now on (as a
                // released one), not the overload it broke at.
                *state = GraspState::default();
                self.grasp_broken = true;
            }
        }
    }
}
