//! Evaluation episodes in the simulator: a phase policy run exactly as a unit runs it onboard
//! (core's MLP on [`moonhaul_core::observation::unit_observation`] of the sensed readings, its
//! recorded action map, no exploration noise), and the scripted IK controller as a model-based
//! baseline. Each episode becomes rows of [`EpisodeRow`].

use anyhow::{Context, Result};
use moonhaul_core::observation::{field_range, ACTOR_OBS_DIM};
use moonhaul_core::policy::{Policy, PolicyScratch};
use moonhaul_core::state::{Phase, UnitCommand, UNIT_ACTION_DIM};
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

pub use moonhaul_deploy::daemon::load_policy;

/// The row of one control tick.
fn row(task: &PhaseTask, episode: &Episode, state: &EnvState) -> EpisodeRow {
    let p = &state.payload;
    let v_cmd = episode.command_velocity_mps(task);
    EpisodeRow {
        t_s: episode.time_s(task),
        phase: task.phase,
        goal_height_m: episode.goal_height_m(),
        payload_height_m: p.height_m,
        payload_tilt_deg: p.tilt_rad.to_degrees(),
        payload_vx_mps: p.linvel_mps.x,
        payload_vy_mps: p.linvel_mps.y,
        payload_vz_mps: p.linvel_mps.z,
        command_vx_mps: v_cmd.x,
        command_vy_mps: v_cmd.y,
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
/// termination or the time limit).
pub fn learned(
    scene: &SceneModel,
    task: &PhaseTask,
    policy: &Policy,
    case: Case,
    run: Episodes,
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
    for _ in 0..steps {
        batch.for_each_with(&mut slots, |scene, env, state, slot| {
            if slot.done {
                return Ok(());
            }
            step_with_policy(task, policy, scene, env, state, slot)
        })?;
        if slots.iter().all(|s| s.done) {
            break;
        }
    }
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
    let mut commands = [UnitCommand::default(); UNITS];
    for (i, command) in commands.iter_mut().enumerate() {
        let mut obs = [0.0; ACTOR_OBS_DIM];
        slot.episode.observe(task, scene, i, &mut obs)?;
        let mut u = [0.0; UNIT_ACTION_DIM];
        policy
            .act(&obs, &mut slot.scratch, &mut u)
            .context("running the policy")?;
        *command = UnitCommand::from_action(&u);
    }
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

/// Runs seeded scripted missions lifting to `lift_m`.
pub fn scripted(
    scene: &SceneModel,
    plan: &MissionPlan,
    lift_m: f64,
    run: Episodes,
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
            let p = &s.payload;
            segment.push(EpisodeRow {
                t_s: t - start,
                phase: if phase == Phase::Idle {
                    Phase::Place
                } else {
                    phase
                },
                goal_height_m: if phase == Phase::Place || phase == Phase::Idle {
                    0.0
                } else {
                    lift_m
                },
                payload_height_m: p.height_m,
                payload_tilt_deg: p.tilt_rad.to_degrees(),
                payload_vx_mps: p.linvel_mps.x,
                payload_vy_mps: p.linvel_mps.y,
                payload_vz_mps: p.linvel_mps.z,
                command_vx_mps: speed,
                command_vy_mps: 0.0,
                ground_contact: p.ground_contact,
                grasp_force_1_n: s.units[0].grasp.force_n,
                grasp_force_2_n: s.units[1].grasp.force_n,
            });
        })?;
        *slot = Some(segments);
        Ok::<_, moonhaul_sim::SimError>(())
    })?;
    Ok(slots.into_iter().flatten().collect())
}

/// The deployed stack's settings: what each unit's daemon runs besides the policies.
pub struct Stack<'a> {
    pub gate: &'a moonhaul_coord::GateConfig,
    pub sync: &'a moonhaul_coord::SyncConfig,
    /// The phase tasks (lift, transport, place) and their policies.
    pub phases: &'a [(Phase, PhaseTask, Policy)],
}

/// One deployed mission's rows, split by phase, and what the clamp did.
pub struct DeployedMission {
    pub segments: ScriptedSegments,
    /// Ticks the clamp ran, and how many issued less than the policies' full step.
    pub ticks: u64,
    pub clamped_ticks: u64,
    pub holds: u64,
    /// Mean t_max over the mission.
    pub mean_t_max: f64,
    /// Whether the gate reached Idle (released) before the mission's time ran out.
    pub completed: bool,
}

