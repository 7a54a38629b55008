//! Multi-unit agreement: every unit runs the phase gate on the shared state, but a phase change
//! takes effect only once every unit of the team has proposed it (a barrier).
//!
//! Protocol (for N units; each runs one [`Team`]):
//! - A unit whose gate fires proposes the transition (mission, from, to), re-sends the proposal
//!   every tick and holds until it commits. A unit that hears a peer's proposal for its own
//!   phase holds too, so the team never moves while a change is pending.
//! - A unit commits when it holds a matching proposal from every peer, or an acknowledgement
//!   from any peer (a peer only commits, and acknowledges, after hearing all N proposals).
//!   Acknowledgements are re-sent for one pending window so dropped ones are covered.
//! - Any safety stop — this unit's fault, a peer's announced stop, the operator's stop, a peer
//!   whose latest state is older than the staleness bound, a change pending longer than the
//!   window, or a peer reporting a phase the barrier cannot explain — sends the unit to Idle at
//!   once, without a barrier. Stops a unit detects itself are announced every tick they last.
//! - Idle is left only on an operator start for a mission newer than any seen before; it is
//!   one-shot, so a stopped team never resumes on its own. A peer whose authenticated messages
//!   are refused (out of physical bounds) stops the team like a silent one, named as that
//!   peer's fault ([`StopReason::PeerRejected`]); once its messages are good again, the next
//!   start runs.
//! - Every operator command is answered ([`OperatorAck`], in every outgoing message): a start
//!   is accepted when it starts the team (or names the mission already running: a resend),
//!   refused when the team is in another mission, the mission is not newer, or a stop holds.
//!
//! Consequences the tests check: no two units ever run different phase policies in the same
//! tick (a unit runs a new phase only after all units proposed it, and a proposer holds until it
//! commits), committed phases differ for at most the pending window plus one message delay,
//! and a silent peer stops every unit as soon as its last state is older than the bound.

use crate::clamp::HoldReason;
use crate::config::{AgreementConfig, TeamError, TeamSettings};
use crate::gate::{next_phase, Measurements, PhaseEvents, PhaseGate};
use crate::message::{
    Announcements, Body, Envelope, FaultKind, OperatorAck, OperatorCommand, Refusal, Sender,
    StopReason, Transition, Verdict,
};
use crate::GateConfig;
use moonhaul_core::state::Phase;

/// What this unit does this tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Directive {
    /// Run this phase's policy and clamp its command.
    Run(Phase),
    /// Issue the clamp's hold command.
    Hold(HoldReason),
}

/// The result of one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Decision {
    /// The committed phase.
    pub phase: Phase,
    pub directive: Directive,
    /// To send in this tick's [`crate::message::UnitTick`].
    pub announce: Announcements,
}

impl Decision {
    /// The hold to request from the clamp, if any.
    pub fn hold(&self) -> Option<HoldReason> {
        match self.directive {
            Directive::Run(_) => None,
            Directive::Hold(reason) => Some(reason),
        }
    }
}

/// What this unit knows of one peer.
#[derive(Debug, Clone, Copy, Default)]
struct PeerView {
    /// Sender stamp of its latest state, µs.
    last_state_us: Option<u64>,
    /// Its committed phase, as last reported.
    phase: Option<Phase>,
    proposal: Option<Transition>,
    ack: Option<Transition>,
    /// A safety stop it announced since the last tick.
    stop: bool,
    /// Its latest authenticated message was refused (and none accepted since).
    rejected: bool,
}

/// One unit's side of the agreement; create once, feed validated messages with
/// [`Team::receive`], then call [`Team::tick`] once per control tick. Does not allocate after
/// construction.
#[derive(Debug, Clone)]
pub struct Team {
    settings: TeamSettings,
    agreement: AgreementConfig,
    gate: PhaseGate,
    tick: u64,
    phase: Phase,
    /// The mission of the latest accepted start.
    mission: Option<u32>,
    /// The mission and sequence number of a start received since the last tick.
    start: Option<(u32, u64)>,
    /// The answer to the latest operator command, repeated in every message.
    operator_ack: Option<OperatorAck>,
    operator_stop: bool,
    peers: Vec<PeerView>,
    /// This unit's own outstanding proposal.
    proposal: Option<Transition>,
    /// First tick of the current pending episode (own or a peer's proposal).
    pending_since: Option<u64>,
    /// The last commit and how many more ticks to acknowledge it.
    ack: Option<(Transition, u32)>,
}

