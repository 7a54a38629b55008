//! A unit's actor observation o⁽ⁱ⁾ = [x⁽ⁱ⁾, Δxᶜ, Δx⁽ʲ⁾, goal] (paper, Observation Model): the one
//! function that both the training tasks (on the simulator's sensed readings) and the onboard
//! daemon (on HAL readings and decoded peer messages) call, so training and deployment see the
//! same vector by construction.
//!
//! It uses only what a unit knows onboard: its own encoders and wheel odometry, its peer's
//! published [`UnitState`], and forward kinematics of the rigid grasp. There is no cargo sensor
//! (the paper has none): the cargo is where the closed chain puts it, so the end effector's
//! displacement from where it grasped the payload at rest *is* the cargo's displacement, and
//! the peer's end effector (by its encoders and the shared module model) gives the neighbour's
//! side of the chain.
//!
//! **Actor shape.** One shared per-unit actor o⁽ⁱ⁾ → u⁽ⁱ⁾ ∈ ℝ⁹, the same weights on every unit
//! (parameter sharing), trained centrally with a critic that sees privileged state. Why not a
//! joint actor s → a ∈ ℝ¹⁸: onboard, unit i has only its own sensors and its peer's last message,
//! so a joint actor would have to be fed a reconstructed joint state and its other nine outputs
//! thrown away; a per-unit actor consumes exactly what deployment has, and the point-symmetric
//! formation makes both units' problems the same in their own frames, so one actor serves both
//! and sees twice the data. Every quantity is in the unit's own frames for that reason.
//!
//! **Frames.** "Base frame" is the unit's planar odometry frame: origin on the ground under the
//! base, x forward, z up. Poses from [`UnitState::base_pose`] are wheel odometry in the team's
//! shared world frame (all units start from known poses in it).
//!
//! **The policy sees what it commands** (layout 3). The action is an increment on U_{k−1}, so
//! whatever part of an increment the closed chain resists stays in U_{k−1} − Y as servo force;
//! a policy that cannot see it winds its command up against the chain (layout 2 held on half its
//! ticks and squeezed with twice the scripted grasp force). Layout 3 adds what a unit knows of
//! the commands and the pipeline ([`CommandState`]): its own U_{k−1} relative to its encoders, its
//! peer's published command relative to its published joints, the last t_max and whether the
//! pipeline held, and from the phase goal the phase's progress and the reference's offset (the
//! transport reference runs on a clock the goal alone does not show).
//!
//! **Layout** ([`OBS_LAYOUT_VERSION`], [`OBS_FIELDS`]): the policy file records both; a runtime
//! refuses a policy whose layout differs ([`check_layout`]).

use nalgebra::{Isometry3, UnitQuaternion, Vector2, Vector3};

use crate::kinematics::KinematicsError;
use crate::state::{PlanarPose, UnitCommand, UnitState, ARM_JOINTS, WHEEL_JOINTS};
use crate::unit::UnitSpec;

/// Version of the observation layout below; bump it with any change to the fields or their
/// meaning.
pub const OBS_LAYOUT_VERSION: u32 = 3;

/// The fields of o⁽ⁱ⁾ in order, with their widths.
pub const OBS_FIELDS: [(&str, usize); 19] = [
    // x⁽ⁱ⁾: own encoders, and the own command U_{k−1} (arm relative to the encoders).
    ("own.arm_position_rad", ARM_JOINTS),
    ("own.arm_velocity_radps", ARM_JOINTS),
    ("own.wheel_velocity_radps", WHEEL_JOINTS),
    ("own.arm_command_minus_sensed_rad", ARM_JOINTS),
    ("own.wheel_command_radps", WHEEL_JOINTS),
    // Δxᶜ: the cargo's displacement from its grasp at rest, by FK of the own arm.
    ("cargo.ee_displacement_m", 3),
    ("cargo.ee_rotation_rad", 3),
    // Δx⁽ʲ⁾: the neighbour, from its published state.
    ("peer.ee_displacement_m", 3),
    ("peer.ee_rotation_rad", 3),
    ("peer.base_offset", 3),
    ("peer.wheel_velocity_radps", WHEEL_JOINTS),
    ("peer.arm_command_minus_sensed_rad", ARM_JOINTS),
    ("peer.wheel_command_radps", WHEEL_JOINTS),
    // The action pipeline's last step.
    ("pipeline.last_t_max", 1),
    ("pipeline.last_held", 1),
    // The phase goal.
    ("goal.height_m", 1),
    ("goal.base", 4),
    ("goal.phase_progress", 1),
    ("goal.reference_offset_m", 2),
];

