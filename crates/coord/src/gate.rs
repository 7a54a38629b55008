//! The phase gate: the paper's mode transition m_{t+1} = f(m_t, events) (eq. mode_transition).
//!
//! ```text
//! m_{t+1} = 0  if σ_t = 1                        (safety stop wins over everything)
//!           1  if m_t = 0 ∧ start
//!           2  if m_t = 1 ∧ h_payload ≥ h_min
//!           3  if m_t = 2 ∧ d_goal ≤ τ_place ∧ |ω_cmd| ≤ ω_stop
//!           0  if m_t = 3 ∧ released
//!           m_t otherwise
//! ```
//!
//! [`next_phase`] is the pure table on boolean events. [`PhaseGate`] measures the task events
//! from sensed quantities first: each is a threshold with hysteresis (a Schmitt trigger, so
//! noise near the threshold does not chatter) that must hold for a configured number of
//! consecutive ticks (debounce). Only the event that leaves the current phase is watched, and
//! its count restarts whenever the phase changes, so a condition met in one phase never carries
//! over into the next.
//!
//! `at_goal` also asks that the team has stopped driving: every unit's last commanded wheel
//! speed at most `transport.wheel_speed_max_radps` (a stopped-goal check, as Nav2's
//! `StoppedGoalChecker`; the paper names only τ_place). The transport profile ends at rest on
//! the goal, but τ_place is met about 2.5 cm before it, at 0.1 m/s, and the agreement hold
//! stops the wheels in one tick: the closed chain then squeezed the payload (grasp forces
//! 65 → 350 N) and in some missions the drives never caught up (tracking stop).
//!
//! `released` is measured as: payload height above the ground ≤ `place.payload_height_max_m`
//! (it rests) AND the largest grasp force over all units ≤ `place.grasp_force_max_n` (every arm
//! has let go), both holding together for `place.debounce_ticks` ticks.
//!
//! `start` is a one-shot event (an operator start received this tick), never a level: after a
//! safety stop the gate sits in Idle until a new start arrives, whatever the measurements say.

use crate::config::GateConfig;
use moonhaul_core::state::Phase;

/// The task events of one control tick, already measured.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PhaseEvents {
    /// σ: fault, peer timeout or operator stop.
    pub safety_stop: bool,
    /// Operator start command received this tick.
    pub start: bool,
    /// Payload height ≥ h_min (debounced).
    pub payload_lifted: bool,
    /// Payload distance to the goal ≤ τ_place (debounced).
    pub at_goal: bool,
    /// Payload resting on the ground and all grasps let go (debounced).
    pub released: bool,
}

/// One step of the phase MDP. At most one task-driven step is taken per tick, so no phase is
/// ever skipped.
pub fn next_phase(current: Phase, events: &PhaseEvents) -> Phase {
    if events.safety_stop {
        return Phase::Idle;
    }
    match current {
        Phase::Idle if events.start => Phase::Lift,
        Phase::Lift if events.payload_lifted => Phase::Transport,
        Phase::Transport if events.at_goal => Phase::Place,
        Phase::Place if events.released => Phase::Idle,
        unchanged => unchanged,
    }
}

/// The sensed quantities the task events are measured from, shared by the whole team.
#[derive(Debug, Clone, Copy)]
pub struct Measurements<'a> {
    /// Height of the payload's underside above the ground beneath it, m.
    pub payload_height_m: f64,
    /// Horizontal distance from the payload to its goal, m.
    pub goal_distance_m: f64,
    /// The largest wheel speed the team last commanded (every unit's U_{k−1}), rad/s: whether
    /// the team is still driving.
    pub wheel_speed_radps: f64,
    /// Magnitude of each unit's grasp force on the payload, N (one entry per unit).
    pub grasp_force_n: &'a [f64],
}

/// Which side of the threshold asserts a condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sense {
    AtLeast,
    AtMost,
}

/// A threshold with hysteresis: asserts on crossing `threshold`, releases only once the value is
/// `hysteresis` back on the other side. A non-finite value releases it.
#[derive(Debug, Clone, Copy)]
struct Schmitt {
    threshold: f64,
    hysteresis: f64,
    sense: Sense,
    on: bool,
}

impl Schmitt {
    fn new(threshold: f64, hysteresis: f64, sense: Sense) -> Self {
        Schmitt {
            threshold,
            hysteresis,
            sense,
            on: false,
        }
    }

