//! The phase tasks (lift, transport, place) as episodes of one simulated world: how an episode
//! starts, what each unit senses and observes, how raw actions become motor commands, and when
//! an episode ends. Training (`moonhaul-learn`'s phase envs, which add the paper's rewards) and
//! evaluation (`moonhaul eval`, no libtorch) share this one definition.
//!
//! **Episodes** (settings in `configs/tasks.toml`):
//! - *Lift* starts grasped with the payload resting on the ground; the goal height h* is the
//!   mission's (`transport.start_height_m`, what a deployed lift aims at) in a fraction
//!   `lift.mission_goal_fraction` of episodes, else drawn uniformly from `lift.goal_height_m`,
//!   and given to the policy, so one policy serves every target. The bases should hold still:
//!   their goal is where they start.
//! - *Transport* starts with the payload held `transport.start_height_m` up and moves it
//!   `distance_m` along +X under a trapezoidal velocity command (accelerate at `accel_mps2`,
//!   cruise at `speed_mps`, decelerate to stop at p_B). The reward's p_B is the profile's
//!   reference point at that instant (reaching the goal p_B when the profile ends): with a
//!   fixed p_B the position term would pay a policy to run ahead of v_cmd, contradicting the
//!   paper's velocity tracking result.
//! - *Place* starts held aloft near p_B (drawn within ±`place.goal_offset_m` of the start along
//!   X); it ends released: the grasps open as onboard, once the units' touchdown signal
//!   ([`moonhaul_core::touchdown`], from the sensed joints and the commands) has lasted
//!   `release_after_contact_s` (the gripper is not part of u⁽ⁱ⁾).
//! - *Hand-over starts* ([`PhaseTask::begin_handover`], [`crate::handover`]): a transport or
//!   place episode can instead begin where a deployed mission handed over, in the replayed
//!   world of that mission, with each unit's onboard U_{k−1}, clamp step, hold count,
//!   odometry and rest grasp, and the mission's goals. Training configs choose the share.
//!
//! **Terminations** (no value beyond them): a grasp broke by overload; the payload tilted past
//! `safety.max_tilt_deg` (a safety bound, far above the 10° reward tolerance); the world
//! diverged (non-finite state). **Truncation** (bootstrapped): the phase's `duration_s`.
//!
//! **Sensing.** Each unit sees its encoders with Gaussian noise (`[sensing]`) and its base
//! pose by integrating the *sensed* wheel velocities from the known start pose (wheel odometry,
//! as onboard; wheel slip makes it drift from the truth). **Peers lag one tick**, as onboard
//! (`deploy/src/tick.rs`): a unit's observation and its clamp see its own reading of this tick
//! and the peer's state as published at the end of the peer's previous tick (with the command
//! issued then). The actor observation is
//! [`moonhaul_core::observation::unit_observation`] of those readings; the critic additionally
//! sees privileged truth ([`CRITIC_EXTRA`]).
//!
//! **Rest reference of a lifted start.** The onboard lift estimate is the FK lift of the end
//! effector since the rest grasp. A lifted start has no rest grasp of its own, so it takes the
//! commanded grasp solution (`PayloadModel::grasp_q_rad`, where the mission's lift began): the
//! arm drives hold their set-points (see `scene/actuation.rs`) and the start is settled with
//! the payload in the arms, so the estimate equals the start lift, and the true payload height
//! is that lift plus the 2 mm the world spawns it above the ground (checked within 5 mm for
//! every shipped payload in `tests/drives.rs`).
//!
//! **Actions.** The paper's increment through the one action pipeline
//! ([`moonhaul_coord::pipeline`]), exactly as onboard: a raw policy output a ∈ ℝ⁹ is scaled to
//! the increment Δ = step ⊙ a (`[action]` of tasks.toml, [`moonhaul_core::action`]; the exported
//! policy's output affine is this scale), F = U_{k−1} + clip(Δ, ±step), then each unit's clamp
//! over both units' stacked state (its own F, the peer's S = F = U_{k−1}) gives U_k. Every
//! episode starts anchored on the sensed joints (wheels stopped). A unit whose drives stay
//! beyond tolerance of their command for `hold.tracking_stop_ticks` raises a safety stop
//! onboard; here that ends the episode ([`Termination::TrackingLost`]).