/// Length of o⁽ⁱ⁾.
pub const ACTOR_OBS_DIM: usize = {
    let mut n = 0;
    let mut i = 0;
    while i < OBS_FIELDS.len() {
        n += OBS_FIELDS[i].1;
        i += 1;
    }
    n
};

/// Where field `name` of [`OBS_FIELDS`] lies in o⁽ⁱ⁾ (for readers of an observation, such as
/// the phase gate's onboard estimates), or `None` for a name not in the layout.
pub fn field_range(name: &str) -> Option<std::ops::Range<usize>> {
    let mut start = 0;
    for (field, width) in OBS_FIELDS {
        if field == name {
            return Some(start..start + width);
        }
        start += width;
    }
    None
}

/// Where field `name` starts in o⁽ⁱ⁾, at compile time (a name not in the layout fails the
/// build where it is used in a constant).
const fn field_start(name: &str) -> usize {
    let mut start = 0;
    let mut i = 0;
    while i < OBS_FIELDS.len() {
        let (field, width) = OBS_FIELDS[i];
        if const_str_eq(field, name) {
            return start;
        }
        start += width;
        i += 1;
    }
    panic!("no such observation field");
}

const fn const_str_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    let mut i = 0;
    while i < a.len() {
        if a[i] != b[i] {
            return false;
        }
        i += 1;
    }
    true
}

const CARGO_DISPLACEMENT: usize = field_start("cargo.ee_displacement_m");
const PEER_DISPLACEMENT: usize = field_start("peer.ee_displacement_m");
const GOAL_BASE: usize = field_start("goal.base");

/// Typed reads of the fields of o⁽ⁱ⁾ that onboard estimates and evaluation use.
#[derive(Debug, Clone, Copy)]
pub struct ObservationView<'a>(pub &'a [f64; ACTOR_OBS_DIM]);

impl ObservationView<'_> {
    /// The cargo's lift by FK of the own arm since the rest grasp (z of Δxᶜ), m.
    pub fn cargo_lift_m(&self) -> f64 {
        self.0[CARGO_DISPLACEMENT + 2]
    }

    /// The same lift by FK of the peer's arm from its published joints, m.
    pub fn peer_cargo_lift_m(&self) -> f64 {
        self.0[PEER_DISPLACEMENT + 2]
    }

    /// The onboard payload-height estimate: the mean of both arms' FK lift, m.
    pub fn lift_estimate_m(&self) -> f64 {
        0.5 * (self.cargo_lift_m() + self.peer_cargo_lift_m())
    }

    /// The base goal relative to the own base, in the base frame (x forward), m.
    pub fn goal_offset_m(&self) -> [f64; 2] {
        [self.0[GOAL_BASE], self.0[GOAL_BASE + 1]]
    }
}

/// Metadata key of the layout version in a policy file.
pub const LAYOUT_VERSION_KEY: &str = "obs_layout_version";
/// Metadata key of the field list in a policy file.
pub const LAYOUT_FIELDS_KEY: &str = "obs_fields";

