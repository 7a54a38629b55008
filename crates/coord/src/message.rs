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

use crate::config::TeamSettings;
use moonhaul_core::state::{Phase, UnitCommand, UnitState};
use serde::{Deserialize, Serialize};

/// The protocol version this build speaks; messages of any other version are rejected.
pub const PROTOCOL_VERSION: u16 = 1;
/// Largest encoded message accepted (a unit-state message is well under 1 KiB).
pub const MAX_MESSAGE_BYTES: usize = 4096;

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
    fn kind(&self) -> &'static str {
        match self {
            Body::Unit(_) => "unit",
            Body::Operator(_) => "operator",
        }
    }

    /// The first non-finite number in the body, by field name.
    fn non_finite_field(&self) -> Option<&'static str> {
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
}

/// Encodes a message for the wire, refusing what a receiver would reject as malformed.
pub fn encode(envelope: &Envelope) -> Result<Vec<u8>, EncodeError> {
    let (sender, seq) = (envelope.sender, envelope.seq);
    if let Some(field) = envelope.body.non_finite_field() {
        return Err(EncodeError::NonFinite { sender, seq, field });
    }
    let bytes = serde_json::to_vec(envelope).map_err(|e| EncodeError::Serialize {
        sender,
        seq,
        detail: e.to_string(),
    })?;
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(EncodeError::TooLarge {
            sender,
            seq,
            len: bytes.len(),
        });
    }
    Ok(bytes)
}

/// Why a received message was dropped. Each names the sender where it is known.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Rejection {
    #[error("malformed message of {len} bytes: {detail}")]
    Malformed { len: usize, detail: String },
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
}

/// How many messages were dropped, per reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct RejectCounts {
    pub malformed: u64,
    pub wrong_version: u64,
    pub wrong_team: u64,
    pub unknown_sender: u64,
    pub wrong_sender: u64,
    pub non_finite: u64,
    pub stale: u64,
    pub from_future: u64,
    pub duplicate: u64,
    pub reordered: u64,
}

impl RejectCounts {
    fn record(&mut self, rejection: &Rejection) {
        let counter = match rejection {
            Rejection::Malformed { .. } => &mut self.malformed,
            Rejection::WrongVersion { .. } => &mut self.wrong_version,
            Rejection::WrongTeam { .. } => &mut self.wrong_team,
            Rejection::UnknownSender { .. } => &mut self.unknown_sender,
            Rejection::WrongSender { .. } => &mut self.wrong_sender,
            Rejection::NonFinite { .. } => &mut self.non_finite,
            Rejection::Stale { .. } => &mut self.stale,
            Rejection::FromFuture { .. } => &mut self.from_future,
            Rejection::Duplicate { .. } => &mut self.duplicate,
            Rejection::Reordered { .. } => &mut self.reordered,
        };
        *counter += 1;
    }

    pub fn total(&self) -> u64 {
        let c = self;
        c.malformed
            + c.wrong_version
            + c.wrong_team
            + c.unknown_sender
            + c.wrong_sender
            + c.non_finite
            + c.stale
            + c.from_future
            + c.duplicate
            + c.reordered
    }
}

/// The receiving side of one unit: checks every message, counts and returns every rejection
/// (the daemon logs it), and remembers each sender's last accepted sequence number.
#[derive(Debug, Clone)]
pub struct Validator {
    team: String,
    own_unit: usize,
    /// One slot per unit, then the operator.
    last_seq: Vec<Option<u64>>,
    staleness_us: u64,
    counts: RejectCounts,
}

impl Validator {
    pub fn new(settings: &TeamSettings) -> Self {
        Validator {
            team: settings.team.clone(),
            own_unit: settings.unit_index,
            last_seq: vec![None; settings.team_size + 1],
            staleness_us: settings.staleness_us(),
            counts: RejectCounts::default(),
        }
    }

    pub fn counts(&self) -> &RejectCounts {
        &self.counts
    }