use moonhaul_coord::clamp::anchor_command;
use moonhaul_coord::{ActionPipeline, Increment, PipelineInput, PipelineReport, SyncConfig};
use moonhaul_core::action::ActionMap;
use moonhaul_core::observation::{
    unit_observation, CommandState, GraspReference, ObservationView, PhaseGoal, ACTOR_OBS_DIM,
};
use moonhaul_core::scripted::{MissionPlan, PhaseScript, ScriptInput};
use moonhaul_core::seed::stream_seed;
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand, UnitState, UNIT_ACTION_DIM};
use moonhaul_core::touchdown::{team_arms, Touchdown};
use nalgebra::Vector2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::handover::HandOver;
use crate::scene::{Env, EnvOptions, EnvState, SceneModel, UNITS};
use crate::SimError;

pub use moonhaul_core::task_config::{
    ActionSettings, LiftTask, MissionTask, PlaceTask, Safety, Sensing, TaskConfig, TransportTask,
    VelocityProfile,
};

/// Extra critic inputs after the actor's: true payload height error, tilt, linear and angular
/// velocity, both grasps' force (over the fair weight share) and torque, wheel friction,
/// payload mass, the payload's planar error to the reference in the own frame, the fraction of
/// the episode left, whether the grasps are released and the payload touches the ground, and how
/// close the unit's hold rule is to its tracking stop (ticks beyond tolerance over
/// `tracking_stop_ticks`), so the critic can predict the stop that ends an episode.
pub const CRITIC_EXTRA: usize = 20;
/// Width of a critic observation.
pub const CRITIC_OBS_DIM: usize = ACTOR_OBS_DIM + CRITIC_EXTRA;

/// What ended an episode early.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    GraspBroken,
    Tilted,
    NonFinite,
    /// A unit's drives could not reach its command (the onboard hold rule's safety stop).
    TrackingLost,
}

/// The answer of [`Episode::advance`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StepOutcome {
    pub terminated: Option<Termination>,
    pub truncated: bool,
}

/// One phase task: its settings and action map; shared by all worlds.
#[derive(Debug, Clone)]
pub struct PhaseTask {
    /// The phase an episode starts in (lift for the mission).
    pub phase: Phase,
    /// The monolithic baseline: the whole mission as one episode, the reward following its
    /// progress (lift until the payload is `mission.lift_done_height_m` up, transport until
    /// the velocity profile ends, then place), the policy never told the phase.
    pub mission: bool,
    pub config: TaskConfig,
    /// The synchronization clamp and hold rule of `configs/sync.toml`.
    pub sync: SyncConfig,
    map: ActionMap,
    control_period_s: f64,
    max_steps: u64,
}

impl PhaseTask {
    /// The task of `phase` on `scene`, stepping through the clamp of `sync`.
    pub fn new(
        phase: Phase,
        config: TaskConfig,
        sync: SyncConfig,
        scene: &SceneModel,
    ) -> Result<Self, SimError> {
        if phase == Phase::Idle {
            return Err(SimError::Config {
                field: "phase",
                reason: "idle has no task".into(),
            });
        }
        let control_period_s = 1.0 / scene.config.control_hz;
        Ok(PhaseTask {
            phase,
            mission: false,
            map: ActionMap::from_settings(&config.action),
            sync,
            max_steps: (config.duration_s(phase) / control_period_s).round() as u64,
            control_period_s,
            config,
        })
    }

