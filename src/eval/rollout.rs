//! Evaluation episodes in the simulator: a phase policy run exactly as a unit runs it onboard
//! (core's MLP on [`moonhaul_core::observation::unit_observation`] of the sensed readings, its
//! increment through each unit's action pipeline and clamp, no exploration noise), and the
//! scripted IK controller's time-scheduled mission as a model-based baseline. Each episode
//! becomes rows of [`EpisodeRow`].

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use moonhaul_core::observation::ACTOR_OBS_DIM;
use moonhaul_core::policy::{Policy, PolicyScratch};
use moonhaul_core::state::{Phase, UNIT_ACTION_DIM};
use moonhaul_sim::scene::{Env, EnvState, SceneModel, UNITS};
use moonhaul_sim::scripted::{run_mission, MissionPlan};
use moonhaul_sim::task::{Episode, PhaseTask};
use moonhaul_sim::{BatchEnv, EnvOptions, PayloadKind};
use rand_chacha::ChaCha8Rng;

use super::episode::EpisodeRow;

/// One evaluation case: a phase, and for lift the target height.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Case {
    pub phase: Phase,
    pub goal_height_m: Option<f64>,
}

impl Case {
    /// The paper's five cases.
    pub const ALL: [Case; 5] = [
        Case::lift(0.3),
        Case::lift(0.5),
        Case::lift(0.75),
        Case {
            phase: Phase::Transport,
            goal_height_m: None,
        },
        Case {
            phase: Phase::Place,
            goal_height_m: None,
        },
    ];

    const fn lift(height_m: f64) -> Case {
        Case {
            phase: Phase::Lift,
            goal_height_m: Some(height_m),
        }
    }

    /// `lift-0.3`, `transport`, `place`: the folder name of the case's CSVs.
    pub fn name(&self) -> String {
        match self.goal_height_m {
            Some(h) => format!("{}-{h}", self.phase.name()),
            None => self.phase.name().to_owned(),
        }
    }
}

pub use moonhaul_deploy::cli_support::load_policy;

/// The row of one control tick of a phase episode.
fn row(task: &PhaseTask, episode: &Episode, state: &EnvState) -> EpisodeRow {
    let v_cmd = episode.command_velocity_mps(task);
    state_row(
        episode.time_s(task),
        task.phase,
        episode.goal_height_m(),
        [v_cmd.x, v_cmd.y],
        state,
    )
}

/// A row of the simulator's truth `state` at `t_s`, in `phase`, against h* = `goal_height_m`
/// and v_cmd = `command_mps` (world frame).
pub fn state_row(
    t_s: f64,
    phase: Phase,
    goal_height_m: f64,
    command_mps: [f64; 2],
    state: &EnvState,
) -> EpisodeRow {
    let p = &state.payload;
    EpisodeRow {
        t_s,
        phase,
        goal_height_m,
        payload_height_m: p.height_m,
        payload_tilt_deg: p.tilt_rad.to_degrees(),
        payload_vx_mps: p.linvel_mps.x,
        payload_vy_mps: p.linvel_mps.y,
        payload_vz_mps: p.linvel_mps.z,
        command_vx_mps: command_mps[0],
        command_vy_mps: command_mps[1],
        ground_contact: p.ground_contact,
        grasp_force_1_n: state.units[0].grasp.force_n,
        grasp_force_2_n: state.units[1].grasp.force_n,
    }
}

/// Which seeded episodes to run: on which payload, how many, and how.
#[derive(Debug, Clone, Copy)]
pub struct Episodes {
    pub payload: PayloadKind,
    /// Domain randomization on, or the nominal world.
    pub randomize: bool,
    pub count: usize,
    /// Episode k's world is seeded with the k-th stream of this seed.
    pub seed: u64,
    /// Simulator threads (0: one per core).
    pub threads: usize,
}

/// One world's evaluation episode in progress.
struct Slot {
    episode: Episode,
    rng: ChaCha8Rng,
    scratch: PolicyScratch,
    rows: Vec<EpisodeRow>,
    done: bool,
}

