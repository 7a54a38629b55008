//! World building: the rapier world of one episode (integration parameters, ground, the two
//! unit multibodies, the payload and its collider), settled and grasped at reset.
//!
//! **Settling.** Everything is spawned a little above the ground and settles for [`SETTLE_S`],
//! the arm drives holding their start joints, before the grasps close (a grasp made in mid-air
//! would take the settling transient as a spike). A ground start then begins: the payload
//! rests on the ground, the arms carry only themselves. A lifted start (transport, place) has
//! held the payload still in the air (kinematic, as a fixture would) while the unloaded arms
//! settled; once the grasps close it turns dynamic and the world settles for another
//! [`LOADED_SETTLE_S`] with the drives holding the start joints, so the episode begins from a
//! loaded grasp at rest, as after a real lift, not from the transient of the payload dropping
//! into the arms.

use moonhaul_core::state::{UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rapier3d::prelude::*;

use super::actuation::ArmDrive;
use super::ground::{ground_height, terrain_collider};
use super::{Env, EnvOptions, GraspState, SceneModel, UNITS};
use crate::convert::{to_pose, to_vector};
use crate::model::Shape;
use crate::randomization::Randomization;
use crate::SimError;

/// Time the world settles at reset before the grasps close, s (not counted in episode time):
/// the bases tip onto a caster (15 mm clearance, 3.4°) within about 0.4 s of being spawned
/// level; a grasp closed before that would hang a still-tipping base from the payload.
const SETTLE_S: f64 = 0.5;
/// Time a lifted start settles with the payload in the arms, s (not counted in episode time):
/// the arm drives' integral terms take up the load within about half of it (with the shipped
/// `[motors]`), the rest lets the payload come to rest.
const LOADED_SETTLE_S: f64 = 1.0;
/// Clearance at which bodies are spawned above the ground, m: they settle in the first steps.
const SPAWN_CLEARANCE_M: f64 = 0.002;

/// Rapier handles of one unit.
#[derive(Debug, Clone)]
pub(super) struct UnitHandles {
    /// Per model body.
    pub(super) bodies: Vec<RigidBodyHandle>,
    pub(super) wheels: [MultibodyJointHandle; WHEEL_JOINTS],
    pub(super) arm: [MultibodyJointHandle; ARM_JOINTS],
}

impl Env {
    /// A world seeded with `seed`, reset to its first episode.
    pub fn new(scene: &SceneModel, seed: u64, options: EnvOptions) -> Result<Self, SimError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut env = Self::build(scene, &mut rng, options)?;
        env.rng = rng;
        Ok(env)
    }

    /// Starts a new episode by restoring the world as it was built: settled, grasped, at
    /// time zero. Costs a copy of rapier's sets instead of a rebuild (terrain, IK, 0.25 s of
    /// settling), so a reset is cheaper than a control step.
    ///
    /// The world-level draws — terrain, wheel friction, payload kind and mass, initial joint
    /// offsets — are therefore made once per env, when it is built (Isaac Lab's `startup`
    /// randomization events); a batch of N envs trains on N different worlds and
    /// [`crate::BatchEnv::reseed`] draws N new ones. What varies per episode is drawn by the
    /// task (goals) and every step (command noise, from this env's stream, which a reset
    /// does not rewind).
    pub fn reset(&mut self) {
        let t = &*self.template;
        let w = &mut self.world;
        w.islands.clone_from(&t.islands);
        w.broad_phase.clone_from(&t.broad_phase);
        w.narrow_phase.clone_from(&t.narrow_phase);
        w.bodies.clone_from(&t.bodies);
        w.colliders.clone_from(&t.colliders);
        w.impulse_joints.clone_from(&t.impulse_joints);
        w.multibody_joints.clone_from(&t.multibody_joints);
        self.drives = t.drives;
        self.grasps = t.grasps;
        self.grasp_state = t.grasp_state;
        self.grasp_broken = false;
        self.pipeline_steps = 0;
    }

    /// Makes the world as it is now the one [`Env::reset`] restores, at time zero (a
    /// hand-over start, [`crate::handover`]).
    pub(crate) fn rebase(&mut self) {
        self.pipeline_steps = 0;
        *self.template = Template::of(self);
    }

    /// Runs the drives on `hold` without noise for `seconds` (rounded to control periods).
    fn settle(&mut self, scene: &SceneModel, hold: &[UnitCommand; UNITS], seconds: f64) {
        let noiseless = [([0.0; WHEEL_JOINTS], [0.0; ARM_JOINTS]); UNITS];
        for _ in 0..(seconds * scene.config.control_hz).round() as usize {
            self.control_step(scene, hold, &noiseless);
        }
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
        let payload_model = scene.payload(draw.payload)?;

        let mut world = PhysicsWorld::new();
        world.gravity = Vector::new(0.0, 0.0, config.physics.gravity_mps2 as f32);
        let p = &mut world.integration_parameters;
        let physics = &config.physics;
        p.dt = (1.0 / physics.collision_hz) as f32;
        p.num_solver_iterations = config.substeps();
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
                Translation3::new(
                    0.0,
                    y,
                    ground_z + scene.spec.base_height_m + SPAWN_CLEARANCE_M,
                ),
                rotation,
            );
            let mut q = payload_model.lift_q(options.start_lift_m);
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
        // A lifted start holds the payload still (kinematic) while the arms settle onto it, as
        // a fixture would; it turns dynamic once the grasps hold it.
        let lifted = options.start_lift_m > 0.0;
        let payload_builder = if lifted {
            RigidBodyBuilder::kinematic_position_based()
        } else {
            RigidBodyBuilder::dynamic()
        };
        let payload = world.insert_body(
            payload_builder
                .can_sleep(false)
                .pose(to_pose(&Isometry3::translation(
                    0.0,
                    0.0,
                    // Where the arms' start joints hold it: the lift path ends at the arm's
                    // reach, which for some payloads is below the asked-for lift.
                    under
                        + he.z
                        + SPAWN_CLEARANCE_M
                        + options.start_lift_m.min(payload_model.max_lift_m()),
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
            drives: start_q.map(|q| ArmDrive::holding(&q)),
            payload_kind: draw.payload,
            draw,
            noise,
            rng: ChaCha8Rng::seed_from_u64(0),
            pipeline_steps: 0,
            template: Box::default(),
        };
        // Everything drops the spawn clearance and settles on the terrain (module docs).
        let hold = start_q.map(|q| UnitCommand {
            arm_position_rad: q,
            ..UnitCommand::default()
        });
        env.settle(scene, &hold, SETTLE_S);
        env.attach_grasps(scene);
        if lifted {
            if let Some(rb) = env.world.bodies.get_mut(env.payload) {
                rb.set_body_type(RigidBodyType::Dynamic, true);
            }
            env.settle(scene, &hold, LOADED_SETTLE_S);
        }
        // The episode starts now.
        env.pipeline_steps = 0;
        env.template = Box::new(Template::of(&env));
        Ok(env)
    }
}

/// What [`Env::reset`] restores: the rapier data of the world as built, and its grasps. The
/// heightfield is shared with the live world (rapier's shapes are reference counted); the
/// pipelines are scratch space and stay with the world. Soft bodies and CCD are not used.
#[derive(Clone, Default)]
pub(super) struct Template {
    islands: IslandManager,
    broad_phase: DefaultBroadPhase,
    narrow_phase: NarrowPhase,
    bodies: RigidBodySet,
    colliders: ColliderSet,
    impulse_joints: ImpulseJointSet,
    multibody_joints: MultibodyJointSet,
    drives: [ArmDrive; UNITS],
    grasps: [Option<ImpulseJointHandle>; UNITS],
    grasp_state: [GraspState; UNITS],
}

impl Template {
    fn of(env: &Env) -> Self {
        let w = &env.world;
        Template {
            islands: w.islands.clone(),
            broad_phase: w.broad_phase.clone(),
            narrow_phase: w.narrow_phase.clone(),
            bodies: w.bodies.clone(),
            colliders: w.colliders.clone(),
            impulse_joints: w.impulse_joints.clone(),
            multibody_joints: w.multibody_joints.clone(),
            drives: env.drives,
            grasps: env.grasps,
            grasp_state: env.grasp_state,
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
        // Every drive is force-based: gains in N·m per rad (arms) or per rad/s (wheels).
        if scene.wheel_bodies.contains(&b) || scene.arm_bodies.contains(&b) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SimConfig;

    /// The unit's joint-space inertia as rapier (with vendor/rapier3d's mass-matrix patch)
    /// assembles it, against MuJoCo 4.0's on the same URDF: `1/(M⁻¹)ᵢᵢ` of each arm DoF at the
    /// grasp configuration, free base included, payload not (`mj_solveM`, printed by
    /// `../shared/bench/mujoco/mj_behave.py` for unit 0, kg·m²).
    #[test]
    fn arm_inertia_matches_mujoco() {
        const MUJOCO_M_EFF: [f64; ARM_JOINTS] =
            [0.6635, 1.0127, 0.2499, 0.3147, 0.0247, 0.0215, 0.0020];
        let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
        let options = EnvOptions {
            randomize: false,
            ..EnvOptions::default()
        };
        let mut env = Env::new(&scene, 0, options).unwrap();
        let world = &mut env.world;
        let (multibody, _) = world.multibody_joints.get_mut(env.units[0].arm[0]).unwrap();
        let inverse = multibody.dof_inverse_inertia(&world.bodies);
        let multibody = &world.multibody_joints.get(env.units[0].arm[0]).unwrap().0;
        for (j, (&handle, mujoco)) in env.units[0].arm.iter().zip(MUJOCO_M_EFF).enumerate() {
            let link = world.multibody_joints.get(handle).unwrap().1;
            let dof = multibody.link(link).unwrap().assembly_id();
            let m_eff = 1.0 / inverse[dof] as f64;
            let error = (m_eff - mujoco).abs() / mujoco;
            assert!(
                error < 0.02,
                "arm joint {}: rapier {m_eff:.4} kg m², MuJoCo {mujoco:.4}",
                j + 1
            );
        }
    }
}
