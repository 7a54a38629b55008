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
//! - its `seq` is at most `stamp_us` plus the lead ([`Rejection::SeqAhead`]): for a unit, the
//!   staleness bound plus one control period ([`crate::TeamSettings::seq_lead_us`], 80 ms at
//!   50 Hz with 3 periods); for a monitor, which does not bound stamps, [`MAX_SEQ_LEAD_US`]. By
//!   the convention above a sender's seq is its boot time plus the number of messages since, and
//!   it sends far fewer than one message per µs, so `seq ≤ stamp_us` for every honest sender.
//!   The bound is what keeps a keyed sender (a holder of a unit's key, or a buggy unit) from
//!   numbering a frame far ahead: once accepted, every genuine frame below it would be refused
//!   as reordered, and a frame 59 s ahead stopped the team for 59 s; now the furthest an
//!   accepted seq can run ahead of real time is the lead plus the staleness bound, 140 ms. A
//!   message numbered near `u64::MAX` is rejected and never recorded.
//!
//!   A unit whose clock really did step back by more than the lead after boot sends frames
//!   its peers refuse (`seq_ahead` in their rejection counts): they hold once its state is
//!   stale. Its seq grows by one per message while its stamps grow by a period, so the gap
//!   closes at almost real time and its frames are accepted again about one step's length
//!   later; the team then takes the next operator start. A rebooted sender starts at its new
//!   boot time, above every seq it used before unless its clock went back.
//!
//! A recorded frame is thus useless once its stamp is stale, and a newer key epoch retires all
//! of them. One exception: an operator stop that names its mission
//! ([`OperatorCommand::Stop`]), with a valid tag, team and epoch, is accepted even when stale,
//! from the future or out of sequence (it does not advance the sequence then): stopping is
//! always safe, so a stop must never be lost to a clock or sequence problem. Its mission bounds
//! what a recording can do: a unit refuses a stop for a mission older than the one it is in
//! ([`Rejection::WrongMission`]; the console names the mission the units report in
//! [`Announcements::mission`]), so a replayed stop can stop again only the mission it was sent
//! in (a denial of service within that mission, never an unsafe motion), never a later one. A
//! stop naming no mission (a console that heard no unit) gets no exception: it must be fresh
//! and in sequence like any other command.
//!
//! # Physical bounds
//!
//! An authenticated unit message is also held to [`MessageBounds`] (the receiver's unit model:
//! every unit of a team is the same module pair): base pose within the arena
//! ([`ARENA_HALF_WIDTH_M`]), heading bounded, arm joints within the URDF limits plus
//! [`JOINT_LIMIT_TOLERANCE_RAD`], velocities within the URDF limits times [`VELOCITY_MARGIN`],
//! commands likewise. A message beyond them is refused ([`Rejection::OutOfBounds`], naming the
//! field and the sender) and is that peer's fault ([`Rejection::peer_fault`]): the receiver
//! keeps the peer's last good state, and once nothing usable from the peer is within the
//! staleness bound it stops the team for that peer ([`StopReason::PeerRejected`]), never
//! latching a fault of its own; when the peer's messages are good again the stop clears and the
//! team takes the next operator start.
//!
//! # Operator commands and their acknowledgement
//!
//! Every unit message carries, in [`Announcements::operator`], what the unit did with the
//! latest operator command: accepted, or refused and why ([`Refusal`]). A frame that fails
//! authentication is answered without a sequence number (nothing in it can be trusted, so the
//! unit cannot tell whose it was): "the latest frame claiming to be the operator failed
//! authentication". The console matches answers to the sequence numbers it sent.

use moonhaul_core::state::{Phase, UnitCommand, UnitState, ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_core::unit::UnitSpec;
use serde::{Deserialize, Serialize};

/// The protocol version this build speaks; messages of any other version are rejected.
pub const PROTOCOL_VERSION: u16 = 2;
/// Largest encoded message accepted (a unit-state message is well under 1 KiB).
pub const MAX_MESSAGE_BYTES: usize = 4096;
/// How far a message's `seq` may exceed its own `stamp_us` at a monitor (see the
/// [module docs](self#replay-protection)), whose clock need not be the team's: 60 s. A unit
/// bounds the lead by its staleness bound instead ([`crate::TeamSettings::seq_lead_us`]).
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
    /// The mission of the latest start this unit accepted (the console names it in a stop).
    pub mission: Option<u32>,
    /// What this unit did with the latest operator command it heard (or the latest frame that
    /// claimed to be one and was refused); repeated every tick until the next one.
    pub operator: Option<OperatorAck>,
}