    /// Decodes and validates bytes from the network at local time `now_us`. Never panics.
    pub fn receive_bytes(&mut self, bytes: &[u8], now_us: u64) -> Result<Envelope, Rejection> {
        let envelope = decode(bytes);
        let result = envelope.and_then(|e| self.validate(e, now_us));
        if let Err(rejection) = &result {
            self.counts.record(rejection);
        }
        result
    }

    /// Validates an already decoded message at local time `now_us`.
    pub fn receive(&mut self, envelope: Envelope, now_us: u64) -> Result<Envelope, Rejection> {
        let result = self.validate(envelope, now_us);
        if let Err(rejection) = &result {
            self.counts.record(rejection);
        }
        result
    }

    fn validate(&mut self, e: Envelope, now_us: u64) -> Result<Envelope, Rejection> {
        let (sender, seq) = (e.sender, e.seq);
        if e.version != PROTOCOL_VERSION {
            return Err(Rejection::WrongVersion { got: e.version });
        }
        if e.team != self.team {
            return Err(Rejection::WrongTeam {
                sender,
                got: e.team,
            });
        }
        let slot = match sender {
            Sender::Unit(i) if i < self.last_seq.len() - 1 && i != self.own_unit => i,
            Sender::Unit(_) => return Err(Rejection::UnknownSender { sender }),
            Sender::Operator => self.last_seq.len() - 1,
        };
        if matches!(sender, Sender::Operator) != matches!(e.body, Body::Operator(_)) {
            return Err(Rejection::WrongSender {
                sender,
                body: e.body.kind(),
            });
        }
        if let Some(field) = e.body.non_finite_field() {
            return Err(Rejection::NonFinite { sender, seq, field });
        }
        let bound_us = self.staleness_us;
        if now_us > e.stamp_us.saturating_add(bound_us) {
            return Err(Rejection::Stale {
                sender,
                seq,
                age_us: now_us - e.stamp_us,
                bound_us,
            });
        }
        if e.stamp_us > now_us.saturating_add(bound_us) {
            return Err(Rejection::FromFuture {
                sender,
                seq,
                ahead_us: e.stamp_us - now_us,
                bound_us,
            });
        }
        match self.last_seq[slot] {
            Some(last) if seq == last => return Err(Rejection::Duplicate { sender, seq }),
            Some(last) if seq < last => return Err(Rejection::Reordered { sender, seq, last }),
            _ => self.last_seq[slot] = Some(seq),
        }
        Ok(e)
    }
}

/// The version alone, read before the rest so other versions are named, not "malformed".
#[derive(Deserialize)]
struct Header {
    version: u16,
}

