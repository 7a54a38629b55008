//! One simulated world: two wheel–arm units rigidly grasping one payload on a heightfield.
//!
//! **Formation.** The payload sits at the origin, its long side along +X (the travel
//! direction). Unit 0 stands at y = −(w/2 + reach) heading +X, unit 1 at y = +(w/2 + reach)
//! heading −X: the formation is point-symmetric about the payload's vertical axis, so both arms
//! take the same joint configuration and share the load equally by construction. Both wheel
//! axles lie on one line (x = 0, along Y). A differential-drive base can only move along its
//! heading and turn about a point on its axle line; with collinear axles the rigidly coupled
//! Wheel₁–Arm₁–Cargo–Arm₂–Wheel₂ chain moves like one wide differential-drive vehicle: driving
//! both bases at the same ground speed translates the payload along X, and turning about any
//! point on the shared axle line is admissible for both bases at once. A formation with the
//! units in line (one ahead of the payload, one behind) could drive straight but could not turn
//! without dragging a base sideways against its wheels. Unit 1 faces −X, so its wheel
//! velocities are negated to move the payload toward +X.
//!
//! **Bodies.** Each unit is one reduced-coordinate rapier multibody (free base, two wheel
//! joints with velocity motors, seven arm joints with position servos that hold a load without
//! sag, limits, URDF effort limits and damping). The payload is a free rigid body. Each grasp is an impulse fixed joint
//! between an end effector and the payload, made at reset from the actual relative pose and
//! removed on release or when its wrench exceeds the configured limit. Only wheels, casters,
//! the payload and the ground collide.
//!
//! **Payloads.** A payload is a URDF with exactly one link, named `payload`, with a positive
//! mass and exactly one `<collision>`: a `<box>` centred on and aligned with the link frame
//! (no collision `<origin>` offset), its long side along x (size x ≥ size y), the direction
//! of travel; the units grasp its ±y faces at the height of its centre. The centre of mass
//! may be offset (`<inertial><origin>`). Core's reader checks the physical values (finite,
//! non-negative mass, a plausible inertia, positive sizes), and the grasp solver must find an
//! arm configuration that reaches the grasp; every violation is an error naming the file. The shipped
//! payloads are `assets/payload_<name>.urdf` ([`PayloadKind::ALL`]); any other file is loaded
//! with [`SceneModel::add_payload_file`] as [`PayloadKind::Custom`], one per scene, named by
//! its file stem ([`SceneModel::payload_name`]). A scene also generates the family of
//! `[randomization.generated_payloads]` ([`PayloadKind::Generated`], `gen<i>`), from URDF text
//! through the same checks.
//!
//! **Files.** This root holds the shared types ([`SceneModel`], [`Env`]); the private
//! submodules hold one concept each: `payload` loads and checks payload URDFs, `grasp` solves
//! the grasp configuration, `world` builds the rapier world at reset, `ground` is the terrain
//! heightfield, `grasp_joint` makes, measures and breaks the grasps, `actuation` runs the
//! drives (wheel velocity motors, arm position servos) on the commands, and `readout` reads the
//! world into an [`EnvState`].

mod actuation;
mod grasp;
mod grasp_joint;
mod ground;
mod payload;
mod readout;
mod world;

use std::collections::HashMap;

use moonhaul_core::config::Validate;
use moonhaul_core::kinematics::Chain;
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::{UnitSpec, EE_LINK};
use nalgebra::{Isometry3, Vector3};
use rand_chacha::ChaCha8Rng;
use rapier3d::prelude::*;

use crate::config::SimConfig;
use crate::model::{self, RobotModel};
use crate::randomization::{CommandNoise, EpisodeDraw, PayloadKind};
use crate::SimError;

pub use grasp_joint::GraspState;
pub use payload::PAYLOAD_LINK;
pub use readout::{EnvState, PayloadReadout, UnitReadout};

use world::UnitHandles;

/// Number of wheel–arm units in the formation.
pub const UNITS: usize = 2;