impl Team {
    pub fn new(settings: TeamSettings, gate: &GateConfig) -> Result<Self, TeamError> {
        settings.validate()?;
        Ok(Team {
            peers: vec![PeerView::default(); settings.team_size],
            settings,
            agreement: gate.agreement,
            gate: PhaseGate::new(gate),
            tick: 0,
            phase: Phase::Idle,
            mission: None,
            start: None,
            operator_ack: None,
            operator_stop: false,
            proposal: None,
            pending_since: None,
            ack: None,
        })
    }

    /// The committed phase.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// The mission of the latest start this unit accepted.
    pub fn mission(&self) -> Option<u32> {
        self.mission
    }

    /// Notes that an authenticated message of peer `unit` was refused (out of physical bounds):
    /// until one of its messages is accepted again, its staleness is its fault
    /// ([`StopReason::PeerRejected`]).
    pub fn peer_rejected(&mut self, unit: usize) {
        if unit != self.settings.unit_index {
            if let Some(peer) = self.peers.get_mut(unit) {
                peer.rejected = true;
            }
        }
    }

    /// Notes that a frame claiming to be an operator command was refused before it reached the
    /// team, to answer it in the next messages.
    pub fn operator_refused(&mut self, seq: Option<u64>, refusal: Refusal) {
        self.operator_ack = Some(OperatorAck {
            seq,
            verdict: Verdict::Rejected(refusal),
        });
    }

    /// Takes in one message that passed the [`crate::validator::Validator`].
    pub fn receive(&mut self, message: &Envelope) {
        let peer = match message.sender {
            Sender::Unit(i) if i != self.settings.unit_index => self.peers.get_mut(i),
            _ => None,
        };
        match (&message.body, peer) {
            (Body::Unit(tick), Some(peer)) => {
                if peer.last_state_us.is_none_or(|t| message.stamp_us >= t) {
                    peer.last_state_us = Some(message.stamp_us);
                    peer.phase = Some(tick.phase);
                }
                // Announcements repeat while they hold, so the latest message is the peer's
                // current word; a stop counts for the tick it arrives in.
                let a = &tick.announce;
                peer.rejected = false;
                peer.proposal = a.propose;
                peer.ack = a.ack;
                peer.stop |= a.safety_stop.is_some();
            }
            (Body::Operator(OperatorCommand::Start { mission }), _) => {
                self.start = Some((*mission, message.seq));
            }
            (Body::Operator(OperatorCommand::Stop { .. }), _) => {
                // The validator refused stops for older missions already.
                self.operator_stop = true;
                self.operator_ack = Some(OperatorAck {
                    seq: Some(message.seq),
                    verdict: Verdict::Accepted,
                });
            }
            // Unit bodies from a non-peer: the validator already rejects these.
            _ => {}
        }
    }