    /// The monolithic baseline's task: the whole mission, lift + transport + place long.
    pub fn mission(
        config: TaskConfig,
        sync: SyncConfig,
        scene: &SceneModel,
    ) -> Result<Self, SimError> {
        let mut task = Self::new(Phase::Lift, config, sync, scene)?;
        let total_s: f64 = [Phase::Lift, Phase::Transport, Phase::Place]
            .iter()
            .map(|&p| config.duration_s(p))
            .sum();
        task.mission = true;
        task.max_steps = (total_s / task.control_period_s).round() as u64;
        Ok(task)
    }

    /// The same task with its episodes cut at `time_limit_s` instead of the phase's
    /// `duration_s`, which the actor's phase progress keeps measuring: evaluation runs a
    /// placement on past its training horizon to see the released payload settle.
    pub fn with_time_limit_s(mut self, time_limit_s: f64) -> Self {
        self.max_steps = (time_limit_s / self.control_period_s).round() as u64;
        self
    }

    /// A scripted expert for one unit of an episode of this task: it takes the phase over with
    /// the payload where the task starts it (`start_lift_m`: a transport or place start, or a
    /// hand-over, holds the mission's transport height).
    pub fn expert(&self, plan: MissionPlan) -> PhaseScript {
        PhaseScript::resume(plan, self.phase, self.config.start_lift_m(self.phase))
    }

    /// The increment map: the exported policy's output scale is its steps.
    pub fn action_map(&self) -> &ActionMap {
        &self.map
    }

    /// Control steps in a full episode.
    pub fn max_steps(&self) -> u64 {
        self.max_steps
    }

    /// How a world must be built for this task.
    pub fn env_options(&self, randomize: bool, payload: Option<crate::PayloadKind>) -> EnvOptions {
        EnvOptions {
            randomize,
            payload,
            start_lift_m: self.config.start_lift_m(self.phase),
        }
    }

    /// One unit's increment Δ = step ⊙ a for raw action `raw` (`[UNIT_ACTION_DIM]`); the
    /// pipeline bounds it to ±step.
    pub fn increment(&self, raw: &[f64]) -> [f64; UNIT_ACTION_DIM] {
        std::array::from_fn(|k| self.map.step[k] * raw[k])
    }

    /// The task's random stream for the world seeded with `env_seed` (goals, sensing noise),
    /// independent of the world's own.
    pub fn rng(env_seed: u64) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(stream_seed(env_seed, 0x7a5c))
    }

    /// Starts an episode on the freshly reset world `env` in state `state`.
    pub fn begin(
        &self,
        scene: &SceneModel,
        env: &Env,
        state: &EnvState,
        rng: &mut ChaCha8Rng,
    ) -> Result<Episode, SimError> {
        let c = &self.config;
        let goal_height_m = match self.phase {
            // The mission lifts to the transport height and never says it is placing.
            Phase::Lift if self.mission => c.transport.start_height_m,
            Phase::Lift if rng.random_bool(c.lift.mission_goal_fraction) => {
                c.transport.start_height_m
            }
            Phase::Lift => {
                let [lo, hi] = c.lift.goal_height_m;
                if hi > lo {
                    rng.random_range(lo..hi)
                } else {
                    lo
                }
            }
            Phase::Transport => c.transport.start_height_m,
            Phase::Place | Phase::Idle => 0.0,
        };
        let place_offset_m = if self.phase == Phase::Place && c.place.goal_offset_m > 0.0 {
            rng.random_range(-c.place.goal_offset_m..c.place.goal_offset_m)
        } else {
            0.0
        };
        let start_base = state.units.map(|u| u.state.base_pose);
        let payload_start = state.payload.pose.translation.vector.xy();
        let mut episode = Episode {
            phase: self.phase,
            phase_start_step: 0,
            goal_height_m,
            place_offset_m,
            start_base,
            payload_start,
            odometry: start_base,
            sensed: [UnitState::default(); UNITS],
            published: [UnitState::default(); UNITS],
            // Replaced below once the first readings are sensed.
            reference: [GraspReference {
                ee_rest_in_base: nalgebra::Isometry3::identity(),
                peer_ee_rest_in_base: nalgebra::Isometry3::identity(),
                peer_base_rest: PlanarPose::default(),
            }; UNITS],
            steps: 0,
            touchdown: [Touchdown::default(); UNITS],
            released: [false; UNITS],
            previous: [UnitCommand::default(); UNITS],
            pipelines: self.pipelines(scene)?,
            reports: None,
            last_step: [(0.0, true); UNITS],
        };
        episode.sense(self, scene, state, rng, false);
        episode.published = episode.sensed;
        episode.previous = episode.sensed.map(|s| anchor_command(&s));
        // The rest grasp is where the arms are now when the payload rests; a lifted start
        // takes it from the grasp solution (where the mission's lift began).
        let rest_q = if self.config.start_lift_m(self.phase) > 0.0 {
            Some(scene.payloads[&env.payload_kind()].grasp_q_rad)
        } else {
            None
        };
        let mut at_rest = episode.sensed;
        if let Some(q) = rest_q {
            for unit in &mut at_rest {
                unit.arm.position_rad = q;
            }
        }
        for i in 0..UNITS {
            episode.reference[i] =
                GraspReference::capture(&scene.spec, &at_rest[i], &at_rest[1 - i])
                    .map_err(|e| SimError::Kinematics(e.to_string()))?;
        }
        Ok(episode)
    }
}

