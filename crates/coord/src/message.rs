//! Peer messages: what units (and the operator) tell each other, and the validation every
//! received message passes before it can influence a unit.
//!
//! Encoding: JSON (serde_json, already a workspace dependency). At 50 Hz and a few hundred
//! bytes per unit-state message the bandwidth is negligible on any link a team shares, and a
//! self-describing text encoding can be read straight out of packet captures and mission logs.
//! Decoding never panics: a size cap comes first, then the version is read from a minimal
//! header (so a peer on another protocol version is reported as such, not as garbage), then the
//! full envelope with unknown fields denied.
//!
//! A unit sends exactly one message per control tick ([`Body::Unit`]): its state plus whatever
//! the agreement announces that tick (proposal, acknowledgement, safety stop). One datagram per
//! tick cannot be reordered against itself, so a late datagram is simply older news and is
//! dropped as reordered without losing anything: every announcement is repeated on later ticks
//! for as long as it matters.
//!
//! Conventions every transport must keep: `stamp_us` is the sender's clock, which
//! is synchronized across the team (e.g. PTP), in µs; `seq` increases by at least one per
//! message of a sender and starts at the sender's boot time in µs, so a rebooted sender never
//! reuses sequence numbers.
//!
//! On the wire every envelope travels in an authenticated frame ([`crate::auth`]): sealed with
//! [`crate::auth::Sealer`], received with [`crate::validator::Validator::receive_frame`], which checks the tag
//! before it trusts anything in the envelope.
//!
//! # Replay protection
//!
//! A frame with a valid tag may still be a recording. Within one key epoch the validator
//! accepts a sender's message only if
//! - its stamp is within the staleness bound of the receiver's clock, in both directions, and
//! - its `seq` is above that sender's last accepted one (equal: [`Rejection::Duplicate`], lower:
//!   [`Rejection::Reordered`]), and
//! - its `seq` is at most `stamp_us + MAX_SEQ_LEAD_US` ([`Rejection::SeqAhead`]). By the
//!   convention above a sender's seq is its boot time plus the number of messages since, and it
//!   sends far fewer than one message per µs, so `seq ≤ stamp_us` for every honest sender; the
//!   lead covers clocks stepped back after boot. A rebooted sender starts at its new boot time,
//!   above every seq it used before, so it is accepted at once. The bound is defence in depth
//!   against a buggy keyed sender (forgeries already fail the tag): a message numbered near
//!   `u64::MAX` is rejected and never recorded, so it cannot block later real ones; the
//!   furthest an accepted seq can run ahead of real time is the lead plus the staleness bound.
//!
//! A recorded frame is thus useless once its stamp is stale, and a newer key epoch retires all
//! of them. One exception: an operator `Stop` with a valid tag, team and epoch is accepted
//! even when stale, from the future or out of sequence (it does not advance the sequence then):
//! stopping is always safe, so a stop must never be lost to a clock or sequence problem. The
//! price is that whoever recorded a stop can replay it to stop the team again (a denial of
//! service, never an unsafe motion).

use moonhaul_core::state::{Phase, UnitCommand, UnitState};
use serde::{Deserialize, Serialize};

/// The protocol version this build speaks; messages of any other version are rejected.
pub const PROTOCOL_VERSION: u16 = 1;
/// Largest encoded message accepted (a unit-state message is well under 1 KiB).
pub const MAX_MESSAGE_BYTES: usize = 4096;
/// How far a message's `seq` may exceed its own `stamp_us` (see the
/// [module docs](self#replay-protection)): 60 s, far more than any clock step a synchronized
/// team sees after boot.
pub const MAX_SEQ_LEAD_US: u64 = 60_000_000;

/// Who sent a message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sender {
    /// Unit `i` of the team (0-based).
    Unit(usize),
    /// The operator console.
    Operator,
}

impl std::fmt::Display for Sender {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Sender::Unit(i) => write!(f, "unit {i}"),
            Sender::Operator => f.write_str("operator"),
        }
    }
}

/// Every message on the wire.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Envelope {
    pub version: u16,
    pub team: String,
    pub sender: Sender,
    /// Strictly increasing per sender.
    pub seq: u64,
    /// Sender's (team-synchronized) clock when sent, µs.
    pub stamp_us: u64,
    pub body: Body,
}

// Unit messages are nearly all the traffic (one per unit per tick); boxing them to shrink the
// rare operator variant would add an allocation to each.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Body {
    /// A unit's message of one tick.
    Unit(UnitTick),
    Operator(OperatorCommand),
}