/// Seeded whole missions flown as the units fly them, in process: lift to 0.3 m, transport,
/// place, each phase's policy switched by the phase gate (`configs/gate.toml`) and every
/// command passed through the synchronization clamp (`configs/sync.toml`). The gate measures
/// payload height as the units' mean FK estimate of the cargo's lift and the goal distance by
/// odometry; the grasp forces are the simulator's wrench (the stand-in for a unit's
/// current-based estimate). One world is one team: the distributed agreement over the network
/// is the daemon's (it decides the same transitions when no message is lost).
pub fn deployed(scene: &SceneModel, stack: &Stack, run: Episodes) -> Result<Vec<DeployedMission>> {
    use moonhaul_coord::clamp::hold_command;
    use moonhaul_coord::{Clamp, ClampInput, Measurements, PhaseGate, UnitModel};

    let find = |phase: Phase| {
        stack
            .phases
            .iter()
            .find(|(p, ..)| *p == phase)
            .with_context(|| format!("the deployed stack needs a {phase} policy"))
    };
    for phase in [Phase::Lift, Phase::Transport, Phase::Place] {
        find(phase)?;
    }
    let (_, lift_task, _) = find(Phase::Lift)?;
    let period_s = 1.0 / scene.config.control_hz;
    let budget_s: f64 = [Phase::Lift, Phase::Transport, Phase::Place]
        .iter()
        .map(|&p| lift_task.config.duration_s(p))
        .sum();
    let model = UnitModel::new(scene.spec.clone());
    let field = |name: &str| {
        field_range(name).with_context(|| format!("the observation layout has no {name}"))
    };
    // z of the cargo's displacement, and the base goal's x (y follows).
    let lift_index = field("cargo.ee_displacement_m")?.start + 2;
    let goal_base = field("goal.base")?.start;
    let options = lift_task.env_options(run.randomize, Some(run.payload));
    let mut batch = BatchEnv::new(scene.clone(), run.count, run.seed, options, run.threads)?;
    let mut work: Vec<(u64, Option<DeployedMission>)> = (0..run.count)
        .map(|i| (moonhaul_sim::batch::env_seed(run.seed, i), None))
        .collect();
    batch.for_each_with(
        &mut work,
        |scene, env, state, (env_seed, slot)| -> Result<()> {
            let mut rng = PhaseTask::rng(*env_seed);
            let mut phase = Phase::Lift;
            let mut episode = lift_task
                .begin(scene, env, state, &mut rng)?
                .with_goal_height(lift_task.config.transport.start_height_m);
            let mut gate = PhaseGate::new(stack.gate);
            let mut clamp = Clamp::new(model.clone(), stack.sync, period_s, UNITS)?;
            let mut previous = [0, 1].map(|i| hold_command(episode.sensed(i)));
            let mut scratch = find(Phase::Lift)?.2.scratch();
            let mut segments = ScriptedSegments {
                lift: Vec::new(),
                transport: Vec::new(),
                place: Vec::new(),
            };
            let (mut ticks, mut clamped, mut holds, mut t_sum) = (0u64, 0u64, 0u64, 0.0);
            let mut completed = false;
            let mut mission_s = 0.0;
            let mut after_release_s = 0.0;
            while mission_s < budget_s {
                let (_, task, policy) = find(phase)?;
                let mut obs = [[0.0; ACTOR_OBS_DIM]; UNITS];
                let mut targets = [UnitCommand::default(); UNITS];
                for i in 0..UNITS {
                    episode.observe(task, scene, i, &mut obs[i])?;
                    let mut u = [0.0; UNIT_ACTION_DIM];
                    policy
                        .act(&obs[i], &mut scratch, &mut u)
                        .context("running the policy")?;
                    targets[i] = UnitCommand::from_action(&u);
                }
                let sensed = [*episode.sensed(0), *episode.sensed(1)];
                let mut issued = [UnitCommand::default(); UNITS];
                let hold = completed.then_some(moonhaul_coord::HoldReason::Idle);
                let report = clamp.step(
                    &ClampInput {
                        sensed: &sensed,
                        previous: &previous,
                        target: &targets,
                    },
                    hold,
                    &mut issued,
                )?;
                ticks += 1;
                t_sum += report.t_max;
                clamped += u64::from(report.t_max < 1.0);
                holds += u64::from(report.hold.is_some());
                previous = issued;
                env.step(scene, &issued);
                env.state_into(scene, state);
                let outcome = episode.advance(task, scene, env, state, &mut rng);
                mission_s += period_s;
                if !state.is_finite() {
                    break;
                }
                let segment = match phase {
                    Phase::Lift => &mut segments.lift,
                    Phase::Transport => &mut segments.transport,
                    Phase::Place | Phase::Idle => &mut segments.place,
                };
                let mut r = row(task, &episode, state);
                if let Some(first) = segment.first() {
                    r.t_s = first.t_s + (segment.len() as f64) * period_s;
                }
                segment.push(r);
                if outcome.terminated.is_some() {
                    break;
                }
                if completed {
                    // A second of rest after the release, for the steady-state figures.
                    after_release_s += period_s;
                    if after_release_s >= super::metrics::STEADY_WINDOW_S {
                        break;
                    }
                    continue;
                }
                // The gate's onboard estimates, read from the units' observations after the step:
                // the mean FK lift of the cargo and unit 0's odometric distance to its goal.
                let mut lift_estimate = 0.0;
                for (i, o) in obs.iter_mut().enumerate() {
                    episode.observe(task, scene, i, o)?;
                    lift_estimate += o[lift_index] / UNITS as f64;
                }
                let goal_distance_m = obs[0][goal_base].hypot(obs[0][goal_base + 1]);
                let forces = state.units.map(|u| u.grasp.force_n);
                let measured = Measurements {
                    payload_height_m: lift_estimate,
                    goal_distance_m,
                    grasp_force_n: &forces,
                };
                let next = gate.step(phase, &measured, false, false);
                if next == Phase::Idle {
                    completed = true;
                } else if next != phase {
                    phase = next;
                    episode = find(next)?.1.continue_from(&episode, state);
                    scratch = find(next)?.2.scratch();
                }
            }
            *slot = Some(DeployedMission {
                segments,
                ticks,
                clamped_ticks: clamped,
                holds,
                mean_t_max: if ticks > 0 { t_sum / ticks as f64 } else { 0.0 },
                completed,
            });
            Ok(())
        },
    )?;
    Ok(work.into_iter().filter_map(|(_, m)| m).collect())
}
