//! Teams of simulated units exchanging encoded messages over a lossy network with random delay
//! (hence reordering): a whole mission through the gate, the barrier and the safety logic.

use moonhaul_coord::gate::Measurements;
use moonhaul_coord::message::{
    Body, Envelope, MessageBounds, OperatorCommand, Sender, StopReason, UnitTick, PROTOCOL_VERSION,
};
use moonhaul_coord::{
    Directive, GateConfig, HoldReason, KeyFile, Sealer, Team, TeamSettings, Validator,
};
use moonhaul_core::state::{Phase, UnitCommand, UnitState};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const PERIOD_US: u64 = 20_000;
const STALENESS_PERIODS: u32 = 3;

/// The network and the world of one simulation.
struct Sim {
    units: Vec<SimUnit>,
    rng: ChaCha8Rng,
    /// (delivery tick, receiver, bytes).
    in_flight: Vec<(u64, usize, Vec<u8>)>,
    drop_probability: f64,
    /// Delays are uniform in 1..=max_delay_ticks.
    max_delay_ticks: u64,
    operator: Sealer,
    operator_seq: u64,
    /// Payload height above the ground, goal distance, grasp force (m, m, N).
    world: (f64, f64, f64),
}

struct SimUnit {
    team: Team,
    validator: Validator,
    sealer: Sealer,
    seq: u64,
    /// Constant measurement bias (m) so units detect events at different ticks.
    bias_m: f64,
    /// Silent (crashed) from this tick on.
    silent_from: Option<u64>,
    log: Vec<(Phase, Directive)>,
}

impl Sim {
    fn new(n: usize, seed: u64, drop_probability: f64, max_delay_ticks: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let gate = GateConfig::shipped().unwrap();
        let keys = KeyFile::generate("moonhaul", n, 1).unwrap();
        let units = (0..n)
            .map(|i| {
                let settings = TeamSettings {
                    team: "moonhaul".into(),
                    team_size: n,
                    unit_index: i,
                    control_period_us: PERIOD_US,
                    peer_staleness_periods: STALENESS_PERIODS,
                };
                SimUnit {
                    validator: Validator::new(&settings, &keys, MessageBounds::shipped().unwrap())
                        .unwrap(),
                    sealer: keys.sealer(Sender::Unit(i)).unwrap(),
                    team: Team::new(settings, &gate).unwrap(),
                    seq: 0,
                    bias_m: rng.random_range(-0.004..0.004),
                    silent_from: None,
                    log: Vec::new(),
                }
            })
            .collect();
        Sim {
            units,
            rng,
            in_flight: Vec::new(),
            drop_probability,
            max_delay_ticks,
            operator: keys.sealer(Sender::Operator).unwrap(),
            operator_seq: 0,
            world: (0.0, 1.0, 30.0),
        }
    }

    fn send(&mut self, from: Option<usize>, tick: u64, body: Body) {
        let sender = match from {
            Some(i) => {
                self.units[i].seq += 1;
                Sender::Unit(i)
            }
            None => {
                self.operator_seq += 1;
                Sender::Operator
            }
        };
        let seq = from.map_or(self.operator_seq, |i| self.units[i].seq);
        let envelope = Envelope {
            version: PROTOCOL_VERSION,
            team: "moonhaul".into(),
            sender,
            seq,
            stamp_us: tick * PERIOD_US,
            body,
        };
        let sealer = from.map_or(&self.operator, |i| &self.units[i].sealer);
        let bytes = sealer.seal(&envelope).unwrap();
        for to in 0..self.units.len() {
            if Some(to) == from || self.rng.random_bool(self.drop_probability) {
                continue;
            }
            let delay = self.rng.random_range(1..=self.max_delay_ticks);
            self.in_flight.push((tick + delay, to, bytes.clone()));
        }
    }