/// Runs the episodes of `case` with `policy` and returns each episode's rows (cut at a
/// termination or the time limit). `progress` counts the control steps of the batch (its
/// length: `task.max_steps()`).
pub fn learned(
    scene: &SceneModel,
    task: &PhaseTask,
    policy: &Policy,
    case: Case,
    run: Episodes,
    progress: &ProgressBar,
) -> Result<Vec<Vec<EpisodeRow>>> {
    let options = task.env_options(run.randomize, Some(run.payload));
    let mut batch = BatchEnv::new(scene.clone(), run.count, run.seed, options, run.threads)?;
    let mut slots = Vec::with_capacity(run.count);
    for (i, (env, state)) in batch.envs().iter().zip(batch.states()).enumerate() {
        let mut rng = PhaseTask::rng(moonhaul_sim::batch::env_seed(run.seed, i));
        let mut episode = task.begin(scene, env, state, &mut rng)?;
        if let Some(h) = case.goal_height_m {
            episode = episode.with_goal_height(h);
        }
        let rows = vec![row(task, &episode, state)];
        slots.push(Slot {
            episode,
            rng,
            scratch: policy.scratch(),
            rows,
            done: false,
        });
    }
    let steps = task.max_steps();
    for step in 1..=steps {
        batch.for_each_with(&mut slots, |scene, env, state, slot| {
            if slot.done {
                return Ok(());
            }
            step_with_policy(task, policy, scene, env, state, slot)
        })?;
        // The worlds step together, so the time left is in steps, not in episodes done.
        progress.set_position(step);
        if slots.iter().all(|s| s.done) {
            break;
        }
    }
    progress.set_position(steps);
    Ok(slots.into_iter().map(|s| s.rows).collect())
}

fn step_with_policy(
    task: &PhaseTask,
    policy: &Policy,
    scene: &SceneModel,
    env: &mut Env,
    state: &mut EnvState,
    slot: &mut Slot,
) -> Result<()> {
    let mut deltas = [[0.0; UNIT_ACTION_DIM]; UNITS];
    for (i, delta) in deltas.iter_mut().enumerate() {
        let mut obs = [0.0; ACTOR_OBS_DIM];
        slot.episode.observe(task, scene, i, &mut obs)?;
        policy
            .act(&obs, &mut slot.scratch, delta)
            .context("running the policy")?;
    }
    let commands = slot.episode.commands(task, &deltas)?;
    env.step(scene, &commands);
    env.state_into(scene, state);
    let outcome = slot.episode.advance(task, scene, env, state, &mut slot.rng);
    if state.is_finite() {
        slot.rows.push(row(task, &slot.episode, state));
    }
    slot.done = outcome.terminated.is_some() || outcome.truncated;
    Ok(())
}

/// The scripted controller's rows of one mission, split into its lift, transport and place
/// segments (place runs to the end of the mission, after the release), each timed from the
/// segment's start.
pub struct ScriptedSegments {
    pub lift: Vec<EpisodeRow>,
    pub transport: Vec<EpisodeRow>,
    pub place: Vec<EpisodeRow>,
}

/// Runs seeded scripted missions lifting to `lift_m`; `progress` advances by one per finished
/// mission (from the batch's threads).
pub fn scripted(
    scene: &SceneModel,
    plan: &MissionPlan,
    lift_m: f64,
    run: Episodes,
    progress: &ProgressBar,
) -> Result<Vec<ScriptedSegments>> {
    let plan = MissionPlan {
        lift_height_m: lift_m,
        ..*plan
    };
    let options = EnvOptions {
        randomize: run.randomize,
        payload: Some(run.payload),
        start_lift_m: 0.0,
    };
    let mut batch = BatchEnv::new(scene.clone(), run.count, run.seed, options, run.threads)?;
    let mut slots: Vec<Option<ScriptedSegments>> = (0..run.count).map(|_| None).collect();
    batch.for_each_with(&mut slots, |scene, env, state, slot| {
        let t0 = state.time_s;
        let mut segments = ScriptedSegments {
            lift: Vec::new(),
            transport: Vec::new(),
            place: Vec::new(),
        };
        let mut starts = [None::<f64>; 3];
        run_mission(scene, env, plan, |phase, s| {
            let t = s.time_s - t0;
            let (segment, start) = match phase {
                Phase::Lift => (&mut segments.lift, &mut starts[0]),
                Phase::Transport => (&mut segments.transport, &mut starts[1]),
                Phase::Place => (&mut segments.place, &mut starts[2]),
                Phase::Idle if t >= plan.release_s() => (&mut segments.place, &mut starts[2]),
                Phase::Idle => return,
            };
            let start = *start.get_or_insert(t);
            let (_, _, speed) = plan.at(t);
            let placing = phase == Phase::Place || phase == Phase::Idle;
            segment.push(state_row(
                t - start,
                if placing { Phase::Place } else { phase },
                if placing { 0.0 } else { lift_m },
                [speed, 0.0],
                s,
            ));
        })?;
        *slot = Some(segments);
        progress.inc(1);
        Ok::<_, moonhaul_sim::SimError>(())
    })?;
    Ok(slots.into_iter().flatten().collect())
}
