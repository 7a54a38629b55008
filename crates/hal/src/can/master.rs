//! The CANopen master for a unit's nine CiA 402 drives, and its [`WheelDrive`]/[`ArmDrive`]
//! implementation.
//!
//! Start-up (per drive, by SDO): check the device type is CiA 402, set the heartbeat producer,
//! set and verify the mode of operation, map RPDO1 (controlword + target) and TPDO1/TPDO2
//! (statusword + position, velocity + torque), all synchronous; then NMT start. Each control
//! cycle sends the nine RPDOs and a SYNC, then receives until the period ends: TPDOs update the
//! feedback, heartbeats and EMCYs are supervised. Every anomaly latches a [`CanError`] naming
//! the joint and node (or the stranger's COB-ID); nothing a frame contains can panic the master,
//! and every wait is bounded by a configured time-out on the bus clock.
//!
//! On a latched fault the master no longer walks drives towards Operation Enabled (a drive that
//! dropped out is not silently re-enabled) but leaves enabled drives holding their targets:
//! whether to stop or to drop torque is the daemon's decision, not the bus layer's.
//!
//! **Files.** This root holds the master's state (one `Axis` per drive), its bus accessors and
//! the drive-trait implementations; `startup` brings the drives up (NMT, SDO configuration,
//! the enable, disable and fault-reset sequences) and `cycle` is the cyclic exchange (RPDOs,
//! SYNC, TPDO feedback, heartbeat and process-data watchdogs).

mod cycle;
mod startup;

use std::time::Duration;

use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};

use super::cia402::{Cia402State, OperationMode};
use super::config::{DriveConfig, UnitCanConfig};
use super::protocol::Message;
use super::{CanBus, CanError, CanFrame, NodeRef};
use crate::{check_finite, ArmDrive, Drive, HalError, JointReading, Quantity, WheelDrive};

/// Traffic counters, for summaries and benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MasterStats {
    pub frames_sent: u64,
    pub frames_received: u64,
    pub cycles: u64,
}

/// What the master knows about one drive.
#[derive(Debug, Clone)]
struct Axis {
    at: NodeRef,
    config: DriveConfig,
    last_heartbeat: Duration,
    state: Option<Cia402State>,
    /// Reached Operation Enabled since the last enable request.
    reached_enabled: bool,
    /// Last raw position, to unwrap the 32-bit counter.
    raw_position: Option<i32>,
    position_counts: i64,
    velocity_countsps: i32,
    torque_permille: i16,
    feedback_stamp: Option<Duration>,
    /// Commanded target once enabled: counts (CSP) or counts/s (CSV).
    target: i32,
    controlword: u16,
    fault: Option<CanError>,
}

impl Axis {
    fn new(config: &DriveConfig) -> Self {
        Axis {
            at: NodeRef {
                joint: config.joint.clone(),
                node: config.node_id,
            },
            config: config.clone(),
            last_heartbeat: Duration::ZERO,
            state: None,
            reached_enabled: false,
            raw_position: None,
            position_counts: 0,
            velocity_countsps: 0,
            torque_permille: 0,
            feedback_stamp: None,
            target: 0,
            controlword: 0,
            fault: None,
        }
    }

    /// The target that holds the drive still: its position (CSP) or zero velocity (CSV).
    fn hold_target(&self) -> i32 {
        match self.config.mode {
            OperationMode::Csp => self.raw_position.unwrap_or(0),
            OperationMode::Csv => 0,
        }
    }

    fn latch(&mut self, error: CanError) {
        self.fault.get_or_insert(error);
    }
}

/// The master of one unit's CAN bus; wheels are axes 0–1, arm joints 2–8.
pub struct Cia402Master<B> {
    bus: B,
    config: UnitCanConfig,
    axes: Vec<Axis>,
    names: Vec<String>,
    /// Node id → axis index.
    node_axis: [Option<u8>; 128],
    /// Set once started: when supervision (heartbeat, TPDO time-outs) began counting.
    started: Option<Duration>,
    enable: bool,
    reset: bool,
    bus_fault: Option<CanError>,
    stats: MasterStats,
}

impl<B: CanBus> Cia402Master<B> {
    /// A master for the drives of `config` (validated by [`UnitCanConfig::from_file`]).
    pub fn new(bus: B, config: &UnitCanConfig) -> Self {
        let axes: Vec<Axis> = config.drives().map(Axis::new).collect();
        let mut node_axis = [None; 128];
        for (i, axis) in axes.iter().enumerate() {
            node_axis[usize::from(axis.at.node & 0x7F)] = Some(i as u8);
        }
        Cia402Master {
            bus,
            config: config.clone(),
            names: axes.iter().map(|a| a.at.joint.clone()).collect(),
            axes,
            node_axis,
            started: None,
            enable: false,
            reset: false,
            bus_fault: None,
            stats: MasterStats::default(),
        }
    }