    /// One control tick at local time `now_us`, after this tick's messages were received.
    /// `fault` is this unit's own fault, if any.
    pub fn tick(
        &mut self,
        now_us: u64,
        measured: &Measurements,
        fault: Option<FaultKind>,
    ) -> Decision {
        self.tick += 1;
        let stop = self.stop_reason(now_us, fault);
        // A start counts only in Idle with nothing pending and no stop; otherwise it is dropped
        // (and a later start must name a newer mission anyway).
        let idle = self.phase == Phase::Idle && self.proposal.is_none();
        let mut start = None;
        if let Some((mission, seq)) = self.start.take() {
            let verdict = match self.mission {
                // A resend of the start of the mission running now.
                Some(m) if m == mission && !idle => Verdict::Accepted,
                Some(last) if mission <= last => Verdict::Rejected(Refusal::NotNewer { last }),
                _ => match stop {
                    Some(reason) => Verdict::Rejected(Refusal::Stopped(reason)),
                    None if !idle => Verdict::Rejected(Refusal::InMission {
                        current: self.mission.unwrap_or_default(),
                    }),
                    None => {
                        start = Some(mission);
                        Verdict::Accepted
                    }
                },
            };
            self.operator_ack = Some(OperatorAck {
                seq: Some(seq),
                verdict,
            });
        }
        if start.is_some() {
            self.mission = start;
        }
        self.operator_stop = false;
        for peer in &mut self.peers {
            peer.stop = false;
        }
        let wanted = self
            .gate
            .step(self.phase, measured, start.is_some(), stop.is_some());
        let mut outgoing = Announcements {
            mission: self.mission,
            operator: self.operator_ack,
            ..Announcements::default()
        };
        if let Some(reason) = stop {
            self.phase = Phase::Idle;
            self.reset_agreement();
            outgoing.safety_stop = reason.announce().then_some(reason);
            let directive = Directive::Hold(HoldReason::SafetyStop(reason));
            return Decision {
                phase: self.phase,
                directive,
                announce: outgoing,
            };
        }
        if self.proposal.is_none() && wanted != self.phase {
            // A start has set the mission; later transitions stay in it.
            if let Some(mission) = self.mission {
                self.proposal = Some(Transition {
                    mission,
                    from: self.phase,
                    to: wanted,
                });
            }
        }
        if let Some(t) = self.proposal {
            let acked = self.peers.iter().any(|p| p.ack == Some(t));
            let me = self.settings.unit_index;
            let all = self
                .peers
                .iter()
                .enumerate()
                .all(|(i, p)| i == me || p.proposal == Some(t));
            if acked || all {
                self.phase = t.to;
                self.reset_agreement();
                self.ack = Some((t, self.agreement.pending_window_ticks));
            }
        }
        outgoing.propose = self.proposal;
        if let Some((t, left)) = &mut self.ack {
            outgoing.ack = Some(*t);
            *left -= 1;
            if *left == 0 {
                self.ack = None;
            }
        }
        let pending = self.proposal.or_else(|| {
            let (phase, mission) = (self.phase, self.mission);
            self.peers
                .iter()
                .filter_map(|p| p.proposal)
                .find(|t| t.from == phase && Some(t.mission) == mission)
        });
        let directive = match pending {
            Some(t) => {
                self.pending_since.get_or_insert(self.tick);
                Directive::Hold(HoldReason::PhasePending(t))
            }
            None => {
                self.pending_since = None;
                match self.phase {
                    Phase::Idle => Directive::Hold(HoldReason::Idle),
                    active => Directive::Run(active),
                }
            }
        };
        Decision {
            phase: self.phase,
            directive,
            announce: outgoing,
        }
    }

    /// σ for this tick and its reason: the first that applies, in the order listed.
    fn stop_reason(&self, now_us: u64, fault: Option<FaultKind>) -> Option<StopReason> {
        let me = self.settings.unit_index;
        let staleness_us = self.settings.staleness_us();
        let peers = || self.peers.iter().enumerate().filter(move |(i, _)| *i != me);
        let timed_out = self.pending_since.is_some_and(|since| {
            self.tick - since >= u64::from(self.agreement.pending_window_ticks)
        });
        fault
            .map(StopReason::Fault)
            .or(self.operator_stop.then_some(StopReason::Operator))
            .or_else(|| {
                peers()
                    .find(|(_, p)| p.stop)
                    .map(|(unit, _)| StopReason::PeerStop { unit })
            })
            .or_else(|| {
                peers()
                    .find(|(_, p)| {
                        p.last_state_us
                            .is_none_or(|t| now_us > t.saturating_add(staleness_us))
                    })
                    .map(|(unit, p)| match p.rejected {
                        true => StopReason::PeerRejected { unit },
                        false => StopReason::PeerStale { unit },
                    })
            })
            .or(timed_out.then_some(StopReason::PhaseTimeout))
            .or_else(|| {
                peers()
                    .find(|(_, p)| p.phase.is_some_and(|q| !self.explains(q)))
                    .map(|(unit, _)| StopReason::PhaseMismatch { unit })
            })
    }

    /// Whether a peer reporting committed phase `peer` is consistent with the barrier: the same
    /// phase, one step ahead while this unit proposes that step (the peer committed first), or
    /// one step behind (this unit committed first, so the peer proposed and is about to).
    fn explains(&self, peer: Phase) -> bool {
        peer == self.phase
            || self.proposal.is_some_and(|t| t.to == peer)
            || successor(peer) == self.phase
    }

    fn reset_agreement(&mut self) {
        self.proposal = None;
        self.pending_since = None;
        self.ack = None;
        for peer in &mut self.peers {
            peer.proposal = None;
            peer.ack = None;
        }
    }
}