impl Body {
    pub(crate) fn kind(&self) -> &'static str {
        match self {
            Body::Unit(_) => "unit",
            Body::Operator(_) => "operator",
        }
    }

    /// The first non-finite number in the body, by field name.
    pub(crate) fn non_finite_field(&self) -> Option<&'static str> {
        let Body::Unit(report) = self else {
            return None;
        };
        let s = &report.state;
        let c = &report.command;
        let fields: [(&'static str, &[f64]); 8] = [
            ("state.wheels.position_rad", &s.wheels.position_rad),
            ("state.wheels.velocity_radps", &s.wheels.velocity_radps),
            ("state.arm.position_rad", &s.arm.position_rad),
            ("state.arm.velocity_radps", &s.arm.velocity_radps),
            (
                "state.base_pose",
                &[s.base_pose.x_m, s.base_pose.y_m, s.base_pose.yaw_rad],
            ),
            (
                "state.base_velocity",
                &[s.base_velocity.forward_mps, s.base_velocity.yaw_rate_radps],
            ),
            ("command.wheel_velocity_radps", &c.wheel_velocity_radps),
            ("command.arm_position_rad", &c.arm_position_rad),
        ];
        let bad = fields
            .iter()
            .find(|(_, v)| v.iter().any(|x| !x.is_finite()));
        bad.map(|(name, _)| *name)
    }
}

/// One unit's message of one tick: its state and its announcements.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitTick {
    /// The unit's committed phase.
    pub phase: Phase,
    pub state: UnitState,
    /// U_{k-1}: the command it issued last tick.
    pub command: UnitCommand,
    pub announce: Announcements,
}

/// What a unit's agreement logic tells its peers this tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Announcements {
    /// "My gate wants this transition"; repeated every tick while pending.
    pub propose: Option<Transition>,
    /// "I committed this transition", which proves every unit proposed it; repeated for one
    /// pending window after the commit.
    pub ack: Option<Transition>,
    /// "I stopped for this reason"; every unit that hears it stops too. Repeated every tick the
    /// stop condition lasts.
    pub safety_stop: Option<StopReason>,
}

/// A phase change within one mission. Each transition happens at most once per mission, so
/// (mission, from, to) identifies it and a proposal from an earlier mission never counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Transition {
    pub mission: u32,
    pub from: Phase,
    pub to: Phase,
}

/// Why a unit stopped (σ = 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// The unit's own hardware, sensing or policy failed.
    Fault(FaultKind),
    /// The operator pressed stop.
    Operator,
    /// Unit `unit` announced a safety stop.
    PeerStop { unit: usize },
    /// Nothing fresh from unit `unit` within the staleness bound.
    PeerStale { unit: usize },
    /// A phase change stayed pending past the agreement window.
    PhaseTimeout,
    /// Unit `unit` reports a phase the barrier cannot explain (e.g. it missed a stop).
    PhaseMismatch { unit: usize },
}

impl StopReason {
    /// Whether this unit should announce the stop; stops that came from a peer or from the
    /// operator (who tells every unit) are not re-announced, so stops never echo.
    pub fn announce(self) -> bool {
        !matches!(self, StopReason::PeerStop { .. } | StopReason::Operator)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// A drive reported a fault or stopped answering.
    Drive,
    /// A sensor reading is missing or not finite.
    Sensor,
    /// The policy or the clamp produced an unusable command.
    Policy,
    /// The unit's drives stayed beyond the clamp's tolerance of their command for
    /// `hold.tracking_stop_ticks` (configs/sync.toml): they cannot reach it.
    Tracking,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum OperatorCommand {
    /// Start mission `mission`; missions must increase, so an old start never restarts a team.
    Start {
        mission: u32,
    },
    Stop,
}

/// Why a message could not be sent.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    #[error("{sender} message #{seq}: {field} is not finite")]
    NonFinite {
        sender: Sender,
        seq: u64,
        field: &'static str,
    },
    #[error(
        "{sender} message #{seq} encodes to {len} bytes, over the {MAX_MESSAGE_BYTES}-byte limit"
    )]
    TooLarge {
        sender: Sender,
        seq: u64,
        len: usize,
    },
    #[error("{sender} message #{seq}: {detail}")]
    Serialize {
        sender: Sender,
        seq: u64,
        detail: String,
    },
    #[error("{sender} message #{seq} cannot be sealed with the key of {sealer}")]
    ForeignSender {
        sender: Sender,
        seq: u64,
        sealer: Sender,
    },
}

/// The JSON of a message (a frame's payload, and what mission logs record), refusing what a
/// receiver would reject as malformed. On the wire, seal it instead
/// ([`crate::auth::Sealer::seal`]).
pub fn encode(envelope: &Envelope) -> Result<Vec<u8>, EncodeError> {
    let mut bytes = Vec::with_capacity(512);
    encode_into(envelope, &mut bytes)?;
    Ok(bytes)
}

