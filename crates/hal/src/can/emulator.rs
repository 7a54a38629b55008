//! An emulated CiA 402 drive for the virtual bus: the object dictionary subset the master
//! uses, NMT, expedited SDO, one RPDO and two TPDOs configurable by SDO, SYNC response,
//! heartbeat, EMCY, the power-drive state machine, a first-order motor and fault injection.
//! It is driven only by frames and explicit time, so it is deterministic: replaying a recorded
//! log into a fresh drive reproduces its answers frame for frame.

use std::collections::VecDeque;
use std::time::Duration;

use super::cia402::{self as od, Cia402State, OperationMode};
use super::config::{DriveConfig, EmulatorConfig};
use super::protocol::{
    mapped_bytes, pack_pdo, unpack_pdo, MapEntry, Message, NmtCommand, NmtState, Sdo, RPDO_BASE,
    TPDO_BASE,
};
use super::CanFrame;

/// SDO abort codes the emulated drive answers with (CiA 301).
mod abort {
    pub const NO_OBJECT: u32 = 0x0602_0000;
    pub const NO_SUB: u32 = 0x0609_0011;
    pub const READ_ONLY: u32 = 0x0601_0002;
    pub const LENGTH: u32 = 0x0607_0010;
    pub const VALUE_RANGE: u32 = 0x0609_0030;
    pub const NOT_MAPPABLE: u32 = 0x0604_0041;
    pub const PDO_LENGTH: u32 = 0x0604_0042;
    pub const DEVICE_STATE: u32 = 0x0800_0022;
    pub const COMMAND: u32 = 0x0504_0001;
}

/// EMCY error register bit 0: generic error.
const GENERIC_ERROR: u8 = 0x01;
/// Mapping entries per PDO (CiA 301 allows 64; 8 bytes never need more than 8).
const MAX_MAPPED: usize = 8;

/// Objects that may appear in an RPDO mapping.
const RPDO_MAPPABLE: [u16; 3] = [od::CONTROLWORD, od::TARGET_POSITION, od::TARGET_VELOCITY];
/// Objects that may appear in a TPDO mapping.
const TPDO_MAPPABLE: [u16; 4] = [
    od::STATUSWORD,
    od::POSITION_ACTUAL,
    od::VELOCITY_ACTUAL,
    od::TORQUE_ACTUAL,
];

#[derive(Debug, Clone, PartialEq)]
struct Pdo {
    cob_id: u32,
    transmission: u8,
    mapping: Vec<MapEntry>,
    syncs_seen: u8,
}

impl Pdo {
    fn new(cob_id: u16) -> Self {
        Pdo {
            cob_id: u32::from(cob_id) | od::PDO_INVALID,
            transmission: od::TRANSMISSION_SYNC,
            mapping: Vec::new(),
            syncs_seen: 0,
        }
    }

    fn valid(&self) -> bool {
        self.cob_id & od::PDO_INVALID == 0
    }
}

/// Faults a test switches on in an emulated drive.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DriveFaults {
    /// Sends nothing at all: heartbeat loss, SDO time-out, missing TPDOs.
    pub silent: bool,
    /// Answers every SDO request for this object with this abort code.
    pub sdo_abort: Option<(u16, u8, u32)>,
}

/// Communication parameters that NMT reset-communication restores.
#[derive(Debug, Clone, PartialEq)]
struct Comm {
    heartbeat_ms: u16,
    next_heartbeat: Duration,
    /// RPDO1, TPDO1, TPDO2.
    pdos: [Pdo; 3],
}

/// Index of RPDO1 in [`Comm::pdos`]; the TPDOs follow.
const RPDO: usize = 0;

impl Comm {
    fn new(node: u8) -> Self {
        let node = u16::from(node);
        Comm {
            heartbeat_ms: 0,
            next_heartbeat: Duration::ZERO,
            pdos: [
                Pdo::new(RPDO_BASE[0] + node),
                Pdo::new(TPDO_BASE[0] + node),
                Pdo::new(TPDO_BASE[1] + node),
            ],
        }
    }
}

