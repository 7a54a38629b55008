//! Joint and unit state types and the mission phase: plain, serde-serializable data.
//!
//! One wheel–arm unit has [`WHEEL_JOINTS`] driven wheels (velocity-commanded) and
//! [`ARM_JOINTS`] arm joints (position-commanded); its policy action u⁽ⁱ⁾ ∈ ℝ⁹ is the two wheel
//! velocities followed by the seven arm joint positions (paper, eq. for a_t).

use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Driven wheels per differential-drive wheel module.
pub const WHEEL_JOINTS: usize = 2;
/// Joints of the serial arm module.
pub const ARM_JOINTS: usize = 7;
/// Length of one unit's action u⁽ⁱ⁾: wheel velocities, then arm joint positions.
pub const UNIT_ACTION_DIM: usize = WHEEL_JOINTS + ARM_JOINTS;

/// The most units a team may have: each unit's tick evaluates the whole stacked state. The unit
/// config's bound; fixed-size per-unit state such as [`crate::touchdown`]'s is sized by it.
pub const MAX_TEAM_SIZE: usize = 16;

/// The mission phase m ∈ {0 Idle, 1 Lift, 2 Transport, 3 Place} of the paper's phase MDP.
///
/// Exactly one phase policy is active in Lift, Transport and Place; none in Idle.
/// A unit boots in Idle (the default).
#[derive(
    Debug, Clone, Copy, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Phase {
    #[default]
    Idle = 0,
    Lift = 1,
    Transport = 2,
    Place = 3,
}

impl Phase {
    /// All phases in mission order.
    pub const ALL: [Phase; 4] = [Phase::Idle, Phase::Lift, Phase::Transport, Phase::Place];

    /// The lowercase name used in configs, file names and policy metadata.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Idle => "idle",
            Phase::Lift => "lift",
            Phase::Transport => "transport",
            Phase::Place => "place",
        }
    }

    /// The paper's mode index m.
    pub fn index(self) -> u8 {
        self as u8
    }

    /// Whether a phase policy runs in this phase (the indicator gating of the paper).
    pub fn has_policy(self) -> bool {
        self != Phase::Idle
    }
}

impl std::fmt::Display for Phase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A phase name that is not one of `idle`, `lift`, `transport`, `place`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown phase {0:?} (expected idle, lift, transport or place)")]
pub struct UnknownPhase(pub String);

impl std::str::FromStr for Phase {
    type Err = UnknownPhase;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Phase::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| UnknownPhase(s.to_owned()))
    }
}

/// One feedback sample of N joints. `effort_nm` is `None` where the motors do not report it.
/// What a hardware backend reads once per tick; [`WheelJoints`] and [`ArmJoints`] are the
/// parts of it a unit's state keeps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointReading<const N: usize> {
    pub position_rad: [f64; N],
    pub velocity_radps: [f64; N],
    /// Joint torque, N·m.
    pub effort_nm: Option<[f64; N]>,
    /// Time of the sample on the driver's clock (simulated for mocks and the virtual bus).
    pub stamp: Duration,
}

/// Positions and velocities of a unit's two driven wheels (left, right).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct WheelJoints {
    pub position_rad: [f64; WHEEL_JOINTS],
    pub velocity_radps: [f64; WHEEL_JOINTS],
}

/// Positions and velocities of a unit's seven arm joints, base to tip.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ArmJoints {
    pub position_rad: [f64; ARM_JOINTS],
    pub velocity_radps: [f64; ARM_JOINTS],
}

/// A wheel base's pose in the plane of the shared world frame (Z up). Strict like every config
/// type (`[start_pose]` of a unit config): an unknown key such as `yaw_deg` is an error.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanarPose {
    pub x_m: f64,
    pub y_m: f64,
    /// Heading about +Z, counter-clockwise from +X.
    pub yaw_rad: f64,
}

/// A differential-drive base's velocity in its own frame (it cannot move sideways).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanarVelocity {
    pub forward_mps: f64,
    pub yaw_rate_radps: f64,
}

/// Everything one wheel–arm unit knows about itself at a control tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UnitState {
    pub wheels: WheelJoints,
    pub arm: ArmJoints,
    pub base_pose: PlanarPose,
    pub base_velocity: PlanarVelocity,
}

/// One unit's command u⁽ⁱ⁾: wheel velocities (velocity-controlled drives) and arm joint
/// positions (position-controlled drives).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UnitCommand {
    pub wheel_velocity_radps: [f64; WHEEL_JOINTS],
    pub arm_position_rad: [f64; ARM_JOINTS],
}

#[cfg(test)]
impl UnitState {
    /// A unit at rest at base pose (`x`, `y`, `yaw`) with arm joints `q` (tests).
    pub(crate) fn at(x: f64, y: f64, yaw: f64, q: [f64; ARM_JOINTS]) -> Self {
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
}

impl UnitCommand {
    /// Splits a policy action u⁽ⁱ⁾ = [ω_left, ω_right, q₁ … q₇].
    pub fn from_action(action: &[f64; UNIT_ACTION_DIM]) -> Self {
        let mut command = UnitCommand::default();
        command
            .wheel_velocity_radps
            .copy_from_slice(&action[..WHEEL_JOINTS]);
        command
            .arm_position_rad
            .copy_from_slice(&action[WHEEL_JOINTS..]);
        command
    }

    /// The inverse of [`UnitCommand::from_action`].
    pub fn to_action(&self) -> [f64; UNIT_ACTION_DIM] {
        let mut action = [0.0; UNIT_ACTION_DIM];
        action[..WHEEL_JOINTS].copy_from_slice(&self.wheel_velocity_radps);
        action[WHEEL_JOINTS..].copy_from_slice(&self.arm_position_rad);
        action
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phase_names_round_trip_and_gate_policies() {
        for phase in Phase::ALL {
            assert_eq!(phase.name().parse::<Phase>(), Ok(phase));
            assert_eq!(phase.has_policy(), phase != Phase::Idle);
        }
        assert_eq!("hover".parse::<Phase>(), Err(UnknownPhase("hover".into())));
        assert_eq!(Phase::Transport.index(), 2);
    }

    #[test]
    fn state_serializes_with_unit_named_fields() {
        let json = serde_json::to_value(UnitState::default()).unwrap();
        assert!(json["arm"]["position_rad"]
            .as_array()
            .is_some_and(|a| a.len() == ARM_JOINTS));
        assert_eq!(serde_json::to_string(&Phase::Lift).unwrap(), "\"lift\"");
    }

    #[test]
    fn action_split_round_trips() {
        let action = [0.5, -0.5, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7];
        let command = UnitCommand::from_action(&action);
        assert_eq!(command.wheel_velocity_radps, [0.5, -0.5]);
        assert_eq!(command.arm_position_rad[6], 0.7);
        assert_eq!(command.to_action(), action);
    }
}