/// A payload's model and the grasp configuration found for it.
#[derive(Debug, Clone)]
pub struct PayloadModel {
    pub model: RobotModel,
    /// Half extents of its box, m.
    pub half_extents_m: Vector3<f64>,
    /// Arm joint positions that put the end effector on the payload's side face, at the height
    /// of the payload's centre when it rests on flat ground.
    pub grasp_q_rad: [f64; ARM_JOINTS],
    /// The grasp configuration followed up the lift: entry k at a lift of
    /// k·[`grasp::MAX_LIFT_M`]/[`grasp::LIFT_CHECKS`] (fewer entries if the arm cannot reach the
    /// top).
    lift_path_q_rad: Vec<[f64; ARM_JOINTS]>,
}

impl PayloadModel {
    /// The grasp configuration lifted by `lift_m` (clamped to the reachable path), linearly
    /// interpolated between the 5 mm steps of the IK path.
    pub fn lift_q(&self, lift_m: f64) -> [f64; ARM_JOINTS] {
        let step = grasp::MAX_LIFT_M / grasp::LIFT_CHECKS as f64;
        let last = self.lift_path_q_rad.len() - 1;
        let x = (lift_m / step).clamp(0.0, last as f64);
        let (k, frac) = (x.floor() as usize, x.fract());
        let (a, b) = (
            self.lift_path_q_rad[k],
            self.lift_path_q_rad[(k + 1).min(last)],
        );
        std::array::from_fn(|j| a[j] + (b[j] - a[j]) * frac)
    }

    /// The highest lift the arm configuration path reaches, m.
    pub fn max_lift_m(&self) -> f64 {
        (self.lift_path_q_rad.len() - 1) as f64 * grasp::MAX_LIFT_M / grasp::LIFT_CHECKS as f64
    }

    /// Per arm joint, the largest distance from the rest grasp along the lift path, rad.
    pub fn lift_envelope_rad(&self) -> [f64; ARM_JOINTS] {
        std::array::from_fn(|j| {
            self.lift_path_q_rad
                .iter()
                .map(|q| (q[j] - self.grasp_q_rad[j]).abs())
                .fold(0.0, f64::max)
        })
    }
}

/// Everything the worlds share: models, the arm chain, the grasp configurations. Built once.
#[derive(Debug, Clone)]
pub struct SceneModel {
    pub config: SimConfig,
    /// The unit as its URDF describes it: joint order, wheel geometry, arm chain, limits.
    pub spec: UnitSpec,
    pub unit: RobotModel,
    /// Forward kinematics base_link → ee.
    pub arm_chain: Chain,
    pub payloads: HashMap<PayloadKind, PayloadModel>,
    wheel_bodies: [usize; WHEEL_JOINTS],
    arm_bodies: [usize; ARM_JOINTS],
    /// Per arm joint, the bodies outboard of it (its own body included): what its drive's
    /// gravity feed-forward holds.
    arm_subtree: [Vec<usize>; ARM_JOINTS],
    ee_body: usize,
    ee_offset: Isometry3<f64>,
    /// rapier pipeline steps per control step.
    pipeline_steps: usize,
    /// Integration steps per control step.
    decimation: usize,
}