/// Which PDO a parameter object belongs to, and whether it is its mapping object.
fn pdo_slot(index: u16) -> Option<(usize, bool)> {
    match index {
        i if i == od::RPDO_COMM => Some((RPDO, false)),
        i if i == od::RPDO_MAP => Some((RPDO, true)),
        i if (od::TPDO_COMM..od::TPDO_COMM + 2).contains(&i) => {
            Some((1 + usize::from(i - od::TPDO_COMM), false))
        }
        i if (od::TPDO_MAP..od::TPDO_MAP + 2).contains(&i) => {
            Some((1 + usize::from(i - od::TPDO_MAP), true))
        }
        _ => None,
    }
}

/// One emulated drive; the joint units come from the same [`DriveConfig`] the master uses.
#[derive(Debug, Clone)]
pub struct EmulatedDrive {
    config: DriveConfig,
    emulator: EmulatorConfig,
    node: u8,
    nmt: NmtState,
    comm: Comm,
    state: Cia402State,
    controlword: u16,
    mode: i8,
    error_code: u16,
    target_position: i32,
    target_velocity: i32,
    /// Counts and counts/s, unrounded.
    position: f64,
    velocity: f64,
    torque_permille: i16,
    /// RPDO payload received, applied on the next SYNC (synchronous transmission type).
    pending_rpdo: Option<CanFrame>,
    now: Duration,
    outbox: VecDeque<CanFrame>,
    pub faults: DriveFaults,
}

impl EmulatedDrive {
    /// A drive that has just powered up: pre-operational, boot-up message queued.
    pub fn new(config: &DriveConfig, emulator: EmulatorConfig) -> Self {
        let mut drive = EmulatedDrive {
            node: config.node_id,
            config: config.clone(),
            emulator,
            nmt: NmtState::PreOperational,
            comm: Comm::new(config.node_id),
            state: Cia402State::SwitchOnDisabled,
            controlword: 0,
            mode: 0,
            error_code: 0,
            target_position: 0,
            target_velocity: 0,
            position: 0.0,
            velocity: 0.0,
            torque_permille: 0,
            pending_rpdo: None,
            now: Duration::ZERO,
            outbox: VecDeque::new(),
            faults: DriveFaults::default(),
        };
        drive.boot();
        drive
    }

    pub fn node(&self) -> u8 {
        self.node
    }

    pub fn state(&self) -> Cia402State {
        self.state
    }

    pub fn nmt_state(&self) -> NmtState {
        self.nmt
    }

    /// Joint position, rad.
    pub fn position_rad(&self) -> f64 {
        self.config.to_rad(self.position)
    }

    /// Places the joint (its position at power-on), rad.
    pub fn set_position_rad(&mut self, position_rad: f64) {
        self.position = f64::from(self.config.to_counts(position_rad));
        self.target_position = self.config.to_counts(position_rad);
    }

    /// Raises a drive fault: Fault state, error code in 0x603F, EMCY with `code`.
    pub fn raise_fault(&mut self, code: u16) {
        self.state = Cia402State::Fault;
        self.error_code = code;
        self.send_emergency(code);
    }

    /// Drops out of Operation Enabled without a fault, as an STO input or a local stop would.
    pub fn drop_out(&mut self) {
        self.state = Cia402State::SwitchOnDisabled;
    }

    /// Frames this drive sent since the last call.
    pub fn drain(&mut self, out: &mut VecDeque<CanFrame>) {
        if self.faults.silent {
            self.outbox.clear();
        }
        out.append(&mut self.outbox);
    }