    fn step(&mut self, tick: u64) {
        let now_us = tick * PERIOD_US;
        // Deliver in random order.
        let mut due: Vec<_> = Vec::new();
        self.in_flight.retain(|m| {
            let keep = m.0 > tick;
            if !keep {
                due.push(m.clone());
            }
            keep
        });
        for i in (1..due.len()).rev() {
            due.swap(i, self.rng.random_range(0..=i));
        }
        for (_, to, bytes) in due {
            let unit = &mut self.units[to];
            if unit.silent_from.is_some_and(|s| tick >= s) {
                continue;
            }
            if let Ok(envelope) = unit.validator.receive_frame(&bytes, now_us) {
                unit.team.receive(&envelope);
            }
        }
        let (height, goal, force) = self.world;
        let forces = vec![force; self.units.len()];
        let mut sends = Vec::new();
        for (i, unit) in self.units.iter_mut().enumerate() {
            if unit.silent_from.is_some_and(|s| tick >= s) {
                continue;
            }
            let noise = self.rng.random_range(-0.003..0.003);
            let measured = Measurements {
                payload_height_m: height + unit.bias_m + noise,
                goal_distance_m: goal + unit.bias_m + noise,
                wheel_speed_radps: 0.0,
                grasp_force_n: &forces,
            };
            let decision = unit.team.tick(now_us, &measured, None);
            unit.log.push((decision.phase, decision.directive));
            let tick_message = UnitTick {
                phase: decision.phase,
                state: UnitState::default(),
                command: UnitCommand::default(),
                announce: decision.announce,
            };
            sends.push((i, Body::Unit(tick_message)));
        }
        for (i, body) in sends {
            self.send(Some(i), tick, body);
        }
        // The world moves only while every live unit runs the same phase policy.
        let live: Vec<_> = self
            .units
            .iter()
            .filter(|u| u.silent_from.is_none_or(|s| tick < s))
            .collect();
        let running = live
            .iter()
            .map(|u| u.log.last().map(|l| l.1))
            .collect::<Vec<_>>();
        if let Some(Some(Directive::Run(phase))) = running.first().copied() {
            if running.iter().all(|r| *r == Some(Directive::Run(phase))) {
                let (h, g, f) = &mut self.world;
                match phase {
                    Phase::Lift => *h = (*h + 0.01).min(0.4),
                    Phase::Transport => *g = (*g - 0.01).max(0.0),
                    Phase::Place if *h > 0.0 => *h = (*h - 0.01).max(0.0),
                    Phase::Place => *f = (*f - 2.0).max(0.0),
                    Phase::Idle => {}
                }
            }
        }
    }

    /// Runs `ticks` ticks; the operator asks to start mission 1 on ticks 5..15 (re-sent, since
    /// the network drops messages).
    fn run(&mut self, ticks: u64) {
        for tick in 1..=ticks {
            if (5..15).contains(&tick) {
                self.send(
                    None,
                    tick,
                    Body::Operator(OperatorCommand::Start { mission: 1 }),
                );
            }
            self.step(tick);
        }
    }

    /// Longest stretch of ticks during which live units' committed phases differ.
    fn longest_disagreement(&self) -> usize {
        let ticks = self.units.iter().map(|u| u.log.len()).max().unwrap_or(0);
        let mut longest = 0;
        let mut current = 0;
        for k in 0..ticks {
            let phases: Vec<_> = self
                .units
                .iter()
                .filter_map(|u| u.log.get(k).map(|l| l.0))
                .collect();
            if phases.windows(2).any(|w| w[0] != w[1]) {
                current += 1;
                longest = longest.max(current);
            } else {
                current = 0;
            }
        }
        longest
    }

    /// No tick where two units run different phase policies.
    fn assert_one_policy_at_a_time(&self) {
        let ticks = self.units.iter().map(|u| u.log.len()).max().unwrap_or(0);
        for k in 0..ticks {
            let mut running = self.units.iter().filter_map(|u| match u.log.get(k) {
                Some((_, Directive::Run(p))) => Some(*p),
                _ => None,
            });
            if let Some(first) = running.next() {
                assert!(
                    running.all(|p| p == first),
                    "tick {}: units run different policies",
                    k + 1
                );
            }
        }
    }

    /// Phases each unit went through, in order, without repeats.
    fn phase_history(&self, unit: usize) -> Vec<Phase> {
        let mut out: Vec<Phase> = Vec::new();
        for (phase, _) in &self.units[unit].log {
            if out.last() != Some(phase) {
                out.push(*phase);
            }
        }
        out
    }
}

const FULL_MISSION: [Phase; 5] = [
    Phase::Idle,
    Phase::Lift,
    Phase::Transport,
    Phase::Place,
    Phase::Idle,
];

#[test]
fn perfect_network_completes_the_mission_in_lockstep() {
    for n in [2, 3] {
        let mut sim = Sim::new(n, 1, 0.0, 1);
        sim.run(400);
        for i in 0..n {
            assert_eq!(sim.phase_history(i), FULL_MISSION, "unit {i} of {n}");
        }
        sim.assert_one_policy_at_a_time();
        // With one-tick delays a commit reaches the others on the next tick.
        assert!(
            sim.longest_disagreement() <= 1,
            "{}",
            sim.longest_disagreement()
        );
        for u in &sim.units {
            assert_eq!(u.validator.counts().total(), 0);
        }
    }
}

