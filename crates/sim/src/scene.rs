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
//! joints with velocity motors, seven arm joints with position motors, limits, URDF effort
//! limits and damping). The payload is a free rigid body. Each grasp is an impulse fixed joint
//! between an end effector and the payload, made at reset from the actual relative pose and
//! removed on release or when its wrench exceeds the configured limit. Only wheels, casters,
//! the payload and the ground collide.

use std::collections::HashMap;

use moonhaul_core::kinematics::Chain;
use moonhaul_core::state::{
    ArmJoints, PlanarPose, PlanarVelocity, UnitCommand, UnitState, WheelJoints, ARM_JOINTS,
    WHEEL_JOINTS,
};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rapier3d::parry::shape::HeightField;
use rapier3d::parry::utils::Array2;
use rapier3d::prelude::*;

use crate::config::SimConfig;
use crate::convert::{from_vector, to_isometry, to_pose, to_vector};
use crate::ik::{self, IkSettings};
use crate::model::{RobotModel, Shape};
use crate::randomization::{CommandNoise, EpisodeDraw, PayloadKind, Randomization};
use crate::SimError;

/// Number of wheel–arm units in the formation.
pub const UNITS: usize = 2;

/// Link and joint names the simulator expects in `unit.urdf`.
const BASE_LINK: &str = "base_link";
const EE_LINK: &str = "ee";
const WHEEL_JOINT_NAMES: [&str; WHEEL_JOINTS] = ["wheel_left_joint", "wheel_right_joint"];
const ARM_JOINT_NAMES: [&str; ARM_JOINTS] = [
    "arm_joint_1",
    "arm_joint_2",
    "arm_joint_3",
    "arm_joint_4",
    "arm_joint_5",
    "arm_joint_6",
    "arm_joint_7",
];
/// Highest lift the grasp configuration must allow, m (the paper's largest lift target).
const MAX_LIFT_M: f64 = 0.75;
/// Steps in which the grasp configuration is tracked up the lift (5 mm each): small enough
/// that IK follows one branch, as the scripted controller will.
const LIFT_CHECKS: usize = 150;
/// Time the world settles at reset before the grasps close, s (not counted in episode time).
const SETTLE_S: f64 = 0.25;
/// Clearance at which bodies are spawned above the ground, m: they settle in the first steps.
const SPAWN_CLEARANCE_M: f64 = 0.002;

/// A payload's model and the grasp configuration found for it.
#[derive(Debug, Clone)]
pub struct PayloadModel {
    pub model: RobotModel,
    /// Half extents of its box, m.
    pub half_extents_m: Vector3<f64>,
    /// Arm joint positions that put the end effector on the payload's side face, at the height
    /// of the payload's centre when it rests on flat ground.
    pub grasp_q_rad: [f64; ARM_JOINTS],
}

/// Everything the worlds share: models, the arm chain, the grasp configurations. Built once.
#[derive(Debug, Clone)]
pub struct SceneModel {
    pub config: SimConfig,
    pub unit: RobotModel,
    /// Forward kinematics base_link → ee.
    pub arm_chain: Chain,
    pub payloads: HashMap<PayloadKind, PayloadModel>,
    wheel_bodies: [usize; WHEEL_JOINTS],
    arm_bodies: [usize; ARM_JOINTS],
    ee_body: usize,
    ee_offset: Isometry3<f64>,
    wheel_radius_m: f64,
    /// rapier pipeline steps per control step.
    pipeline_steps: usize,
    /// Integration steps per control step.
    decimation: usize,
}

/// The end-effector orientation of a grasp in the base frame: approach (z) along the base's
/// +Y toward the payload, paddle x pointing down.
fn grasp_rotation() -> UnitQuaternion<f64> {
    let x = Vector3::new(0.0, 0.0, -1.0);
    let z = Vector3::new(0.0, 1.0, 0.0);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(
        &[x, z.cross(&x), z],
    )))
}