    /// Advances the motor and the heartbeat producer to `now`.
    pub fn advance(&mut self, now: Duration) {
        let dt = now.saturating_sub(self.now).as_secs_f64();
        self.now = now;
        if dt > 0.0 {
            self.move_motor(dt);
        }
        if self.comm.heartbeat_ms > 0 && now >= self.comm.next_heartbeat {
            self.send(Message::Heartbeat {
                node: self.node,
                state: self.nmt,
            });
            self.comm.next_heartbeat = now + Duration::from_millis(self.comm.heartbeat_ms.into());
        }
    }

    fn move_motor(&mut self, dt: f64) {
        let old_velocity = self.velocity;
        let alpha = 1.0 - (-dt / self.emulator.time_constant_s).exp();
        if self.state != Cia402State::OperationEnabled {
            self.velocity = 0.0;
        } else if self.mode == OperationMode::Csv.code() {
            self.velocity += (f64::from(self.target_velocity) - self.velocity) * alpha;
            self.position += self.velocity * dt;
        } else if self.mode == OperationMode::Csp.code() {
            let next = self.position + (f64::from(self.target_position) - self.position) * alpha;
            self.velocity = (next - self.position) / dt;
            self.position = next;
        }
        let accel_radps2 = self.config.to_rad(self.velocity - old_velocity) / dt;
        self.torque_permille = self
            .config
            .to_permille(self.emulator.inertia_kgm2 * accel_radps2);
    }

    /// Handles one frame seen on the bus.
    pub fn receive(&mut self, frame: &CanFrame) {
        let Ok(message) = Message::decode(frame) else {
            return; // a real node ignores what it cannot parse
        };
        match message {
            Message::Nmt { command, node } if node == 0 || node == self.node => self.nmt(command),
            Message::Sync if self.nmt == NmtState::Operational => self.sync(),
            Message::Rpdo { node, pdo: 1, .. }
                if node == self.node
                    && self.nmt == NmtState::Operational
                    && self.comm.pdos[RPDO].valid() =>
            {
                self.pending_rpdo = Some(*frame);
            }
            Message::SdoRequest { node, sdo }
                if node == self.node && self.nmt != NmtState::Stopped =>
            {
                let reply = self.sdo(sdo);
                self.send(Message::SdoResponse {
                    node: self.node,
                    sdo: reply,
                });
            }
            _ => {}
        }
    }

    fn send(&mut self, message: Message) {
        self.outbox.push_back(message.encode());
    }

    fn send_emergency(&mut self, code: u16) {
        self.send(Message::Emergency {
            node: self.node,
            code,
            register: if code == 0 { 0 } else { GENERIC_ERROR },
        });
    }

    fn boot(&mut self) {
        self.nmt = NmtState::PreOperational;
        self.comm = Comm::new(self.node);
        self.send(Message::Heartbeat {
            node: self.node,
            state: NmtState::BootUp,
        });
    }

    fn nmt(&mut self, command: NmtCommand) {
        match command {
            NmtCommand::Start => self.nmt = NmtState::Operational,
            NmtCommand::Stop => self.nmt = NmtState::Stopped,
            NmtCommand::PreOperational => self.nmt = NmtState::PreOperational,
            NmtCommand::ResetNode => {
                *self = EmulatedDrive {
                    position: self.position,
                    now: self.now,
                    faults: self.faults,
                    ..EmulatedDrive::new(&self.config, self.emulator)
                };
            }
            NmtCommand::ResetCommunication => self.boot(),
        }
    }

