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

use std::time::Duration;

use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};

use super::cia402::{self as od, next_controlword, Cia402State, OperationMode, TPDO1, TPDO2};
use super::config::{DriveConfig, UnitCanConfig};
use super::protocol::{
    abort_reason, emergency_description, pack_pdo, unpack_pdo, MapEntry, Message, NmtCommand,
    NmtState, Sdo, RPDO_BASE, SDO_TX_BASE, TPDO_BASE,
};
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

    /// Sends an NMT command to `node` (0: every node).
    pub fn nmt(&mut self, command: NmtCommand, node: u8) -> Result<(), CanError> {
        self.send(Message::Nmt { command, node })
    }

    /// Resets communication of every drive, configures each by SDO and starts them (NMT).
    pub fn start_up(&mut self) -> Result<(), CanError> {
        self.started = None;
        self.nmt(NmtCommand::ResetCommunication, 0)?;
        for i in 0..self.axes.len() {
            self.configure(i)?;
        }
        self.nmt(NmtCommand::Start, 0)?;
        self.started = Some(self.bus.now());
        Ok(())
    }

    /// Disables every drive, then stops them (NMT); `start_up` brings them back.
    pub fn shut_down(&mut self) -> Result<(), CanError> {
        let disabled = self.disable_drives();
        self.nmt(NmtCommand::Stop, 0)?;
        self.started = None;
        disabled
    }

    fn configure(&mut self, i: usize) -> Result<(), CanError> {
        let (node, mode) = (self.axes[i].at.node, self.axes[i].config.mode);
        let device_type = self.sdo_upload(i, od::DEVICE_TYPE, 0)?;
        if device_type & 0xFFFF != od::CIA402_PROFILE {
            return Err(CanError::NotCia402 {
                at: self.axes[i].at.clone(),
                found: device_type,
            });
        }
        let heartbeat_ms = self.config.heartbeat_producer_ms;
        self.sdo_download(i, od::HEARTBEAT_PRODUCER, 0, heartbeat_ms.into(), 2)?;
        self.sdo_download(i, od::MODES_OF_OPERATION, 0, mode.code() as u8 as u32, 1)?;
        let found = self.sdo_upload(i, od::MODES_DISPLAY, 0)? as u8 as i8;
        if found != mode.code() {
            return Err(CanError::ModeMismatch {
                at: self.axes[i].at.clone(),
                requested: mode.code(),
                found,
            });
        }
        let node = u16::from(node);
        self.configure_pdo(
            i,
            od::RPDO_COMM,
            od::RPDO_MAP,
            RPDO_BASE[0] + node,
            mode.rpdo(),
        )?;
        self.configure_pdo(i, od::TPDO_COMM, od::TPDO_MAP, TPDO_BASE[0] + node, &TPDO1)?;
        self.configure_pdo(
            i,
            od::TPDO_COMM + 1,
            od::TPDO_MAP + 1,
            TPDO_BASE[1] + node,
            &TPDO2,
        )
    }

    /// CiA 301 PDO set-up: invalidate, clear the mapping, map, set the count, synchronous
    /// transmission, validate.
    fn configure_pdo(
        &mut self,
        i: usize,
        comm: u16,
        map: u16,
        cob_id: u16,
        entries: &[MapEntry],
    ) -> Result<(), CanError> {
        let cob_id = u32::from(cob_id);
        self.sdo_download(i, comm, 1, cob_id | od::PDO_INVALID, 4)?;
        self.sdo_download(i, map, 0, 0, 1)?;
        for (sub, entry) in (1..).zip(entries) {
            self.sdo_download(i, map, sub, entry.raw(), 4)?;
        }
        self.sdo_download(i, map, 0, entries.len() as u32, 1)?;
        self.sdo_download(i, comm, 2, od::TRANSMISSION_SYNC.into(), 1)?;
        self.sdo_download(i, comm, 1, cob_id, 4)
    }

    /// Expedited SDO download of `size` bytes to axis `i`.
    pub fn sdo_download(
        &mut self,
        i: usize,
        index: u16,
        sub: u8,
        value: u32,
        size: u8,
    ) -> Result<(), CanError> {
        match self.sdo_transfer(
            i,
            Sdo::Download {
                index,
                sub,
                value,
                size,
            },
        )? {
            Sdo::DownloadAck { .. } => Ok(()),
            other => Err(self.sdo_protocol(
                i,
                index,
                sub,
                format!("expected a download ack, got {other:?}"),
            )),
        }
    }

    /// Expedited SDO upload from axis `i`.
    pub fn sdo_upload(&mut self, i: usize, index: u16, sub: u8) -> Result<u32, CanError> {
        match self.sdo_transfer(i, Sdo::Upload { index, sub })? {
            Sdo::UploadReply { value, .. } => Ok(value),
            other => Err(self.sdo_protocol(
                i,
                index,
                sub,
                format!("expected an upload reply, got {other:?}"),
            )),
        }
    }

    fn sdo_protocol(&self, i: usize, index: u16, sub: u8, reason: String) -> CanError {
        CanError::SdoProtocol {
            at: self.axes[i].at.clone(),
            index,
            sub,
            reason,
        }
    }

    /// One request and its reply (or abort, or time-out); other traffic is handled meanwhile.
    fn sdo_transfer(&mut self, i: usize, request: Sdo) -> Result<Sdo, CanError> {
        let node = self.axes[i].at.node;
        let (index, sub) = request.object();
        self.send(Message::SdoRequest { node, sdo: request })?;
        let waited = Duration::from_secs_f64(self.config.sdo_timeout_s);
        let deadline = self.bus.now() + waited;
        while let Some(frame) = self.recv(deadline)? {
            if frame.id() != SDO_TX_BASE + u16::from(node) {
                self.handle(&frame);
                continue;
            }
            let reply = match Message::decode(&frame) {
                Ok(Message::SdoResponse { sdo, .. }) => sdo,
                other => return Err(self.sdo_protocol(i, index, sub, format!("{other:?}"))),
            };
            if reply.object() != (index, sub) {
                return Err(self.sdo_protocol(
                    i,
                    index,
                    sub,
                    format!("reply for another object: {reply:?}"),
                ));
            }
            if let Sdo::Abort { code, .. } = reply {
                return Err(CanError::SdoAbort {
                    at: self.axes[i].at.clone(),
                    index,
                    sub,
                    code,
                    reason: abort_reason(code),
                });
            }
            return Ok(reply);
        }
        Err(CanError::SdoTimeout {
            at: self.axes[i].at.clone(),
            index,
            sub,
            waited,
        })
    }

    /// One control cycle: RPDOs, SYNC, then everything received until the period ends.
    pub fn cycle(&mut self) -> Result<(), CanError> {
        let start = self.bus.now();
        if self.started.is_some() {
            let faulted = self.first_fault().is_some();
            for i in 0..self.axes.len() {
                let axis = &self.axes[i];
                let holding = axis.state == Some(Cia402State::OperationEnabled);
                let enable = self.enable && (!faulted || holding);
                let cw = next_controlword(axis.state, enable, self.reset, axis.controlword);
                let target = if self.enable && axis.reached_enabled {
                    axis.target
                } else {
                    axis.hold_target()
                };
                let (data, len) = pack_pdo(axis.config.mode.rpdo(), |e| {
                    if e.index == od::CONTROLWORD {
                        cw.into()
                    } else {
                        target as u32
                    }
                });
                self.axes[i].controlword = cw;
                let node = self.axes[i].at.node;
                self.send(Message::Rpdo {
                    node,
                    pdo: 1,
                    data: &data[..len],
                })?;
            }
        }
        self.send(Message::Sync)?;
        let deadline = start + self.config.sync_period();
        while let Some(frame) = self.recv(deadline)? {
            self.handle(&frame);
        }
        self.supervise();
        self.stats.cycles += 1;
        Ok(())
    }

    /// Applies one received frame; anything wrong latches a fault, nothing panics.
    pub fn handle(&mut self, frame: &CanFrame) {
        let now = self.bus.now();
        let cob_id = frame.id();
        let axis = self.node_axis[usize::from(cob_id & 0x7F)].map(usize::from);
        let message = match Message::decode(frame) {
            Ok(message) => message,
            Err(reason) => {
                match axis {
                    Some(i) => {
                        let at = self.axes[i].at.clone();
                        self.axes[i].latch(CanError::Malformed { at, cob_id, reason })
                    }
                    None => self.foreign(cob_id, format!("undecodable: {reason}")),
                }
                return;
            }
        };
        let i = match (message, axis) {
            (
                Message::Nmt { .. }
                | Message::Sync
                | Message::Rpdo { .. }
                | Message::SdoRequest { .. },
                _,
            ) => {
                return self.foreign(cob_id, "a frame only a master sends".into());
            }
            (_, None) => return self.foreign(cob_id, "unknown node".into()),
            (_, Some(i)) => i,
        };
        let started = self.started.is_some();
        let axis = &mut self.axes[i];
        match message {
            Message::Heartbeat { state, .. } => {
                axis.last_heartbeat = now;
                if state == NmtState::BootUp && started {
                    axis.latch(CanError::Rebooted {
                        at: axis.at.clone(),
                    });
                }
            }
            Message::Emergency { code, register, .. } if code != 0 => {
                axis.latch(CanError::Emergency {
                    at: axis.at.clone(),
                    code,
                    register,
                    description: emergency_description(code),
                })
            }
            Message::Tpdo { pdo: 1, data, .. } => self.tpdo1(i, data, now),
            Message::Tpdo { pdo: 2, data, .. } => {
                let (mut velocity, mut torque) = (0, 0);
                let unpacked = unpack_pdo(&TPDO2, data, |e, v| match e.index {
                    od::VELOCITY_ACTUAL => velocity = v as i32,
                    _ => torque = v as u16 as i16,
                });
                match unpacked {
                    Ok(()) => (axis.velocity_countsps, axis.torque_permille) = (velocity, torque),
                    Err(reason) => axis.latch(CanError::Malformed {
                        at: axis.at.clone(),
                        cob_id,
                        reason,
                    }),
                }
            }
            Message::Tpdo { .. } => axis.latch(CanError::Malformed {
                at: axis.at.clone(),
                cob_id,
                reason: super::protocol::DecodeError::Unsupported,
            }),
            // Error resets and SDO replies that arrive after their time-out carry no news.
            _ => {}
        }
    }

    fn tpdo1(&mut self, i: usize, data: &[u8], now: Duration) {
        let enable = self.enable;
        let axis = &mut self.axes[i];
        let (mut statusword, mut position) = (0, 0);
        let unpacked = unpack_pdo(&TPDO1, data, |e, v| match e.index {
            od::STATUSWORD => statusword = v as u16,
            _ => position = v as i32,
        });
        if let Err(reason) = unpacked {
            return axis.latch(CanError::Malformed {
                at: axis.at.clone(),
                cob_id: TPDO_BASE[0] + u16::from(axis.at.node),
                reason,
            });
        }
        axis.position_counts = match axis.raw_position {
            Some(last) => axis.position_counts + i64::from(position.wrapping_sub(last)),
            None => position.into(),
        };
        axis.raw_position = Some(position);
        axis.feedback_stamp = Some(now);
        let state = Cia402State::from_statusword(statusword);
        match state {
            Some(Cia402State::Fault | Cia402State::FaultReactionActive) => {
                axis.latch(CanError::DriveFault {
                    at: axis.at.clone(),
                    statusword,
                })
            }
            Some(Cia402State::OperationEnabled) if enable && !axis.reached_enabled => {
                // Commands start from where the drive was enabled: no jump.
                axis.reached_enabled = true;
                axis.target = axis.hold_target();
            }
            Some(Cia402State::OperationEnabled) => {}
            Some(other) if enable && axis.reached_enabled => {
                axis.reached_enabled = false;
                axis.latch(CanError::LeftOperationEnabled {
                    at: axis.at.clone(),
                    state: other,
                });
            }
            _ => {}
        }
        axis.state = state;
    }

    fn foreign(&mut self, cob_id: u16, what: String) {
        self.bus_fault
            .get_or_insert(CanError::Foreign { cob_id, what });
    }

    /// Heartbeat and process-data time-outs.
    fn supervise(&mut self) {
        let Some(started) = self.started else {
            return;
        };
        let now = self.bus.now();
        let heartbeat_timeout = Duration::from_secs_f64(self.config.heartbeat_timeout_s);
        let feedback_timeout = Duration::from_secs_f64(self.config.feedback_timeout_s);
        for axis in &mut self.axes {
            let silent = now.saturating_sub(axis.last_heartbeat.max(started));
            if silent > heartbeat_timeout {
                axis.latch(CanError::HeartbeatLost {
                    at: axis.at.clone(),
                    waited: silent,
                });
            }
            let stale = now.saturating_sub(axis.feedback_stamp.unwrap_or(started).max(started));
            if stale > feedback_timeout {
                axis.latch(CanError::NoFeedback {
                    at: axis.at.clone(),
                    waited: stale,
                });
            }
        }
    }

    /// Cycles until every drive satisfies `done`, failing on a fault (when `stop_on_fault`) or
    /// after the configured state-change time-out.
    fn cycle_until(
        &mut self,
        wanted: Cia402State,
        stop_on_fault: bool,
        done: fn(Option<Cia402State>) -> bool,
    ) -> Result<(), CanError> {
        let waited = Duration::from_secs_f64(self.config.state_change_timeout_s);
        let deadline = self.bus.now() + waited;
        loop {
            if stop_on_fault {
                self.fault_result()?;
            }
            if let Some(axis) = self.axes.iter().find(|a| !done(a.state)) {
                if self.bus.now() >= deadline {
                    return Err(CanError::StateTimeout {
                        at: axis.at.clone(),
                        state: axis.state,
                        wanted,
                        waited,
                    });
                }
            } else {
                return Ok(());
            }
            self.cycle()?;
        }
    }

    /// Walks every drive to Operation Enabled, holding its position (running start-up first
    /// if needed).
    pub fn enable_drives(&mut self) -> Result<(), CanError> {
        if self.started.is_none() {
            self.start_up()?;
        }
        self.fault_result()?;
        for axis in &mut self.axes {
            axis.reached_enabled = false;
        }
        self.enable = true;
        self.cycle_until(Cia402State::OperationEnabled, true, |s| {
            s == Some(Cia402State::OperationEnabled)
        })
    }

    /// Takes every drive out of Operation Enabled (torque off), also while faulted.
    pub fn disable_drives(&mut self) -> Result<(), CanError> {
        self.enable = false;
        self.cycle_until(Cia402State::ReadyToSwitchOn, false, |s| {
            s != Some(Cia402State::OperationEnabled)
        })
    }

    /// Clears latched faults and resets drives in Fault; drives end disabled.
    pub fn reset_faults(&mut self) -> Result<(), CanError> {
        // Time-outs count afresh from now: a drive still silent faults again after them.
        self.started = self.started.map(|_| self.bus.now());
        self.bus_fault = None;
        self.enable = false;
        for axis in &mut self.axes {
            axis.fault = None;
        }
        self.reset = true;
        let result = self.cycle_until(Cia402State::SwitchOnDisabled, true, |s| {
            !matches!(
                s,
                Some(Cia402State::Fault | Cia402State::FaultReactionActive)
            )
        });
        self.reset = false;
        result
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
        let efforts: Option<Vec<f64>> = axes
            .iter()
            .map(|a| a.config.to_effort_nm(a.torque_permille))
            .collect();
        Ok(JointReading {
            position_rad: std::array::from_fn(|j| {
                axes[j].config.to_rad(axes[j].position_counts as f64)
            }),
            velocity_radps: std::array::from_fn(|j| {
                axes[j].config.to_rad(axes[j].velocity_countsps.into())
            }),
            effort_nm: efforts.map(|e| std::array::from_fn(|j| e[j])),
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