/// The field list as a policy file records it: `name:width` joined by commas.
pub fn layout_fields() -> String {
    OBS_FIELDS
        .iter()
        .map(|(name, width)| format!("{name}:{width}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// A policy's recorded layout differs from the one this build computes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("policy observation layout {found} does not match this build's {expected}")]
pub struct LayoutMismatch {
    pub expected: String,
    pub found: String,
}

/// Checks a policy's `obs_layout_version` and `obs_fields` metadata against this build.
pub fn check_layout(
    extra: &std::collections::BTreeMap<String, String>,
) -> Result<(), LayoutMismatch> {
    let describe = |v: Option<&str>, f: Option<&str>| {
        format!(
            "version {} [{}]",
            v.unwrap_or("<missing>"),
            f.unwrap_or("<missing>")
        )
    };
    let version = extra.get(LAYOUT_VERSION_KEY).map(String::as_str);
    let fields = extra.get(LAYOUT_FIELDS_KEY).map(String::as_str);
    let expected_fields = layout_fields();
    let expected_version = OBS_LAYOUT_VERSION.to_string();
    if version == Some(expected_version.as_str()) && fields == Some(expected_fields.as_str()) {
        Ok(())
    } else {
        let mut found = describe(version, fields);
        crate::input::clip_for_message(&mut found, 200);
        Err(LayoutMismatch {
            expected: describe(Some(&expected_version), Some(&expected_fields)),
            found,
        })
    }
}

/// What a unit records when the grasp closes on the payload at rest, the origin of Δxᶜ and
/// Δx⁽ʲ⁾: its own and its peer's end-effector poses (each in its own base frame) and the peer's
/// base pose. Each arm's displacement is measured from its own rest pose, so both units compute
/// the same cargo lift from the same joints (layout version 2; version 1 measured the peer
/// from the own rest pose, which put the two units' estimates apart by their arms' difference
/// at rest, a centimetre with the randomized initial joints, and split the phase gate).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GraspReference {
    /// The end-effector pose in the base frame at the rest grasp.
    pub ee_rest_in_base: Isometry3<f64>,
    /// The peer's end-effector pose in its own base frame at the rest grasp (from its
    /// published joints).
    pub peer_ee_rest_in_base: Isometry3<f64>,
    /// The peer's base pose in the own base frame at the rest grasp.
    pub peer_base_rest: PlanarPose,
}

impl GraspReference {
    /// The reference of the current state: own arm by FK, peer base by both odometries.
    pub fn capture(
        spec: &UnitSpec,
        own: &UnitState,
        peer: &UnitState,
    ) -> Result<Self, KinematicsError> {
        Ok(GraspReference {
            ee_rest_in_base: ee_in_base(spec, &own.arm.position_rad)?,
            peer_ee_rest_in_base: ee_in_base(spec, &peer.arm.position_rad)?,
            peer_base_rest: relative_pose(&own.base_pose, &peer.base_pose),
        })
    }
}

/// The phase goal in the team's world frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PhaseGoal {
    /// Target payload height h* above the ground, m (0 when placing).
    pub height_m: f64,
    /// Where this unit's base should end up, world frame, m (its current position when the
    /// phase has no travel).
    pub base_goal_m: Vector2<f64>,
    /// The commanded payload velocity now, world frame, m/s.
    pub velocity_mps: Vector2<f64>,
    /// Where this unit's base should be now on the phase's reference (the transport profile's
    /// point; the base goal in the other phases), world frame, m.
    pub reference_m: Vector2<f64>,
    /// Time since the phase began over the phase's episode length, clamped to [0, 1].
    pub progress: f64,
}

/// What a unit knows of the commands and of its action pipeline, besides its sensors
/// (observation layout 3).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CommandState {
    /// U_{k−1}: the command this unit issued last tick.
    pub own: UnitCommand,
    /// The command the peer published with its last state.
    pub peer: UnitCommand,
    /// t_max of the pipeline's last step (0 when it held).
    pub last_t_max: f64,
    /// Whether the pipeline's last step was a hold (requested, or no admissible step).
    pub last_held: bool,
}

impl CommandState {
    /// The state before any step of a phase was issued: both units at `own` and `peer`, after
    /// a hold (a phase always begins after the gate's hold in Idle or a transition).
    pub fn after_hold(own: UnitCommand, peer: UnitCommand) -> Self {
        CommandState {
            own,
            peer,
            last_t_max: 0.0,
            last_held: true,
        }
    }
}

/// The end-effector pose in the base (odometry) frame for arm joints `q`.
pub fn ee_in_base(
    spec: &UnitSpec,
    q: &[f64; ARM_JOINTS],
) -> Result<Isometry3<f64>, KinematicsError> {
    Ok(spec.ground_to_base() * spec.arm.forward(q)?)
}