    fn sync(&mut self) {
        if let Some(frame) = self.pending_rpdo.take() {
            // A wrongly sized RPDO is ignored, as CiA 301 drives do.
            let mut writes = [None; MAX_MAPPED];
            let mapping = &self.comm.pdos[RPDO].mapping;
            if unpack_pdo(mapping, frame.data(), |e, v| {
                if let Some(slot) = writes.iter_mut().find(|w| w.is_none()) {
                    *slot = Some((e, v));
                }
            })
            .is_ok()
            {
                for (entry, value) in writes.into_iter().flatten() {
                    let _ = self.write(entry.index, entry.sub, value, entry.bits / 8);
                }
            }
        }
        for (i, pdo) in [(1, 1u8), (2, 2)] {
            let pdo_state = &mut self.comm.pdos[i];
            if !pdo_state.valid() || !(1..=240).contains(&pdo_state.transmission) {
                continue;
            }
            pdo_state.syncs_seen += 1;
            if pdo_state.syncs_seen < pdo_state.transmission {
                continue;
            }
            pdo_state.syncs_seen = 0;
            let (data, len) = pack_pdo(&self.comm.pdos[i].mapping, |e| {
                self.read(e.index, e.sub).map_or(0, |(value, _)| value)
            });
            self.send(Message::Tpdo {
                node: self.node,
                pdo,
                data: &data[..len],
            });
        }
    }

    fn sdo(&mut self, request: Sdo) -> Sdo {
        let (index, sub) = request.object();
        let aborted = |code| Sdo::Abort { index, sub, code };
        if let Some((i, s, code)) = self.faults.sdo_abort {
            if (i, s) == (index, sub) {
                return aborted(code);
            }
        }
        match request {
            Sdo::Upload { .. } => match self.read(index, sub) {
                Ok((value, size)) => Sdo::UploadReply {
                    index,
                    sub,
                    value,
                    size,
                },
                Err(code) => aborted(code),
            },
            Sdo::Download { value, size, .. } => match self.write(index, sub, value, size) {
                Ok(()) => Sdo::DownloadAck { index, sub },
                Err(code) => aborted(code),
            },
            _ => aborted(abort::COMMAND),
        }
    }

    /// Reads an object: (value, size in bytes) or an abort code.
    fn read(&self, index: u16, sub: u8) -> Result<(u32, u8), u32> {
        if let Some((slot, mapping)) = pdo_slot(index) {
            let pdo = &self.comm.pdos[slot];
            return match (mapping, sub) {
                (false, 0) => Ok((2, 1)),
                (false, 1) => Ok((pdo.cob_id, 4)),
                (false, 2) => Ok((pdo.transmission.into(), 1)),
                (true, 0) => Ok((pdo.mapping.len() as u32, 1)),
                (true, s) => pdo
                    .mapping
                    .get(usize::from(s) - 1)
                    .map(|e| (e.raw(), 4))
                    .ok_or(abort::NO_SUB),
                _ => Err(abort::NO_SUB),
            };
        }
        if sub != 0 {
            return Err(if self.known(index) {
                abort::NO_SUB
            } else {
                abort::NO_OBJECT
            });
        }
        let (value, size) = match index {
            od::DEVICE_TYPE => (0x0002_0000 | od::CIA402_PROFILE, 4),
            od::ERROR_REGISTER => (u32::from(self.error_code != 0), 1),
            od::HEARTBEAT_PRODUCER => (self.comm.heartbeat_ms.into(), 2),
            od::ERROR_CODE => (self.error_code.into(), 2),
            od::CONTROLWORD => (self.controlword.into(), 2),
            od::STATUSWORD => (self.state.statusword().into(), 2),
            od::MODES_OF_OPERATION | od::MODES_DISPLAY => (self.mode as u8 as u32, 1),
            od::POSITION_ACTUAL => (self.position.round() as i32 as u32, 4),
            od::VELOCITY_ACTUAL => (self.velocity.round() as i32 as u32, 4),
            od::TORQUE_ACTUAL => (self.torque_permille as u16 as u32, 2),
            od::TARGET_POSITION => (self.target_position as u32, 4),
            od::TARGET_VELOCITY => (self.target_velocity as u32, 4),
            _ => return Err(abort::NO_OBJECT),
        };
        Ok((value, size))
    }

    fn known(&self, index: u16) -> bool {
        self.read(index, 0).is_ok()
    }

