//! The sim-backed hardware: one unit's drives served by the simulated world in another
//! process, over zenoh, the way a SYNC-driven bus serves real drives.
//!
//! Each world step the world publishes every unit's [`SimSensed`] (encoders with the training
//! noise, and the wrist-force estimate); the unit ticks on it and answers with one
//! [`SimCommand`] for the same tick. In lockstep the world steps once every live unit answered,
//! so the physics never waits on the wall clock and runs as fast as the machine allows (every
//! step sees every unit's command of that tick, whatever the scheduling); in real time it steps
//! on the wall clock with whatever command is newest. The world treats a unit that stops
//! answering as a drive that lost its master: quick stop (wheels to zero, arm holding).
//!
//! The link is the simulator's drive bus, not team traffic: it carries no MAC (a real bus has
//! none either), but both ends validate every frame — size, unit, tick, finiteness — and drop
//! what does not fit, counting it.

use moonhaul_core::state::{Phase, UnitCommand, ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_hal::unit::{UnitHardware, UnitOutput, UnitReading};
use moonhaul_hal::HalError;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Largest frame either side accepts.
pub const MAX_FRAME_BYTES: usize = 2048;

/// What the world's simulated drives and wrist sensor report to unit `unit` at `tick`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimSensed {
    pub unit: usize,
    pub tick: u64,
    /// Simulated time, µs: the team's synchronized clock in a simulated mission.
    pub stamp_us: u64,
    pub wheel_position_rad: [f64; WHEEL_JOINTS],
    pub wheel_velocity_radps: [f64; WHEEL_JOINTS],
    pub arm_position_rad: [f64; ARM_JOINTS],
    pub arm_velocity_radps: [f64; ARM_JOINTS],
    /// Magnitude of the grasp force, N (the simulator's wrench as a wrist-force estimate).
    pub grasp_force_n: f64,
}

/// What unit `unit` commands for world tick `tick`; its phase rides along for the world's
/// ground-truth log (the mission profile's phase shading).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimCommand {
    pub unit: usize,
    pub tick: u64,
    pub phase: Phase,
    pub command: UnitCommand,
    pub grasp_open: bool,
}

/// Why a link frame was dropped.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LinkError {
    #[error("sim link frame of {0} bytes is over the {MAX_FRAME_BYTES}-byte limit")]
    TooLarge(usize),
    #[error("malformed sim link frame: {0}")]
    Malformed(String),
    #[error("sim link frame for unit {got}, expected unit {expected}")]
    WrongUnit { got: usize, expected: usize },
    #[error("sim link frame of unit {unit} has a non-finite value")]
    NonFinite { unit: usize },
}

fn finite(values: impl IntoIterator<Item = f64>) -> bool {
    values.into_iter().all(f64::is_finite)
}

impl SimSensed {
    /// Decodes and checks a frame meant for unit `unit`.
    pub fn decode(bytes: &[u8], unit: usize) -> Result<Self, LinkError> {
        let s: SimSensed = decode(bytes)?;
        if s.unit != unit {
            return Err(LinkError::WrongUnit {
                got: s.unit,
                expected: unit,
            });
        }
        // A non-finite reading is passed on: detecting a failed sensor is the tick's job.
        Ok(s)
    }
}

impl SimCommand {
    /// Decodes and checks a command frame from any unit below `team_size`.
    pub fn decode(bytes: &[u8], team_size: usize) -> Result<Self, LinkError> {
        let c: SimCommand = decode(bytes)?;
        if c.unit >= team_size {
            return Err(LinkError::WrongUnit {
                got: c.unit,
                expected: team_size.saturating_sub(1),
            });
        }
        let values = c
            .command
            .wheel_velocity_radps
            .iter()
            .chain(&c.command.arm_position_rad)
            .copied();
        if !finite(values) {
            return Err(LinkError::NonFinite { unit: c.unit });
        }
        Ok(c)
    }
}

fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Result<T, LinkError> {
    if bytes.len() > MAX_FRAME_BYTES {
        return Err(LinkError::TooLarge(bytes.len()));
    }
    serde_json::from_slice(bytes).map_err(|e| LinkError::Malformed(e.to_string()))
}

/// Encodes a link frame (plain data; cannot fail for finite or non-finite numbers alike,
/// non-finite ones are written as null and rejected by the receiver).
pub fn encode<T: Serialize>(value: &T) -> Vec<u8> {
    serde_json::to_vec(value).unwrap_or_default()
}

