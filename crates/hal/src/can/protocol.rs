//! The CANopen (CiA 301) messages a CiA 402 master and drive exchange, with one codec used by
//! both sides: [`Message::decode`] turns any frame into a message or a [`DecodeError`] (never a
//! panic), [`Message::encode`] builds frames. Also the SDO abort and EMCY code texts and the PDO
//! packing shared by the master and the emulated drive.

use super::CanFrame;

pub const NMT_ID: u16 = 0x000;
pub const SYNC_ID: u16 = 0x080;
/// TIME stamp object: broadcast, not used by this master.
pub const TIME_ID: u16 = 0x100;
pub const EMCY_BASE: u16 = 0x080;
/// TPDO1..4 base COB-IDs (drive → master).
pub const TPDO_BASE: [u16; 4] = [0x180, 0x280, 0x380, 0x480];
/// RPDO1..4 base COB-IDs (master → drive).
pub const RPDO_BASE: [u16; 4] = [0x200, 0x300, 0x400, 0x500];
/// SDO server → client (responses).
pub const SDO_TX_BASE: u16 = 0x580;
/// SDO client → server (requests).
pub const SDO_RX_BASE: u16 = 0x600;
pub const HEARTBEAT_BASE: u16 = 0x700;

/// Why a frame is not a valid CANopen message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    #[error("{got} data bytes, need {need}")]
    Truncated { got: usize, need: usize },
    #[error("node id 0 is not a device")]
    NodeZero,
    #[error("unknown NMT command 0x{0:02X}")]
    NmtCommand(u8),
    #[error("unknown NMT state 0x{0:02X}")]
    NmtState(u8),
    #[error("unsupported SDO command byte 0x{0:02X} (only expedited transfers)")]
    SdoCommand(u8),
    #[error("COB-ID function is not used by this master")]
    Unsupported,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtCommand {
    Start = 0x01,
    Stop = 0x02,
    PreOperational = 0x80,
    ResetNode = 0x81,
    ResetCommunication = 0x82,
}

/// A node's NMT state as its heartbeat reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtState {
    BootUp = 0x00,
    Stopped = 0x04,
    Operational = 0x05,
    PreOperational = 0x7F,
}

/// An expedited SDO transfer step (segmented transfers are not needed for CiA 402 set-up).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sdo {
    /// Write `size` (1–4) bytes of `value`.
    Download {
        index: u16,
        sub: u8,
        value: u32,
        size: u8,
    },
    DownloadAck {
        index: u16,
        sub: u8,
    },
    Upload {
        index: u16,
        sub: u8,
    },
    /// `size` is 4 when the server did not indicate it.
    UploadReply {
        index: u16,
        sub: u8,
        value: u32,
        size: u8,
    },
    Abort {
        index: u16,
        sub: u8,
        code: u32,
    },
}

impl Sdo {
    pub fn object(&self) -> (u16, u8) {
        match *self {
            Sdo::Download { index, sub, .. }
            | Sdo::DownloadAck { index, sub }
            | Sdo::Upload { index, sub }
            | Sdo::UploadReply { index, sub, .. }
            | Sdo::Abort { index, sub, .. } => (index, sub),
        }
    }

    fn encode(&self) -> [u8; 8] {
        let (index, sub) = self.object();
        let (command, payload) = match *self {
            Sdo::Download { value, size, .. } => (0x23 | ((4 - size.clamp(1, 4)) << 2), value),
            Sdo::DownloadAck { .. } => (0x60, 0),
            Sdo::Upload { .. } => (0x40, 0),
            Sdo::UploadReply { value, size, .. } => (0x43 | ((4 - size.clamp(1, 4)) << 2), value),
            Sdo::Abort { code, .. } => (0x80, code),
        };
        let mut bytes = [0; 8];
        bytes[0] = command;
        bytes[1..3].copy_from_slice(&index.to_le_bytes());
        bytes[3] = sub;
        bytes[4..8].copy_from_slice(&payload.to_le_bytes());
        bytes
    }

    /// `request`: client → server (0x600 + node) rather than server → client.
    fn decode(data: &[u8], request: bool) -> Result<Sdo, DecodeError> {
        let bytes: &[u8; 8] = data.try_into().map_err(|_| DecodeError::Truncated {
            got: data.len(),
            need: 8,
        })?;
        let command = bytes[0];
        let index = u16::from_le_bytes([bytes[1], bytes[2]]);
        let sub = bytes[3];
        let raw = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
        let expedited = command & 0x02 != 0;
        let size = if command & 0x01 != 0 {
            4 - ((command >> 2) & 0x03)
        } else {
            4
        };
        let value = raw & (u32::MAX >> (32 - 8 * u32::from(size)));
        match (command >> 5, request) {
            (1, true) if expedited => Ok(Sdo::Download {
                index,
                sub,
                value,
                size,
            }),
            (2, true) => Ok(Sdo::Upload { index, sub }),
            (3, false) => Ok(Sdo::DownloadAck { index, sub }),
            (2, false) if expedited => Ok(Sdo::UploadReply {
                index,
                sub,
                value,
                size,
            }),
            (4, _) => Ok(Sdo::Abort {
                index,
                sub,
                code: raw,
            }),
            _ => Err(DecodeError::SdoCommand(command)),
        }
    }
}

