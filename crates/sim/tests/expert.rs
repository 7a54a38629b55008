//! The scripted expert inside the training episodes: each unit's [`PhaseScript`] driven by
//! `Episode::expert_action` from what the unit knows onboard, its action through the same
//! increment map, pipeline and clamp a policy's goes through (the labels a policy is cloned
//! from must be actions that fly). On randomized worlds and every shipped payload, it lifts
//! to the paper's three heights, carries the payload to the transport goal and places it.

use moonhaul_core::scripted::MissionPlan;
use moonhaul_core::state::{Phase, UNIT_ACTION_DIM};
use moonhaul_sim::scene::UNITS;
use moonhaul_sim::task::{PhaseTask, StepOutcome, TaskConfig};
use moonhaul_sim::{Env, EnvState, PayloadKind, SceneModel, SimConfig};

/// What one expert episode ended with.
#[derive(Debug)]
struct Flown {
    outcome: StepOutcome,
    steps: u64,
    /// Payload height and planar position at the end, m.
    height_m: f64,
    position_m: [f64; 2],
    /// The planar goal of the payload at the end (the reward's p_B), m.
    reference_m: [f64; 2],
    released: bool,
    /// Largest |raw action| component the expert asked for.
    max_raw: f64,
}

fn fly(
    scene: &SceneModel,
    task: &PhaseTask,
    payload: PayloadKind,
    seed: u64,
    goal_height_m: Option<f64>,
) -> Flown {
    let plan = MissionPlan::shipped().unwrap();
    let mut env = Env::new(scene, seed, task.env_options(true, Some(payload))).unwrap();
    let mut state: EnvState = env.state(scene);
    let mut rng = PhaseTask::rng(seed);
    let mut episode = task.begin(scene, &env, &state, &mut rng).unwrap();
    if let Some(h) = goal_height_m {
        episode = episode.with_goal_height(h);
    }
    let mut scripts = [task.expert(plan), task.expert(plan)];
    let mut max_raw = 0.0f64;
    loop {
        let mut deltas = [[0.0; UNIT_ACTION_DIM]; UNITS];
        for (i, script) in scripts.iter_mut().enumerate() {
            let raw = episode.expert_action(task, scene, i, script).unwrap();
            assert!(raw.iter().all(|a| a.abs() <= 1.0), "{raw:?}");
            max_raw = raw.iter().fold(max_raw, |m, a| m.max(a.abs()));
            deltas[i] = task.increment(&raw);
        }
        let commands = episode.commands(task, &deltas).unwrap();
        env.step(scene, &commands);
        env.state_into(scene, &mut state);
        let outcome = episode.advance(task, scene, &mut env, &mut state, &mut rng);
        if outcome.terminated.is_some() || outcome.truncated {
            let reference = episode.reference_position_m(task);
            let p = state.payload.pose.translation.vector;
            return Flown {
                outcome,
                steps: episode.steps(),
                height_m: state.payload.height_m,
                position_m: [p.x, p.y],
                reference_m: [reference.x, reference.y],
                released: episode.released(),
                max_raw,
            };
        }
    }
}

fn task(scene: &SceneModel, phase: Phase) -> PhaseTask {
    PhaseTask::new(
        phase,
        TaskConfig::shipped().unwrap(),
        moonhaul_coord::SyncConfig::shipped().unwrap(),
        scene,
    )
    .unwrap()
}

/// Seeds per payload and case: enough to see a systematic failure, few enough for CI.
const SEEDS: [u64; 2] = [11, 12];

#[test]
fn the_expert_lifts_to_the_papers_heights_through_the_pipeline() {
    let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
    let task = task(&scene, Phase::Lift);
    let mut failures = Vec::new();
    for payload in PayloadKind::ALL {
        for h in [0.3, 0.5, 0.75] {
            for seed in SEEDS {
                let f = fly(&scene, &task, payload, seed, Some(h));
                println!(
                    "lift {payload:?} h* {h} seed {seed}: {:?} after {} steps, height {:.1} mm",
                    f.outcome,
                    f.steps,
                    f.height_m * 1e3
                );
                // Table II's lift tolerance h_tol = 3 cm.
                if f.outcome.terminated.is_some() || (f.height_m - h).abs() > 0.03 {
                    failures.push(format!("{payload:?} h* {h} seed {seed}: {f:?}"));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn the_expert_carries_and_places_through_the_pipeline() {
    let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
    let config = TaskConfig::shipped().unwrap();
    let mut failures = Vec::new();
    for phase in [Phase::Transport, Phase::Place] {
        let task = task(&scene, phase);
        for payload in PayloadKind::ALL {
            for seed in SEEDS {
                let f = fly(&scene, &task, payload, seed, None);
                let off = ((f.position_m[0] - f.reference_m[0]).powi(2)
                    + (f.position_m[1] - f.reference_m[1]).powi(2))
                .sqrt();
                println!(
                    "{phase:?} {payload:?} seed {seed}: {:?} after {} steps, {off:.3} m from \
                     the goal, height {:.1} mm, released {}, largest |a| {:.2}",
                    f.outcome,
                    f.steps,
                    f.height_m * 1e3,
                    f.released,
                    f.max_raw
                );
                let ok = f.outcome.terminated.is_none()
                    && match phase {
                        // Carried to the goal at the transport height, within Table II's
                        // planar position (0.2 m) and height (3 cm) tolerances. The expert
                        // steers by odometry, which the gate trusts to 5 cm; the true payload
                        // ends 7-10 cm off on seed 12's terrain (0.097-0.100 m for the sledge,
                        // as the arm's increment changed), so a bound of 0.1 m judged odometry
                        // drift by the millimetre.
                        Phase::Transport => {
                            off <= 0.2
                                && (f.height_m - config.transport.start_height_m).abs() <= 0.03
                        }
                        // Set down and let go.
                        _ => f.released && f.height_m <= 0.02,
                    };
                if !ok {
                    failures.push(format!("{phase:?} {payload:?} seed {seed}: {f:?}"));
                }
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