/// [`encode`], appending to `out`; on error `out` may hold part of the message.
pub(crate) fn encode_into(envelope: &Envelope, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    let (sender, seq) = (envelope.sender, envelope.seq);
    if let Some(field) = envelope.body.non_finite_field() {
        return Err(EncodeError::NonFinite { sender, seq, field });
    }
    let start = out.len();
    serde_json::to_writer(&mut *out, envelope).map_err(|e| EncodeError::Serialize {
        sender,
        seq,
        detail: e.to_string(),
    })?;
    let len = out.len() - start;
    if len > MAX_MESSAGE_BYTES {
        return Err(EncodeError::TooLarge { sender, seq, len });
    }
    Ok(())
}

/// Why a received message was dropped. Each names the sender where it is known (before the
/// tag is verified, the sender a frame claims).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejection {
    #[error("malformed message of {len} bytes: {detail}")]
    Malformed { len: usize, detail: String },
    #[error("frame sealed under key epoch {got}; this unit holds the keys of epoch {expected}")]
    StaleKey { got: u32, expected: u32 },
    #[error("frame claiming to be from {sender} fails authentication (wrong key or altered)")]
    BadMac { sender: Sender },
    #[error("protocol version {got}, expected {PROTOCOL_VERSION}")]
    WrongVersion { got: u16 },
    #[error("{sender} belongs to team {got:?}, not ours")]
    WrongTeam { sender: Sender, got: String },
    #[error("{sender} is not a peer of this unit")]
    UnknownSender { sender: Sender },
    #[error("{sender} may not send a {body} message")]
    WrongSender { sender: Sender, body: &'static str },
    #[error("{sender} message #{seq}: {field} is not finite")]
    NonFinite {
        sender: Sender,
        seq: u64,
        field: &'static str,
    },
    #[error("{sender} message #{seq} is {age_us} us old (bound {bound_us} us)")]
    Stale {
        sender: Sender,
        seq: u64,
        age_us: u64,
        bound_us: u64,
    },
    #[error(
        "{sender} message #{seq} is stamped {ahead_us} us in the future (bound {bound_us} us)"
    )]
    FromFuture {
        sender: Sender,
        seq: u64,
        ahead_us: u64,
        bound_us: u64,
    },
    #[error("{sender} message #{seq} was already accepted")]
    Duplicate { sender: Sender, seq: u64 },
    #[error("{sender} message #{seq} arrived after #{last}")]
    Reordered { sender: Sender, seq: u64, last: u64 },
    #[error(
        "{sender} message #{seq} is numbered more than {lead_us} ahead of its stamp {stamp_us} us"
    )]
    SeqAhead {
        sender: Sender,
        seq: u64,
        stamp_us: u64,
        lead_us: u64,
    },
}

/// How many messages were dropped, per reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RejectCounts {
    pub malformed: u64,
    pub stale_key: u64,
    pub bad_mac: u64,
    pub wrong_version: u64,
    pub wrong_team: u64,
    pub unknown_sender: u64,
    pub wrong_sender: u64,
    pub non_finite: u64,
    pub stale: u64,
    pub from_future: u64,
    pub duplicate: u64,
    pub reordered: u64,
    pub seq_ahead: u64,
}

impl RejectCounts {
    pub(crate) fn record(&mut self, rejection: &Rejection) {
        let counter = match rejection {
            Rejection::Malformed { .. } => &mut self.malformed,
            Rejection::StaleKey { .. } => &mut self.stale_key,
            Rejection::BadMac { .. } => &mut self.bad_mac,
            Rejection::WrongVersion { .. } => &mut self.wrong_version,
            Rejection::WrongTeam { .. } => &mut self.wrong_team,
            Rejection::UnknownSender { .. } => &mut self.unknown_sender,
            Rejection::WrongSender { .. } => &mut self.wrong_sender,
            Rejection::NonFinite { .. } => &mut self.non_finite,
            Rejection::Stale { .. } => &mut self.stale,
            Rejection::FromFuture { .. } => &mut self.from_future,
            Rejection::Duplicate { .. } => &mut self.duplicate,
            Rejection::Reordered { .. } => &mut self.reordered,
            Rejection::SeqAhead { .. } => &mut self.seq_ahead,
        };
        *counter += 1;
    }

    pub fn total(&self) -> u64 {
        let c = self;
        c.malformed
            + c.stale_key
            + c.bad_mac
            + c.wrong_version
            + c.wrong_team
            + c.unknown_sender
            + c.wrong_sender
            + c.non_finite
            + c.stale
            + c.from_future
            + c.duplicate
            + c.reordered
            + c.seq_ahead
    }
}
