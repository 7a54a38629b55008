//! Readout: what a task senses of one world at a control tick ([`EnvState`]).

use moonhaul_core::state::{ArmJoints, PlanarPose, PlanarVelocity, UnitState, WheelJoints};
use nalgebra::{Isometry3, Vector3};
use rapier3d::prelude::*;

use super::ground::ground_height;
use super::{Env, GraspState, SceneModel, UNITS};
use crate::convert::{from_vector, to_isometry};

/// One unit's readout.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct UnitReadout {
    pub state: UnitState,
    /// End-effector pose in the world frame.
    pub ee_pose: Isometry3<f64>,
    /// End-effector pose in the unit's base frame.
    pub ee_in_base: Isometry3<f64>,
    pub grasp: GraspState,
}

/// The payload's readout.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PayloadReadout {
    pub pose: Isometry3<f64>,
    pub linvel_mps: Vector3<f64>,
    pub angvel_radps: Vector3<f64>,
    /// Height of the box's bottom face centre above the ground straight below the payload,
    /// measured as if the box were level: 0 when resting on flat ground, m.
    pub height_m: f64,
    /// Angle between the payload's z axis and world up, rad.
    pub tilt_rad: f64,
    /// Whether the payload touches the ground.
    pub ground_contact: bool,
}

/// Everything a task reads from one world at a control tick.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EnvState {
    pub time_s: f64,
    pub units: [UnitReadout; UNITS],
    pub payload: PayloadReadout,
    /// Whether a grasp broke by overload during this episode.
    pub grasp_broken: bool,
}

impl EnvState {
    /// Whether every number is finite (a diverged simulation is not).
    pub fn is_finite(&self) -> bool {
        let iso = |p: &Isometry3<f64>| {
            p.translation
                .vector
                .iter()
                .chain(p.rotation.coords.iter())
                .all(|v| v.is_finite())
        };
        self.units.iter().all(|u| {
            iso(&u.ee_pose)
                && u.state
                    .arm
                    .position_rad
                    .iter()
                    .chain(&u.state.arm.velocity_radps)
                    .all(|v| v.is_finite())
                && u.state.wheels.velocity_radps.iter().all(|v| v.is_finite())
        }) && iso(&self.payload.pose)
            && self.payload.linvel_mps.iter().all(|v| v.is_finite())
            && self.payload.height_m.is_finite()
    }
}

impl Env {
    /// Reads the world into `out` (no allocation).
    pub fn state_into(&self, scene: &SceneModel, out: &mut EnvState) {
        let bodies = &self.world.bodies;
        out.time_s = self.pipeline_steps as f64 / scene.config.physics.collision_hz;
        out.grasp_broken = self.grasp_broken;
        for ((unit, readout), grasp) in self.units.iter().zip(&mut out.units).zip(&self.grasp_state)
        {
            let base_rb = &bodies[unit.bodies[0]];
            let base = to_isometry(base_rb.position());
            let heading = base.rotation * Vector3::x();
            let yaw_rad = heading.y.atan2(heading.x);
            let linvel = from_vector(base_rb.linvel());
            let planar = Vector3::new(heading.x, heading.y, 0.0).normalize();
            readout.state = UnitState {
                wheels: WheelJoints::default(),
                arm: ArmJoints::default(),
                base_pose: PlanarPose {
                    x_m: base.translation.x,
                    y_m: base.translation.y,
                    yaw_rad,
                },
                base_velocity: PlanarVelocity {
                    forward_mps: linvel.dot(&planar),
                    yaw_rate_radps: base_rb.angvel().z as f64,
                },
            };
            let joint = |h: &MultibodyJointHandle| {
                self.world
                    .multibody_joints
                    .get(*h)
                    .and_then(|(mb, id)| mb.link(id).map(|l| (mb, l)))
                    .map_or((0.0, 0.0), |(mb, l)| {
                        (l.joint.coords()[3] as f64, mb.joint_velocity(l)[0] as f64)
                    })
            };
            for (i, h) in unit.wheels.iter().enumerate() {
                (
                    readout.state.wheels.position_rad[i],
                    readout.state.wheels.velocity_radps[i],
                ) = joint(h);
            }
            for (i, h) in unit.arm.iter().enumerate() {
                (
                    readout.state.arm.position_rad[i],
                    readout.state.arm.velocity_radps[i],
                ) = joint(h);
            }
            readout.ee_pose =
                to_isometry(bodies[unit.bodies[scene.ee_body]].position()) * scene.ee_offset;
            readout.ee_in_base = base.inverse() * readout.ee_pose;
            readout.grasp = *grasp;
        }
        let rb = &bodies[self.payload];
        let pose = to_isometry(rb.position());
        let up = pose.rotation * Vector3::z();
        let he = scene.payloads[&self.payload_kind].half_extents_m;
        let ground = ground_height(
            &self.world,
            self.ground,
            pose.translation.x,
            pose.translation.y,
        );
        out.payload = PayloadReadout {
            pose,
            linvel_mps: from_vector(rb.linvel()),
            angvel_radps: from_vector(rb.angvel()),
            height_m: pose.translation.z - he.z - ground,
            tilt_rad: up.z.clamp(-1.0, 1.0).acos(),
            ground_contact: self
                .world
                .narrow_phase
                .contact_pair(self.ground, self.payload_collider)
                .is_some_and(|p| p.has_any_active_contact()),
        };
    }

    /// The current readout.
    pub fn state(&self, scene: &SceneModel) -> EnvState {
        let mut s = EnvState::default();
        self.state_into(scene, &mut s);
        s
    }
}