    /// CiA 301 PDO set-up: COB-ID and transmission type, and a mapping that may only change
    /// while the PDO is invalid (sub 0 cleared, entries written in order, then sub 0 = count).
    fn write_pdo_parameter(
        &mut self,
        slot: usize,
        mapping: bool,
        sub: u8,
        value: u32,
        size: u8,
    ) -> Result<(), u32> {
        let expected = match (mapping, sub) {
            (false, 1) | (true, 1..=8) => 4,
            (false, 2) | (true, 0) => 1,
            (false, 0) => return Err(abort::READ_ONLY),
            _ => return Err(abort::NO_SUB),
        };
        if size != expected {
            return Err(abort::LENGTH);
        }
        let mappable: &[u16] = if slot == RPDO {
            &RPDO_MAPPABLE
        } else {
            &TPDO_MAPPABLE
        };
        let pdo = &mut self.comm.pdos[slot];
        match (mapping, sub) {
            (false, 1) => pdo.cob_id = value,
            (false, _) => pdo.transmission = value as u8,
            (true, _) if pdo.valid() => return Err(abort::DEVICE_STATE),
            (true, 0) => {
                let count = value as usize;
                if count > pdo.mapping.len() {
                    return Err(abort::VALUE_RANGE);
                }
                pdo.mapping.truncate(count);
            }
            (true, s) => {
                let entry = MapEntry::from_raw(value);
                let at = usize::from(s) - 1;
                if at > pdo.mapping.len() {
                    return Err(abort::VALUE_RANGE);
                }
                if !mappable.contains(&entry.index) || entry.sub != 0 || entry.bits % 8 != 0 {
                    return Err(abort::NOT_MAPPABLE);
                }
                let before: usize = mapped_bytes(&pdo.mapping[..at]);
                if before + usize::from(entry.bits / 8) > 8 {
                    return Err(abort::PDO_LENGTH);
                }
                pdo.mapping.truncate(at);
                pdo.mapping.push(entry);
            }
        }
        Ok(())
    }