/// A decoded CANopen message; PDO payloads borrow from the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Message<'a> {
    /// `node` 0 addresses every node.
    Nmt {
        command: NmtCommand,
        node: u8,
    },
    Sync,
    Emergency {
        node: u8,
        code: u16,
        register: u8,
    },
    /// `pdo` is 1–4.
    Tpdo {
        node: u8,
        pdo: u8,
        data: &'a [u8],
    },
    Rpdo {
        node: u8,
        pdo: u8,
        data: &'a [u8],
    },
    SdoRequest {
        node: u8,
        sdo: Sdo,
    },
    SdoResponse {
        node: u8,
        sdo: Sdo,
    },
    Heartbeat {
        node: u8,
        state: NmtState,
    },
}

fn need(data: &[u8], need: usize) -> Result<(), DecodeError> {
    if data.len() < need {
        return Err(DecodeError::Truncated {
            got: data.len(),
            need,
        });
    }
    Ok(())
}

impl<'a> Message<'a> {
    pub fn decode(frame: &'a CanFrame) -> Result<Self, DecodeError> {
        let id = frame.id();
        let data = frame.data();
        let node = (id & 0x7F) as u8;
        let function = id & 0x780;
        if id == NMT_ID {
            need(data, 2)?;
            let command = match data[0] {
                0x01 => NmtCommand::Start,
                0x02 => NmtCommand::Stop,
                0x80 => NmtCommand::PreOperational,
                0x81 => NmtCommand::ResetNode,
                0x82 => NmtCommand::ResetCommunication,
                other => return Err(DecodeError::NmtCommand(other)),
            };
            return Ok(Message::Nmt {
                command,
                node: data[1],
            });
        }
        if id == SYNC_ID {
            return Ok(Message::Sync);
        }
        if node == 0 {
            return Err(if id == TIME_ID {
                DecodeError::Unsupported
            } else {
                DecodeError::NodeZero
            });
        }
        if let Some(n) = TPDO_BASE.iter().position(|&b| b == function) {
            return Ok(Message::Tpdo {
                node,
                pdo: n as u8 + 1,
                data,
            });
        }
        if let Some(n) = RPDO_BASE.iter().position(|&b| b == function) {
            return Ok(Message::Rpdo {
                node,
                pdo: n as u8 + 1,
                data,
            });
        }
        match function {
            EMCY_BASE => {
                need(data, 3)?;
                Ok(Message::Emergency {
                    node,
                    code: u16::from_le_bytes([data[0], data[1]]),
                    register: data[2],
                })
            }
            SDO_TX_BASE => Ok(Message::SdoResponse {
                node,
                sdo: Sdo::decode(data, false)?,
            }),
            SDO_RX_BASE => Ok(Message::SdoRequest {
                node,
                sdo: Sdo::decode(data, true)?,
            }),
            HEARTBEAT_BASE => {
                need(data, 1)?;
                let state = match data[0] & 0x7F {
                    0x00 => NmtState::BootUp,
                    0x04 => NmtState::Stopped,
                    0x05 => NmtState::Operational,
                    0x7F => NmtState::PreOperational,
                    other => return Err(DecodeError::NmtState(other)),
                };
                Ok(Message::Heartbeat { node, state })
            }
            _ => Err(DecodeError::Unsupported),
        }
    }

    /// The frame for this message. PDO payloads longer than 8 bytes are cut (the PDO packers
    /// here never build them).
    pub fn encode(&self) -> CanFrame {
        let frame = CanFrame::from_parts;
        match *self {
            Message::Nmt { command, node } => frame(NMT_ID, &[command as u8, node]),
            Message::Sync => frame(SYNC_ID, &[]),
            Message::Emergency {
                node,
                code,
                register,
            } => {
                let [lo, hi] = code.to_le_bytes();
                frame(
                    EMCY_BASE + u16::from(node),
                    &[lo, hi, register, 0, 0, 0, 0, 0],
                )
            }
            Message::Tpdo { node, pdo, data } => frame(pdo_id(&TPDO_BASE, pdo, node), data),
            Message::Rpdo { node, pdo, data } => frame(pdo_id(&RPDO_BASE, pdo, node), data),
            Message::SdoRequest { node, sdo } => {
                frame(SDO_RX_BASE + u16::from(node), &sdo.encode())
            }
            Message::SdoResponse { node, sdo } => {
                frame(SDO_TX_BASE + u16::from(node), &sdo.encode())
            }
            Message::Heartbeat { node, state } => {
                frame(HEARTBEAT_BASE + u16::from(node), &[state as u8])
            }
        }
    }
}