impl PhaseTask {
    /// Starts an episode where a deployed mission handed over ([`crate::handover`]): on `env`,
    /// [`Env::replay`]ed from `handover` and reset (so in the captured world state `state`),
    /// with each unit's captured onboard state — its U_{k−1}, pipeline step and hold count,
    /// odometry, rest grasp and the phase start its goals are measured from — and the peers'
    /// published states of the hand-over tick. The goals are the mission's, as onboard.
    pub fn begin_handover(
        &self,
        scene: &SceneModel,
        state: &EnvState,
        handover: &HandOver,
        rng: &mut ChaCha8Rng,
    ) -> Result<Episode, SimError> {
        if self.mission || handover.phase != self.phase {
            return Err(SimError::Config {
                field: "handover",
                reason: format!(
                    "a hand-over into {} cannot start a {} episode",
                    handover.phase,
                    if self.mission {
                        "mission".to_string()
                    } else {
                        self.phase.to_string()
                    }
                ),
            });
        }
        let units = &handover.units;
        let (goal_height_m, _) = self.config.mission_targets(self.phase);
        let mut pipelines = self.pipelines(scene)?;
        for (pipeline, unit) in pipelines.iter_mut().zip(units) {
            pipeline.resume(unit.beyond_ticks);
        }
        let mut episode = Episode {
            phase: self.phase,
            phase_start_step: 0,
            goal_height_m,
            place_offset_m: 0.0,
            start_base: units.map(|u| u.phase_start_base),
            payload_start: state.payload.pose.translation.vector.xy(),
            odometry: units.map(|u| u.odometry),
            sensed: units.map(|u| u.sensed),
            published: units.map(|u| u.sensed),
            reference: units.map(|u| u.reference),
            steps: 0,
            touchdown: [Touchdown::default(); UNITS],
            released: [false; UNITS],
            previous: units.map(|u| u.command),
            pipelines,
            reports: None,
            last_step: units.map(|u| (u.last_t_max, u.last_held)),
        };
        // The first tick after the hand-over: what was sensed then is now published, and the
        // odometry runs on.
        episode.sense(self, scene, state, rng, true);
        Ok(episode)
    }

    /// One action pipeline per unit, each from its own unit's view.
    fn pipelines(&self, scene: &SceneModel) -> Result<[ActionPipeline; UNITS], SimError> {
        let model = moonhaul_coord::UnitModel::new(scene.spec.clone());
        let make = |i: usize| {
            ActionPipeline::new(model.clone(), &self.sync, self.control_period_s, UNITS, i)
                .map_err(|e| SimError::Kinematics(e.to_string()))
        };
        Ok([make(0)?, make(1)?])
    }
}