impl SceneModel {
    /// Loads the unit and the shipped payload URDFs and solves the grasp configurations.
    pub fn new(config: SimConfig) -> Result<Self, SimError> {
        config.validate()?;
        let unit_path = config.unit_urdf();
        // One read of the unit URDF serves the unit description and the rigid bodies.
        let robot = model::read_urdf(&unit_path)?;
        let spec = UnitSpec::from_robot(&robot).map_err(|e| SimError::Model {
            path: unit_path.clone(),
            reason: e.to_string(),
        })?;
        let unit = RobotModel::from_robot(&unit_path, &robot)?;
        let arm_chain = spec.arm.clone();
        let mut wheel_bodies = [0; WHEEL_JOINTS];
        for (b, name) in wheel_bodies.iter_mut().zip(&spec.wheel_joints) {
            *b = unit.joint_body(name)?;
        }
        let mut arm_bodies = [0; ARM_JOINTS];
        for (b, name) in arm_bodies.iter_mut().zip(&spec.arm_joints) {
            *b = unit.joint_body(name)?;
        }
        let (ee_body, ee_offset) = unit.link_frame(EE_LINK)?;
        let outboard = |root: usize, body: usize| {
            let mut b = body;
            loop {
                if b == root {
                    return true;
                }
                match &unit.bodies[b].joint {
                    Some(j) => b = j.parent,
                    None => return false,
                }
            }
        };
        let arm_subtree = arm_bodies.map(|root| {
            (0..unit.bodies.len())
                .filter(|&b| outboard(root, b))
                .collect::<Vec<_>>()
        });
        let mut scene = SceneModel {
            pipeline_steps: config.pipeline_steps_per_control(),
            decimation: config.decimation(),
            config,
            spec,
            unit,
            arm_chain,
            payloads: HashMap::new(),
            wheel_bodies,
            arm_bodies,
            arm_subtree,
            ee_body,
            ee_offset,
        };
        for kind in PayloadKind::ALL {
            let path = scene
                .config
                .scene
                .assets_dir
                .join(format!("payload_{}.urdf", kind.name()));
            let payload = scene.load_payload(&path)?;
            scene.payloads.insert(kind, payload);
        }
        scene.generate_payloads()?;
        Ok(scene)
    }

    /// Integration steps per control step.
    pub fn decimation(&self) -> usize {
        self.decimation
    }

    /// The base pose of unit `i` with the payload at the origin, before terrain.
    fn base_pose(&self, i: usize, payload: &PayloadModel) -> (f64, f64) {
        let y = payload.half_extents_m.y + self.config.scene.reach_m;
        if i == 0 {
            (-y, 0.0)
        } else {
            (y, std::f64::consts::PI)
        }
    }
}

/// How an env draws its episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvOptions {
    /// Domain randomization on (paper) or the nominal world.
    pub randomize: bool,
    /// Forces this payload instead of drawing one.
    pub payload: Option<PayloadKind>,
    /// Lift at which the episode starts, m: 0 grasps the payload resting on the ground; more
    /// starts it held aloft by that much (transport and place start lifted).
    pub start_lift_m: f64,
}

impl Default for EnvOptions {
    fn default() -> Self {
        EnvOptions {
            randomize: true,
            payload: None,
            start_lift_m: 0.0,
        }
    }
}

/// One simulated world.
pub struct Env {
    world: PhysicsWorld,
    units: [UnitHandles; UNITS],
    payload: RigidBodyHandle,
    payload_collider: ColliderHandle,
    ground: ColliderHandle,
    grasps: [Option<ImpulseJointHandle>; UNITS],
    grasp_state: [GraspState; UNITS],
    grasp_broken: bool,
    /// Each unit's arm-drive memory (last commands, for the velocity feed-forward).
    drives: [actuation::ArmDrive; UNITS],
    payload_kind: PayloadKind,
    draw: EpisodeDraw,
    noise: CommandNoise,
    rng: ChaCha8Rng,
    /// rapier pipeline steps since the episode started.
    pipeline_steps: u64,
    /// The world as built, restored at reset.
    template: Box<world::Template>,
}

impl Env {
    /// The payload of this episode.
    pub fn payload_kind(&self) -> PayloadKind {
        self.payload_kind
    }

    /// This episode's randomization draw.
    pub fn draw(&self) -> &EpisodeDraw {
        &self.draw
    }

    /// This episode's payload mass (its URDF mass times the drawn scale), kg.
    pub fn payload_mass_kg(&self, scene: &SceneModel) -> f64 {
        scene.payloads[&self.payload_kind].model.bodies[0]
            .inertia
            .mass_kg
            * self.draw.payload_mass_scale
    }
}
