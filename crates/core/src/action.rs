//! The paper's action (eq. target_state): a controller's output a_k is a bounded *increment* on
//! the previous command, F_k = U_{k−1} ⊕ Δ(U_{k−1}, a_k), never an absolute target.
//!
//! ⊕ is addition in joint space on both parts of u⁽ⁱ⁾ (the clamp interpolates there too):
//! - **arm**: each joint position command moves by at most `arm_step_rad` per tick;
//! - **wheels**: each wheel *velocity* command changes by at most `wheel_step_radps` per tick —
//!   the paper's "addition on the planar wheel components" read on the velocity-controlled
//!   drives a unit actually has: a bounded change of the commanded wheel speeds is a bounded
//!   change of the commanded base motion (an acceleration limit), and a zero increment keeps
//!   the base moving as commanded.
//!
//! Then F_k is kept inside the joints' URDF limits (position for the arm, velocity for the
//! wheels), as a drive would refuse anything beyond them; the clamp then admits the largest
//! safe step from U_{k−1} toward F_k. Every controller goes through [`ActionMap::target`]: the
//! learned policies (whose file records the map, [`check_policy`]) and the scripted IK
//! controller ([`ActionMap::toward`] turns its absolute IK solution into the increment).

use std::collections::BTreeMap;

use crate::policy::Policy;
use crate::state::{UnitCommand, UNIT_ACTION_DIM, WHEEL_JOINTS};
use crate::task_config::ActionSettings;
use crate::unit::UnitSpec;

/// Version of the action map below. 1 was absolute joint targets (`offset + scale ⊙ a`); 2 is
/// the per-tick increment. Bump it with any change to what a policy output means.
pub const ACTION_MAP_VERSION: u32 = 2;
/// Metadata key of the action map's version in a policy file.
pub const ACTION_MAP_VERSION_KEY: &str = "action_map_version";
/// Metadata key naming the action map in a policy file.
pub const ACTION_MAP_KEY: &str = "action_map";
/// The value of [`ACTION_MAP_KEY`]: F_k = U_{k−1} + clip(output, ±step).
pub const ACTION_MAP_NAME: &str = "increment";

/// The per-tick bound of each component of the increment, in u⁽ⁱ⁾'s order (two wheel speeds in
/// rad/s per tick, seven arm joints in rad per tick).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActionMap {
    pub step: [f64; UNIT_ACTION_DIM],
}

/// A policy file whose action map this build does not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ActionMapError {
    #[error(
        "policy action map {found}; this build runs {ACTION_MAP_NAME:?} version \
         {ACTION_MAP_VERSION} (an increment on the previous command): retrain it"
    )]
    Version { found: String },
    #[error("policy action map: offset {index} is {value}, an increment map has no offset")]
    Offset { index: usize, value: f32 },
    #[error("policy action map: step {index} is {value}, must be finite and positive")]
    Step { index: usize, value: f32 },
}

impl ActionMap {
    /// The map of `configs/tasks.toml [action]`.
    pub fn from_settings(a: &ActionSettings) -> Self {
        let mut step = [a.arm_step_rad; UNIT_ACTION_DIM];
        step[..WHEEL_JOINTS].fill(a.wheel_step_radps);
        ActionMap { step }
    }

    /// The map a policy file records: its output affine is `0 + step ⊙ network output`, so the
    /// policy emits the increment and its scale tensor holds the steps. Checks the metadata's
    /// map name and version first.
    pub fn of_policy(policy: &Policy) -> Result<Self, ActionMapError> {
        check_policy(&policy.metadata().extra)?;
        let affine = policy.action_affine();
        if let Some((index, &value)) = affine
            .offset
            .data()
            .iter()
            .enumerate()
            .find(|(_, v)| **v != 0.0)
        {
            return Err(ActionMapError::Offset { index, value });
        }
        let mut step = [0.0; UNIT_ACTION_DIM];
        for (index, (s, &value)) in step.iter_mut().zip(affine.scale.data()).enumerate() {
            if !(value.is_finite() && value > 0.0) {
                return Err(ActionMapError::Step { index, value });
            }
            *s = f64::from(value);
        }
        Ok(ActionMap { step })
    }