/// What a unit's encoders report of its true state `truth`: the joints with the Gaussian
/// noise of `[sensing]` (arm positions, arm velocities, wheel velocities, drawn in that order
/// from `rng`), wheel positions as they are. The base pose and velocity are left as the truth;
/// onboard they come from odometry. The training tasks and the mission's world process sense
/// through this one function.
pub fn encoder_reading(truth: &UnitState, sensing: &Sensing, rng: &mut ChaCha8Rng) -> UnitState {
    let mut noise = |std: f64| std * rng.sample::<f64, _>(StandardNormal);
    let mut sensed = *truth;
    for q in &mut sensed.arm.position_rad {
        *q += noise(sensing.arm_position_noise_std_rad);
    }
    for v in &mut sensed.arm.velocity_radps {
        *v += noise(sensing.arm_velocity_noise_std_radps);
    }
    for v in &mut sensed.wheels.velocity_radps {
        *v += noise(sensing.wheel_velocity_noise_std_radps);
    }
    sensed
}

/// One world's episode in progress.
#[derive(Debug, Clone)]
pub struct Episode {
    /// The phase whose reward applies now (the task's, or the mission's progress).
    phase: Phase,
    phase_start_step: u64,
    goal_height_m: f64,
    place_offset_m: f64,
    start_base: [PlanarPose; UNITS],
    payload_start: Vector2<f64>,
    /// Each unit's wheel odometry.
    odometry: [PlanarPose; UNITS],
    /// What each unit sensed at the last tick.
    sensed: [UnitState; UNITS],
    /// What each unit published at the end of its previous tick: its sensed state of the tick
    /// before (peers see it one tick late).
    published: [UnitState; UNITS],
    reference: [GraspReference; UNITS],
    steps: u64,
    /// Each unit's touchdown, from its own view (its lift estimate), as onboard.
    touchdown: [Touchdown; UNITS],
    /// Each unit's gripper opened.
    released: [bool; UNITS],
    /// U_{k−1} of each unit.
    previous: [UnitCommand; UNITS],
    /// Each unit's action pipeline (its clamp over both units, its hold rule).
    pipelines: [ActionPipeline; UNITS],
    /// What each unit's pipeline did at the last step.
    reports: Option<[PipelineReport; UNITS]>,
    /// Each unit's last pipeline step as its observation sees it: t_max and whether it held
    /// (before the first step, a hold, or the hand-over's).
    last_step: [(f64, bool); UNITS],
}

impl Episode {
    /// Both units' commands U_k for increments `deltas` (Δ = step ⊙ a, e.g. from
    /// [`PhaseTask::increment`] or a policy file's output), through each unit's pipeline —
    /// the function the onboard tick calls.
    pub fn commands(
        &mut self,
        task: &PhaseTask,
        deltas: &[[f64; UNIT_ACTION_DIM]; UNITS],
    ) -> Result<[UnitCommand; UNITS], SimError> {
        let mut issued = [UnitCommand::default(); UNITS];
        let mut next = self.previous;
        let mut reports = [None; UNITS];
        for (i, pipeline) in self.pipelines.iter_mut().enumerate() {
            let mut view = self.published;
            view[i] = self.sensed[i];
            let report = pipeline
                .step(
                    &PipelineInput {
                        sensed: &view,
                        previous: &self.previous,
                        increment: Some(Increment {
                            map: &task.map,
                            delta: &deltas[i],
                        }),
                    },
                    None,
                    &mut issued,
                )
                .map_err(|e| SimError::Kinematics(e.to_string()))?;
            next[i] = issued[i];
            reports[i] = Some(report);
        }
        self.previous = next;
        self.reports = reports[0].zip(reports[1]).map(|(a, b)| [a, b]);
        if let Some(reports) = &self.reports {
            self.last_step = reports.map(|r| (r.clamp.t_max, r.clamp.hold.is_some()));
        }
        Ok(next)
    }