    fn update(&mut self, value: f64) -> bool {
        let band = if self.on { self.hysteresis } else { 0.0 };
        self.on = match self.sense {
            Sense::AtLeast => value >= self.threshold - band,
            Sense::AtMost => value <= self.threshold + band,
        };
        // NaN compares false, so it releases; ±∞ are rejected explicitly.
        self.on &= value.is_finite();
        self.on
    }
}

/// The measured-event half of the phase MDP; create once, call [`PhaseGate::step`] every tick.
#[derive(Debug, Clone)]
pub struct PhaseGate {
    config: GateConfig,
    lifted: Schmitt,
    at_goal: Schmitt,
    stopped: Schmitt,
    resting: Schmitt,
    let_go: Schmitt,
    /// The phase whose exit event is being debounced.
    watching: Phase,
    /// Consecutive ticks the watched condition has held.
    held_ticks: u32,
}

impl PhaseGate {
    pub fn new(config: &GateConfig) -> Self {
        let (l, t, p) = (&config.lift, &config.transport, &config.place);
        PhaseGate {
            config: *config,
            lifted: Schmitt::new(l.payload_height_min_m, l.hysteresis_m, Sense::AtLeast),
            at_goal: Schmitt::new(t.goal_distance_max_m, t.hysteresis_m, Sense::AtMost),
            stopped: Schmitt::new(
                t.wheel_speed_max_radps,
                t.wheel_speed_hysteresis_radps,
                Sense::AtMost,
            ),
            resting: Schmitt::new(p.payload_height_max_m, p.height_hysteresis_m, Sense::AtMost),
            let_go: Schmitt::new(p.grasp_force_max_n, p.force_hysteresis_n, Sense::AtMost),
            watching: Phase::Idle,
            held_ticks: 0,
        }
    }

    /// Measures this tick's events for a mission in phase `current`.
    pub fn events(
        &mut self,
        current: Phase,
        measured: &Measurements,
        start: bool,
        safety_stop: bool,
    ) -> PhaseEvents {
        if current != self.watching || safety_stop {
            *self = PhaseGate {
                watching: current,
                ..PhaseGate::new(&self.config)
            };
        }
        let (condition, debounce_ticks) = match current {
            Phase::Idle => (false, 1),
            Phase::Lift => (
                self.lifted.update(measured.payload_height_m),
                self.config.lift.debounce_ticks,
            ),
            Phase::Transport => {
                let at_goal = self.at_goal.update(measured.goal_distance_m);
                let stopped = self.stopped.update(measured.wheel_speed_radps);
                (at_goal && stopped, self.config.transport.debounce_ticks)
            }
            Phase::Place => {
                let resting = self.resting.update(measured.payload_height_m);
                let let_go = self.let_go.update(largest_force(measured.grasp_force_n));
                (resting && let_go, self.config.place.debounce_ticks)
            }
        };
        self.held_ticks = if condition {
            self.held_ticks.saturating_add(1)
        } else {
            0
        };
        let fired = self.held_ticks >= debounce_ticks;
        PhaseEvents {
            safety_stop,
            start,
            payload_lifted: fired && current == Phase::Lift,
            at_goal: fired && current == Phase::Transport,
            released: fired && current == Phase::Place,
        }
    }

    /// The phase the gate would move to from `current` this tick.
    pub fn step(
        &mut self,
        current: Phase,
        measured: &Measurements,
        start: bool,
        safety_stop: bool,
    ) -> Phase {
        let events = self.events(current, measured, start, safety_stop);
        next_phase(current, &events)
    }
}

