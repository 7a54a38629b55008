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
//! **Layout** ([`OBS_LAYOUT_VERSION`], [`OBS_FIELDS`]): the policy file records both; a runtime
//! refuses a policy whose layout differs ([`check_layout`]).

use nalgebra::{Isometry3, UnitQuaternion, Vector2, Vector3};

use crate::kinematics::KinematicsError;
use crate::state::{PlanarPose, UnitState, ARM_JOINTS, WHEEL_JOINTS};
use crate::unit::UnitSpec;

/// Version of the observation layout below; bump it with any change to the fields or their
/// meaning.
pub const OBS_LAYOUT_VERSION: u32 = 2;

/// The fields of o⁽ⁱ⁾ in order, with their widths.
pub const OBS_FIELDS: [(&str, usize); 11] = [
    // x⁽ⁱ⁾: own encoders.
    ("own.arm_position_rad", ARM_JOINTS),
    ("own.arm_velocity_radps", ARM_JOINTS),
    ("own.wheel_velocity_radps", WHEEL_JOINTS),
    // Δxᶜ: the cargo's displacement from its grasp at rest, by FK of the own arm.
    ("cargo.ee_displacement_m", 3),
    ("cargo.ee_rotation_rad", 3),
    // Δx⁽ʲ⁾: the neighbour, from its published state.
    ("peer.ee_displacement_m", 3),
    ("peer.ee_rotation_rad", 3),
    ("peer.base_offset", 3),
    ("peer.wheel_velocity_radps", WHEEL_JOINTS),
    // The phase goal.
    ("goal.height_m", 1),
    ("goal.base", 4),
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
        found.truncate(200);
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
#[derive(Debug, Clone, Copy, PartialEq)]
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

/// Writes o⁽ⁱ⁾ of a unit with state `own` whose peer published `peer`, into `out`
/// (`[ACTOR_OBS_DIM]`). Pure and allocation-free; FK fails only on a malformed spec.
pub fn unit_observation(
    spec: &UnitSpec,
    reference: &GraspReference,
    own: &UnitState,
    peer: &UnitState,
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
    push(&[goal.height_m]);
    let (sin, cos) = own.base_pose.yaw_rad.sin_cos();
    let to_base = |v: Vector2<f64>| [cos * v.x + sin * v.y, -sin * v.x + cos * v.y];
    let to_go = to_base(goal.base_goal_m - Vector2::new(own.base_pose.x_m, own.base_pose.y_m));
    let velocity = to_base(goal.velocity_mps);
    push(&[to_go[0], to_go[1], velocity[0], velocity[1]]);
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
        let mut s = UnitState {
            base_pose: PlanarPose {
                x_m: x,
                y_m: y,
                yaw_rad: yaw,
            },
            ..Default::default()
        };
        s.arm.position_rad = q;
        s
    }

    #[test]
    fn layout_fields_add_up_and_round_trip_through_metadata() {
        assert_eq!(ACTOR_OBS_DIM, 38);
        assert_eq!(field_range("cargo.ee_displacement_m"), Some(16..19));
        assert_eq!(field_range("goal.base"), Some(34..38));
        assert_eq!(field_range("nope"), None);
        assert_eq!(CARGO_DISPLACEMENT, 16);
        assert_eq!(
            field_range("peer.ee_displacement_m").map(|r| r.start),
            Some(PEER_DISPLACEMENT)
        );
        assert_eq!(GOAL_BASE, 34);
        let mut obs = [0.0; ACTOR_OBS_DIM];
        obs[18] = 0.2;
        obs[PEER_DISPLACEMENT + 2] = 0.4;
        obs[34] = 1.5;
        let view = ObservationView(&obs);
        assert!((view.lift_estimate_m() - 0.3).abs() < 1e-15);
        assert_eq!(view.goal_offset_m(), [1.5, 0.0]);
        let mut extra = std::collections::BTreeMap::new();
        assert!(check_layout(&extra).is_err());
        extra.insert(LAYOUT_VERSION_KEY.into(), OBS_LAYOUT_VERSION.to_string());
        extra.insert(LAYOUT_FIELDS_KEY.into(), layout_fields());
        assert_eq!(check_layout(&extra), Ok(()));
        extra.insert(LAYOUT_VERSION_KEY.into(), "0".into());
        let err = check_layout(&extra).unwrap_err().to_string();
        assert!(
            err.contains("version 0") && err.contains("version 2"),
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
        };
        let mut out = [f64::NAN; ACTOR_OBS_DIM];
        unit_observation(&spec, &reference, &own, &peer, &goal, &mut out).unwrap();
        assert_eq!(&out[..7], &q);
        assert!(out[16..33].iter().all(|v| v.abs() < 1e-12), "{out:?}");
        assert_eq!(out[33], 0.3);
        assert!((out[34] - 2.0).abs() < 1e-12 && out[35].abs() < 1e-12);
        assert!((out[36] - 0.2).abs() < 1e-12);
        // The peer faces −X: the same goal in its frame is behind it.
        let mut peer_out = [0.0; ACTOR_OBS_DIM];
        let peer_ref = GraspReference::capture(&spec, &peer, &own).unwrap();
        let peer_goal = PhaseGoal {
            base_goal_m: Vector2::new(2.0, 0.8),
            ..goal
        };
        unit_observation(&spec, &peer_ref, &peer, &own, &peer_goal, &mut peer_out).unwrap();
        assert!((peer_out[34] + 2.0).abs() < 1e-12 && (peer_out[36] + 0.2).abs() < 1e-12);
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
        let mut out = [0.0; ACTOR_OBS_DIM];
        unit_observation(
            &spec,
            &reference,
            &lifted,
            &moved_peer,
            &PhaseGoal::default(),
            &mut out,
        )
        .unwrap();
        let expected = ee_in_base(&spec, &lifted.arm.position_rad)
            .unwrap()
            .translation
            .vector
            - reference.ee_rest_in_base.translation.vector;
        assert!((Vector3::new(out[16], out[17], out[18]) - expected).norm() < 1e-12);
        assert!(expected.norm() > 1e-3);
        // Peer 0.1 m behind in world x: in the own frame (heading +X) that is −0.1 m in x.
        assert!((out[28] + 0.1).abs() < 1e-12 && out[29].abs() < 1e-12);
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
