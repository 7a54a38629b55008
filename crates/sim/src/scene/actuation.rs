//! Actuation: both units' commands, plus the episode's command noise, applied to the wheel
//! velocity motors and the arm drives, clamped to the joints' limits.
//!
//! **Arm drives** imitate a position-controlled arm joint as industrial and collaborative arms
//! run them (a CiA 402 servo in cyclic synchronous position mode with the arm controller's
//! gravity and load compensation, as Franka's or KUKA's configured load data): every control
//! cycle the drive gets a position set-point and holds it with
//!
//! - a spring–damper on the set-point of the stiffness a joint of its torque rating has
//!   (rapier's force-based motor, solved implicitly every substep; `[motors]`), the command
//!   clamped to the joint's limits;
//! - velocity feed-forward of the command's rate (q_cmd,k − q_cmd,k−1)/dt, clamped to the
//!   joint's velocity limit, so the damping acts on the velocity *error* and a moving set-point
//!   is tracked without the lag a damper on absolute velocity adds;
//! - **gravity feed-forward from the model**: each arm joint is given the torque that holds its
//!   own outboard links and, while the grasp is closed, its share of the payload's weight
//!   (half of the payload's mass, the load an operator configures, hanging at the end
//!   effector) — computed every cycle from the links' masses and centres of mass and the
//!   joint's axis, applied as equal and opposite torques on the joint's two bodies. The spring
//!   then only sees the disturbances (dynamics, uneven load share, the other arm), not the
//!   static load, so a held payload does not sag.
//!
//! Why not an integral term on the position error: two integrating servos in the closed chain
//! arm–payload–arm wind up against any disagreement of their set-points, and through the
//! bases' compliance on their wheels and casters that windup fed back into more disagreement
//! (the fine-step reference solver tipped the payload 30°+ with it). Feed-forward has no loop.
//! The command noise is added to the set-point, a disturbance the drive cannot tell from the
//! command. Wheels are plain velocity motors.

use moonhaul_core::state::{UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use nalgebra::Vector3;
use rapier3d::prelude::*;

use crate::convert::{from_vector, to_isometry, to_vector};

use super::world::UnitHandles;
use super::{Env, SceneModel, UNITS};

/// One unit's arm drives between control cycles: what a position servo keeps in its memory.
/// Restored at reset with the rest of the world.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct ArmDrive {
    /// The previous cycle's (limited) command per joint, for the velocity feed-forward, rad.
    last_command_rad: [f64; ARM_JOINTS],
}

impl ArmDrive {
    /// Drives that have held `q` (no motion).
    pub(super) fn holding(q: &[f64; ARM_JOINTS]) -> Self {
        ArmDrive {
            last_command_rad: *q,
        }
    }
}

/// One unit's command noise for one control cycle: wheel velocities (rad/s), arm positions
/// (rad).
pub(super) type Noise = ([f64; WHEEL_JOINTS], [f64; ARM_JOINTS]);

impl Env {
    /// Applies both units' commands (plus this episode's command noise) and advances one
    /// control period.
    pub fn step(&mut self, scene: &SceneModel, commands: &[UnitCommand; UNITS]) {
        // Unit by unit, wheels before arms: the order the noise stream has always been drawn.
        let mut noise = [([0.0; WHEEL_JOINTS], [0.0; ARM_JOINTS]); UNITS];
        for n in &mut noise {
            *n = self.noise.sample(&mut self.rng);
        }
        self.control_step(scene, commands, &noise);
    }

    /// One control period: both units' drives run one cycle with `commands` plus `noise`,
    /// then the world advances (grasps measured and broken as in any step).
    pub(super) fn control_step(
        &mut self,
        scene: &SceneModel,
        commands: &[UnitCommand; UNITS],
        noise: &[Noise; UNITS],
    ) {
        let share_n =
            self.payload_mass_kg(scene) * scene.config.physics.gravity_mps2.abs() / UNITS as f64;
        for (i, (((unit, drive), command), (wheel_noise, arm_noise))) in self
            .units
            .iter()
            .zip(&mut self.drives)
            .zip(commands)
            .zip(noise)
            .enumerate()
        {
            let load_n = if self.grasps[i].is_some() {
                share_n
            } else {
                0.0
            };
            gravity_feed_forward(&mut self.world, scene, unit, load_n);
            set_motors(
                &mut self.world,
                scene,
                unit,
                drive,
                command,
                wheel_noise,
                arm_noise,
            );
        }
        for _ in 0..scene.pipeline_steps {
            self.world.step();
            self.pipeline_steps += 1;
            self.update_grasps(scene);
        }
    }
}