    /// What each unit's pipeline did at the last [`Episode::commands`] (`None` before the
    /// first).
    pub fn reports(&self) -> Option<&[PipelineReport; UNITS]> {
        self.reports.as_ref()
    }

    /// Time since the episode began, s.
    pub fn time_s(&self, task: &PhaseTask) -> f64 {
        self.steps as f64 * task.control_period_s
    }

    /// The phase whose reward applies now.
    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// Time since the current phase began, s.
    fn phase_time_s(&self, task: &PhaseTask) -> f64 {
        (self.steps - self.phase_start_step) as f64 * task.control_period_s
    }

    /// How far the payload goes along X in this episode, m.
    fn travel_m(&self, task: &PhaseTask) -> f64 {
        if task.mission || task.phase == Phase::Transport {
            task.config.transport.distance_m
        } else if task.phase == Phase::Place {
            self.place_offset_m
        } else {
            0.0
        }
    }

    /// Control steps since the episode began.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The same episode aiming at h* = `height_m` instead of its drawn goal (evaluation at the
    /// paper's fixed lift targets).
    pub fn with_goal_height(mut self, height_m: f64) -> Self {
        self.goal_height_m = height_m;
        self
    }

    /// h*, m.
    pub fn goal_height_m(&self) -> f64 {
        self.goal_height_m
    }

    /// Every unit's gripper opened.
    pub fn released(&self) -> bool {
        self.released.iter().all(|&r| r)
    }

    /// The payload's planar reference position now (the reward's p_B), world frame.
    pub fn reference_position_m(&self, task: &PhaseTask) -> Vector2<f64> {
        let along = match self.phase {
            Phase::Transport => task.config.profile().travelled_at(self.phase_time_s(task)),
            Phase::Place => self.travel_m(task),
            Phase::Lift | Phase::Idle => 0.0,
        };
        self.payload_start + Vector2::new(along, 0.0)
    }

    /// The commanded payload velocity now (v_cmd), world frame.
    pub fn command_velocity_mps(&self, task: &PhaseTask) -> Vector2<f64> {
        self.goal(task, 0).velocity_mps
    }

    /// Unit `i`'s phase goal in the world frame (core's one definition, with this episode's
    /// drawn h* and travel).
    pub fn goal(&self, task: &PhaseTask, i: usize) -> PhaseGoal {
        task.config.phase_goal(
            self.phase,
            self.goal_height_m,
            &self.start_base[i],
            self.travel_m(task),
            self.phase_time_s(task),
        )
    }

    /// Unit `i`'s rest-grasp reference (what its daemon records when the grasp closes).
    pub fn reference(&self, i: usize) -> &GraspReference {
        &self.reference[i]
    }

    /// What unit `i` sensed at the last tick.
    pub fn sensed(&self, i: usize) -> &UnitState {
        &self.sensed[i]
    }

    /// What unit `i` published at the end of its previous tick: what its peer sees of it now.
    pub fn published(&self, i: usize) -> &UnitState {
        &self.published[i]
    }

    /// What unit `i` knows of the commands and its pipeline: its own U_{k−1}, the peer's, and
    /// its pipeline's last step (before the first step, a hold: a phase begins after one; a
    /// hand-over start's, as captured).
    pub fn command_state(&self, i: usize) -> CommandState {
        let (last_t_max, last_held) = self.last_step[i];
        CommandState {
            last_t_max,
            last_held,
            ..CommandState::after_hold(self.previous[i], self.previous[1 - i])
        }
    }