impl SceneModel {
    /// Loads the unit and payload URDFs and solves the grasp configurations.
    pub fn new(config: SimConfig) -> Result<Self, SimError> {
        config.validate()?;
        let unit = RobotModel::from_file(config.unit_urdf())?;
        let arm_chain = unit
            .tree
            .chain(BASE_LINK, EE_LINK)
            .map_err(|e| SimError::Model {
                path: unit.path.clone(),
                reason: e.to_string(),
            })?;
        let mut wheel_bodies = [0; WHEEL_JOINTS];
        for (b, name) in wheel_bodies.iter_mut().zip(WHEEL_JOINT_NAMES) {
            *b = unit.joint_body(name)?;
        }
        let mut arm_bodies = [0; ARM_JOINTS];
        for (b, name) in arm_bodies.iter_mut().zip(ARM_JOINT_NAMES) {
            *b = unit.joint_body(name)?;
        }
        let (ee_body, ee_offset) = unit.link_frame(EE_LINK)?;
        let wheel_radius_m = unit.bodies[wheel_bodies[0]]
            .colliders
            .iter()
            .find_map(|c| match c.shape {
                Shape::Ball { radius_m } => Some(radius_m),
                Shape::Cuboid { .. } => None,
            })
            .ok_or_else(|| SimError::Model {
                path: unit.path.clone(),
                reason: "wheel has no sphere collider".into(),
            })?;
        let mut scene = SceneModel {
            pipeline_steps: config.physics.pipeline_steps_per_control()?,
            decimation: config.physics.decimation()?,
            config,
            unit,
            arm_chain,
            payloads: HashMap::new(),
            wheel_bodies,
            arm_bodies,
            ee_body,
            ee_offset,
            wheel_radius_m,
        };
        for kind in PayloadKind::ALL {
            let path = scene
                .config
                .scene
                .assets_dir
                .join(format!("payload_{}.urdf", kind.name()));
            let model = RobotModel::from_file(&path)?;
            let half_extents_m = match model.bodies[0].colliders.first().map(|c| c.shape) {
                Some(Shape::Cuboid { half_extents_m }) => half_extents_m,
                _ => {
                    return Err(SimError::Model {
                        path,
                        reason: "payload needs one box collider".into(),
                    })
                }
            };
            let grasp_q_rad = scene.solve_grasp(&half_extents_m)?;
            scene.payloads.insert(
                kind,
                PayloadModel {
                    model,
                    half_extents_m,
                    grasp_q_rad,
                },
            );
        }
        Ok(scene)
    }

    /// The end-effector pose in the base frame that grasps a resting payload of these half
    /// extents, raised by `lift_m`.
    pub fn grasp_target(&self, half_extents_m: &Vector3<f64>, lift_m: f64) -> Isometry3<f64> {
        let z = half_extents_m.z - self.wheel_radius_m + lift_m;
        Isometry3::from_parts(
            Translation3::new(0.0, self.config.scene.reach_m, z),
            grasp_rotation(),
        )
    }

    /// IK from a small set of elbow-up/elbow-down seeds. A seed's solution is followed up
    /// the whole lift range (the paper's targets reach [`MAX_LIFT_M`]); the configuration
    /// that lifts farthest, then stays farthest from its joint limits, wins.
    fn solve_grasp(&self, half_extents_m: &Vector3<f64>) -> Result<[f64; ARM_JOINTS], SimError> {
        let limits: Vec<_> = self.arm_chain.limits().copied().collect();
        let margin = |q: &[f64; ARM_JOINTS]| {
            q.iter()
                .zip(&limits)
                .map(|(q, l)| (q - l.lower).min(l.upper - q) / (l.upper - l.lower))
                .fold(f64::INFINITY, f64::min)
        };
        let settings = IkSettings::default();
        let mut best: Option<(usize, f64, [f64; ARM_JOINTS])> = None;
        let h = std::f64::consts::FRAC_PI_2;
        for seed in (0..16).map(|k| {
            let s = |bit: usize| if k & (1 << bit) == 0 { 1.0 } else { -1.0 };
            [h * s(0), 0.6 * s(1), 0.0, 1.4 * s(2), 0.0, 0.8 * s(3), 0.0]
        }) {
            let Ok(q0) = ik::solve(
                &self.arm_chain,
                &self.grasp_target(half_extents_m, 0.0),
                &seed,
                &settings,
            ) else {
                continue;
            };
            let (mut q, mut reached, mut worst) = (q0, 0, margin(&q0));
            for k in 1..=LIFT_CHECKS {
                let lift = MAX_LIFT_M * k as f64 / LIFT_CHECKS as f64;
                match ik::solve(
                    &self.arm_chain,
                    &self.grasp_target(half_extents_m, lift),
                    &q,
                    &settings,
                ) {
                    Ok(next) => (q, reached, worst) = (next, k, worst.min(margin(&next))),
                    Err(_) => break,
                }
            }
            if best.is_none_or(|(r, m, _)| (reached, worst) > (r, m)) {
                best = Some((reached, worst, q0));
            }
        }
        best.map(|(_, _, q)| q).ok_or_else(|| {
            SimError::Kinematics(format!(
                "no arm configuration reaches the grasp at {:?}",
                self.grasp_target(half_extents_m, 0.0)
                    .translation
                    .vector
                    .as_slice()
            ))
        })
    }