/// The phase a task-driven transition leads to: the gate's table with every task event set.
fn successor(phase: Phase) -> Phase {
    let every_task_event = PhaseEvents {
        safety_stop: false,
        start: true,
        payload_lifted: true,
        at_goal: true,
        released: true,
    };
    next_phase(phase, &every_task_event)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::message::{UnitTick, PROTOCOL_VERSION};
    use moonhaul_core::state::{UnitCommand, UnitState};

    const NOW: u64 = 1_000_000;

    fn peer(seq: u64, announce: Announcements) -> Envelope {
        Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender: Sender::Unit(1),
            seq,
            stamp_us: NOW,
            body: Body::Unit(UnitTick {
                phase: Phase::Idle,
                state: UnitState::default(),
                command: UnitCommand::default(),
                announce,
            }),
        }
    }

    /// A commit by acknowledgement needs an ack of exactly the transition this unit proposes:
    /// another mission's, another phase pair's or a stale one never moves it.
    #[test]
    fn only_an_ack_of_the_own_proposal_commits() {
        let settings = TeamSettings {
            team: "moonhaul".into(),
            team_size: 2,
            unit_index: 0,
            control_period_us: 20_000,
            peer_staleness_periods: 3,
        };
        let mut team = Team::new(settings, &GateConfig::shipped().unwrap()).unwrap();
        let forces = [30.0, 30.0];
        let measured = Measurements {
            payload_height_m: 0.0,
            goal_distance_m: 2.0,
            wheel_speed_radps: 0.0,
            grasp_force_n: &forces,
        };
        team.receive(&peer(1, Announcements::default()));
        team.receive(&Envelope {
            sender: Sender::Operator,
            body: Body::Operator(OperatorCommand::Start { mission: 1 }),
            ..peer(1, Announcements::default())
        });
        let own = Transition {
            mission: 1,
            from: Phase::Idle,
            to: Phase::Lift,
        };
        let decision = team.tick(NOW, &measured, None);
        assert_eq!(decision.announce.propose, Some(own));
        assert_eq!(decision.phase, Phase::Idle);
        let others = [
            Transition { mission: 2, ..own },
            Transition {
                mission: u32::MAX,
                ..own
            },
            Transition {
                mission: 1,
                from: Phase::Lift,
                to: Phase::Transport,
            },
            Transition {
                mission: 1,
                from: Phase::Idle,
                to: Phase::Place,
            },
        ];
        for (k, ack) in others.into_iter().enumerate() {
            team.receive(&peer(
                2 + k as u64,
                Announcements {
                    ack: Some(ack),
                    ..Default::default()
                },
            ));
            let decision = team.tick(NOW, &measured, None);
            assert_eq!(decision.phase, Phase::Idle, "ack of {ack:?} committed");
            assert_eq!(
                decision.directive,
                Directive::Hold(HoldReason::PhasePending(own))
            );
        }
        team.receive(&peer(
            9,
            Announcements {
                ack: Some(own),
                ..Default::default()
            },
        ));
        assert_eq!(team.tick(NOW, &measured, None).phase, Phase::Lift);
    }

    fn two_units() -> (Team, [f64; 2]) {
        let settings = TeamSettings {
            team: "moonhaul".into(),
            team_size: 2,
            unit_index: 0,
            control_period_us: 20_000,
            peer_staleness_periods: 3,
        };
        let team = Team::new(settings, &GateConfig::shipped().unwrap()).unwrap();
        (team, [30.0, 30.0])
    }

    fn start(seq: u64, mission: u32) -> Envelope {
        Envelope {
            sender: Sender::Operator,
            body: Body::Operator(OperatorCommand::Start { mission }),
            ..peer(seq, Announcements::default())
        }
    }

    /// Every operator command is answered in the outgoing announcements: a start that runs
    /// (and its resend), a second start during the mission, an old mission, a start while a
    /// stop holds, and a stop.
    #[test]
    fn operator_commands_are_answered() {
        let (mut team, forces) = two_units();
        let measured = Measurements {
            payload_height_m: 0.0,
            goal_distance_m: 2.0,
            wheel_speed_radps: 0.0,
            grasp_force_n: &forces,
        };
        let ack = |d: &Decision| d.announce.operator.unwrap();
        let accepted = |seq| OperatorAck {
            seq: Some(seq),
            verdict: Verdict::Accepted,
        };
        // Silent peer: a start is refused because the team is stopped.
        team.receive(&start(10, 5));
        let d = team.tick(NOW, &measured, None);
        assert_eq!(
            ack(&d),
            OperatorAck {
                seq: Some(10),
                verdict: Verdict::Rejected(Refusal::Stopped(StopReason::PeerStale { unit: 1 }))
            }
        );
        assert_eq!(d.announce.mission, None);
        team.receive(&peer(1, Announcements::default()));
        team.receive(&start(11, 5));
        let d = team.tick(NOW, &measured, None);
        assert_eq!(ack(&d), accepted(11));
        assert_eq!(d.announce.mission, Some(5));
        assert_eq!(team.mission(), Some(5));
        // A resend of that start is accepted; a newer start during the mission is not.
        team.receive(&peer(2, Announcements::default()));
        team.receive(&start(12, 5));
        assert_eq!(ack(&team.tick(NOW, &measured, None)), accepted(12));
        team.receive(&peer(3, Announcements::default()));
        team.receive(&start(13, 6));
        let d = team.tick(NOW, &measured, None);
        assert_eq!(
            ack(&d),
            OperatorAck {
                seq: Some(13),
                verdict: Verdict::Rejected(Refusal::InMission { current: 5 })
            }
        );
        assert_eq!(team.mission(), Some(5));
        // A stop is answered; afterwards an old mission's start is refused as not newer.
        team.receive(&peer(4, Announcements::default()));
        team.receive(&Envelope {
            body: Body::Operator(OperatorCommand::Stop { mission: Some(5) }),
            ..start(14, 0)
        });
        let d = team.tick(NOW, &measured, None);
        assert_eq!(ack(&d), accepted(14));
        assert_eq!(d.hold(), Some(HoldReason::SafetyStop(StopReason::Operator)));
        team.receive(&peer(5, Announcements::default()));
        team.receive(&start(15, 4));
        let d = team.tick(NOW, &measured, None);
        assert_eq!(
            ack(&d),
            OperatorAck {
                seq: Some(15),
                verdict: Verdict::Rejected(Refusal::NotNewer { last: 5 })
            }
        );
        // A frame refused before the team is answered too, until the next command.
        team.operator_refused(None, Refusal::Authentication);
        team.receive(&peer(6, Announcements::default()));
        let d = team.tick(NOW, &measured, None);
        assert_eq!(
            ack(&d),
            OperatorAck {
                seq: None,
                verdict: Verdict::Rejected(Refusal::Authentication)
            }
        );
    }

    /// A peer whose messages are refused stops the team for that peer once its last good state
    /// is stale, and the stop clears (the next start runs) once its messages are good again.
    #[test]
    fn a_rejected_peer_is_a_peer_fault_that_clears() {
        let (mut team, forces) = two_units();
        let measured = Measurements {
            payload_height_m: 0.0,
            goal_distance_m: 2.0,
            wheel_speed_radps: 0.0,
            grasp_force_n: &forces,
        };
        team.receive(&peer(1, Announcements::default()));
        assert_eq!(
            team.tick(NOW, &measured, None).hold(),
            Some(HoldReason::Idle)
        );
        team.peer_rejected(1);
        // Within the bound the last good state serves.
        assert_eq!(
            team.tick(NOW + 60_000, &measured, None).hold(),
            Some(HoldReason::Idle)
        );
        let d = team.tick(NOW + 60_001, &measured, None);
        assert_eq!(
            d.hold(),
            Some(HoldReason::SafetyStop(StopReason::PeerRejected { unit: 1 }))
        );
        assert_eq!(
            d.announce.safety_stop,
            Some(StopReason::PeerRejected { unit: 1 })
        );
        // Good again: no stop, and a start runs.
        let later = NOW + 100_000;
        team.receive(&Envelope {
            stamp_us: later,
            ..peer(2, Announcements::default())
        });
        assert_eq!(
            team.tick(later, &measured, None).hold(),
            Some(HoldReason::Idle)
        );
        team.receive(&start(3, 1));
        let d = team.tick(later, &measured, None);
        assert_eq!(d.announce.propose.map(|t| t.to), Some(Phase::Lift));
        assert_eq!(
            d.announce.operator.map(|a| a.verdict),
            Some(Verdict::Accepted)
        );
    }
}