#[test]
fn delayed_dropped_reordered_messages_never_split_the_team() {
    let window = GateConfig::shipped()
        .unwrap()
        .agreement
        .pending_window_ticks as usize;
    let max_delay = 2;
    let mut completed = 0;
    let mut reordered = 0;
    let runs = 40;
    for n in [2, 3] {
        for seed in 0..runs {
            let mut sim = Sim::new(n, seed, 0.05, max_delay);
            sim.run(500);
            sim.assert_one_policy_at_a_time();
            let longest = sim.longest_disagreement();
            assert!(
                longest <= window + max_delay as usize,
                "n {n} seed {seed}: disagreed for {longest} ticks"
            );
            // Whatever happened, no unit skipped a phase.
            for i in 0..n {
                for w in sim.phase_history(i).windows(2) {
                    let forward = (w[1].index() + 4 - w[0].index()) % 4;
                    assert!(
                        forward == 1 || w[1] == Phase::Idle,
                        "unit {i}: {} -> {}",
                        w[0],
                        w[1]
                    );
                }
            }
            completed += usize::from((0..n).all(|i| sim.phase_history(i) == FULL_MISSION));
            reordered += sim
                .units
                .iter()
                .map(|u| u.validator.counts().reordered)
                .sum::<u64>();
        }
    }
    // The scenario is not vacuous: most missions complete and messages did arrive out of order.
    assert!(
        completed >= runs as usize,
        "only {completed} of {} missions completed",
        2 * runs
    );
    assert!(reordered > 0);
}

#[test]
fn a_silent_peer_stops_everyone_within_the_staleness_bound() {
    for n in [2, 3] {
        for seed in 0..10 {
            let mut sim = Sim::new(n, seed, 0.0, 2);
            let silent = n - 1;
            // Find a tick in Transport, then silence the last unit.
            let mut tick = 0;
            while sim.units[0].log.last().map(|l| l.1) != Some(Directive::Run(Phase::Transport)) {
                tick += 1;
                if (5..15).contains(&tick) {
                    sim.send(
                        None,
                        tick,
                        Body::Operator(OperatorCommand::Start { mission: 1 }),
                    );
                }
                sim.step(tick);
                assert!(tick < 300, "never reached Transport");
            }
            let silent_from = tick + 1;
            sim.units[silent].silent_from = Some(silent_from);
            // Its last message was stamped at tick silent_from − 1; a state older than
            // STALENESS_PERIODS periods is stale from tick silent_from − 1 + STALENESS_PERIODS + 1.
            let stale_tick = silent_from + u64::from(STALENESS_PERIODS);
            for t in silent_from..silent_from + 20 {
                sim.step(t);
                if t < stale_tick {
                    continue;
                }
                for (i, u) in sim.units.iter().enumerate().filter(|(i, _)| *i != silent) {
                    let (phase, directive) = *u.log.last().unwrap();
                    assert_eq!(phase, Phase::Idle, "unit {i} at tick {t}");
                    assert!(
                        matches!(directive, Directive::Hold(HoldReason::SafetyStop(_))),
                        "unit {i} at tick {t}: {directive:?}"
                    );
                }
            }
            // At least one unit names the silent one.
            let named = sim.units.iter().any(|u| {
                u.log.iter().any(|l| {
                    l.1 == Directive::Hold(HoldReason::SafetyStop(StopReason::PeerStale {
                        unit: silent,
                    }))
                })
            });
            assert!(named);
        }
    }
}

#[test]
fn a_unit_that_never_sees_the_event_times_the_change_out_and_stops_the_team() {
    for n in [2, 3] {
        let mut sim = Sim::new(n, 7, 0.0, 1);
        // Unit 0's height sensor reads 20 cm low: it never sees the payload lifted.
        sim.units[0].bias_m = -0.2;
        sim.run(200);
        sim.assert_one_policy_at_a_time();
        for i in 0..n {
            assert_eq!(
                sim.phase_history(i),
                [Phase::Idle, Phase::Lift, Phase::Idle],
                "unit {i}"
            );
        }
        let timed_out = sim.units.iter().any(|u| {
            u.log
                .iter()
                .any(|l| l.1 == Directive::Hold(HoldReason::SafetyStop(StopReason::PhaseTimeout)))
        });
        assert!(timed_out);
        // And nobody resumes on its own: the world still says "lifted", yet every unit stays Idle.
        assert!(sim
            .units
            .iter()
            .all(|u| u.log[150..].iter().all(|l| l.0 == Phase::Idle)));
    }
}