    pub fn bus(&self) -> &B {
        &self.bus
    }

    pub fn bus_mut(&mut self) -> &mut B {
        &mut self.bus
    }

    pub fn into_bus(self) -> B {
        self.bus
    }

    pub fn stats(&self) -> MasterStats {
        self.stats
    }

    /// Each drive's last reported CiA 402 state, wheels then arm.
    pub fn drive_states(&self) -> impl Iterator<Item = (&NodeRef, Option<Cia402State>)> {
        self.axes.iter().map(|a| (&a.at, a.state))
    }

    /// The first latched fault: the bus's, else the first drive's in axis order.
    pub fn first_fault(&self) -> Option<&CanError> {
        self.bus_fault
            .as_ref()
            .or_else(|| self.axes.iter().find_map(|a| a.fault.as_ref()))
    }

    fn fault_result(&self) -> Result<(), CanError> {
        self.first_fault().cloned().map_or(Ok(()), Err)
    }

    fn send(&mut self, message: Message) -> Result<(), CanError> {
        self.bus.send(&message.encode())?;
        self.stats.frames_sent += 1;
        Ok(())
    }

    fn recv(&mut self, deadline: Duration) -> Result<Option<CanFrame>, CanError> {
        let frame = self.bus.recv_until(deadline)?;
        self.stats.frames_received += u64::from(frame.is_some());
        Ok(frame)
    }

    fn check_commandable(&self, axes: std::ops::Range<usize>) -> Result<(), HalError> {
        self.fault_result()?;
        match self.axes[axes]
            .iter()
            .find(|a| !self.enable || a.state != Some(Cia402State::OperationEnabled))
        {
            Some(axis) => Err(HalError::NotEnabled {
                joint: axis.at.joint.clone(),
            }),
            None => Ok(()),
        }
    }

    fn command(
        &mut self,
        first: usize,
        values: &[f64],
        quantity: Quantity,
    ) -> Result<(), HalError> {
        let axes = first..first + values.len();
        self.check_commandable(axes.clone())?;
        check_finite(&self.names[axes.clone()], values, quantity)?;
        for (axis, &value) in self.axes[axes].iter_mut().zip(values) {
            axis.target = axis.config.to_counts(value);
        }
        Ok(())
    }

    fn reading<const N: usize>(&self, first: usize) -> Result<JointReading<N>, HalError> {
        let axes = &self.axes[first..first + N];
        let mut stamp = Duration::MAX;
        for axis in axes {
            stamp = stamp.min(axis.feedback_stamp.ok_or_else(|| HalError::NoFeedback {
                joint: axis.at.joint.clone(),
                waited: self.bus.now(),
            })?);
        }
        // Effort only where every drive has a rated torque; no allocation on the cyclic path.
        let mut effort_nm = Some([0.0; N]);
        for (j, axis) in axes.iter().enumerate() {
            match (
                effort_nm.as_mut(),
                axis.config.to_effort_nm(axis.torque_permille),
            ) {
                (Some(e), Some(value)) => e[j] = value,
                _ => effort_nm = None,
            }
        }
        Ok(JointReading {
            position_rad: std::array::from_fn(|j| {
                axes[j].config.to_rad(axes[j].position_counts as f64)
            }),
            velocity_radps: std::array::from_fn(|j| {
                axes[j].config.to_rad(axes[j].velocity_countsps.into())
            }),
            effort_nm,
            stamp,
        })
    }
}

impl<B: CanBus> Drive for Cia402Master<B> {
    fn enable(&mut self) -> Result<(), HalError> {
        Ok(self.enable_drives()?)
    }

    fn disable(&mut self) -> Result<(), HalError> {
        Ok(self.disable_drives()?)
    }

    fn fault(&self) -> Option<HalError> {
        self.first_fault().cloned().map(HalError::Can)
    }

    fn reset_fault(&mut self) -> Result<(), HalError> {
        Ok(self.reset_faults()?)
    }

    fn sync(&mut self) -> Result<(), HalError> {
        self.cycle()?;
        Ok(self.fault_result()?)
    }
}

impl<B: CanBus> WheelDrive for Cia402Master<B> {
    fn command_velocity(&mut self, velocity_radps: &[f64; WHEEL_JOINTS]) -> Result<(), HalError> {
        self.command(0, velocity_radps, Quantity::Velocity)
    }

    fn read_wheels(&mut self) -> Result<JointReading<WHEEL_JOINTS>, HalError> {
        self.reading(0)
    }
}

impl<B: CanBus> ArmDrive for Cia402Master<B> {
    fn command_position(&mut self, position_rad: &[f64; ARM_JOINTS]) -> Result<(), HalError> {
        self.command(WHEEL_JOINTS, position_rad, Quantity::Position)
    }

    fn read_arm(&mut self) -> Result<JointReading<ARM_JOINTS>, HalError> {
        self.reading(WHEEL_JOINTS)
    }
}