    /// F_k = U_{k−1} + clip(increment, ±step), within the joints' limits. A non-finite
    /// increment gives a non-finite target (the caller's check of the target catches it).
    pub fn target(
        &self,
        spec: &UnitSpec,
        previous: &UnitCommand,
        increment: &[f64; UNIT_ACTION_DIM],
    ) -> UnitCommand {
        let bounded = |k: usize| {
            let s = self.step[k];
            let d = increment[k];
            if d.is_nan() {
                d
            } else {
                d.clamp(-s, s)
            }
        };
        let mut f = *previous;
        for (j, (w, limits)) in f
            .wheel_velocity_radps
            .iter_mut()
            .zip(&spec.wheel_limits)
            .enumerate()
        {
            *w = clamp_nan(*w + bounded(j), -limits.velocity, limits.velocity);
        }
        for (j, (q, limits)) in f
            .arm_position_rad
            .iter_mut()
            .zip(&spec.arm_limits)
            .enumerate()
        {
            *q = clamp_nan(*q + bounded(WHEEL_JOINTS + j), limits.lower, limits.upper);
        }
        f
    }

    /// The increment that moves `previous` toward `desired` (a controller that computes an
    /// absolute command, such as the scripted IK controller), within the steps. The arm's part
    /// is scaled down as a whole until every joint's fits its step, so a command beyond one
    /// tick's reach is approached along the straight line in joint space: clipping each joint
    /// on its own turns the motion, and an IK step near a singular pose (one joint asked for
    /// 0.1 rad, the others for a millimetre of end-effector travel) then moved the others in
    /// full and that one by its step, running the end effector 3 mm per tick below its path
    /// until the placement held without an admissible step (measured, offset-COM crate). The
    /// wheel speeds are left to [`ActionMap::target`]'s clip, each on its own.
    pub fn toward(&self, previous: &UnitCommand, desired: &UnitCommand) -> [f64; UNIT_ACTION_DIM] {
        let (from, to) = (previous.to_action(), desired.to_action());
        let mut delta: [f64; UNIT_ACTION_DIM] = std::array::from_fn(|k| to[k] - from[k]);
        let arm = WHEEL_JOINTS..UNIT_ACTION_DIM;
        let worst = arm
            .clone()
            .map(|k| delta[k].abs() / self.step[k])
            .fold(1.0, f64::max);
        for d in &mut delta[arm] {
            *d /= worst;
        }
        delta
    }