fn decode(bytes: &[u8]) -> Result<Envelope, Rejection> {
    let malformed = |detail: String| Rejection::Malformed {
        len: bytes.len(),
        detail,
    };
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(malformed(format!(
            "over the {MAX_MESSAGE_BYTES}-byte limit"
        )));
    }
    let header: Header = serde_json::from_slice(bytes).map_err(|e| malformed(e.to_string()))?;
    if header.version != PROTOCOL_VERSION {
        return Err(Rejection::WrongVersion {
            got: header.version,
        });
    }
    serde_json::from_slice(bytes).map_err(|e| malformed(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const PERIOD_US: u64 = 20_000;

    fn settings() -> TeamSettings {
        TeamSettings {
            team: "moonhaul".into(),
            team_size: 3,
            unit_index: 0,
            control_period_us: PERIOD_US,
            peer_staleness_periods: 3,
        }
    }

    fn report() -> UnitTick {
        UnitTick {
            phase: Phase::Lift,
            state: UnitState::default(),
            command: UnitCommand::default(),
            announce: Announcements::default(),
        }
    }

    fn msg(sender: Sender, seq: u64, stamp_us: u64, body: Body) -> Envelope {
        Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender,
            seq,
            stamp_us,
            body,
        }
    }

    fn state(unit: usize, seq: u64, stamp_us: u64) -> Envelope {
        msg(Sender::Unit(unit), seq, stamp_us, Body::Unit(report()))
    }

    #[test]
    fn every_body_round_trips_through_bytes() {
        let mut v = Validator::new(&settings());
        let t = Transition {
            mission: 7,
            from: Phase::Lift,
            to: Phase::Transport,
        };
        let announcing = UnitTick {
            announce: Announcements {
                propose: Some(t),
                ack: Some(Transition {
                    from: Phase::Idle,
                    to: Phase::Lift,
                    ..t
                }),
                safety_stop: Some(StopReason::Fault(FaultKind::Drive)),
            },
            ..report()
        };
        let bodies = [
            (Sender::Unit(1), Body::Unit(report())),
            (Sender::Unit(2), Body::Unit(announcing)),
            (
                Sender::Operator,
                Body::Operator(OperatorCommand::Start { mission: 7 }),
            ),
            (Sender::Operator, Body::Operator(OperatorCommand::Stop)),
        ];
        for (seq, (sender, body)) in bodies.into_iter().enumerate() {
            let e = msg(sender, seq as u64, 1_000_000, body);
            let bytes = encode(&e).unwrap();
            assert!(bytes.len() < 1024, "{} bytes", bytes.len());
            assert_eq!(v.receive_bytes(&bytes, 1_000_000).unwrap(), e);
        }
        assert_eq!(v.counts().total(), 0);
    }

    /// One case per rejection reason; each is counted in its own counter.
    #[test]
    fn each_rejection_reason_is_detected_and_counted() {
        let now = 10_000_000;
        let bound = 3 * PERIOD_US;
        let mut nan = report();
        nan.state.arm.position_rad[3] = f64::NAN;
        let mut inf = report();
        inf.command.wheel_velocity_radps[1] = f64::INFINITY;
        let cases: Vec<(Envelope, Rejection)> = vec![
            (
                Envelope {
                    version: 2,
                    ..state(1, 1, now)
                },
                Rejection::WrongVersion { got: 2 },
            ),
            (
                Envelope {
                    team: "other".into(),
                    ..state(1, 1, now)
                },
                Rejection::WrongTeam {
                    sender: Sender::Unit(1),
                    got: "other".into(),
                },
            ),
            (
                state(3, 1, now),
                Rejection::UnknownSender {
                    sender: Sender::Unit(3),
                },
            ),
            (
                state(0, 1, now),
                Rejection::UnknownSender {
                    sender: Sender::Unit(0),
                },
            ),
            (
                msg(
                    Sender::Unit(1),
                    1,
                    now,
                    Body::Operator(OperatorCommand::Stop),
                ),
                Rejection::WrongSender {
                    sender: Sender::Unit(1),
                    body: "operator",
                },
            ),
            (
                msg(Sender::Operator, 1, now, Body::Unit(report())),
                Rejection::WrongSender {
                    sender: Sender::Operator,
                    body: "unit",
                },
            ),
            (
                msg(Sender::Unit(1), 1, now, Body::Unit(nan)),
                Rejection::NonFinite {
                    sender: Sender::Unit(1),
                    seq: 1,
                    field: "state.arm.position_rad",
                },
            ),
            (
                msg(Sender::Unit(1), 1, now, Body::Unit(inf)),
                Rejection::NonFinite {
                    sender: Sender::Unit(1),
                    seq: 1,
                    field: "command.wheel_velocity_radps",
                },
            ),
            (
                state(1, 1, now - bound - 1),
                Rejection::Stale {
                    sender: Sender::Unit(1),
                    seq: 1,
                    age_us: bound + 1,
                    bound_us: bound,
                },
            ),
            (
                state(1, 1, now + bound + 1),
                Rejection::FromFuture {
                    sender: Sender::Unit(1),
                    seq: 1,
                    ahead_us: bound + 1,
                    bound_us: bound,
                },
            ),
        ];
        let mut v = Validator::new(&settings());
        for (i, (e, expected)) in cases.into_iter().enumerate() {
            assert_eq!(v.receive(e, now), Err(expected.clone()));
            assert_eq!(v.counts().total(), i as u64 + 1, "{expected}");
        }
        // Exactly at the staleness bound is still fresh; then sequence checks.
        assert!(v.receive(state(1, 5, now - bound), now).is_ok());
        assert_eq!(
            v.receive(state(1, 5, now), now),
            Err(Rejection::Duplicate {
                sender: Sender::Unit(1),
                seq: 5
            })
        );
        assert_eq!(
            v.receive(state(1, 4, now), now),
            Err(Rejection::Reordered {
                sender: Sender::Unit(1),
                seq: 4,
                last: 5
            })
        );
        // Sequence numbers are per sender: unit 2 may use 4.
        assert!(v.receive(state(2, 4, now), now).is_ok());
        // Malformed bytes, an oversize message and a wrong version read from the header.
        let malformed = v
            .receive_bytes(b"{\"version\":1,\"team\":", now)
            .unwrap_err();
        assert!(
            matches!(malformed, Rejection::Malformed { len: 20, .. }),
            "{malformed}"
        );
        let big = vec![b' '; MAX_MESSAGE_BYTES + 1];
        assert!(matches!(
            v.receive_bytes(&big, now),
            Err(Rejection::Malformed { .. })
        ));
        let future_format = br#"{"version":9,"whatever":{"new":"layout"}}"#;
        assert_eq!(
            v.receive_bytes(future_format, now),
            Err(Rejection::WrongVersion { got: 9 })
        );
        let mut extra = serde_json::to_value(state(1, 9, now)).unwrap();
        extra["priority"] = 1.into();
        let extra = serde_json::to_vec(&extra).unwrap();
        assert!(matches!(
            v.receive_bytes(&extra, now),
            Err(Rejection::Malformed { .. })
        ));
        let c = *v.counts();
        let expected = RejectCounts {
            malformed: 3,
            wrong_version: 2,
            wrong_team: 1,
            unknown_sender: 2,
            wrong_sender: 2,
            non_finite: 2,
            stale: 1,
            from_future: 1,
            duplicate: 1,
            reordered: 1,
        };
        assert_eq!(c, expected);
        // Rejection messages name the sender for the log.
        let text = Rejection::Reordered {
            sender: Sender::Unit(2),
            seq: 4,
            last: 5,
        }
        .to_string();
        assert!(text.contains("unit 2") && text.contains("#4"), "{text}");
    }

    #[test]
    fn non_finite_messages_are_refused_at_the_sender() {
        let mut r = report();
        r.state.base_pose.yaw_rad = f64::NAN;
        let err = encode(&msg(Sender::Unit(1), 3, 0, Body::Unit(r))).unwrap_err();
        assert_eq!(
            err,
            EncodeError::NonFinite {
                sender: Sender::Unit(1),
                seq: 3,
                field: "state.base_pose"
            }
        );
    }

    proptest! {
        /// Whatever arrives, decoding returns and counts a rejection instead of panicking.
        #[test]
        fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            let mut v = Validator::new(&settings());
            let before = v.counts().total();
            if v.receive_bytes(&bytes, 1_000_000).is_err() {
                prop_assert_eq!(v.counts().total(), before + 1);
            }
        }

        /// Mutating one byte of a valid message never panics either.
        #[test]
        fn corrupted_messages_never_panic(index in any::<prop::sample::Index>(), byte in any::<u8>()) {
            let mut bytes = encode(&state(1, 1, 1_000_000)).unwrap();
            let i = index.index(bytes.len());
            bytes[i] = byte;
            let mut v = Validator::new(&settings());
            let _ = v.receive_bytes(&bytes, 1_000_000);
        }
    }
}
