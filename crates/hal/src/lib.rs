//! # moonhaul-hal
//!
//! The hardware seam of a wheel–arm unit. The onboard daemon talks only to the small,
//! object-safe traits here — [`Drive`] for power-stage control and the control period,
//! [`WheelDrive`] for the differential-drive wheel pair (velocity commands), [`ArmDrive`] for the
//! seven-joint arm (position commands) — so the same control path runs on CiA 402 drives over
//! CAN ([`can::Cia402Master`]), on mock hardware ([`mock::MockDrive`]) and in the simulator.
//! Limits from the URDF wrap any driver as a decorator ([`limits::Limited`]) rather than living
//! inside each driver.
//!
//! The daemon sees a whole unit through [`UnitHardware`] (ros2_control's system interface: one
//! `read` and one `write` per tick, `activate`/`deactivate`), implemented by [`DriveUnit`] (any
//! wheel drive plus any arm drive), [`MockUnit`] and [`can::Cia402Master`]; tests inject
//! faults through [`FaultInjection`].
//!
//! Commands are latched: `command_*` stores the target that the next [`Drive::sync`] sends, and
//! `read_*` returns the feedback the last `sync` collected. That mirrors a SYNC-driven CAN cycle
//! and lets mocks advance simulated time explicitly, so tests are deterministic.

pub mod can;
pub mod limits;
pub mod mock;
pub mod unit;

use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use std::time::Duration;

/// The physical quantity a limit or an invalid value refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// rad
    Position,
    /// rad/s
    Velocity,
    /// N·m
    Effort,
}

impl std::fmt::Display for Quantity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Quantity::Position => "position (rad)",
            Quantity::Velocity => "velocity (rad/s)",
            Quantity::Effort => "effort (N·m)",
        })
    }
}

/// Why a drive call failed; every variant names the joint (or bus) at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HalError {
    #[error("joint {joint}: drive fault: {reason}")]
    DriveFault { joint: String, reason: String },
    #[error("joint {joint}: no feedback for {waited:?}")]
    NoFeedback { joint: String, waited: Duration },
    #[error("joint {joint}: {quantity} {value} outside [{lower}, {upper}]")]
    OutOfLimits {
        joint: String,
        quantity: Quantity,
        value: f64,
        lower: f64,
        upper: f64,
    },
    #[error("joint {joint}: non-finite {quantity} command {value}")]
    NonFinite {
        joint: String,
        quantity: Quantity,
        value: f64,
    },
    #[error("joint {joint}: drive not enabled")]
    NotEnabled { joint: String },
    #[error("bus {bus}: {reason}")]
    Bus { bus: String, reason: String },
    #[error(transparent)]
    Can(#[from] can::CanError),
}

pub use moonhaul_core::state::JointReading;
pub use unit::{
    emulated_unit, emulated_unit_on, kernel_unit, DriveUnit, FaultInjection, GraspModel,
    InjectedFault, LoadShareGrasp, MockUnit, NoGrasp, UnitHardware, UnitOutput, UnitReading,
    INJECTED_EMCY_CODE, INJECTED_MOTOR_FAULT_CODE, UNIT_JOINTS,
};

/// Power-stage control and the control period, shared by both drive kinds.
pub trait Drive {
    /// Brings every joint to its operational (torque-on) state, holding its current position.
    fn enable(&mut self) -> Result<(), HalError>;
    /// Removes torque from every joint.
    fn disable(&mut self) -> Result<(), HalError>;
    /// The first latched fault, if any.
    fn fault(&self) -> Option<HalError>;
    /// Clears latched faults; the drive stays disabled until `enable`.
    fn reset_fault(&mut self) -> Result<(), HalError>;
    /// Runs one control period: sends the latched commands, lets the hardware move and collects
    /// feedback. Returns the latched fault, if any, so a control loop stops at once.
    fn sync(&mut self) -> Result<(), HalError>;
}

/// The two driven wheels of a differential-drive module (left, right).
pub trait WheelDrive: Drive {
    /// Latches wheel velocity targets, rad/s, for the next [`Drive::sync`].
    fn command_velocity(&mut self, velocity_radps: &[f64; WHEEL_JOINTS]) -> Result<(), HalError>;
    /// The wheel feedback of the last [`Drive::sync`].
    fn read_wheels(&mut self) -> Result<JointReading<WHEEL_JOINTS>, HalError>;
}

/// The seven position-controlled joints of an arm module, base to tip.
pub trait ArmDrive: Drive {
    /// Latches arm joint position targets, rad, for the next [`Drive::sync`].
    fn command_position(&mut self, position_rad: &[f64; ARM_JOINTS]) -> Result<(), HalError>;
    /// The arm feedback of the last [`Drive::sync`].
    fn read_arm(&mut self) -> Result<JointReading<ARM_JOINTS>, HalError>;
}

/// Rejects NaN and infinite commands before any driver turns them into motion (a NaN cast to
/// encoder counts would silently become 0).
pub(crate) fn check_finite(
    names: &[String],
    values: &[f64],
    quantity: Quantity,
) -> Result<(), HalError> {
    match names.iter().zip(values).find(|(_, v)| !v.is_finite()) {
        Some((joint, &value)) => Err(HalError::NonFinite {
            joint: joint.clone(),
            quantity,
            value,
        }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn traits_are_object_safe() {
        fn takes(_: Option<&mut dyn WheelDrive>, _: Option<&mut dyn ArmDrive>) {}
        takes(None, None);
    }

    #[test]
    fn non_finite_commands_name_the_joint() {
        let names = ["a".to_owned(), "b".to_owned()];
        let err = check_finite(&names, &[0.0, f64::NAN], Quantity::Velocity).unwrap_err();
        assert!(matches!(err, HalError::NonFinite { ref joint, .. } if joint == "b"));
        assert!(check_finite(&names, &[0.0, 1.0], Quantity::Velocity).is_ok());
    }
}