/// A unit's answer to an operator command, carried in every state message so the console can
/// tell each unit's verdict (see [`crate::message`]'s operator section).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OperatorAck {
    /// The command's sequence number; `None` when the frame failed authentication, so nothing
    /// in it (its number included) can be trusted.
    pub seq: Option<u64>,
    pub verdict: Verdict,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// A start that this unit now runs (or already ran: a resend), or a stop it obeyed.
    Accepted,
    Rejected(Refusal),
}

/// Why a unit refused an operator command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Refusal {
    /// The frame failed authentication (its tag, or its team): not sealed with this team's
    /// operator key.
    Authentication,
    /// Replay protection refused it: stale, stamped in the future, or numbered below an earlier
    /// command.
    Replay,
    /// A stop naming mission `got`, older than the mission `current` this unit is in.
    WrongMission { got: u32, current: u32 },
    /// A start while the unit is in mission `current` (not Idle).
    InMission { current: u32 },
    /// A start naming a mission that is not newer than the last one started, `last`.
    NotNewer { last: u32 },
    /// A start while a safety stop holds the team.
    Stopped(StopReason),
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::Authentication => f.write_str(
                "authentication failed (the frame was not sealed with this team's operator key)",
            ),
            Refusal::Replay => {
                f.write_str("replay protection (stale, from the future or out of sequence)")
            }
            Refusal::WrongMission { got, current } => {
                write!(
                    f,
                    "wrong mission: the stop names mission {got}, the unit is in {current}"
                )
            }
            Refusal::InMission { current } => write!(f, "already in mission {current}"),
            Refusal::NotNewer { last } => {
                write!(
                    f,
                    "the mission is not newer than the last one started ({last})"
                )
            }
            Refusal::Stopped(reason) => write!(f, "the team is stopped: {reason:?}"),
        }
    }
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
    /// Unit `unit`'s messages arrive authenticated but are refused (out of physical bounds or
    /// not finite), so nothing usable from it within the staleness bound: a fault of that peer,
    /// never of this unit.
    PeerRejected { unit: usize },
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
    Start { mission: u32 },
    /// Stop mission `mission` (the one the units report, [`Announcements::mission`]); a stop
    /// for an older mission is refused, so a recorded stop never stops a later mission. `None`
    /// (a console that heard no unit's mission) stops whatever runs but only when fresh and in
    /// sequence: it has no replay exception (see [replay protection](self#replay-protection)).
    Stop { mission: Option<u32> },
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
    #[error("{sender} message #{seq}: {field} = {value} is beyond its physical bound {bound}")]
    OutOfBounds {
        sender: Sender,
        seq: u64,
        field: &'static str,
        value: f64,
        bound: f64,
    },
    #[error("{sender} message #{seq}: a stop for mission {got}, older than the current mission {current}")]
    WrongMission {
        sender: Sender,
        seq: u64,
        got: u32,
        current: u32,
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

impl Rejection {
    /// The peer unit at fault when an authenticated message of it is unusable (out of physical
    /// bounds, not finite): the receiver holds for that peer ([`StopReason::PeerRejected`])
    /// instead of taking its values in.
    pub fn peer_fault(&self) -> Option<usize> {
        match self {
            Rejection::OutOfBounds {
                sender: Sender::Unit(i),
                ..
            }
            | Rejection::NonFinite {
                sender: Sender::Unit(i),
                ..
            } => Some(*i),
            _ => None,
        }
    }

    /// What a unit answers a refused frame that claims to be the operator's: the command's
    /// sequence number where it can be trusted (the tag verified) and the refusal. A duplicate
    /// has none: its original was answered already.
    pub fn operator_refusal(&self) -> Option<(Option<u64>, Refusal)> {
        let op = Sender::Operator;
        Some(match *self {
            Rejection::BadMac { sender } if sender == op => (None, Refusal::Authentication),
            Rejection::WrongTeam { sender, .. } if sender == op => (None, Refusal::Authentication),
            Rejection::WrongMission {
                sender,
                seq,
                got,
                current,
            } if sender == op => (Some(seq), Refusal::WrongMission { got, current }),
            Rejection::Stale { sender, seq, .. }
            | Rejection::FromFuture { sender, seq, .. }
            | Rejection::Reordered { sender, seq, .. }
            | Rejection::SeqAhead { sender, seq, .. }
                if sender == op =>
            {
                (Some(seq), Refusal::Replay)
            }
            _ => return None,
        })
    }
}

/// How far a unit's base may be from the world origin in x and in y, m: a generous arena
/// (2 km across) that no mission of these units leaves, so only a broken or hostile sender's
/// pose exceeds it. There is no arena size in the configs; missions run metres from the
/// origin.
pub const ARENA_HALF_WIDTH_M: f64 = 1000.0;
/// The largest base heading, rad (about 1,600 turns; odometry accumulates the heading
/// without wrapping it).
pub const MAX_YAW_RAD: f64 = 1.0e4;
/// The largest wheel position, rad (about 1,000 km of travel on a 0.1 m wheel; wheels are
/// continuous, their positions accumulate).
pub const MAX_WHEEL_POSITION_RAD: f64 = 1.0e7;
/// How far past a URDF position limit a sensed or commanded arm joint may be reported, rad:
/// encoder noise and a servo's overshoot at its stop, never a joint that left its range.
pub const JOINT_LIMIT_TOLERANCE_RAD: f64 = 0.1;
/// Velocities may be reported up to this multiple of the URDF velocity limit (sensed velocity
/// is a noisy difference quotient, and a drive briefly overshoots); beyond it a reading is
/// broken, not fast.
pub const VELOCITY_MARGIN: f64 = 2.0;

/// The physical bounds every unit-state message must meet to be accepted: base pose within the
/// arena, heading bounded, arm joints within the unit's URDF limits plus
/// [`JOINT_LIMIT_TOLERANCE_RAD`], joint and base velocities within the URDF velocity limits
/// times [`VELOCITY_MARGIN`], commands likewise. Every unit of a team is the same module pair,
/// so a receiver checks its peers against its own unit model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MessageBounds {
    pub arena_half_width_m: f64,
    pub max_yaw_rad: f64,
    pub max_wheel_position_rad: f64,
    /// Per arm joint, base to tip: the lowest and highest accepted position, rad.
    pub arm_position_rad: [(f64, f64); ARM_JOINTS],
    /// Per arm joint: the largest accepted |velocity| (sensed), rad/s.
    pub arm_velocity_radps: [f64; ARM_JOINTS],
    /// Per wheel: the largest accepted |velocity| (sensed or commanded), rad/s.
    pub wheel_velocity_radps: [f64; WHEEL_JOINTS],
    /// The largest accepted |forward speed| of the base, m/s.
    pub forward_mps: f64,
    /// The largest accepted |yaw rate| of the base, rad/s.
    pub yaw_rate_radps: f64,
}

