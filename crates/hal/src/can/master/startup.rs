//! Start-up and bring-up: NMT, per-drive SDO configuration (device type, heartbeat, mode of
//! operation, PDO mapping), and the state-machine sequences that enable, disable and reset the
//! drives by cycling until every drive has reached the wanted state.

use std::time::Duration;

use super::Cia402Master;
use crate::can::cia402::{self as od, Cia402State, TPDO1, TPDO2};
use crate::can::protocol::{
    abort_reason, MapEntry, Message, NmtCommand, Sdo, RPDO_BASE, SDO_TX_BASE, TPDO_BASE,
};
use crate::can::{CanBus, CanError};

impl<B: CanBus> Cia402Master<B> {
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
}
