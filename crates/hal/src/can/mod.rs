//! CiA 402 drives over CAN: frames, the [`CanBus`] seam (SocketCAN or an in-memory virtual
//! bus with emulated drives), the CANopen codec, the master that implements the drive traits,
//! candump recording and replay, and the unit's drive config.
//!
//! The master is synchronous and talks to the bus through [`CanBus::recv_until`], a receive
//! with a deadline on the *bus's* clock. On SocketCAN that clock is the wall clock; on the
//! [`VirtualBus`] it is simulated and only moves while the master waits, so every time-out
//! (SDO, heartbeat, enable) is exercised deterministically and at full CPU speed. A real-time
//! daemon runs the master on its own thread (or `spawn_blocking`), paced by its SYNC period.

pub mod candump;
pub mod cia402;
pub mod config;
pub mod emulator;
pub mod master;
pub mod protocol;
pub mod socketcan_bus;
pub mod virtual_bus;

pub use candump::{LogEntry, RecordingBus};
pub use config::UnitCanConfig;
pub use emulator::EmulatedDrive;
pub use master::{Cia402Master, MasterStats};
pub use socketcan_bus::SocketCanBus;
pub use virtual_bus::VirtualBus;

use std::time::Duration;

use cia402::Cia402State;
use protocol::DecodeError;

/// A classic CAN 2.0A data frame: 11-bit identifier, 0–8 data bytes (all CANopen uses).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: u16,
    len: u8,
    data: [u8; 8],
}

/// Why bytes are not a classic 11-bit CAN frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("identifier 0x{0:X} does not fit in 11 bits")]
    BadId(u32),
    #[error("{0} data bytes (at most 8)")]
    TooLong(usize),
}

impl CanFrame {
    pub const MAX_ID: u16 = 0x7FF;

    pub fn new(id: u16, data: &[u8]) -> Result<Self, FrameError> {
        if id > Self::MAX_ID {
            return Err(FrameError::BadId(id.into()));
        }
        if data.len() > 8 {
            return Err(FrameError::TooLong(data.len()));
        }
        Ok(Self::from_parts(id, data))
    }

    /// For ids and payloads built in this crate (≤ 0x7FF, ≤ 8 bytes by construction).
    pub(crate) fn from_parts(id: u16, data: &[u8]) -> Self {
        let len = data.len().min(8);
        let mut bytes = [0; 8];
        bytes[..len].copy_from_slice(&data[..len]);
        CanFrame {
            id: id & Self::MAX_ID,
            len: len as u8,
            data: bytes,
        }
    }

    pub fn id(&self) -> u16 {
        self.id
    }

    pub fn data(&self) -> &[u8] {
        &self.data[..usize::from(self.len)]
    }
}

/// A failure of the bus itself (not of a drive on it).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BusError {
    #[error("cannot open CAN interface {bus}: {reason}")]
    Open { bus: String, reason: String },
    #[error("CAN interface {bus}: {reason}")]
    Io { bus: String, reason: String },
}

/// A CAN bus as the master sees it. Object-safe so tests, tools and the daemon can swap buses.
pub trait CanBus {
    /// The interface name, as written into candump logs.
    fn name(&self) -> &str;
    /// Time on the bus clock since the bus was opened.
    fn now(&self) -> Duration;
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError>;
    /// The next received frame, or `None` once the bus clock reaches `deadline`.
    fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError>;
}

/// A drive as errors name it: the joint from the unit config and its CANopen node id.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeRef {
    pub joint: String,
    pub node: u8,
}

impl std::fmt::Display for NodeRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "joint {} (CAN node {})", self.joint, self.node)
    }
}

/// A fault of the CAN drive layer; every drive-level variant names the joint and node.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CanError {
    #[error(transparent)]
    Bus(#[from] BusError),
    #[error("{at}: SDO {index:04X}:{sub:02X} aborted: {reason} (0x{code:08X})")]
    SdoAbort {
        at: NodeRef,
        index: u16,
        sub: u8,
        code: u32,
        reason: &'static str,
    },
    #[error("{at}: SDO {index:04X}:{sub:02X} got no reply within {waited:?}")]
    SdoTimeout {
        at: NodeRef,
        index: u16,
        sub: u8,
        waited: Duration,
    },
    #[error("{at}: SDO {index:04X}:{sub:02X}: {reason}")]
    SdoProtocol {
        at: NodeRef,
        index: u16,
        sub: u8,
        reason: String,
    },
    #[error("{at}: device type 0x{found:08X} is not a CiA 402 drive")]
    NotCia402 { at: NodeRef, found: u32 },
    #[error("{at}: reports mode of operation {found} after {requested} was requested")]
    ModeMismatch {
        at: NodeRef,
        requested: i8,
        found: i8,
    },
    #[error("{at}: no heartbeat for {waited:?}")]
    HeartbeatLost { at: NodeRef, waited: Duration },
    #[error("{at}: no process data (TPDO) for {waited:?}")]
    NoFeedback { at: NodeRef, waited: Duration },
    #[error("{at}: emergency 0x{code:04X} ({description}), error register 0x{register:02X}")]
    Emergency {
        at: NodeRef,
        code: u16,
        register: u8,
        description: &'static str,
    },
    #[error("{at}: drive in Fault (statusword 0x{statusword:04X})")]
    DriveFault { at: NodeRef, statusword: u16 },
    #[error("{at}: dropped out of Operation Enabled into {state:?}")]
    LeftOperationEnabled { at: NodeRef, state: Cia402State },
    #[error("{at}: still {state:?} after {waited:?} (wanted {wanted:?})")]
    StateTimeout {
        at: NodeRef,
        state: Option<Cia402State>,
        wanted: Cia402State,
        waited: Duration,
    },
    #[error("{at}: drive rebooted (boot-up message) while in use")]
    Rebooted { at: NodeRef },
    #[error("{at}: malformed frame 0x{cob_id:03X}: {reason}")]
    Malformed {
        at: NodeRef,
        cob_id: u16,
        reason: DecodeError,
    },
    #[error("{at}: not started (run start-up first)")]
    NotStarted { at: NodeRef },
    #[error("frame 0x{cob_id:03X} from outside the unit: {what}")]
    Foreign { cob_id: u16, what: String },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_reject_long_ids_and_payloads() {
        assert_eq!(CanFrame::new(0x800, &[]), Err(FrameError::BadId(0x800)));
        assert_eq!(CanFrame::new(0x1, &[0; 9]), Err(FrameError::TooLong(9)));
        let f = CanFrame::new(0x601, &[1, 2, 3]).unwrap();
        assert_eq!((f.id(), f.data()), (0x601, &[1u8, 2, 3][..]));
    }
}
