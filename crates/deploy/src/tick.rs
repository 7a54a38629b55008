//! One unit's control tick, the onboard corridor of DESIGN.md in one place:
//!
//! hal reading → own state and wheel odometry → grasp FK → peers' latest published states →
//! team agreement and phase gate (measurements from onboard estimates only) → observation
//! (core's [`unit_observation`], the function training used) → active controller (a phase
//! policy on core's MLP, or the scripted IK controller) → its increment through the one action
//! pipeline (coord's [`ActionPipeline`]: F_k = U_{k−1} ⊕ Δ, clamp, hold rule) → hardware output
//! → mission-log record and the message to publish.
//!
//! [`Onboard`] is transport- and clock-free: the daemon feeds it validated peer messages
//! ([`Onboard::receive`]) and one hardware reading per tick ([`Onboard::tick`]), then writes
//! the returned output to its hardware and publishes the returned message. Integration tests
//! run whole teams of it in one process; the daemon runs one per process over zenoh. After
//! construction a tick allocates nothing.
//!
//! **Choices the paper leaves open** (written down here, where they are made):
//! - *Peers lag one tick.* A unit ticks on its own reading and its peers' newest messages, which
//!   were sent at the end of their previous tick: a distributed 50 Hz team cannot see a peer's
//!   state of the same instant. Training saw same-instant peer states; 20 ms is inside the
//!   clamp's tolerances at the commanded speeds.
//! - *The clamp across units* is coord's [`ActionPipeline`] (the function training and eval
//!   call too): its own S = U_{k-1} and F = U_{k-1} ⊕ Δ, and for each peer S = F = the command
//!   the peer last published. A peer lagging its own command beyond tolerance makes every step
//!   of this unit inadmissible, so it holds (arm at U_{k-1}, wheels stopped) — the
//!   synchronization the clamp exists for; its own drives failing to reach U_{k-1} for
//!   `hold.tracking_stop_ticks` latch a `tracking` fault.
//! - *The first command* is the anchor on the first sensed joints (wheels stopped): U_{k-1}
//!   does not exist before it.
//! - *Controllers.* [`Controller::Learned`] runs the phase policies (their files record the
//!   increment map, [`ActionMap::of_policy`]); [`Controller::Scripted`] runs core's
//!   [`PhaseScript`] on the same observation inputs (own encoders and odometry, the rest
//!   grasp, the phase goal) with the shipped map of `configs/tasks.toml`.
//! - *Measurements for the gate.* Payload height: the mean over the units of the FK lift of
//!   the cargo (own arm, and the peer's arm from its published joints), in Place measured from
//!   the ground found at touchdown (below). Goal distance: the payload's, as the mean of the
//!   units' odometric offsets from their phase goals (own and published poses). Driving: the
//!   largest wheel speed in the team's last commands (own and published). Release: this
//!   unit's own grasp force (a wrist force estimate where the hardware has one; otherwise 0
//!   once its gripper is open and unbounded before), entered for every unit: the barrier then
//!   commits Place → Idle only when every unit has seen its own grasp let go.
//! - *Opening the gripper.* The gripper is not part of u⁽ⁱ⁾. In Place, once the team's
//!   touchdown ([`moonhaul_core::touchdown`]: the largest height of a unit's sensed end
//!   effector over its command, from every unit's last published state and command) has lasted
//!   `place.release_after_contact_s` of ticks in total, the unit opens its gripper. The units
//!   see the same signal a tick apart, so they open, and agree on Idle, together.
//! - *Faults latch.* A drive fault, a non-finite reading or a non-finite policy output stops
//!   the team (σ) and keeps this unit stopped, announcing why, until the daemon restarts.