    /// Integration steps per control step.
    pub fn decimation(&self) -> usize {
        self.decimation
    }

    /// Half the distance between the wheels, m.
    pub fn wheel_half_track_m(&self) -> f64 {
        let y = |b: usize| {
            self.unit.bodies[b]
                .joint
                .as_ref()
                .map_or(0.0, |j| j.frame_in_parent.translation.y)
        };
        0.5 * (y(self.wheel_bodies[0]) - y(self.wheel_bodies[1])).abs()
    }

    /// Wheel radius, m (from the wheel's sphere collider).
    pub fn wheel_radius_m(&self) -> f64 {
        self.wheel_radius_m
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

/// Rapier handles of one unit.
#[derive(Debug, Clone)]
struct UnitHandles {
    /// Per model body.
    bodies: Vec<RigidBodyHandle>,
    wheels: [MultibodyJointHandle; WHEEL_JOINTS],
    arm: [MultibodyJointHandle; ARM_JOINTS],
}

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

/// How an env draws its episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvOptions {
    /// Domain randomization on (paper) or the nominal world.
    pub randomize: bool,
    /// Forces this payload instead of drawing one.
    pub payload: Option<PayloadKind>,
}

impl Default for EnvOptions {
    fn default() -> Self {
        EnvOptions {
            randomize: true,
            payload: None,
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
    payload_kind: PayloadKind,
    draw: EpisodeDraw,
    noise: CommandNoise,
    rng: ChaCha8Rng,
    options: EnvOptions,
    /// rapier pipeline steps since the episode started.
    pipeline_steps: u64,
}

fn ground_height(world: &PhysicsWorld, ground: ColliderHandle, x: f64, y: f64) -> f64 {
    let collider = &world.colliders[ground];
    let ray = Ray::new(
        Vector::new(x as f32, y as f32, 10.0),
        Vector::new(0.0, 0.0, -1.0),
    );
    collider
        .shape()
        .cast_ray(collider.position(), &ray, 20.0, true)
        .map_or(0.0, |toi| 10.0 - toi as f64)
}

impl Env {
    /// A world seeded with `seed`, reset to its first episode.
    pub fn new(scene: &SceneModel, seed: u64, options: EnvOptions) -> Result<Self, SimError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut env = Self::build(scene, &mut rng, options)?;
        env.rng = rng;
        Ok(env)
    }

    /// Starts a new episode, drawing from this env's own random stream.
    pub fn reset(&mut self, scene: &SceneModel) -> Result<(), SimError> {
        let mut rng = self.rng.clone();
        let mut env = Self::build(scene, &mut rng, self.options)?;
        env.rng = rng;
        *self = env;
        Ok(())
    }

    fn build(
        scene: &SceneModel,
        rng: &mut ChaCha8Rng,
        options: EnvOptions,
    ) -> Result<Self, SimError> {
        let config = &scene.config;
        let r = &config.randomization;
        let mut draw = if options.randomize {
            r.draw(rng)
        } else {
            r.nominal(options.payload.unwrap_or(r.payloads[0]))
        };
        if let Some(p) = options.payload {
            draw.payload = p;
        }
        let noise = if options.randomize {
            r.command_noise()
        } else {
            Randomization::noiseless()
        };
        let payload_model = &scene.payloads[&draw.payload];

        let mut world = PhysicsWorld::new();
        world.gravity = Vector::new(0.0, 0.0, config.physics.gravity_mps2 as f32);
        let p = &mut world.integration_parameters;
        let physics = &config.physics;
        p.dt = (1.0 / physics.collision_hz) as f32;
        p.num_solver_iterations = physics.substeps()?;
        p.num_internal_pgs_iterations = physics.num_internal_pgs_iterations;
        p.num_internal_stabilization_iterations = physics.num_internal_stabilization_iterations;
        // `length_unit` is 1 (metres), so the normalized distance is in metres.
        p.normalized_prediction_distance = physics.prediction_distance_m as f32;

        let ground =
            world.insert_collider(terrain_collider(config, draw.terrain.as_ref(), rng)?, None);

        let mut units = Vec::with_capacity(UNITS);
        let mut start_q = [[0.0; ARM_JOINTS]; UNITS];
        for (i, start) in start_q.iter_mut().enumerate() {
            let (y, yaw) = scene.base_pose(i, payload_model);
            let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
            // Rest the base on the higher of the ground points under its wheels.
            let ground_z = scene
                .wheel_bodies
                .iter()
                .filter_map(|&b| scene.unit.bodies[b].joint.as_ref())
                .map(|j| {
                    let at = rotation * j.frame_in_parent.translation.vector;
                    ground_height(&world, ground, at.x, y + at.y)
                })
                .fold(f64::NEG_INFINITY, f64::max);
            let base = Isometry3::from_parts(
                Translation3::new(0.0, y, ground_z + scene.wheel_radius_m + SPAWN_CLEARANCE_M),
                rotation,
            );
            let mut q = payload_model.grasp_q_rad;
            for (q, dq) in q.iter_mut().zip(draw.initial_joint_offset_rad[i]) {
                *q += dq;
            }
            *start = q;
            units.push(insert_unit(
                &mut world,
                scene,
                &base,
                &q,
                draw.wheel_friction,
            )?);
        }
        let units: [UnitHandles; UNITS] = units
            .try_into()
            .map_err(|_| SimError::Kinematics("unit count mismatch".into()))?;

        // Payload: level, at the origin, resting on the highest ground under its footprint.
        let he = payload_model.half_extents_m;
        let under = [
            (0.0, 0.0),
            (he.x, he.y),
            (he.x, -he.y),
            (-he.x, he.y),
            (-he.x, -he.y),
        ]
        .iter()
        .map(|&(x, y)| ground_height(&world, ground, x, y))
        .fold(f64::NEG_INFINITY, f64::max);
        let body = &payload_model.model.bodies[0];
        let inertia = body.inertia;
        let scale = draw.payload_mass_scale;
        let payload = world.insert_body(
            RigidBodyBuilder::dynamic()
                .can_sleep(false)
                .pose(to_pose(&Isometry3::translation(
                    0.0,
                    0.0,
                    under + he.z + SPAWN_CLEARANCE_M,
                )))
                .additional_mass_properties(MassProperties::with_inertia_matrix(
                    to_vector(&inertia.com_m),
                    (inertia.mass_kg * scale) as f32,
                    mat3(&(inertia.inertia_kgm2 * scale)),
                )),
        );
        let payload_collider = world.insert_collider(
            ColliderBuilder::cuboid(he.x as f32, he.y as f32, he.z as f32)
                .density(0.0)
                .friction(config.scene.payload_friction as f32)
                .friction_combine_rule(CoefficientCombineRule::Min),
            Some(payload),
        );

        let mut env = Env {
            world,
            units,
            payload,
            payload_collider,
            ground,
            grasps: [None; UNITS],
            grasp_state: [GraspState::default(); UNITS],
            grasp_broken: false,
            payload_kind: draw.payload,
            draw,
            noise,
            rng: ChaCha8Rng::seed_from_u64(0),
            options,
            pipeline_steps: 0,
        };
        // Everything drops the spawn clearance and settles on the terrain, arms holding their
        // start positions, before the grasps close: a grasp made in mid-air would take the
        // settling transient as a spike and could break at the first step.
        for (unit, q) in env.units.iter().zip(&start_q) {
            let hold = UnitCommand {
                arm_position_rad: *q,
                ..UnitCommand::default()
            };
            set_motors(
                &mut env.world,
                scene,
                unit,
                &hold,
                &[0.0; WHEEL_JOINTS],
                &[0.0; ARM_JOINTS],
            );
        }
        for _ in 0..(SETTLE_S * config.physics.collision_hz).round() as usize {
            env.world.step();
        }
        env.attach_grasps(scene);
        Ok(env)
    }

    /// Makes each grasp a fixed joint at the current end-effector–payload pose.
    fn attach_grasps(&mut self, scene: &SceneModel) {
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
        for (grasp, state) in self.grasps.iter_mut().zip(&mut self.grasp_state) {
            if let Some(h) = grasp.take() {
                self.world.remove_impulse_joint(h);
            }
            *state = GraspState::default();
        }
    }

    /// The payload of this episode.
    pub fn payload_kind(&self) -> PayloadKind {
        self.payload_kind
    }

    /// This episode's randomization draw.
    pub fn draw(&self) -> &EpisodeDraw {
        &self.draw
    }

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

    /// Reads each grasp's wrench from its joint impulses and breaks overloaded grasps.
    fn update_grasps(&mut self, scene: &SceneModel) {
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
                state.attached = false;
                self.grasp_broken = true;
            }
        }
    }

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

/// Sets one unit's motor targets: wheel velocities and arm positions plus noise, clamped to
/// the joints' velocity and position limits.
fn set_motors(
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

fn mat3(m: &Matrix3<f64>) -> rapier3d::math::Matrix {
    rapier3d::math::Matrix::from_cols_array(&[
        m[(0, 0)] as f32,
        m[(1, 0)] as f32,
        m[(2, 0)] as f32,
        m[(0, 1)] as f32,
        m[(1, 1)] as f32,
        m[(2, 1)] as f32,
        m[(0, 2)] as f32,
        m[(1, 2)] as f32,
        m[(2, 2)] as f32,
    ])
}

/// The ground: a heightfield (flat when `terrain` is `None`). parry's heightfields are Y-up
/// with rows along local z; the collider is turned by +90° about X so heights point along
/// world Z, which maps local z to world −Y: terrain rows (along +Y) are stored in reverse.
fn terrain_collider(
    config: &SimConfig,
    terrain: Option<&crate::terrain::TerrainRandomization>,
    rng: &mut ChaCha8Rng,
) -> Result<ColliderBuilder, SimError> {
    let s = &config.scene;
    let cells = (s.terrain_size_m / s.terrain_spacing_m).round() as usize + 1;
    let heights = match terrain {
        Some(t) => {
            t.sample(cells, s.terrain_spacing_m, rng)
                .map_err(|e| SimError::Config {
                    field: "randomization.terrain",
                    reason: e.to_string(),
                })?
                .heights_m
        }
        None => vec![0.0; cells * cells],
    };
    let mut data = vec![0.0f32; cells * cells];
    for row in 0..cells {
        for col in 0..cells {
            data[(cells - 1 - row) + col * cells] = heights[row * cells + col] as f32;
        }
    }
    let extent = ((cells - 1) as f64 * s.terrain_spacing_m) as f32;
    let shape = HeightField::new(
        Array2::new(cells, cells, data),
        Vector::new(extent, 1.0, extent),
    );
    let pose = Pose::from_parts(
        Vector::new(s.terrain_center_x_m as f32, 0.0, 0.0),
        Rotation::from_rotation_x(std::f32::consts::FRAC_PI_2),
    );
    Ok(ColliderBuilder::new(SharedShape::new(shape))
        .position(pose)
        .friction(1.0)
        .friction_combine_rule(CoefficientCombineRule::Min))
}

/// Inserts one unit as a multibody at `base` with arm joints at `arm_q`.
fn insert_unit(
    world: &mut PhysicsWorld,
    scene: &SceneModel,
    base: &Isometry3<f64>,
    arm_q: &[f64; ARM_JOINTS],
    wheel_friction: f64,
) -> Result<UnitHandles, SimError> {
    let model = &scene.unit;
    // Body poses at the initial configuration; wheels at 0 rad.
    let mut q_of_body = vec![0.0; model.bodies.len()];
    for (b, q) in scene.arm_bodies.iter().zip(arm_q) {
        q_of_body[*b] = *q;
    }
    let mut poses: Vec<Isometry3<f64>> = Vec::with_capacity(model.bodies.len());
    let mut handles = Vec::with_capacity(model.bodies.len());
    for (b, body) in model.bodies.iter().enumerate() {
        let pose = match &body.joint {
            None => *base,
            Some(j) => {
                poses[j.parent]
                    * j.frame_in_parent
                    * UnitQuaternion::from_axis_angle(&j.axis, q_of_body[b])
            }
        };
        poses.push(pose);
        let i = body.inertia;
        let h = world.insert_body(
            // Sleeping would freeze arms whose motor targets change while they are at rest.
            RigidBodyBuilder::dynamic()
                .can_sleep(false)
                .pose(to_pose(&pose))
                .additional_mass_properties(MassProperties::with_inertia_matrix(
                    to_vector(&i.com_m),
                    i.mass_kg as f32,
                    mat3(&i.inertia_kgm2),
                )),
        );
        let is_wheel = scene.wheel_bodies.contains(&b);
        for c in &body.colliders {
            let builder = match c.shape {
                Shape::Ball { radius_m } => ColliderBuilder::ball(radius_m as f32),
                Shape::Cuboid { half_extents_m: e } => {
                    ColliderBuilder::cuboid(e.x as f32, e.y as f32, e.z as f32)
                }
            };
            // Wheels grip with the randomized μ; casters are frictionless support balls.
            let mu = if is_wheel { wheel_friction } else { 0.0 };
            world.insert_collider(
                builder
                    .position(to_pose(&c.pose))
                    .density(0.0)
                    .friction(mu as f32)
                    .friction_combine_rule(CoefficientCombineRule::Min),
                Some(h),
            );
        }
        handles.push(h);
    }
    let mut joint_handles = vec![None; model.bodies.len()];
    for (b, body) in model.bodies.iter().enumerate() {
        let Some(j) = &body.joint else { continue };
        // Joint frames map rapier's free axis (X) onto the URDF axis.
        let align = UnitQuaternion::rotation_between(&Vector3::x(), &j.axis).unwrap_or_else(|| {
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI)
        });
        let mut data = GenericJointBuilder::new(JointAxesMask::LOCKED_REVOLUTE_AXES)
            .local_frame1(to_pose(&(j.frame_in_parent * align)))
            .local_frame2(to_pose(&Isometry3::from_parts(
                Translation3::identity(),
                align,
            )))
            .motor_max_force(JointAxis::AngX, j.limits.effort as f32)
            .build();
        if scene.wheel_bodies.contains(&b) {
            data.set_motor_model(JointAxis::AngX, MotorModel::ForceBased);
        }
        if j.limits.lower.is_finite() && j.limits.upper.is_finite() {
            data.set_limits(
                JointAxis::AngX,
                [j.limits.lower as f32, j.limits.upper as f32],
            );
        }
        let h = world
            .insert_multibody_joint(handles[j.parent], handles[b], data)
            .ok_or_else(|| SimError::Model {
                path: model.path.clone(),
                reason: format!("joint {:?} would close a kinematic loop", j.name),
            })?;
        joint_handles[b] = Some(h);
    }
    // Initial joint coordinates and URDF damping, per generalized coordinate.
    let mut per_dof = Vec::with_capacity(model.bodies.len());
    for (b, body) in model.bodies.iter().enumerate() {
        if let (Some(j), Some(h)) = (&body.joint, joint_handles[b]) {
            if let Some((mb, id)) = world.multibody_joints.get(h) {
                let dof = mb.link(id).map_or(0, |l| l.assembly_id());
                per_dof.push((dof, q_of_body[b] as f32, j.damping as f32));
            }
        }
    }
    let root = model
        .bodies
        .iter()
        .position(|b| b.joint.is_some())
        .and_then(|b| joint_handles[b]);
    if let Some((mb, _)) = root.and_then(|h| world.multibody_joints.get_mut(h)) {
        let mut disp = vec![0.0f32; mb.ndofs()];
        // The free root's six coordinates come first; its default damping would slow the base.
        mb.damping_mut().rows_mut(0, 6).fill(0.0);
        for &(dof, q, damping) in &per_dof {
            disp[dof] = q;
            mb.damping_mut()[dof] = damping;
        }
        mb.apply_displacements(&disp);
        mb.forward_kinematics(&world.bodies, true);
        mb.update_rigid_bodies(&mut world.bodies, true);
    }
    let handle = |b: usize| {
        joint_handles[b].ok_or_else(|| SimError::Model {
            path: model.path.clone(),
            reason: format!("body {:?} has no joint", model.bodies[b].link),
        })
    };
    let mut wheels = [MultibodyJointHandle::invalid(); WHEEL_JOINTS];
    for (w, b) in wheels.iter_mut().zip(scene.wheel_bodies) {
        *w = handle(b)?;
    }
    let mut arm = [MultibodyJointHandle::invalid(); ARM_JOINTS];
    for (a, b) in arm.iter_mut().zip(scene.arm_bodies) {
        *a = handle(b)?;
    }
    Ok(UnitHandles {
        bodies: handles,
        wheels,
        arm,
    })
}