    /// The scripted expert's action for unit `i` now: the raw action a whose increment
    /// Δ = step ⊙ a moves U_{k−1} toward what `script` (this unit's, kept across the episode's
    /// ticks) commands from what the unit knows onboard (its sensed state and odometry, the
    /// peer's published state, the rest grasp, the phase clock, start pose and goal), each
    /// component clipped to ±1 (the pipeline bounds the increment to ±step). The labels a
    /// policy is cloned from: the expert flies the same pipeline and clamp the policy does.
    /// Start the script with [`PhaseTask::expert`].
    pub fn expert_action(
        &self,
        task: &PhaseTask,
        scene: &SceneModel,
        i: usize,
        script: &mut PhaseScript,
    ) -> Result<[f64; UNIT_ACTION_DIM], SimError> {
        let input = ScriptInput {
            spec: &scene.spec,
            phase: self.phase,
            phase_time_s: self.phase_time_s(task),
            reference: &self.reference[i],
            own: &self.sensed[i],
            peer: &self.published[1 - i],
            phase_start_base: &self.start_base[i],
            goal: &self.goal(task, i),
            profile: &task.config.profile(),
            previous: &self.previous[i],
            grasp_open: self.released[i],
        };
        let desired = script
            .command(&input)
            .map_err(|e| SimError::Kinematics(format!("the scripted expert of unit {i}: {e}")))?;
        let delta = task.map.toward(&self.previous[i], &desired);
        Ok(std::array::from_fn(|k| {
            (delta[k] / task.map.step[k]).clamp(-1.0, 1.0)
        }))
    }

    /// Unit `i`'s actor observation.
    pub fn observe(
        &self,
        task: &PhaseTask,
        scene: &SceneModel,
        i: usize,
        out: &mut [f64; ACTOR_OBS_DIM],
    ) -> Result<(), SimError> {
        unit_observation(
            &scene.spec,
            &self.reference[i],
            &self.sensed[i],
            &self.published[1 - i],
            &self.command_state(i),
            &self.goal(task, i),
            out,
        )
        .map_err(|e| SimError::Kinematics(e.to_string()))
    }

    /// Unit `i`'s critic observation: its actor observation, then privileged truth.
    pub fn observe_critic(
        &self,
        task: &PhaseTask,
        scene: &SceneModel,
        env: &Env,
        state: &EnvState,
        i: usize,
        out: &mut [f64],
    ) -> Result<(), SimError> {
        let mut actor = [0.0; ACTOR_OBS_DIM];
        self.observe(task, scene, i, &mut actor)?;
        out[..ACTOR_OBS_DIM].copy_from_slice(&actor);
        let p = &state.payload;
        let draw = env.draw();
        let mass_kg = env.payload_mass_kg(scene);
        let share_n = mass_kg * scene.config.physics.gravity_mps2.abs() / UNITS as f64;
        // The payload's planar error to its reference, in the unit's own (true) frame.
        let error = self.reference_position_m(task) - p.pose.translation.vector.xy();
        let (sin, cos) = state.units[i].state.base_pose.yaw_rad.sin_cos();
        let (ex, ey) = (
            cos * error.x + sin * error.y,
            -sin * error.x + cos * error.y,
        );
        let (own, peer) = (&state.units[i].grasp, &state.units[1 - i].grasp);
        let extra: [f64; CRITIC_EXTRA] = [
            p.height_m - self.goal_height_m,
            p.tilt_rad,
            p.linvel_mps.x,
            p.linvel_mps.y,
            p.linvel_mps.z,
            p.angvel_radps.x,
            p.angvel_radps.y,
            p.angvel_radps.z,
            own.force_n / share_n,
            peer.force_n / share_n,
            own.torque_nm / share_n,
            peer.torque_nm / share_n,
            draw.wheel_friction,
            mass_kg,
            ex,
            ey,
            1.0 - self.steps as f64 / task.max_steps as f64,
            f64::from(u8::from(self.released[i])),
            f64::from(u8::from(p.ground_contact)),
            self.pipelines[i].tracking_stop_progress(),
        ];
        out[ACTOR_OBS_DIM..CRITIC_OBS_DIM].copy_from_slice(&extra);
        Ok(())
    }