use moonhaul_coord::clamp::anchor_command;
use moonhaul_coord::message::{
    Announcements, Body, Envelope, FaultKind, RejectCounts, Rejection, Sender, UnitTick,
    PROTOCOL_VERSION,
};
use moonhaul_coord::{
    ActionPipeline, Decision, Directive, GateConfig, HoldReason, Increment, Measurements,
    PipelineInput, SyncConfig, Team, TeamSettings, UnitModel,
};
use moonhaul_core::action::{ActionMap, ActionMapError};
use moonhaul_core::handover::UnitHandOver;
use moonhaul_core::observation::{
    unit_observation, CommandState, GraspReference, ObservationView, PhaseGoal, ACTOR_OBS_DIM,
};
use moonhaul_core::policy::{Policy, PolicyScratch};
use moonhaul_core::scripted::{MissionPlan, PhaseScript, ScriptInput};
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand, UnitState, UNIT_ACTION_DIM};
use moonhaul_core::task_config::TaskConfig;
use moonhaul_core::touchdown::{team_arms, TeamArms, Touchdown};
use moonhaul_core::unit::UnitSpec;
use moonhaul_hal::unit::{UnitOutput, UnitReading};
use nalgebra::Vector2;

use crate::record::TickRecord;

/// The three phase policies a unit flies.
pub struct PhasePolicies {
    pub lift: Policy,
    pub transport: Policy,
    pub place: Policy,
}

/// What drives a unit's increments.
pub enum Controller {
    /// The three phase policies.
    Learned(Box<PhasePolicies>),
    /// The scripted IK controller (`configs/mission.toml`), a model-based baseline flown
    /// through the same pipeline.
    Scripted(MissionPlan),
}

/// The controller as the tick runs it.
enum Active {
    /// Each phase's policy with its scratch and action map, indexed by [`policy_slot`].
    Learned(Box<[(Policy, PolicyScratch, ActionMap); 3]>),
    Scripted {
        script: Box<PhaseScript>,
        map: ActionMap,
    },
}

impl Active {
    fn new(controller: Controller, tasks: &TaskConfig) -> Result<Self, OnboardError> {
        let policies = match controller {
            Controller::Scripted(plan) => {
                if plan.place_press_m <= tasks.place.contact_press_m {
                    return Err(OnboardError::PressBelowContact {
                        press_m: plan.place_press_m,
                        contact_m: tasks.place.contact_press_m,
                    });
                }
                return Ok(Active::Scripted {
                    script: Box::new(PhaseScript::new(plan)),
                    map: ActionMap::from_settings(&tasks.action),
                });
            }
            Controller::Learned(p) => *p,
        };
        let slot = |phase: Phase, p: Policy| -> Result<_, OnboardError> {
            let map = unit_action_map(phase, &p)?;
            let scratch = p.scratch();
            Ok((p, scratch, map))
        };
        Ok(Active::Learned(Box::new([
            slot(Phase::Lift, policies.lift)?,
            slot(Phase::Transport, policies.transport)?,
            slot(Phase::Place, policies.place)?,
        ])))
    }
}

/// The one check that `policy` is one a unit can fly in `phase`: a unit's observation and
/// action sizes, and an action map (the increment, this build's version). The daemon's loader
/// and [`Onboard::new`] both call it.
pub fn unit_action_map(phase: Phase, policy: &Policy) -> Result<ActionMap, OnboardError> {
    let m = policy.metadata();
    if m.obs_dim != ACTOR_OBS_DIM || m.action_dim != UNIT_ACTION_DIM {
        return Err(OnboardError::PolicyShape {
            phase,
            obs: m.obs_dim,
            actions: m.action_dim,
        });
    }
    ActionMap::of_policy(policy).map_err(|source| OnboardError::ActionMap { phase, source })
}

/// Where `phase`'s policy sits in [`Active::Learned`]; Idle has none.
fn policy_slot(phase: Phase) -> Option<usize> {
    match phase {
        Phase::Lift => Some(0),
        Phase::Transport => Some(1),
        Phase::Place => Some(2),
        Phase::Idle => None,
    }
}

/// Everything a unit's tick is configured with.
pub struct OnboardSettings {
    pub spec: UnitSpec,
    pub team: TeamSettings,
    pub gate: GateConfig,
    pub sync: SyncConfig,
    /// The mission goals: lift height, transport distance and profile, release rule.
    pub tasks: TaskConfig,
    /// Where this unit's base starts, in the team's shared world frame.
    pub start_pose: PlanarPose,
}