#[test]
fn an_operator_stop_stops_all_and_only_a_newer_start_restarts() {
    let mut sim = Sim::new(2, 3, 0.0, 1);
    sim.run(40);
    assert!(sim
        .units
        .iter()
        .all(|u| u.log.last().unwrap().0 == Phase::Lift));
    sim.send(
        None,
        41,
        Body::Operator(OperatorCommand::Stop { mission: Some(1) }),
    );
    for t in 41..60 {
        sim.step(t);
    }
    assert!(sim
        .units
        .iter()
        .all(|u| u.log.last().unwrap().0 == Phase::Idle));
    // The same mission again is ignored; a newer one starts.
    sim.send(
        None,
        60,
        Body::Operator(OperatorCommand::Start { mission: 1 }),
    );
    for t in 60..80 {
        sim.step(t);
    }
    assert!(sim
        .units
        .iter()
        .all(|u| u.log.last().unwrap().0 == Phase::Idle));
    sim.send(
        None,
        80,
        Body::Operator(OperatorCommand::Start { mission: 2 }),
    );
    for t in 80..90 {
        sim.step(t);
    }
    assert!(sim
        .units
        .iter()
        .all(|u| u.log.last().unwrap().0 != Phase::Idle));
}

/// An outsider on the network without the team's keys floods it with forgeries of every kind
/// the unauthenticated protocol fell to: sequence numbers at `u64::MAX` (which would have
/// blocked every later real message of that sender), operator starts for mission `u32::MAX`
/// (every later real start) and stops, and acknowledgements of every transition (each could
/// have committed a phase change). The mission runs exactly as without them.
#[test]
fn forged_frames_on_the_network_change_nothing() {
    let transitions = [
        (Phase::Idle, Phase::Lift),
        (Phase::Lift, Phase::Transport),
        (Phase::Transport, Phase::Place),
        (Phase::Place, Phase::Idle),
    ];
    for n in [2, 3] {
        let mut sim = Sim::new(n, 11, 0.0, 1);
        let attacker = KeyFile::generate("moonhaul", n, 1).unwrap();
        for tick in 1..=400 {
            if (5..15).contains(&tick) {
                sim.send(
                    None,
                    tick,
                    Body::Operator(OperatorCommand::Start { mission: 1 }),
                );
            }
            let stamp_us = tick * PERIOD_US;
            let forge = |sender: Sender, body: Body| {
                let envelope = Envelope {
                    version: PROTOCOL_VERSION,
                    team: "moonhaul".into(),
                    sender,
                    seq: u64::MAX,
                    stamp_us,
                    body,
                };
                attacker.sealer(sender).unwrap().seal(&envelope).unwrap()
            };
            let mut forged = vec![
                forge(
                    Sender::Operator,
                    Body::Operator(OperatorCommand::Start { mission: u32::MAX }),
                ),
                // Late in the mission, a forged stop too (it would send everyone to Idle).
                forge(
                    Sender::Operator,
                    Body::Operator(OperatorCommand::Stop { mission: Some(1) }),
                ),
            ];
            for unit in 0..n {
                for (from, to) in transitions {
                    let mut tick_message = UnitTick {
                        phase: to,
                        state: UnitState::default(),
                        command: UnitCommand::default(),
                        announce: Default::default(),
                    };
                    let t = moonhaul_coord::message::Transition {
                        mission: 1,
                        from,
                        to,
                    };
                    tick_message.announce.ack = Some(t);
                    tick_message.announce.propose = Some(t);
                    forged.push(forge(Sender::Unit(unit), Body::Unit(tick_message)));
                }
            }
            for bytes in forged {
                for to in 0..n {
                    sim.in_flight.push((tick + 1, to, bytes.clone()));
                }
            }
            sim.step(tick);
        }
        for i in 0..n {
            assert_eq!(sim.phase_history(i), FULL_MISSION, "unit {i} of {n}");
        }
        sim.assert_one_policy_at_a_time();
        for u in &sim.units {
            let counts = u.validator.counts();
            assert!(counts.bad_mac > 0);
            // Forgeries naming the receiver itself are dropped before the tag check.
            assert_eq!(
                counts.total(),
                counts.bad_mac + counts.unknown_sender,
                "{counts:?}"
            );
        }
    }
}