    /// Writes an object of `size` bytes (SDO download or RPDO), or returns an abort code.
    fn write(&mut self, index: u16, sub: u8, value: u32, size: u8) -> Result<(), u32> {
        if let Some((slot, mapping)) = pdo_slot(index) {
            return self.write_pdo_parameter(slot, mapping, sub, value, size);
        }
        let (_, expected) = self.read(index, sub)?;
        if size != expected {
            return Err(abort::LENGTH);
        }
        match index {
            od::HEARTBEAT_PRODUCER => {
                self.comm.heartbeat_ms = value as u16;
                self.comm.next_heartbeat = self.now;
            }
            od::CONTROLWORD => {
                let cw = value as u16;
                let before = self.state;
                self.state = self.state.on_controlword(self.controlword, cw);
                self.controlword = cw;
                if before == Cia402State::Fault && self.state != Cia402State::Fault {
                    self.error_code = 0;
                    self.send_emergency(0);
                }
                if before != Cia402State::OperationEnabled
                    && self.state == Cia402State::OperationEnabled
                {
                    // Enabling holds the current position, whatever target was sent before.
                    self.target_position = self.position.round() as i32;
                }
            }
            od::MODES_OF_OPERATION => {
                let mode = value as u8 as i8;
                OperationMode::from_code(mode).ok_or(abort::VALUE_RANGE)?;
                self.mode = mode;
            }
            od::TARGET_POSITION => self.target_position = value as i32,
            od::TARGET_VELOCITY => self.target_velocity = value as i32,
            _ => return Err(abort::READ_ONLY),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::can::config::tests::unit_config;

    fn drive() -> EmulatedDrive {
        let config = unit_config();
        EmulatedDrive::new(&config.arm[0], config.emulator)
    }

    fn sdo(drive: &mut EmulatedDrive, sdo: Sdo) -> Sdo {
        let node = drive.node();
        drive.receive(&Message::SdoRequest { node, sdo }.encode());
        let mut out = VecDeque::new();
        drive.drain(&mut out);
        let frame = out.pop_back().unwrap();
        match Message::decode(&frame) {
            Ok(Message::SdoResponse { sdo, .. }) => sdo,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn object_dictionary_answers_and_aborts() {
        let mut d = drive();
        let up = |index, sub| Sdo::Upload { index, sub };
        assert!(matches!(
            sdo(&mut d, up(0x1000, 0)),
            Sdo::UploadReply {
                value: 0x0002_0192,
                size: 4,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, up(0x2000, 0)),
            Sdo::Abort {
                code: abort::NO_OBJECT,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, up(0x6041, 3)),
            Sdo::Abort {
                code: abort::NO_SUB,
                ..
            }
        ));
        let down = |index, sub, value, size| Sdo::Download {
            index,
            sub,
            value,
            size,
        };
        assert!(matches!(
            sdo(&mut d, down(0x6041, 0, 1, 2)),
            Sdo::Abort {
                code: abort::READ_ONLY,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x6060, 0, 8, 2)),
            Sdo::Abort {
                code: abort::LENGTH,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x6060, 0, 3, 1)),
            Sdo::Abort {
                code: abort::VALUE_RANGE,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x6060, 0, 8, 1)),
            Sdo::DownloadAck { .. }
        ));
        assert!(matches!(
            sdo(&mut d, up(0x6061, 0)),
            Sdo::UploadReply { value: 8, .. }
        ));
        // Mapping a valid PDO is refused; a non-mappable object too.
        assert!(matches!(
            sdo(&mut d, down(0x1A00, 1, 0x6041_0010, 4)),
            Sdo::DownloadAck { .. }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x1A00, 2, 0x1000_0020, 4)),
            Sdo::Abort {
                code: abort::NOT_MAPPABLE,
                ..
            }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x1800, 1, 0x181, 4)),
            Sdo::DownloadAck { .. }
        ));
        assert!(matches!(
            sdo(&mut d, down(0x1A00, 0, 1, 1)),
            Sdo::Abort {
                code: abort::DEVICE_STATE,
                ..
            }
        ));
    }

    proptest::proptest! {
        /// Arbitrary frames, also for this node, never panic the emulated drive.
        #[test]
        fn arbitrary_frames_never_panic(frames in proptest::collection::vec(
            (0u16..=0x7FF, proptest::collection::vec(proptest::prelude::any::<u8>(), 0..=8)), 1..32)) {
            let mut d = drive();
            d.receive(&Message::Nmt { command: NmtCommand::Start, node: 0 }.encode());
            let mut out = VecDeque::new();
            for (id, data) in frames {
                // Aim half of them at this node's COB-IDs.
                let id = if id & 1 == 0 { (id & 0x780) | 3 } else { id };
                d.receive(&CanFrame::new(id, &data).unwrap());
                d.advance(d.now + Duration::from_millis(1));
                d.drain(&mut out);
            }
        }
    }

    #[test]
    fn boot_up_and_heartbeat() {
        let mut d = drive();
        let mut out = VecDeque::new();
        d.drain(&mut out);
        assert_eq!(out.pop_front().unwrap().data(), &[0]);
        sdo(
            &mut d,
            Sdo::Download {
                index: 0x1017,
                sub: 0,
                value: 100,
                size: 2,
            },
        );
        for ms in 1..=250 {
            d.advance(Duration::from_millis(ms));
        }
        d.drain(&mut out);
        assert_eq!(out.len(), 3, "heartbeats at 1, 101, 201 ms"); // producer starts at once
        assert!(out.iter().all(|f| f.id() == 0x703 && f.data() == [0x7F]));
        d.faults.silent = true;
        d.advance(Duration::from_millis(400));
        out.clear();
        d.drain(&mut out);
        assert!(out.is_empty());
    }
}