/// `to` expressed in the frame of `from`.
pub fn relative_pose(from: &PlanarPose, to: &PlanarPose) -> PlanarPose {
    let (sin, cos) = from.yaw_rad.sin_cos();
    let (dx, dy) = (to.x_m - from.x_m, to.y_m - from.y_m);
    PlanarPose {
        x_m: cos * dx + sin * dy,
        y_m: -sin * dx + cos * dy,
        yaw_rad: wrap_angle(to.yaw_rad - from.yaw_rad),
    }
}

/// An angle in (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let w = (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    if w == -std::f64::consts::PI {
        std::f64::consts::PI
    } else {
        w
    }
}

/// Displacement (m) and rotation vector (rad) of an end effector from its rest grasp, both in
/// the base frame.
fn displacement(rest: &Isometry3<f64>, ee: &Isometry3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let dp = ee.translation.vector - rest.translation.vector;
    let dr: UnitQuaternion<f64> = ee.rotation * rest.rotation.inverse();
    (dp, dr.scaled_axis())
}

/// `command` − `sensed` per arm joint, rad.
fn command_minus_sensed(command: &UnitCommand, sensed: &UnitState) -> [f64; ARM_JOINTS] {
    std::array::from_fn(|j| command.arm_position_rad[j] - sensed.arm.position_rad[j])
}