impl MessageBounds {
    /// The bounds of a unit `spec` describes (the constants above for the arena, heading and
    /// margins).
    pub fn of_unit(spec: &UnitSpec) -> Self {
        let tol = JOINT_LIMIT_TOLERANCE_RAD;
        let wheel_velocity_radps = spec.wheel_limits.map(|l| l.velocity * VELOCITY_MARGIN);
        let fastest_wheel = wheel_velocity_radps.iter().copied().fold(0.0, f64::max);
        let forward_mps = fastest_wheel * spec.wheel_radius_m;
        MessageBounds {
            arena_half_width_m: ARENA_HALF_WIDTH_M,
            max_yaw_rad: MAX_YAW_RAD,
            max_wheel_position_rad: MAX_WHEEL_POSITION_RAD,
            arm_position_rad: spec.arm_limits.map(|l| (l.lower - tol, l.upper + tol)),
            arm_velocity_radps: spec.arm_limits.map(|l| l.velocity * VELOCITY_MARGIN),
            wheel_velocity_radps,
            forward_mps,
            yaw_rate_radps: 2.0 * forward_mps / spec.wheel_track_m,
        }
    }

    /// The bounds of this source tree's shipped unit (`assets/unit.urdf`): for tests and
    /// benches run from a checkout.
    pub fn shipped() -> Result<Self, moonhaul_core::unit::UnitSpecError> {
        let urdf = moonhaul_core::config::repo_file("assets/unit.urdf");
        UnitSpec::from_file(&urdf).map(|spec| Self::of_unit(&spec))
    }
}

/// The first of `values` beyond ±`bound`: (index, value, the signed bound crossed).
fn beyond_symmetric(values: &[f64], bound: impl Fn(usize) -> f64) -> Option<(f64, f64)> {
    values.iter().enumerate().find_map(|(i, &v)| {
        let b = bound(i);
        (v.abs() > b).then_some((v, b.copysign(v)))
    })
}

/// The first of `values` outside its `[lo, hi]`: (value, the bound crossed).
fn beyond_range(values: &[f64], range: &[(f64, f64)]) -> Option<(f64, f64)> {
    values
        .iter()
        .zip(range)
        .find_map(|(&v, &(lo, hi))| match v {
            v if v < lo => Some((v, lo)),
            v if v > hi => Some((v, hi)),
            _ => None,
        })
}