/// The largest grasp force; NaN (never "let go") when there is none or one is not finite.
fn largest_force(forces_n: &[f64]) -> f64 {
    if forces_n.is_empty() || forces_n.iter().any(|f| !f.is_finite()) {
        return f64::NAN;
    }
    forces_n
        .iter()
        .fold(f64::NEG_INFINITY, |a, &b| a.max(b.abs()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn events(bits: u8) -> PhaseEvents {
        PhaseEvents {
            safety_stop: bits & 1 != 0,
            start: bits & 2 != 0,
            payload_lifted: bits & 4 != 0,
            at_goal: bits & 8 != 0,
            released: bits & 16 != 0,
        }
    }

    #[test]
    fn transition_table() {
        use Phase::*;
        let none = PhaseEvents::default();
        let stop = PhaseEvents {
            safety_stop: true,
            ..none
        };
        let all = events(0b11111);
        let table = [
            (
                Idle,
                PhaseEvents {
                    start: true,
                    ..none
                },
                Lift,
            ),
            (
                Lift,
                PhaseEvents {
                    payload_lifted: true,
                    ..none
                },
                Transport,
            ),
            (
                Transport,
                PhaseEvents {
                    at_goal: true,
                    ..none
                },
                Place,
            ),
            (
                Place,
                PhaseEvents {
                    released: true,
                    ..none
                },
                Idle,
            ),
            // No event: every phase stays.
            (Idle, none, Idle),
            (Lift, none, Lift),
            (Transport, none, Transport),
            (Place, none, Place),
            // σ from every phase, alone and with every other event.
            (Idle, stop, Idle),
            (Lift, stop, Idle),
            (Transport, stop, Idle),
            (Place, stop, Idle),
            (Lift, all, Idle),
            (Transport, all, Idle),
            // An event that belongs to another phase changes nothing.
            (
                Idle,
                PhaseEvents {
                    payload_lifted: true,
                    at_goal: true,
                    released: true,
                    ..none
                },
                Idle,
            ),
            (
                Lift,
                PhaseEvents {
                    start: true,
                    at_goal: true,
                    released: true,
                    ..none
                },
                Lift,
            ),
            (
                Transport,
                PhaseEvents {
                    start: true,
                    payload_lifted: true,
                    released: true,
                    ..none
                },
                Transport,
            ),
            (
                Place,
                PhaseEvents {
                    start: true,
                    payload_lifted: true,
                    at_goal: true,
                    ..none
                },
                Place,
            ),
        ];
        for (from, e, to) in table {
            assert_eq!(next_phase(from, &e), to, "{from} with {e:?}");
        }
    }

    fn measured(height_m: f64, goal_m: f64, forces: &[f64]) -> Measurements<'_> {
        Measurements {
            payload_height_m: height_m,
            goal_distance_m: goal_m,
            wheel_speed_radps: 0.0,
            grasp_force_n: forces,
        }
    }

    /// Ticks until the gate leaves `phase` with constant measurements (None within 100 ticks).
    fn ticks_to_leave(gate: &mut PhaseGate, phase: Phase, m: &Measurements) -> Option<u32> {
        (1..=100).find(|_| gate.step(phase, m, false, false) != phase)
    }

    #[test]
    fn measured_events_fire_after_their_debounce() {
        let c = GateConfig::shipped().unwrap();
        let loaded = [30.0, 30.0];
        let free = [1.0, 0.5];
        // (phase, measurements, ticks to leave): each event at its threshold, debounced.
        let table = [
            (
                Phase::Lift,
                measured(c.lift.payload_height_min_m, 2.0, &loaded),
                Some(c.lift.debounce_ticks),
            ),
            (Phase::Lift, measured(0.269, 2.0, &loaded), None),
            (
                Phase::Transport,
                measured(0.3, c.transport.goal_distance_max_m, &loaded),
                Some(c.transport.debounce_ticks),
            ),
            (Phase::Transport, measured(0.3, 0.051, &loaded), None),
            // At the goal but still driving: not arrived; stopped at ω_stop: arrived.
            (
                Phase::Transport,
                Measurements {
                    wheel_speed_radps: c.transport.wheel_speed_max_radps + 1e-6,
                    ..measured(0.3, 0.0, &loaded)
                },
                None,
            ),
            (
                Phase::Transport,
                Measurements {
                    wheel_speed_radps: c.transport.wheel_speed_max_radps,
                    ..measured(0.3, 0.0, &loaded)
                },
                Some(c.transport.debounce_ticks),
            ),
            (
                Phase::Transport,
                Measurements {
                    wheel_speed_radps: f64::NAN,
                    ..measured(0.3, 0.0, &loaded)
                },
                None,
            ),
            (
                Phase::Place,
                measured(c.place.payload_height_max_m, 0.0, &free),
                Some(c.place.debounce_ticks),
            ),
            // Resting but still gripping, or let go in the air: not released.
            (Phase::Place, measured(0.0, 0.0, &[1.0, 6.0]), None),
            (Phase::Place, measured(0.05, 0.0, &free), None),
            // No force readings or a broken one: never released.
            (Phase::Place, measured(0.0, 0.0, &[]), None),
            (Phase::Place, measured(0.0, 0.0, &[1.0, f64::NAN]), None),
            (Phase::Lift, measured(f64::INFINITY, 2.0, &loaded), None),
            // Idle leaves only on start, never on measurements.
            (Phase::Idle, measured(0.5, 0.0, &free), None),
        ];
        for (phase, m, expected) in table {
            let mut gate = PhaseGate::new(&c);
            assert_eq!(
                ticks_to_leave(&mut gate, phase, &m),
                expected,
                "{phase} with {m:?}"
            );
        }
    }

    #[test]
    fn hysteresis_keeps_counting_through_noise_and_a_dip_restarts_it() {
        let c = GateConfig::shipped().unwrap();
        let h = c.lift.payload_height_min_m;
        let mut gate = PhaseGate::new(&c);
        let forces = [30.0, 30.0];
        // Alternate between h_min and just below it (inside the band): still fires on time.
        for tick in 1..c.lift.debounce_ticks {
            let height = if tick % 2 == 0 {
                h - 0.9 * c.lift.hysteresis_m
            } else {
                h
            };
            assert_eq!(
                gate.step(Phase::Lift, &measured(height, 1.0, &forces), false, false),
                Phase::Lift
            );
        }
        assert_eq!(
            gate.step(Phase::Lift, &measured(h, 1.0, &forces), false, false),
            Phase::Transport
        );
        // Below the band the count restarts; just inside the band without first crossing h_min
        // never asserts.
        let mut gate = PhaseGate::new(&c);
        for _ in 1..c.lift.debounce_ticks {
            gate.step(Phase::Lift, &measured(h, 1.0, &forces), false, false);
        }
        gate.step(
            Phase::Lift,
            &measured(h - 1.1 * c.lift.hysteresis_m, 1.0, &forces),
            false,
            false,
        );
        assert_eq!(
            ticks_to_leave(&mut gate, Phase::Lift, &measured(h, 1.0, &forces)),
            Some(c.lift.debounce_ticks)
        );
        let mut gate = PhaseGate::new(&c);
        assert_eq!(
            ticks_to_leave(
                &mut gate,
                Phase::Lift,
                &measured(h - 0.5 * c.lift.hysteresis_m, 1.0, &forces)
            ),
            None
        );
    }

    #[test]
    fn a_phase_change_restarts_the_debounce() {
        let c = GateConfig::shipped().unwrap();
        let mut gate = PhaseGate::new(&c);
        let m = measured(0.0, 0.0, &[0.0, 0.0]);
        // A condition held for 100 ticks in Transport counts nothing toward Place.
        for _ in 0..100 {
            gate.step(Phase::Transport, &m, false, false);
        }
        assert_eq!(
            ticks_to_leave(&mut gate, Phase::Place, &m),
            Some(c.place.debounce_ticks)
        );
    }

    #[test]
    fn after_a_safety_stop_only_a_new_start_leaves_idle() {
        let c = GateConfig::shipped().unwrap();
        let mut gate = PhaseGate::new(&c);
        let lifted = measured(0.5, 0.0, &[0.0, 0.0]);
        assert_eq!(
            gate.step(Phase::Transport, &lifted, true, true),
            Phase::Idle
        );
        // Everything says "go" except the start: Idle forever.
        assert_eq!(ticks_to_leave(&mut gate, Phase::Idle, &lifted), None);
        assert_eq!(gate.step(Phase::Idle, &lifted, true, false), Phase::Lift);
    }

    fn phase() -> impl Strategy<Value = Phase> {
        prop::sample::select(Phase::ALL.to_vec())
    }

    proptest! {
        /// Random phase sequences and measurement streams through the stateful gate: σ always
        /// wins, exactly one policy is active outside Idle (the indicator gating), and every
        /// task-driven step goes to the next phase only.
        #[test]
        fn sigma_wins_one_policy_no_skips(
            start_phase in phase(),
            ticks in prop::collection::vec(
                (0.0..0.6f64, 0.0..0.2f64, 0.0..10.0f64, 0.0..10.0f64, any::<bool>(), prop::bool::weighted(0.1)),
                1..200,
            ),
        ) {
            let mut gate = PhaseGate::new(&GateConfig::shipped().unwrap());
            let mut current = start_phase;
            for (height, goal, f0, f1, start, sigma) in ticks {
                let forces = [f0, f1];
                let next = gate.step(current, &measured(height, goal, &forces), start, sigma);
                if sigma {
                    prop_assert_eq!(next, Phase::Idle);
                } else {
                    let forward = (next.index() + 4 - current.index()) % 4;
                    prop_assert!(forward <= 1, "{} -> {} skips a phase", current, next);
                }
                let gates = [Phase::Lift, Phase::Transport, Phase::Place].map(|p| next == p);
                let active = gates.iter().filter(|g| **g).count();
                prop_assert_eq!(active, usize::from(next.has_policy()));
                current = next;
            }
        }

        #[test]
        fn sigma_wins_over_every_event_combination(from in phase(), bits in 0u8..32) {
            let e = PhaseEvents { safety_stop: true, ..events(bits) };
            prop_assert_eq!(next_phase(from, &e), Phase::Idle);
        }
    }
}