/// Writes o⁽ⁱ⁾ of a unit with state `own` whose peer published `peer`, with the commands and
/// pipeline state `commands`, into `out` (`[ACTOR_OBS_DIM]`). Pure and allocation-free; FK
/// fails only on a malformed spec.
pub fn unit_observation(
    spec: &UnitSpec,
    reference: &GraspReference,
    own: &UnitState,
    peer: &UnitState,
    commands: &CommandState,
    goal: &PhaseGoal,
    out: &mut [f64; ACTOR_OBS_DIM],
) -> Result<(), KinematicsError> {
    let mut k = 0;
    let mut push = |values: &[f64]| {
        out[k..k + values.len()].copy_from_slice(values);
        k += values.len();
    };
    push(&own.arm.position_rad);
    push(&own.arm.velocity_radps);
    push(&own.wheels.velocity_radps);
    push(&command_minus_sensed(&commands.own, own));
    push(&commands.own.wheel_velocity_radps);
    let rest = &reference.ee_rest_in_base;
    let (dp, dr) = displacement(rest, &ee_in_base(spec, &own.arm.position_rad)?);
    push(dp.as_slice());
    push(dr.as_slice());
    let (pdp, pdr) = displacement(
        &reference.peer_ee_rest_in_base,
        &ee_in_base(spec, &peer.arm.position_rad)?,
    );
    push(pdp.as_slice());
    push(pdr.as_slice());
    let peer_base = relative_pose(&own.base_pose, &peer.base_pose);
    let r = &reference.peer_base_rest;
    push(&[
        peer_base.x_m - r.x_m,
        peer_base.y_m - r.y_m,
        wrap_angle(peer_base.yaw_rad - r.yaw_rad),
    ]);
    push(&peer.wheels.velocity_radps);
    push(&command_minus_sensed(&commands.peer, peer));
    push(&commands.peer.wheel_velocity_radps);
    push(&[commands.last_t_max, f64::from(u8::from(commands.last_held))]);
    push(&[goal.height_m]);
    let (sin, cos) = own.base_pose.yaw_rad.sin_cos();
    let to_base = |v: Vector2<f64>| [cos * v.x + sin * v.y, -sin * v.x + cos * v.y];
    let position = Vector2::new(own.base_pose.x_m, own.base_pose.y_m);
    let to_go = to_base(goal.base_goal_m - position);
    let velocity = to_base(goal.velocity_mps);
    push(&[to_go[0], to_go[1], velocity[0], velocity[1]]);
    push(&[goal.progress]);
    push(&to_base(goal.reference_m - position));
    debug_assert_eq!(k, ACTOR_OBS_DIM);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::repo_file;

    fn spec() -> UnitSpec {
        UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap()
    }

    fn state(x: f64, y: f64, yaw: f64, q: [f64; ARM_JOINTS]) -> UnitState {
        UnitState::at(x, y, yaw, q)
    }

    #[test]
    fn layout_fields_add_up_and_round_trip_through_metadata() {
        assert_eq!(ACTOR_OBS_DIM, 61);
        assert_eq!(field_range("cargo.ee_displacement_m"), Some(25..28));
        assert_eq!(field_range("goal.base"), Some(54..58));
        assert_eq!(field_range("goal.reference_offset_m"), Some(59..61));
        assert_eq!(field_range("nope"), None);
        assert_eq!(CARGO_DISPLACEMENT, 25);
        assert_eq!(
            field_range("peer.ee_displacement_m").map(|r| r.start),
            Some(PEER_DISPLACEMENT)
        );
        assert_eq!(GOAL_BASE, 54);
        let mut obs = [0.0; ACTOR_OBS_DIM];
        obs[27] = 0.2;
        obs[PEER_DISPLACEMENT + 2] = 0.4;
        obs[54] = 1.5;
        let view = ObservationView(&obs);
        assert!((view.lift_estimate_m() - 0.3).abs() < 1e-15);
        assert_eq!(view.goal_offset_m(), [1.5, 0.0]);
        let mut extra = std::collections::BTreeMap::new();
        assert!(check_layout(&extra).is_err());
        extra.insert(LAYOUT_VERSION_KEY.into(), OBS_LAYOUT_VERSION.to_string());
        extra.insert(LAYOUT_FIELDS_KEY.into(), layout_fields());
        assert_eq!(check_layout(&extra), Ok(()));
        // A hostile file's long non-ASCII metadata is refused, not a panic of the message's cut.
        let mut hostile = extra.clone();
        hostile.insert(LAYOUT_FIELDS_KEY.into(), "€".repeat(500));
        let err = check_layout(&hostile).unwrap_err();
        assert!(
            err.found.len() < 260 && err.found.ends_with('…'),
            "{}",
            err.found
        );
        extra.insert(LAYOUT_VERSION_KEY.into(), "0".into());
        let err = check_layout(&extra).unwrap_err().to_string();
        assert!(
            err.contains("version 0") && err.contains("version 3"),
            "{err}"
        );
    }

    #[test]
    fn at_the_rest_grasp_the_cargo_and_peer_terms_are_zero() {
        let spec = spec();
        let q = [0.3, 0.5, -0.1, 1.2, 0.0, 0.7, 0.1];
        let own = state(0.0, -0.8, 0.0, q);
        let peer = state(0.0, 0.8, std::f64::consts::PI, q);
        let reference = GraspReference::capture(&spec, &own, &peer).unwrap();
        let goal = PhaseGoal {
            height_m: 0.3,
            base_goal_m: Vector2::new(2.0, -0.8),
            velocity_mps: Vector2::new(0.2, 0.0),
            reference_m: Vector2::new(0.5, -0.8),
            progress: 0.25,
        };
        let commands = CommandState::after_hold(held_at(q), held_at(q));
        let mut out = [f64::NAN; ACTOR_OBS_DIM];
        unit_observation(&spec, &reference, &own, &peer, &commands, &goal, &mut out).unwrap();
        let at = |name: &str| &out[field_range(name).unwrap()];
        assert_eq!(at("own.arm_position_rad"), &q);
        assert!(out[16..51].iter().all(|v| v.abs() < 1e-12), "{out:?}");
        assert_eq!(at("pipeline.last_t_max"), &[0.0]);
        assert_eq!(at("pipeline.last_held"), &[1.0]);
        assert_eq!(at("goal.height_m"), &[0.3]);
        let base = at("goal.base");
        assert!((base[0] - 2.0).abs() < 1e-12 && base[1].abs() < 1e-12);
        assert!((base[2] - 0.2).abs() < 1e-12);
        assert_eq!(at("goal.phase_progress"), &[0.25]);
        let reference_offset = at("goal.reference_offset_m");
        assert!((reference_offset[0] - 0.5).abs() < 1e-12 && reference_offset[1].abs() < 1e-12);
        // The peer faces −X: the same goal in its frame is behind it.
        let mut peer_out = [0.0; ACTOR_OBS_DIM];
        let peer_ref = GraspReference::capture(&spec, &peer, &own).unwrap();
        let peer_goal = PhaseGoal {
            base_goal_m: Vector2::new(2.0, 0.8),
            reference_m: Vector2::new(0.5, 0.8),
            ..goal
        };
        unit_observation(
            &spec,
            &peer_ref,
            &peer,
            &own,
            &commands,
            &peer_goal,
            &mut peer_out,
        )
        .unwrap();
        assert!((peer_out[54] + 2.0).abs() < 1e-12 && (peer_out[56] + 0.2).abs() < 1e-12);
        assert!((peer_out[59] + 0.5).abs() < 1e-12);
    }

    #[test]
    fn lifting_the_arm_shows_as_cargo_displacement_and_a_lagging_peer_as_its_own() {
        let spec = spec();
        let q = [0.3, 0.5, -0.1, 1.2, 0.0, 0.7, 0.1];
        let own = state(0.0, -0.8, 0.0, q);
        let peer = state(0.0, 0.8, std::f64::consts::PI, q);
        let reference = GraspReference::capture(&spec, &own, &peer).unwrap();
        let mut lifted = own;
        lifted.arm.position_rad[1] += 0.05;
        let mut moved_peer = peer;
        moved_peer.base_pose.x_m -= 0.1;
        // Own command still at rest (the arm was pushed up past it); the peer's ahead of its
        // joints, wheels commanded forward.
        let mut peer_command = held_at(q);
        peer_command.arm_position_rad[3] += 0.02;
        peer_command.wheel_velocity_radps = [1.0, 1.5];
        let commands = CommandState {
            own: held_at(q),
            peer: peer_command,
            last_t_max: 0.4,
            last_held: false,
        };
        let mut out = [0.0; ACTOR_OBS_DIM];
        unit_observation(
            &spec,
            &reference,
            &lifted,
            &moved_peer,
            &commands,
            &PhaseGoal::default(),
            &mut out,
        )
        .unwrap();
        let at = |name: &str| &out[field_range(name).unwrap()];
        let expected = ee_in_base(&spec, &lifted.arm.position_rad)
            .unwrap()
            .translation
            .vector
            - reference.ee_rest_in_base.translation.vector;
        assert!(
            (Vector3::from_column_slice(at("cargo.ee_displacement_m")) - expected).norm() < 1e-12
        );
        assert!(expected.norm() > 1e-3);
        // Peer 0.1 m behind in world x: in the own frame (heading +X) that is −0.1 m in x.
        let peer_base = at("peer.base_offset");
        assert!((peer_base[0] + 0.1).abs() < 1e-12 && peer_base[1].abs() < 1e-12);
        let own_offset = at("own.arm_command_minus_sensed_rad");
        assert!((own_offset[1] + 0.05).abs() < 1e-12, "{own_offset:?}");
        assert!((at("peer.arm_command_minus_sensed_rad")[3] - 0.02).abs() < 1e-12);
        assert_eq!(at("peer.wheel_command_radps"), &[1.0, 1.5]);
        assert_eq!(at("pipeline.last_t_max"), &[0.4]);
        assert_eq!(at("pipeline.last_held"), &[0.0]);
    }

    fn held_at(q: [f64; ARM_JOINTS]) -> UnitCommand {
        UnitCommand {
            wheel_velocity_radps: [0.0; WHEEL_JOINTS],
            arm_position_rad: q,
        }
    }

    #[test]
    fn relative_pose_inverts_and_angles_wrap() {
        let a = PlanarPose {
            x_m: 1.0,
            y_m: 2.0,
            yaw_rad: 0.5,
        };
        let b = PlanarPose {
            x_m: -1.0,
            y_m: 0.5,
            yaw_rad: 3.0,
        };
        let r = relative_pose(&a, &b);
        let back = relative_pose(&b, &a);
        assert!((r.yaw_rad + back.yaw_rad).abs() < 1e-12);
        assert!(
            ((r.x_m.powi(2) + r.y_m.powi(2)) - (back.x_m.powi(2) + back.y_m.powi(2))).abs() < 1e-12
        );
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.25) + 0.25).abs() < 1e-15);
    }
}
