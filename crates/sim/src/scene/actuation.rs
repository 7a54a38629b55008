//! Actuation: both units' commands, plus the episode's command noise, applied to the wheel
//! velocity motors and arm position motors, clamped to the joints' limits.

use moonhaul_core::state::{UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use rapier3d::prelude::*;

use super::world::UnitHandles;
use super::{Env, SceneModel, UNITS};

impl Env {
    /// Applies both units' commands (plus this episode's command noise) and advances one
    /// control period.
    pub fn step(&mut self, scene: &SceneModel, commands: &[UnitCommand; UNITS]) {
        for (unit, command) in self.units.iter().zip(commands) {
            let (wheel_noise, arm_noise) = self.noise.sample(&mut self.rng);
            set_motors(
                &mut self.world,
                scene,
                unit,
                command,
                &wheel_noise,
                &arm_noise,
            );
        }
        for _ in 0..scene.pipeline_steps {
            self.world.step();
            self.pipeline_steps += 1;
            self.update_grasps(scene);
        }
    }
}

/// Sets one unit's motor targets: wheel velocities and arm positions plus noise, clamped to
/// the joints' velocity and position limits.
pub(super) fn set_motors(
    world: &mut PhysicsWorld,
    scene: &SceneModel,
    unit: &UnitHandles,
    command: &UnitCommand,
    wheel_noise: &[f64; WHEEL_JOINTS],
    arm_noise: &[f64; ARM_JOINTS],
) {
    let m = &scene.config.motors;
    for ((h, b), (w, dw)) in unit
        .wheels
        .iter()
        .zip(scene.wheel_bodies)
        .zip(command.wheel_velocity_radps.iter().zip(wheel_noise))
    {
        let limit = scene.unit.bodies[b]
            .joint
            .as_ref()
            .map_or(0.0, |j| j.limits.velocity);
        let target = (w + dw).clamp(-limit, limit) as f32;
        if let Some(link) = world
            .multibody_joints
            .get_mut(*h)
            .and_then(|(mb, id)| mb.link_mut(id))
        {
            link.joint.data.set_motor_velocity(
                JointAxis::AngX,
                target,
                m.wheel_gain_nms_per_rad as f32,
            );
        }
    }
    for ((h, b), (q, dq)) in unit
        .arm
        .iter()
        .zip(scene.arm_bodies)
        .zip(command.arm_position_rad.iter().zip(arm_noise))
    {
        let (lo, hi) = scene.unit.bodies[b]
            .joint
            .as_ref()
            .map_or((0.0, 0.0), |j| (j.limits.lower, j.limits.upper));
        let target = (q + dq).clamp(lo, hi) as f32;
        if let Some(link) = world
            .multibody_joints
            .get_mut(*h)
            .and_then(|(mb, id)| mb.link_mut(id))
        {
            link.joint.data.set_motor_position(
                JointAxis::AngX,
                target,
                m.arm_stiffness_per_s2 as f32,
                m.arm_damping_per_s as f32,
            );
        }
    }
}