/// [`UnitHardware`] over the link: `read` returns the newest [`SimSensed`] the daemon handed
/// in with [`SimHardware::deliver`]; `write` leaves a [`SimCommand`] for the daemon to publish
/// ([`SimHardware::take_command`]). The network I/O stays in the daemon's async loop.
pub struct SimHardware {
    unit: usize,
    latest: Option<SimSensed>,
    phase: Phase,
    outgoing: Option<SimCommand>,
    active: bool,
}

impl SimHardware {
    pub fn new(unit: usize) -> Self {
        SimHardware {
            unit,
            latest: None,
            phase: Phase::Idle,
            outgoing: None,
            active: false,
        }
    }

    /// The world's newest reading.
    pub fn deliver(&mut self, sensed: SimSensed) {
        self.latest = Some(sensed);
    }

    pub fn latest(&self) -> Option<&SimSensed> {
        self.latest.as_ref()
    }

    /// The phase to report with the next command.
    pub fn set_phase(&mut self, phase: Phase) {
        self.phase = phase;
    }

    /// The command the last `write` produced.
    pub fn take_command(&mut self) -> Option<SimCommand> {
        self.outgoing.take()
    }
}

impl UnitHardware for SimHardware {
    fn activate(&mut self) -> Result<(), HalError> {
        self.active = true;
        Ok(())
    }

    fn deactivate(&mut self) -> Result<(), HalError> {
        self.active = false;
        Ok(())
    }

    fn read(&mut self, out: &mut UnitReading) -> Result<(), HalError> {
        let s = self.latest.as_ref().ok_or_else(|| HalError::NoFeedback {
            joint: "all joints (simulated world)".into(),
            waited: Duration::ZERO,
        })?;
        let stamp = Duration::from_micros(s.stamp_us);
        out.wheels.position_rad = s.wheel_position_rad;
        out.wheels.velocity_radps = s.wheel_velocity_radps;
        out.wheels.effort_nm = None;
        out.wheels.stamp = stamp;
        out.arm.position_rad = s.arm_position_rad;
        out.arm.velocity_radps = s.arm_velocity_radps;
        out.arm.effort_nm = None;
        out.arm.stamp = stamp;
        out.grasp_force_n = Some(s.grasp_force_n);
        Ok(())
    }

    fn write(&mut self, out: &UnitOutput) -> Result<(), HalError> {
        if !self.active {
            return Err(HalError::NotEnabled {
                joint: "all joints (simulated world)".into(),
            });
        }
        let tick = self.latest.map_or(0, |s| s.tick);
        self.outgoing = Some(SimCommand {
            unit: self.unit,
            tick,
            phase: self.phase,
            command: out.command,
            grasp_open: out.grasp_open,
        });
        Ok(())
    }

    fn fault(&self) -> Option<HalError> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_bad_ones_are_named() {
        let s = SimSensed {
            unit: 1,
            tick: 7,
            stamp_us: 140_000,
            wheel_position_rad: [0.1, 0.2],
            wheel_velocity_radps: [0.0; 2],
            arm_position_rad: [0.3; 7],
            arm_velocity_radps: [0.0; 7],
            grasp_force_n: 30.0,
        };
        let bytes = encode(&s);
        assert_eq!(SimSensed::decode(&bytes, 1).unwrap(), s);
        assert!(matches!(
            SimSensed::decode(&bytes, 0),
            Err(LinkError::WrongUnit { got: 1, .. })
        ));
        assert!(matches!(
            SimSensed::decode(&bytes[..10], 1),
            Err(LinkError::Malformed(_))
        ));
        assert!(matches!(
            SimSensed::decode(&vec![b' '; 5000], 1),
            Err(LinkError::TooLarge(5000))
        ));
        let mut hw = SimHardware::new(1);
        let mut reading = UnitReading::default();
        assert!(hw.read(&mut reading).is_err());
        hw.deliver(s);
        hw.activate().unwrap();
        hw.read(&mut reading).unwrap();
        assert_eq!(reading.arm.position_rad, [0.3; 7]);
        hw.write(&UnitOutput::default()).unwrap();
        let c = hw.take_command().unwrap();
        assert_eq!((c.unit, c.tick), (1, 7));
        let mut bad = c;
        bad.command.arm_position_rad[3] = f64::NAN;
        assert!(matches!(
            SimCommand::decode(&encode(&bad), 2),
            Err(LinkError::Malformed(_) | LinkError::NonFinite { .. })
        ));
        assert!(SimCommand::decode(&encode(&c), 2).is_ok());
        assert!(SimCommand::decode(&encode(&c), 1).is_err());
    }
}