fn pdo_id(bases: &[u16; 4], pdo: u8, node: u8) -> u16 {
    bases[usize::from(pdo.clamp(1, 4) - 1)] + u16::from(node & 0x7F)
}

/// Whether the master (not a drive) sends frames with this COB-ID: NMT, SYNC, RPDOs, SDO
/// requests. Replay feeds exactly these into emulated drives.
pub fn from_master(cob_id: u16) -> bool {
    let function = cob_id & 0x780;
    cob_id == NMT_ID
        || cob_id == SYNC_ID
        || RPDO_BASE.contains(&function)
        || function == SDO_RX_BASE
}

/// One PDO mapping entry (CiA 301 0x16xx/0x1Axx sub-entry): object, sub-index, length in bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapEntry {
    pub index: u16,
    pub sub: u8,
    pub bits: u8,
}

impl MapEntry {
    pub const fn raw(self) -> u32 {
        ((self.index as u32) << 16) | ((self.sub as u32) << 8) | self.bits as u32
    }

    pub const fn from_raw(raw: u32) -> Self {
        MapEntry {
            index: (raw >> 16) as u16,
            sub: (raw >> 8) as u8,
            bits: raw as u8,
        }
    }

    fn bytes(self) -> usize {
        usize::from(self.bits / 8)
    }
}

/// Packs mapped values, little-endian, into a PDO payload (at most 8 bytes; entries beyond
/// are dropped, which mapping validation prevents).
pub fn pack_pdo(entries: &[MapEntry], mut value: impl FnMut(MapEntry) -> u32) -> ([u8; 8], usize) {
    let mut bytes = [0; 8];
    let mut at = 0;
    for &entry in entries {
        let n = entry.bytes();
        if at + n > 8 {
            break;
        }
        bytes[at..at + n].copy_from_slice(&value(entry).to_le_bytes()[..n]);
        at += n;
    }
    (bytes, at)
}

/// Splits a PDO payload into mapped values (zero-extended; callers sign-extend by type).
/// The payload must be exactly as long as the mapping.
pub fn unpack_pdo(
    entries: &[MapEntry],
    data: &[u8],
    mut sink: impl FnMut(MapEntry, u32),
) -> Result<(), DecodeError> {
    let need = mapped_bytes(entries);
    if data.len() != need {
        return Err(DecodeError::Truncated {
            got: data.len(),
            need,
        });
    }
    let mut at = 0;
    for &entry in entries {
        let n = entry.bytes();
        let mut word = [0; 4];
        word[..n].copy_from_slice(&data[at..at + n]);
        sink(entry, u32::from_le_bytes(word));
        at += n;
    }
    Ok(())
}

pub fn mapped_bytes(entries: &[MapEntry]) -> usize {
    entries.iter().map(|e| e.bytes()).sum()
}

/// CiA 301 SDO abort code texts.
pub fn abort_reason(code: u32) -> &'static str {
    match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "command specifier not valid or unknown",
        0x0504_0005 => "out of memory",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write-only object",
        0x0601_0002 => "attempt to write a read-only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => "mapped objects would exceed the PDO length",
        0x0604_0043 => "general parameter incompatibility",
        0x0604_0047 => "general internal incompatibility in the device",
        0x0606_0000 => "access failed due to a hardware error",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0607_0012 => "data type does not match, length too high",
        0x0607_0013 => "data type does not match, length too low",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter",
        0x0609_0031 => "value of parameter written too high",
        0x0609_0032 => "value of parameter written too low",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => "data cannot be transferred because of local control",
        0x0800_0022 => "data cannot be transferred because of the present device state",
        0x0800_0023 => "object dictionary not present",
        _ => "unknown abort code",
    }
}