impl Body {
    /// The first value of a unit body beyond `bounds`: (field, value, the bound it crosses).
    /// Operator bodies carry no physical values.
    pub(crate) fn out_of_bounds(&self, b: &MessageBounds) -> Option<(&'static str, f64, f64)> {
        let Body::Unit(report) = self else {
            return None;
        };
        let s = &report.state;
        let c = &report.command;
        let p = &s.base_pose;
        let arena = |_| b.arena_half_width_m;
        let checks: [(&'static str, Option<(f64, f64)>); 10] = [
            ("state.base_pose.x_m", beyond_symmetric(&[p.x_m], arena)),
            ("state.base_pose.y_m", beyond_symmetric(&[p.y_m], arena)),
            (
                "state.base_pose.yaw_rad",
                beyond_symmetric(&[p.yaw_rad], |_| b.max_yaw_rad),
            ),
            (
                "state.base_velocity",
                beyond_symmetric(&[s.base_velocity.forward_mps], |_| b.forward_mps).or_else(|| {
                    beyond_symmetric(&[s.base_velocity.yaw_rate_radps], |_| b.yaw_rate_radps)
                }),
            ),
            (
                "state.wheels.position_rad",
                beyond_symmetric(&s.wheels.position_rad, |_| b.max_wheel_position_rad),
            ),
            (
                "state.wheels.velocity_radps",
                beyond_symmetric(&s.wheels.velocity_radps, |i| b.wheel_velocity_radps[i]),
            ),
            (
                "state.arm.position_rad",
                beyond_range(&s.arm.position_rad, &b.arm_position_rad),
            ),
            (
                "state.arm.velocity_radps",
                beyond_symmetric(&s.arm.velocity_radps, |i| b.arm_velocity_radps[i]),
            ),
            (
                "command.wheel_velocity_radps",
                beyond_symmetric(&c.wheel_velocity_radps, |i| b.wheel_velocity_radps[i]),
            ),
            (
                "command.arm_position_rad",
                beyond_range(&c.arm_position_rad, &b.arm_position_rad),
            ),
        ];
        checks
            .into_iter()
            .find_map(|(field, bad)| bad.map(|(value, bound)| (field, value, bound)))
    }
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
    #[serde(default)]
    pub out_of_bounds: u64,
    #[serde(default)]
    pub wrong_mission: u64,
    pub stale: u64,
    pub from_future: u64,
    pub duplicate: u64,
    pub reordered: u64,
    pub seq_ahead: u64,
}

impl RejectCounts {
    pub fn record(&mut self, rejection: &Rejection) {
        let counter = match rejection {
            Rejection::Malformed { .. } => &mut self.malformed,
            Rejection::StaleKey { .. } => &mut self.stale_key,
            Rejection::BadMac { .. } => &mut self.bad_mac,
            Rejection::WrongVersion { .. } => &mut self.wrong_version,
            Rejection::WrongTeam { .. } => &mut self.wrong_team,
            Rejection::UnknownSender { .. } => &mut self.unknown_sender,
            Rejection::WrongSender { .. } => &mut self.wrong_sender,
            Rejection::NonFinite { .. } => &mut self.non_finite,
            Rejection::OutOfBounds { .. } => &mut self.out_of_bounds,
            Rejection::WrongMission { .. } => &mut self.wrong_mission,
            Rejection::Stale { .. } => &mut self.stale,
            Rejection::FromFuture { .. } => &mut self.from_future,
            Rejection::Duplicate { .. } => &mut self.duplicate,
            Rejection::Reordered { .. } => &mut self.reordered,
            Rejection::SeqAhead { .. } => &mut self.seq_ahead,
        };
        *counter += 1;
    }

    /// Adds `other`'s counts to these, reason by reason.
    pub fn add(&mut self, other: &RejectCounts) {
        let RejectCounts {
            malformed,
            stale_key,
            bad_mac,
            wrong_version,
            wrong_team,
            unknown_sender,
            wrong_sender,
            non_finite,
            out_of_bounds,
            wrong_mission,
            stale,
            from_future,
            duplicate,
            reordered,
            seq_ahead,
        } = *other;
        self.malformed += malformed;
        self.stale_key += stale_key;
        self.bad_mac += bad_mac;
        self.wrong_version += wrong_version;
        self.wrong_team += wrong_team;
        self.unknown_sender += unknown_sender;
        self.wrong_sender += wrong_sender;
        self.non_finite += non_finite;
        self.out_of_bounds += out_of_bounds;
        self.wrong_mission += wrong_mission;
        self.stale += stale;
        self.from_future += from_future;
        self.duplicate += duplicate;
        self.reordered += reordered;
        self.seq_ahead += seq_ahead;
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
            + c.out_of_bounds
            + c.wrong_mission
            + c.stale
            + c.from_future
            + c.duplicate
            + c.reordered
            + c.seq_ahead
    }
}