    /// Reads the units' encoders with noise and advances their wheel odometry (`odometry`
    /// false: at the episode start, where the pose is the known start pose).
    fn sense(
        &mut self,
        task: &PhaseTask,
        scene: &SceneModel,
        state: &EnvState,
        rng: &mut ChaCha8Rng,
        odometry: bool,
    ) {
        if odometry {
            self.published = self.sensed;
        }
        for i in 0..UNITS {
            let mut sensed = encoder_reading(&state.units[i].state, &task.config.sensing, rng);
            if odometry {
                self.odometry[i] = scene.spec.integrate_base(
                    &self.odometry[i],
                    &sensed.wheels.velocity_radps,
                    task.control_period_s,
                );
            }
            sensed.base_pose = self.odometry[i];
            sensed.base_velocity = scene.spec.base_velocity(&sensed.wheels.velocity_radps);
            self.sensed[i] = sensed;
        }
    }

    /// After the world stepped into `state`: senses, counts time, opens the grasps when a
    /// placement has touched down, and says whether the episode ended.
    pub fn advance(
        &mut self,
        task: &PhaseTask,
        scene: &SceneModel,
        env: &mut Env,
        state: &mut EnvState,
        rng: &mut ChaCha8Rng,
    ) -> StepOutcome {
        self.steps += 1;
        if !state.is_finite() {
            return StepOutcome {
                terminated: Some(Termination::NonFinite),
                truncated: false,
            };
        }
        // What the units published last tick, (Y_k, U_k), is what onboard touchdown reads
        // ([`moonhaul_core::touchdown`]); taken before the new readings replace Y_k, and only
        // while placing (the step is the training hot path).
        let arms = (self.phase == Phase::Place && !self.released()).then(|| {
            team_arms(
                &scene.spec,
                (0..UNITS).map(|i| {
                    (
                        &self.sensed[i].arm.position_rad,
                        &self.previous[i].arm_position_rad,
                    )
                }),
            )
        });
        self.sense(task, scene, state, rng, true);
        if task.mission {
            let next = match self.phase {
                Phase::Lift if state.payload.height_m >= task.config.mission.lift_done_height_m => {
                    Some(Phase::Transport)
                }
                Phase::Transport
                    if self.phase_time_s(task) >= task.config.profile().duration_s() =>
                {
                    Some(Phase::Place)
                }
                _ => None,
            };
            if let Some(next) = next {
                self.phase = next;
                self.phase_start_step = self.steps;
            }
        }
        if let (Phase::Place, Some(arms)) = (self.phase, arms) {
            // Each unit opens its own gripper on its own touchdown, from its own estimate (the
            // observation's, as onboard): the two may open a tick apart.
            let mut opened = false;
            for i in 0..UNITS {
                let mut obs = [0.0; ACTOR_OBS_DIM];
                let lift_m = match self.observe(task, scene, i, &mut obs) {
                    Ok(()) => ObservationView(&obs).lift_estimate_m(),
                    Err(_) => f64::NAN,
                };
                let fired = self.touchdown[i].update(
                    &task.config.place,
                    &arms,
                    lift_m,
                    task.control_period_s,
                );
                if fired && !self.released[i] {
                    env.release_grasp(i);
                    self.released[i] = true;
                    opened = true;
                }
            }
            if opened {
                env.state_into(scene, state);
            }
        }
        let tracking_lost = self
            .reports
            .is_some_and(|r| r.iter().any(|r| r.tracking_lost));
        let terminated = if state.grasp_broken {
            Some(Termination::GraspBroken)
        } else if tracking_lost {
            Some(Termination::TrackingLost)
        } else if state.payload.tilt_rad > task.config.safety.max_tilt_deg.to_radians() {
            Some(Termination::Tilted)
        } else {
            None
        };
        StepOutcome {
            terminated,
            truncated: terminated.is_none() && self.steps >= task.max_steps,
        }
    }
}