/// CiA 301/402 emergency error code texts, by the code's class where no exact text exists.
pub fn emergency_description(code: u16) -> &'static str {
    match code {
        0x0000 => "error reset or no error",
        0x2310 => "continuous over-current",
        0x3210 => "DC link over-voltage",
        0x3220 => "DC link under-voltage",
        0x4310 => "excess drive temperature",
        0x7305 => "incremental sensor 1 fault",
        0x8110 => "CAN overrun (objects lost)",
        0x8120 => "CAN in error passive mode",
        0x8130 => "life guard or heartbeat error",
        0x8140 => "recovered from bus off",
        0x8611 => "following error",
        _ => match code >> 12 {
            0x1 => "generic error",
            0x2 => "current",
            0x3 => "voltage",
            0x4 => "temperature",
            0x5 => "device hardware",
            0x6 => "device software",
            0x7 => "additional modules",
            0x8 => "monitoring",
            0x9 => "external error",
            0xF => "device specific",
            _ => "unknown emergency code",
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn sdo_round_trips_through_frames() {
        let cases = [
            Message::SdoRequest {
                node: 5,
                sdo: Sdo::Download {
                    index: 0x6060,
                    sub: 0,
                    value: 8,
                    size: 1,
                },
            },
            Message::SdoRequest {
                node: 5,
                sdo: Sdo::Upload {
                    index: 0x1000,
                    sub: 0,
                },
            },
            Message::SdoResponse {
                node: 5,
                sdo: Sdo::UploadReply {
                    index: 0x6064,
                    sub: 0,
                    value: 0xDEAD_BEEF,
                    size: 4,
                },
            },
            Message::SdoResponse {
                node: 127,
                sdo: Sdo::Abort {
                    index: 0x6060,
                    sub: 0,
                    code: 0x0609_0030,
                },
            },
        ];
        for message in cases {
            let frame = message.encode();
            assert_eq!(Message::decode(&frame), Ok(message));
        }
        // The candump example in the issue: controlword := 6 for node 1.
        let frame = CanFrame::new(0x601, &[0x2B, 0x40, 0x60, 0x00, 0x06, 0, 0, 0]).unwrap();
        assert_eq!(
            Message::decode(&frame),
            Ok(Message::SdoRequest {
                node: 1,
                sdo: Sdo::Download {
                    index: 0x6040,
                    sub: 0,
                    value: 6,
                    size: 2
                }
            })
        );
    }

    #[test]
    fn truncated_and_unknown_frames_are_errors() {
        let f = |id, data: &[u8]| CanFrame::new(id, data).unwrap();
        let decode = |id, data: &[u8]| Message::decode(&f(id, data)).map(|_| ());
        assert_eq!(
            decode(0x581, &[0x60, 0x40]),
            Err(DecodeError::Truncated { got: 2, need: 8 })
        );
        assert_eq!(
            decode(0x081, &[0x10]),
            Err(DecodeError::Truncated { got: 1, need: 3 })
        );
        assert_eq!(decode(0x701, &[0x33]), Err(DecodeError::NmtState(0x33)));
        assert_eq!(
            decode(0x000, &[0x07, 0]),
            Err(DecodeError::NmtCommand(0x07))
        );
        assert_eq!(decode(0x100, &[]), Err(DecodeError::Unsupported));
        assert_eq!(decode(0x180, &[]), Err(DecodeError::NodeZero));
        assert_eq!(
            decode(0x581, &[0x41, 0, 0, 0, 0, 0, 0, 0]),
            Err(DecodeError::SdoCommand(0x41))
        );
    }

    #[test]
    fn pdo_packing_round_trips() {
        let map = [
            MapEntry {
                index: 0x6041,
                sub: 0,
                bits: 16,
            },
            MapEntry {
                index: 0x6064,
                sub: 0,
                bits: 32,
            },
        ];
        let (bytes, len) = pack_pdo(&map, |e| {
            if e.index == 0x6041 {
                0x0237
            } else {
                (-5i32) as u32
            }
        });
        assert_eq!(len, 6);
        let mut got = vec![];
        unpack_pdo(&map, &bytes[..len], |e, v| got.push((e.index, v))).unwrap();
        assert_eq!(got, vec![(0x6041, 0x0237), (0x6064, (-5i32) as u32)]);
        assert!(unpack_pdo(&map, &bytes[..5], |_, _| {}).is_err());
        assert_eq!(MapEntry::from_raw(map[1].raw()), map[1]);
        assert_eq!(map[1].raw(), 0x6064_0020);
    }

    #[test]
    fn code_texts() {
        assert_eq!(
            abort_reason(0x0602_0000),
            "object does not exist in the object dictionary"
        );
        assert_eq!(emergency_description(0x2310), "continuous over-current");
        assert_eq!(emergency_description(0x4201), "temperature");
    }

    proptest! {
        #[test]
        fn decoding_arbitrary_frames_never_panics(id in 0u16..=0x7FF, data in proptest::collection::vec(any::<u8>(), 0..=8)) {
            let frame = CanFrame::new(id, &data).unwrap();
            if let Ok(message) = Message::decode(&frame) {
                // What decodes re-encodes to a frame with the same identifier.
                prop_assert_eq!(message.encode().id(), id);
            }
        }

        #[test]
        fn frame_construction_never_panics(id in any::<u16>(), data in proptest::collection::vec(any::<u8>(), 0..=16)) {
            let _ = CanFrame::new(id, &data);
        }
    }
}