    /// The metadata a policy file records for this map (its steps are the scale tensor).
    pub fn metadata() -> [(&'static str, String); 2] {
        [
            (ACTION_MAP_KEY, ACTION_MAP_NAME.into()),
            (ACTION_MAP_VERSION_KEY, ACTION_MAP_VERSION.to_string()),
        ]
    }
}

/// `v` clamped to [lo, hi]; NaN stays NaN (an unbounded limit is ±∞).
fn clamp_nan(v: f64, lo: f64, hi: f64) -> f64 {
    if v.is_nan() || lo > hi {
        v
    } else {
        v.clamp(lo, hi)
    }
}

/// Checks a policy's `action_map` and `action_map_version` metadata against this build.
pub fn check_policy(extra: &BTreeMap<String, String>) -> Result<(), ActionMapError> {
    let name = extra.get(ACTION_MAP_KEY).map(String::as_str);
    let version = extra.get(ACTION_MAP_VERSION_KEY).map(String::as_str);
    let expected_version = ACTION_MAP_VERSION.to_string();
    if name == Some(ACTION_MAP_NAME) && version == Some(expected_version.as_str()) {
        return Ok(());
    }
    let mut found = format!(
        "{:?} version {}",
        name.unwrap_or("<missing: absolute targets>"),
        version.unwrap_or("1")
    );
    crate::input::clip_for_message(&mut found, 120);
    Err(ActionMapError::Version { found })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::repo_file;

    fn spec() -> UnitSpec {
        UnitSpec::from_file(&repo_file("assets/unit.urdf")).unwrap()
    }

    #[test]
    fn the_target_is_the_previous_command_moved_by_at_most_one_step() {
        let spec = spec();
        let map = ActionMap {
            step: [0.1, 0.1, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01],
        };
        let previous = UnitCommand {
            wheel_velocity_radps: [1.0, -1.0],
            arm_position_rad: [0.2, 0.3, 0.0, -1.5, 0.0, 1.5, 0.1],
        };
        let zero = map.target(&spec, &previous, &[0.0; UNIT_ACTION_DIM]);
        assert_eq!(zero, previous);
        let mut inc = [0.0; UNIT_ACTION_DIM];
        inc[0] = 5.0;
        inc[1] = 0.05;
        inc[3] = -1.0;
        inc[4] = 0.004;
        let f = map.target(&spec, &previous, &inc);
        assert!((f.wheel_velocity_radps[0] - 1.1).abs() < 1e-12);
        assert!((f.wheel_velocity_radps[1] + 0.95).abs() < 1e-12);
        assert!((f.arm_position_rad[1] - 0.29).abs() < 1e-12);
        assert!((f.arm_position_rad[2] - 0.004).abs() < 1e-12);
        let nan = map.target(&spec, &previous, &[f64::NAN; UNIT_ACTION_DIM]);
        assert!(nan.arm_position_rad.iter().all(|q| q.is_nan()));
    }

    #[test]
    fn targets_stay_inside_the_joint_limits() {
        let spec = spec();
        let map = ActionMap {
            step: [1e3; UNIT_ACTION_DIM],
        };
        let f = map.target(&spec, &UnitCommand::default(), &[1e3; UNIT_ACTION_DIM]);
        for (w, l) in f.wheel_velocity_radps.iter().zip(&spec.wheel_limits) {
            assert!(*w <= l.velocity && *w > 0.0);
        }
        for (q, l) in f.arm_position_rad.iter().zip(&spec.arm_limits) {
            assert!(*q <= l.upper && *q >= l.lower);
        }
    }

    #[test]
    fn toward_then_target_reaches_a_near_command_and_bounds_a_far_one() {
        let spec = spec();
        let map = ActionMap {
            step: [0.1, 0.1, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01],
        };
        let previous = UnitCommand {
            wheel_velocity_radps: [0.0; 2],
            arm_position_rad: [0.0, 0.3, 0.0, -1.5, 0.0, 1.5, 0.0],
        };
        let mut near = previous;
        near.arm_position_rad[1] += 0.005;
        near.wheel_velocity_radps[0] = 0.05;
        assert_eq!(
            map.target(&spec, &previous, &map.toward(&previous, &near)),
            near
        );
        // Far: the arm moves along the line toward it, its largest joint by the step.
        let mut far = previous;
        far.arm_position_rad[1] += 0.5;
        far.arm_position_rad[3] += 0.05;
        far.wheel_velocity_radps = [1.0, 0.5];
        let f = map.target(&spec, &previous, &map.toward(&previous, &far));
        assert!((f.arm_position_rad[1] - 0.31).abs() < 1e-12);
        assert!((f.arm_position_rad[3] - (-1.5 + 0.001)).abs() < 1e-12);
        assert_eq!(f.arm_position_rad[0], 0.0);
        // Each wheel speed is clipped on its own.
        assert_eq!(f.wheel_velocity_radps, [0.1, 0.1]);
    }

    #[test]
    fn policies_of_another_action_map_are_refused() {
        let mut extra = BTreeMap::new();
        let err = check_policy(&extra).unwrap_err().to_string();
        assert!(
            err.contains("absolute targets") && err.contains("retrain"),
            "{err}"
        );
        for (k, v) in ActionMap::metadata() {
            extra.insert(k.to_owned(), v);
        }
        assert_eq!(check_policy(&extra), Ok(()));
        extra.insert(ACTION_MAP_VERSION_KEY.into(), "3".into());
        assert!(check_policy(&extra).is_err());
        // Long non-ASCII metadata (a hostile file) is refused without a panic in the message.
        extra.insert(ACTION_MAP_KEY.into(), "ü".repeat(300));
        let err = check_policy(&extra).unwrap_err().to_string();
        assert!(err.contains('…'), "{err}");
    }
}