/// The gravity feed-forward of one unit's arm drives (module docs) for this control cycle:
/// each arm joint's torque holding its outboard links and `load_n` (N, straight down) at the
/// end effector, as equal and opposite torques on the joint's child and parent bodies (a pure
/// joint torque). Replaces last cycle's.
fn gravity_feed_forward(
    world: &mut PhysicsWorld,
    scene: &SceneModel,
    unit: &UnitHandles,
    load_n: f64,
) {
    let g = Vector3::new(0.0, 0.0, scene.config.physics.gravity_mps2);
    for h in &unit.bodies {
        if let Some(rb) = world.bodies.get_mut(*h) {
            rb.reset_torques(false);
        }
    }
    let pose = |b: usize| {
        world
            .bodies
            .get(unit.bodies[b])
            .map(|rb| to_isometry(rb.position()))
    };
    let Some(ee) = pose(scene.ee_body).map(|p| (p * scene.ee_offset).translation.vector) else {
        return;
    };
    let mut torques = [(0, 0, Vector3::zeros()); ARM_JOINTS];
    for (j, &b) in scene.arm_bodies.iter().enumerate() {
        let (Some(joint), Some(parent_pose)) = (
            scene.unit.bodies[b].joint.as_ref(),
            scene.unit.bodies[b]
                .joint
                .as_ref()
                .and_then(|joint| pose(joint.parent)),
        ) else {
            continue;
        };
        let frame = parent_pose * joint.frame_in_parent;
        let (anchor, axis) = (
            frame.translation.vector,
            frame.rotation * joint.axis.into_inner(),
        );
        // The torque gravity and the load exert about the joint; the drive supplies the opposite.
        let mut gravity_nm = axis.dot(&(ee - anchor).cross(&Vector3::new(0.0, 0.0, -load_n)));
        for &k in &scene.arm_subtree[j] {
            if let Some(rb) = world.bodies.get(unit.bodies[k]) {
                let com = from_vector(rb.center_of_mass());
                gravity_nm += axis.dot(&(com - anchor).cross(&(g * f64::from(rb.mass()))));
            }
        }
        torques[j] = (b, joint.parent, axis * -gravity_nm);
    }
    for (child, parent, torque) in torques {
        let torque = to_vector(&torque);
        if let Some(rb) = world.bodies.get_mut(unit.bodies[child]) {
            rb.add_torque(torque, false);
        }
        if let Some(rb) = world.bodies.get_mut(unit.bodies[parent]) {
            rb.add_torque(-torque, false);
        }
    }
}

/// Runs one cycle of one unit's drives: wheel velocities plus noise, clamped to the velocity
/// limits; arm positions as set-points with velocity feed-forward (module docs), clamped to the
/// position limits.
fn set_motors(
    world: &mut PhysicsWorld,
    scene: &SceneModel,
    unit: &UnitHandles,
    drive: &mut ArmDrive,
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
    let dt = 1.0 / scene.config.control_hz;
    for (j, (h, b)) in unit.arm.iter().zip(scene.arm_bodies).enumerate() {
        let (lo, hi, v_max, effort) =
            scene.unit.bodies[b]
                .joint
                .as_ref()
                .map_or((0.0, 0.0, 0.0, 0.0), |j| {
                    (
                        j.limits.lower,
                        j.limits.upper,
                        j.limits.velocity,
                        j.limits.effort,
                    )
                });
        let Some(link) = world
            .multibody_joints
            .get_mut(*h)
            .and_then(|(mb, id)| mb.link_mut(id))
        else {
            continue;
        };
        let q_cmd = command.arm_position_rad[j].clamp(lo, hi);
        let target = (q_cmd + arm_noise[j]).clamp(lo, hi);
        let feed_forward = ((q_cmd - drive.last_command_rad[j]) / dt).clamp(-v_max, v_max);
        drive.last_command_rad[j] = q_cmd;
        link.joint.data.set_motor(
            JointAxis::AngX,
            target as f32,
            feed_forward as f32,
            (effort / m.arm_full_effort_error_rad) as f32,
            (effort / m.arm_full_effort_error_rad * m.arm_damping_time_s) as f32,
        );
    }
}