impl OnboardSettings {
    /// This source tree's shipped settings (`assets/unit.urdf`, `configs/gate.toml`,
    /// `configs/sync.toml`, `configs/tasks.toml`) for `team`, starting at `start_pose`: for
    /// tests and benches run from a checkout.
    pub fn shipped(team: TeamSettings, start_pose: PlanarPose) -> anyhow::Result<Self> {
        let urdf = moonhaul_core::config::repo_file("assets/unit.urdf");
        Ok(OnboardSettings {
            spec: UnitSpec::from_file(&urdf)?,
            team,
            gate: GateConfig::shipped()?,
            sync: SyncConfig::shipped()?,
            tasks: TaskConfig::shipped()?,
            start_pose,
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum OnboardError {
    #[error(transparent)]
    Team(#[from] moonhaul_coord::TeamError),
    #[error(transparent)]
    Clamp(#[from] moonhaul_coord::clamp::ClampError),
    #[error("{phase} policy: {source}")]
    ActionMap {
        phase: Phase,
        source: ActionMapError,
    },
    #[error("{phase} policy maps {obs} observations to {actions} actions; a unit needs {ACTOR_OBS_DIM} → {UNIT_ACTION_DIM}")]
    PolicyShape {
        phase: Phase,
        obs: usize,
        actions: usize,
    },
    #[error("mission.toml place_press_m = {press_m} m must exceed tasks.toml [place] contact_press_m = {contact_m} m, or the scripted placement never shows its touchdown and never releases")]
    PressBelowContact { press_m: f64, contact_m: f64 },
}

/// The phase episode in progress: what its goals are measured from.
#[derive(Debug, Clone, Copy)]
struct PhaseEpisode {
    phase: Phase,
    start_base: PlanarPose,
    start_us: u64,
}

/// What one tick hands back to the daemon.
pub struct TickOutput<'a> {
    /// To write to the hardware.
    pub output: UnitOutput,
    /// To publish to the team.
    pub message: &'a Envelope,
}

/// One unit's onboard logic; see the module docs.
pub struct Onboard {
    spec: UnitSpec,
    unit: usize,
    period_s: f64,
    tasks: TaskConfig,
    team: Team,
    pipeline: ActionPipeline,
    controller: Active,
    odometry: PlanarPose,
    /// U_{k-1} of this unit; `anchored` once it was set from a first reading.
    previous: UnitCommand,
    anchored: bool,
    /// t_max of the pipeline's last step and whether it held (the observation's `pipeline.*`).
    last_t_max: f64,
    last_held: bool,
    /// Stamp of each peer's newest accepted state (`None`: never heard, or this unit). Its
    /// state and command go straight into `sensed` and `previous_all`.
    peer_stamp_us: Vec<Option<u64>>,
    reference: Option<GraspReference>,
    episode: PhaseEpisode,
    grasp_open: bool,
    touchdown: Touchdown,
    latched_fault: Option<(FaultKind, &'static str)>,
    /// Drill: every policy output is made NaN before the tick checks it.
    corrupt_policy: bool,
    last_announce: Announcements,
    tick: u64,
    seq: u64,
    // The clamp's inputs, one entry per unit, reused per tick so the tick does not allocate:
    // own entries are written by the tick, peers' by `receive`.
    sensed: Vec<UnitState>,
    previous_all: Vec<UnitCommand>,
    issued_all: Vec<UnitCommand>,
    forces: Vec<f64>,
    /// Every unit's base pose when the phase episode began (own odometry, peers' published).
    phase_start_poses: Vec<PlanarPose>,
    message: Envelope,
}

impl Onboard {
    /// `boot_us`: the clock at start, the first sequence number (message.rs's convention, so a
    /// restarted unit never reuses one).
    pub fn new(
        settings: OnboardSettings,
        controller: Controller,
        boot_us: u64,
    ) -> Result<Self, OnboardError> {
        let controller = Active::new(controller, &settings.tasks)?;
        let n = settings.team.team_size;
        let unit = settings.team.unit_index;
        let period_s = settings.team.control_period_us as f64 * 1e-6;
        let team = Team::new(settings.team.clone(), &settings.gate)?;
        let pipeline = ActionPipeline::new(
            UnitModel::new(settings.spec.clone()),
            &settings.sync,
            period_s,
            n,
            unit,
        )?;
        let message = Envelope {
            version: PROTOCOL_VERSION,
            team: settings.team.team.clone(),
            sender: Sender::Unit(unit),
            seq: boot_us,
            stamp_us: boot_us,
            body: Body::Unit(UnitTick {
                phase: Phase::Idle,
                state: UnitState::default(),
                command: UnitCommand::default(),
                announce: Announcements::default(),
            }),
        };
        Ok(Onboard {
            spec: settings.spec,
            unit,
            period_s,
            tasks: settings.tasks,
            team,
            pipeline,
            controller,
            odometry: settings.start_pose,
            previous: UnitCommand::default(),
            anchored: false,
            last_t_max: 0.0,
            last_held: true,
            peer_stamp_us: vec![None; n],
            reference: None,
            episode: PhaseEpisode {
                phase: Phase::Idle,
                start_base: settings.start_pose,
                start_us: boot_us,
            },
            grasp_open: false,
            touchdown: Touchdown::default(),
            latched_fault: None,
            corrupt_policy: false,
            last_announce: Announcements::default(),
            tick: 0,
            seq: boot_us,
            sensed: vec![UnitState::default(); n],
            previous_all: vec![UnitCommand::default(); n],
            issued_all: vec![UnitCommand::default(); n],
            forces: vec![0.0; n],
            phase_start_poses: vec![settings.start_pose; n],
            message,
        })
    }

    pub fn unit(&self) -> usize {
        self.unit
    }

    /// The committed phase.
    pub fn phase(&self) -> Phase {
        self.team.phase()
    }

    /// The message of the last tick (what [`TickOutput::message`] returned).
    pub fn last_message(&self) -> &Envelope {
        &self.message
    }

    /// Whether every peer's newest accepted state is stamped at or after `stamp_us`.
    pub fn peers_heard_since(&self, stamp_us: u64) -> bool {
        self.peer_stamp_us
            .iter()
            .enumerate()
            .all(|(i, t)| i == self.unit || t.is_some_and(|t| t >= stamp_us))
    }

    /// The command that holds this unit where it is (wheels stopped, arm at its last command),
    /// once it has issued one.
    pub fn hold_command(&self) -> Option<UnitCommand> {
        self.anchored
            .then(|| moonhaul_coord::clamp::hold_command(&self.previous))
    }

    /// This unit's own latched fault, if any.
    pub fn fault(&self) -> Option<FaultKind> {
        self.latched_fault.map(|(kind, _)| kind)
    }

    /// The mission the team is in (the latest start it accepted): the daemon hands it to its
    /// validator after every tick ([`moonhaul_coord::Validator::set_mission`]).
    pub fn mission(&self) -> Option<u32> {
        self.team.mission()
    }

    /// Takes in one frame the validator refused: an authenticated peer message out of bounds
    /// is that peer's fault (the team stops for it once its last good state is stale, never
    /// latching a fault of this unit), and a refused operator frame is answered in the next
    /// messages.
    pub fn reject(&mut self, rejection: &Rejection) {
        if let Some(unit) = rejection.peer_fault() {
            self.team.peer_rejected(unit);
        }
        if let Some((seq, refusal)) = rejection.operator_refusal() {
            self.team.operator_refused(seq, refusal);
        }
    }

    /// Takes in one message that passed the validator.
    pub fn receive(&mut self, message: &Envelope) {
        if let (Sender::Unit(i), Body::Unit(tick)) = (message.sender, &message.body) {
            if let Some(stamp) = self.peer_stamp_us.get_mut(i).filter(|_| i != self.unit) {
                if stamp.is_none_or(|t| message.stamp_us >= t) {
                    *stamp = Some(message.stamp_us);
                    self.sensed[i] = tick.state;
                    self.previous_all[i] = tick.command;
                }
            }
        }
        self.team.receive(message);
    }

    /// This unit's state for a training episode of the next phase to begin from (see
    /// [`moonhaul_core::handover`]); `None` before its lift recorded a rest grasp.
    pub fn hand_over(&self) -> Option<UnitHandOver> {
        Some(UnitHandOver {
            command: self.previous,
            sensed: self.sensed[self.unit],
            last_t_max: self.last_t_max,
            last_held: self.last_held,
            beyond_ticks: self.pipeline.beyond_ticks(),
            odometry: self.odometry,
            phase_start_base: self.episode.start_base,
            reference: self.reference?,
        })
    }

    /// Drill: from now on the active policy's output is NaN, so the tick's own check of it
    /// (and the stop that follows) runs as on a real failure.
    pub fn inject_policy_nan(&mut self) {
        self.corrupt_policy = true;
    }

    /// Latches a fault found outside the tick (the daemon's hardware read or write failed).
    pub fn latch_fault(&mut self, kind: FaultKind, what: &'static str) {
        self.latched_fault.get_or_insert((kind, what));
    }

    /// One control tick at local (team-synchronized) time `now_us` on `reading`; `None` when
    /// the hardware read failed this tick. Fills `record` in place.
    pub fn tick(
        &mut self,
        now_us: u64,
        reading: Option<&UnitReading>,
        rejected: &RejectCounts,
        record: &mut TickRecord,
    ) -> TickOutput<'_> {
        self.tick += 1;
        let own = match reading {
            Some(r) if reading_is_finite(r) => self.own_state(r),
            Some(_) => {
                self.latch_fault(FaultKind::Sensor, "non-finite joint reading");
                self.sensed[self.unit]
            }
            None => {
                self.latch_fault(FaultKind::Drive, "hardware read failed");
                self.sensed[self.unit]
            }
        };
        let force_n = reading.and_then(|r| r.grasp_force_n);
        if !self.anchored && reading.is_some_and(reading_is_finite) {
            self.previous = anchor_command(&own);
            self.anchored = true;
        }
        self.sensed[self.unit] = own;
        self.previous_all[self.unit] = self.previous;

        let mut obs = [0.0; ACTOR_OBS_DIM];
        let mut goal = self.goal(now_us);
        let mut observed = self.observe(&goal, &mut obs);
        let lift_estimate_m = if observed {
            ObservationView(&obs).lift_estimate_m()
        } else {
            f64::NAN
        };
        let own_force = match force_n {
            Some(f) => f,
            None if self.grasp_open => 0.0,
            None => f64::INFINITY,
        };
        self.forces.fill(own_force);
        let goal_distance_m = self.team_goal_distance_m(now_us);
        let before = self.team.phase();
        let decision = self.team.tick(
            now_us,
            &Measurements {
                payload_height_m: self.touchdown.height_above_ground_m(lift_estimate_m),
                goal_distance_m,
                wheel_speed_radps: self.team_wheel_speed_radps(),
                grasp_force_n: &self.forces,
            },
            self.fault(),
        );
        if decision.phase != before {
            // A new phase episode has new goals (and Lift a new rest grasp): observe again.
            self.begin_phase(decision.phase, now_us, &own);
            goal = self.goal(now_us);
            observed = self.observe(&goal, &mut obs);
        }
        let mut delta = [0.0; UNIT_ACTION_DIM];
        let (hold, map) = self.increment(
            &decision,
            now_us,
            &goal,
            &own,
            observed.then_some(&obs),
            &mut delta,
        );
        let hold = hold.or_else(|| {
            self.fault()
                .map(|f| HoldReason::SafetyStop(moonhaul_coord::message::StopReason::Fault(f)))
        });
        let map = map.filter(|_| hold.is_none());
        let increment = map.as_ref().map(|map| Increment { map, delta: &delta });
        let report = self.pipeline.step(
            &PipelineInput {
                sensed: &self.sensed,
                previous: &self.previous_all,
                increment,
            },
            hold,
            &mut self.issued_all,
        );
        let (issued, report) = match report {
            Ok(r) => (self.issued_all[self.unit], Some(r)),
            Err(_) => {
                // Only non-finite inputs fail the clamp, and those latch above; hold anyway.
                self.latch_fault(FaultKind::Policy, "clamp rejected its inputs");
                (moonhaul_coord::clamp::hold_command(&self.previous), None)
            }
        };
        if report.is_some_and(|r| r.tracking_lost) {
            self.latch_fault(
                FaultKind::Tracking,
                "drives did not reach their command within hold.tracking_stop_ticks",
            );
        }
        let target = *self.pipeline.target();
        self.previous = issued;
        self.last_t_max = report.map_or(0.0, |r| r.clamp.t_max);
        self.last_held = report.is_none_or(|r| r.clamp.hold.is_some());
        // A measurement, not an action: counted on holds too, so the units' counts agree.
        // Only while placing: it costs two FK per unit.
        let press_m = if decision.phase == Phase::Place {
            let arms = self.team_arms();
            let release =
                self.touchdown
                    .update(&self.tasks.place, &arms, lift_estimate_m, self.period_s);
            self.grasp_open |= release;
            arms.largest_press_m()
        } else {
            f64::NAN
        };
        self.last_announce = decision.announce;
        self.fill_message(now_us, decision.phase, own, issued);

        record.unit = self.unit;
        record.tick = self.tick;
        record.stamp_us = now_us;
        record.phase = decision.phase;
        record.hold = report.and_then(|r| r.clamp.hold).or(hold);
        record.t_max = report.map_or(0.0, |r| r.clamp.t_max);
        record.distance = report.and_then(|r| r.clamp.distance);
        record.tracking_d = report.map(|r| r.tracking_d);
        record.sensed = own;
        record.payload_height_estimate_m = lift_estimate_m.is_finite().then_some(lift_estimate_m);
        record.press_m = press_m.is_finite().then_some(press_m);
        record.goal_distance_m = goal_distance_m;
        record.team_sensed.clear();
        record.team_sensed.extend_from_slice(&self.sensed);
        record.team_previous.clear();
        record.team_previous.extend_from_slice(&self.previous_all);
        record.grasp_force_n = force_n;
        record.grasp_open = self.grasp_open;
        record.target = target;
        record.issued = issued;
        record.peer_age_us.clear();
        for stamp in &self.peer_stamp_us {
            record
                .peer_age_us
                .push(stamp.map(|t| now_us.saturating_sub(t)));
        }
        record.fault = self.latched_fault.map(|(_, what)| what.into());
        record.rejected = *rejected;
        TickOutput {
            output: UnitOutput {
                command: issued,
                grasp_open: self.grasp_open,
            },
            message: &self.message,
        }
    }

    /// Own state from a reading: joints as read, base pose by wheel odometry.
    fn own_state(&mut self, r: &UnitReading) -> UnitState {
        let mut s = UnitState::default();
        s.wheels.position_rad = r.wheels.position_rad;
        s.wheels.velocity_radps = r.wheels.velocity_radps;
        s.arm.position_rad = r.arm.position_rad;
        s.arm.velocity_radps = r.arm.velocity_radps;
        if self.tick > 1 {
            self.odometry =
                self.spec
                    .integrate_base(&self.odometry, &r.wheels.velocity_radps, self.period_s);
        }
        s.base_pose = self.odometry;
        s.base_velocity = self.spec.base_velocity(&r.wheels.velocity_radps);
        s
    }

    /// The goal of the phase episode in progress at `now_us` (core's one definition, with the
    /// mission's targets).
    fn goal(&self, now_us: u64) -> PhaseGoal {
        let e = &self.episode;
        let phase_s = now_us.saturating_sub(e.start_us) as f64 * 1e-6;
        let (height_m, travel_m) = self.tasks.mission_targets(e.phase);
        self.tasks
            .phase_goal(e.phase, height_m, &e.start_base, travel_m, phase_s)
    }

    /// o⁽ⁱ⁾ for `goal`; false before a rest grasp was captured or when FK fails.
    fn observe(&self, goal: &PhaseGoal, out: &mut [f64; ACTOR_OBS_DIM]) -> bool {
        let Some(reference) = &self.reference else {
            return false;
        };
        let peer = self.peer_index();
        let commands = CommandState {
            own: self.previous,
            peer: self.previous_all[peer],
            last_t_max: self.last_t_max,
            last_held: self.last_held,
        };
        unit_observation(
            &self.spec,
            reference,
            &self.sensed[self.unit],
            &self.sensed[peer],
            &commands,
            goal,
            out,
        )
        .is_ok()
    }

    /// The neighbour in the closed chain (the paper's j): the next unit, wrapping.
    fn peer_index(&self) -> usize {
        (self.unit + 1) % self.peer_stamp_us.len()
    }

    /// A newly committed phase starts its episode (goals from the odometry now). Entering Lift
    /// starts a mission: the rest grasp is captured and the gripper is closed.
    fn begin_phase(&mut self, phase: Phase, now_us: u64, own: &UnitState) {
        for (start, sensed) in self.phase_start_poses.iter_mut().zip(&self.sensed) {
            *start = sensed.base_pose;
        }
        self.phase_start_poses[self.unit] = self.odometry;
        self.episode = PhaseEpisode {
            phase,
            start_base: self.odometry,
            start_us: now_us,
        };
        if phase == Phase::Lift {
            let peer = self.sensed[self.peer_index()];
            self.reference = GraspReference::capture(&self.spec, own, &peer).ok();
            self.grasp_open = false;
            self.touchdown = Touchdown::default();
        }
    }

    /// The hold reason, or this tick's increment of the active controller written into
    /// `delta` and the map that bounds it (`None` map: nothing to run, hold). A controller
    /// that fails (a non-finite policy output, IK without a solution) latches a policy fault.
    fn increment(
        &mut self,
        decision: &Decision,
        now_us: u64,
        goal: &PhaseGoal,
        own: &UnitState,
        obs: Option<&[f64; ACTOR_OBS_DIM]>,
        delta: &mut [f64; UNIT_ACTION_DIM],
    ) -> (Option<HoldReason>, Option<ActionMap>) {
        let phase = match decision.directive {
            Directive::Hold(reason) => return (Some(reason), None),
            Directive::Run(phase) => phase,
        };
        let profile = self.tasks.profile();
        let phase_time_s = now_us.saturating_sub(self.episode.start_us) as f64 * 1e-6;
        let peer = self.peer_index();
        let failed = match (&mut self.controller, policy_slot(phase), obs) {
            (Active::Learned(policies), Some(slot), Some(obs)) => {
                let (policy, scratch, _) = &mut policies[slot];
                let acted = policy.act(obs, scratch, delta);
                if self.corrupt_policy {
                    delta[0] = f64::NAN;
                }
                acted.is_err() || !delta.iter().all(|v| v.is_finite())
            }
            // An observation exists only once the rest grasp was captured.
            (
                Active::Scripted {
                    script,
                    map: script_map,
                },
                Some(_),
                Some(_),
            ) => match &self.reference {
                Some(reference) => {
                    let input = ScriptInput {
                        spec: &self.spec,
                        phase,
                        phase_time_s,
                        reference,
                        own,
                        peer: &self.sensed[peer],
                        phase_start_base: &self.episode.start_base,
                        goal,
                        profile: &profile,
                        previous: &self.previous,
                        grasp_open: self.grasp_open,
                    };
                    match script.command(&input) {
                        Ok(desired) => {
                            *delta = script_map.toward(&self.previous, &desired);
                            if self.corrupt_policy {
                                delta[0] = f64::NAN;
                            }
                            !delta.iter().all(|v| v.is_finite())
                        }
                        Err(_) => true,
                    }
                }
                None => true,
            },
            _ => true,
        };
        if failed {
            self.latch_fault(FaultKind::Policy, "non-finite or failed controller output");
            return (None, None);
        }
        let map = match &self.controller {
            Active::Learned(policies) => policy_slot(phase).map(|slot| policies[slot].2),
            Active::Scripted { map, .. } => Some(*map),
        };
        (None, map)
    }

    /// The payload's distance to its goal, m: the mean over the units of each base's
    /// odometric offset from its own phase goal (a peer's goal from its published pose when
    /// the phase began). Every unit computes the same figure, a tick apart, so the team
    /// agrees on the transition; one base's own distance would differ by the bases' odometry
    /// drift, enough to split the team past the agreement window.
    fn team_goal_distance_m(&self, now_us: u64) -> f64 {
        let e = &self.episode;
        let phase_s = now_us.saturating_sub(e.start_us) as f64 * 1e-6;
        let (height_m, travel_m) = self.tasks.mission_targets(e.phase);
        let mut offset = Vector2::zeros();
        for (start, sensed) in self.phase_start_poses.iter().zip(&self.sensed) {
            let goal = self
                .tasks
                .phase_goal(e.phase, height_m, start, travel_m, phase_s);
            offset += goal.base_goal_m - Vector2::new(sensed.base_pose.x_m, sensed.base_pose.y_m);
        }
        (offset / self.sensed.len() as f64).norm()
    }

    /// The team's arms for touchdown from every unit's last published (sensed, issued) pair, its own
    /// included: every unit computes it from the same messages, so the units' touchdowns fire
    /// on the same tick and they open their grippers together (each from its own latest
    /// state, the figures differed by a tick of motion, and once the first unit let go the
    /// other's press vanished with the load: the team split on Idle).
    fn team_arms(&self) -> TeamArms {
        let Body::Unit(own) = &self.message.body else {
            unreachable!("a unit's own message has a unit body");
        };
        team_arms(
            &self.spec,
            (0..self.sensed.len()).map(|i| {
                if i == self.unit {
                    (&own.state.arm.position_rad, &own.command.arm_position_rad)
                } else {
                    (
                        &self.sensed[i].arm.position_rad,
                        &self.previous_all[i].arm_position_rad,
                    )
                }
            }),
        )
    }

    /// The largest wheel speed in the team's last commands (own and peers' published U_{k−1}),
    /// rad/s: whether the team still drives, for the gate's stopped-at-goal check.
    fn team_wheel_speed_radps(&self) -> f64 {
        let speeds = self
            .previous_all
            .iter()
            .flat_map(|c| c.wheel_velocity_radps);
        if speeds.clone().any(|w| !w.is_finite()) {
            return f64::NAN;
        }
        speeds.fold(0.0, |a, w| a.max(w.abs()))
    }

    fn fill_message(&mut self, now_us: u64, phase: Phase, own: UnitState, issued: UnitCommand) {
        self.seq = self.seq.max(now_us).saturating_add(1);
        self.message.seq = self.seq;
        self.message.stamp_us = now_us;
        self.message.body = Body::Unit(UnitTick {
            phase,
            state: own,
            command: issued,
            announce: self.last_announce,
        });
    }
}

fn reading_is_finite(r: &UnitReading) -> bool {
    let wheels = &r.wheels;
    let arm = &r.arm;
    wheels
        .position_rad
        .iter()
        .chain(&wheels.velocity_radps)
        .chain(&arm.position_rad)
        .chain(&arm.velocity_radps)
        .all(|v| v.is_finite())
        && r.grasp_force_n.is_none_or(f64::is_finite)
}

impl TickRecord {
    /// An empty record for a team of `team_size`, reused every tick.
    pub fn for_team(team_size: usize) -> Self {
        TickRecord {
            unit: 0,
            tick: 0,
            stamp_us: 0,
            phase: Phase::Idle,
            hold: None,
            t_max: 0.0,
            distance: None,
            tracking_d: None,
            sensed: UnitState::default(),
            payload_height_estimate_m: None,
            press_m: None,
            goal_distance_m: 0.0,
            team_sensed: Vec::with_capacity(team_size),
            team_previous: Vec::with_capacity(team_size),
            grasp_force_n: None,
            grasp_open: false,
            target: UnitCommand::default(),
            issued: UnitCommand::default(),
            peer_age_us: Vec::with_capacity(team_size),
            fault: None,
            rejected: RejectCounts::default(),
            deadline_misses: 0,
            work_us: 0,
        }
    }

    /// Makes this record a copy of `other`, reusing its buffers: a copy without allocating
    /// once the team's vectors have their size (every field is named, so a new one is not
    /// forgotten).
    pub fn copy_from(&mut self, other: &TickRecord) {
        let TickRecord {
            unit,
            tick,
            stamp_us,
            phase,
            hold,
            t_max,
            distance,
            tracking_d,
            sensed,
            payload_height_estimate_m,
            press_m,
            goal_distance_m,
            team_sensed,
            team_previous,
            grasp_force_n,
            grasp_open,
            target,
            issued,
            peer_age_us,
            fault,
            rejected,
            deadline_misses,
            work_us,
        } = other;
        self.unit = *unit;
        self.tick = *tick;
        self.stamp_us = *stamp_us;
        self.phase = *phase;
        self.hold = *hold;
        self.t_max = *t_max;
        self.distance = *distance;
        self.tracking_d = *tracking_d;
        self.sensed = *sensed;
        self.payload_height_estimate_m = *payload_height_estimate_m;
        self.press_m = *press_m;
        self.goal_distance_m = *goal_distance_m;
        self.team_sensed.clone_from(team_sensed);
        self.team_previous.clone_from(team_previous);
        self.grasp_force_n = *grasp_force_n;
        self.grasp_open = *grasp_open;
        self.target = *target;
        self.issued = *issued;
        self.peer_age_us.clone_from(peer_age_us);
        self.fault.clone_from(fault);
        self.rejected = *rejected;
        self.deadline_misses = *deadline_misses;
        self.work_us = *work_us;
    }
}
