//! `moonhaul mission world`: the simulated world of a mission as its own process. It steps the
//! physics, serves each unit's sim-backed drives over zenoh ([`moonhaul_deploy::sim_link`]) and
//! logs ground truth as an external tracker would (the paper's OptiTrack); the units never see
//! it.
//!
//! **Lockstep** (default): step k is taken once every live unit answered reading k; the reading
//! is re-sent every [`RESEND`] until it is, so a unit that starts late or misses a frame
//! catches up. A unit that answered once and then stays silent for [`UNIT_TIMEOUT`] is taken
//! as gone: its drives quick-stop (wheels to zero, arm holding its position), as drives do when
//! their master's SYNC and heartbeat stop. Until a unit leaves Idle (the operator's start),
//! lockstep steps no faster than the wall clock either: the start comes in wall time, and an
//! idle lockstep world running tens of times faster would spend `--max-seconds` before it.
//! **Real time**: steps on the wall clock with each unit's newest command.
//!
//! The world ends itself: [`SETTLE_S`] after every live unit reported Idle again after the
//! mission began (the mission ended, completed or stopped), when no unit is left, or at
//! `--max-seconds` of simulated time. SIGINT/SIGTERM end it too; every exit finishes the log.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::KeyFile;
use moonhaul_core::overwrite::RunInputs;
use moonhaul_core::state::{Phase, PlanarPose, UnitCommand};
use moonhaul_core::task_config::TaskConfig;
use moonhaul_deploy::cli_support::Signals;
use moonhaul_deploy::mission_log::{LogInputs, WorldLog};
use moonhaul_deploy::network::{self, Access, Keys, NetworkSettings, Role};
use moonhaul_deploy::record::WorldFrame;
use moonhaul_deploy::sim_link::{self, SimCommand, SimSensed};
use moonhaul_sim::scene::{Env, EnvState, SceneModel, UNITS};
use moonhaul_sim::task::encoder_reading;
use moonhaul_sim::{EnvOptions, SimConfig};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use tracing::{info, warn};

use crate::payload_arg::{self, PayloadArg};

/// How often an unanswered reading is sent again.
const RESEND: Duration = Duration::from_millis(50);
/// Lockstep: how long a unit that answered before may stay silent before its drives stop.
const UNIT_TIMEOUT: Duration = Duration::from_secs(2);
/// Lockstep: how long the world waits for a unit's very first answer (process start-up).
const STARTUP_TIMEOUT: Duration = Duration::from_secs(60);
/// Simulated seconds the world runs on after the mission ended (the settled height).
const SETTLE_S: f64 = 1.5;

#[derive(Debug, clap::Args)]
pub struct WorldArgs {
    /// box, bricks, sledge, gen<i> (generated), or a payload URDF.
    #[arg(long, value_name = "PAYLOAD")]
    pub payload: PayloadArg,
    /// Seed of the world's draws (terrain, friction, initial joints, command and encoder noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The nominal world instead of the paper's domain randomization.
    #[arg(long)]
    pub no_randomization: bool,
    /// The team whose units this world serves.
    #[arg(long, default_value = "moonhaul")]
    pub team: String,
    /// The team's key file: the world's network credentials derive from it.
    #[arg(long, value_name = "FILE")]
    pub keys: PathBuf,
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(long, value_name = "ENDPOINT", required = true)]
    pub listen: Vec<String>,
    /// Step on the wall clock instead of in lockstep with the units.
    #[arg(long)]
    pub realtime: bool,
    /// The ground-truth log (MCAP).
    #[arg(long, value_name = "FILE")]
    pub log: PathBuf,
    /// Replace an existing `--log` and `--start-file` (never an input of the run).
    #[arg(long)]
    pub force: bool,
    /// Where to write the units' start poses and rest arm joints (JSON) once the world is up.
    #[arg(long, value_name = "FILE")]
    pub start_file: PathBuf,
    /// Longest mission, simulated seconds (at most an hour).
    #[arg(long, default_value_t = 90.0, value_name = "S")]
    pub max_seconds: f64,
    /// The simulator config.
    #[arg(long, default_value = "configs/sim.toml", value_name = "FILE")]
    pub sim: PathBuf,
    /// The task config (encoder noise).
    #[arg(long, default_value = "configs/tasks.toml", value_name = "FILE")]
    pub tasks: PathBuf,
}

/// What a launcher needs to start the units: where each starts (their odometry origin, which
/// all units know) and the arm pose of the grasp.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartInfo {
    pub start_pose: Vec<PlanarPose>,
    pub payload: String,
    pub payload_mass_kg: f64,
    pub control_period_s: f64,
}

/// One unit as the world sees it.
#[derive(Debug, Clone, Copy, Default)]
struct UnitLink {
    /// Newest command, and for which tick.
    command: Option<SimCommand>,
    /// When it last answered (wall clock).
    last_heard: Option<Instant>,
    gone: bool,
}

/// Longest simulated mission, s: the paper's missions take about a minute; a bound of an hour
/// keeps a typo (`--max-seconds 1e300`) from running a world, and its trial, for ever.
pub const MAX_MISSION_S: f64 = 3600.0;

/// Checks a `--max-seconds` (the world's and `mission sim`'s).
pub fn check_max_seconds(max_seconds: f64) -> Result<()> {
    if !(max_seconds.is_finite() && max_seconds > 0.0 && max_seconds <= MAX_MISSION_S) {
        bail!(
            "--max-seconds {max_seconds}: must be a positive number of simulated seconds, at \
             most {MAX_MISSION_S}"
        );
    }
    Ok(())
}

pub async fn run(args: WorldArgs) -> Result<()> {
    // First: a signal from now on ends the world with a finished log.
    let mut signals = Signals::install()?;
    check_max_seconds(args.max_seconds)?;
    let mut inputs = RunInputs::new();
    inputs
        .add("simulator config", &args.sim)
        .add("task config", &args.tasks);
    if let PayloadArg::File(path) = &args.payload {
        inputs.add("payload", path);
    }
    inputs.check_output("--log", &args.log, args.force)?;
    inputs.check_output("--start-file", &args.start_file, args.force)?;
    let sim = SimConfig::load(&args.sim).context("cannot load the simulator config")?;
    let mut scene = SceneModel::new(sim).context("cannot build the simulated scene")?;
    let kind = payload_arg::resolve(&mut scene, &args.payload)?;
    let tasks = TaskConfig::load(&args.tasks)?;
    let options = EnvOptions {
        randomize: !args.no_randomization,
        payload: Some(kind),
        start_lift_m: 0.0,
    };
    let mut env = Env::new(&scene, args.seed, options)?;
    let mut state = env.state(&scene);
    let period_s = 1.0 / scene.config.control_hz;
    let payload_model = scene.payload(kind)?;
    let size = payload_model.half_extents_m * 2.0;
    let mut log = WorldLog::create(
        &args.log,
        [size.x, size.y, size.z],
        UNITS,
        &LogInputs::read(&scene.config.unit_urdf(), &log_inputs(&args))?,
    )?;
    let keys = Keys::new(&args.team);
    let key_file = KeyFile::load(&args.keys)?;
    if key_file.team() != args.team {
        bail!(
            "key file {} is for team {:?}, not the world's team {:?}",
            args.keys.display(),
            key_file.team(),
            args.team
        );
    }
    let access = Access::new(&key_file, Role::World)
        .with_context(|| format!("key file {}", args.keys.display()))?;
    let session = network::open(
        &NetworkSettings {
            connect: Vec::new(),
            listen: args.listen.clone(),
        },
        &access,
    )
    .await?;
    let mut publishers = Vec::with_capacity(UNITS);
    for i in 0..UNITS {
        publishers.push(network::control_publisher(&session, keys.sim_sensed(i)).await?);
    }
    let commands = session
        .declare_subscriber(keys.all_sim_commands())
        .await
        .map_err(|e| anyhow::anyhow!("zenoh subscriber: {e}"))?;
    let start = StartInfo {
        start_pose: state.units.iter().map(|u| u.state.base_pose).collect(),
        payload: scene.payload_name(kind),
        payload_mass_kg: env.payload_mass_kg(&scene),
        control_period_s: period_s,
    };
    write_json(&args.start_file, &start)?;
    info!(payload = %start.payload, seed = args.seed, "world up");

    let mut noise = ChaCha8Rng::seed_from_u64(moonhaul_core::seed::stream_seed(args.seed, 0x5e45));
    let mut links = [UnitLink::default(); UNITS];
    let mut tick: u64 = 0;
    let mut began = false;
    let mut reached_place = false;
    let mut ended_at_s: Option<f64> = None;
    let mut dropped = 0u64;
    // Latched once a unit opens its gripper (the world never grasps again). Not the grasp's
    // attachment: a grasp the simulator broke by overload leaves the gripper closed on nothing,
    // and the log must not read it as a release.
    let mut gripper_open = [false; UNITS];
    let wall_start = Instant::now();
    let outcome: String = 'mission: loop {
        let now_s = tick as f64 * period_s;
        let stamp_us = (now_s * 1e6).round() as u64;
        let readings: Vec<Vec<u8>> = (0..UNITS)
            .map(|i| sim_link::encode(&sense(&state, i, tick, stamp_us, &tasks, &mut noise)))
            .collect();
        // Publish reading k and collect the answers.
        let mut last_send: Option<Instant> = None;
        loop {
            if last_send.is_none_or(|t| t.elapsed() >= RESEND) {
                for (publisher, bytes) in publishers.iter().zip(&readings) {
                    if let Err(e) = network::put(publisher, bytes).await {
                        warn!(error = %e, "publishing a reading");
                    }
                }
                last_send = Some(Instant::now());
            }
            let answered = |l: &UnitLink| l.gone || l.command.is_some_and(|c| c.tick >= tick);
            // Until the team starts, the clock runs no faster than the wall even in lockstep:
            // the operator starts a mission in wall time, and a lockstep world runs tens of
            // times faster than that, so its idle prelude would eat `--max-seconds` before the
            // start arrives.
            let paced = args.realtime || !began;
            let due = wall_start + Duration::from_secs_f64((tick + 1) as f64 * period_s);
            if !args.realtime && links.iter().all(answered) && (!paced || Instant::now() >= due) {
                break;
            }
            if args.realtime && Instant::now() >= due {
                break;
            }
            // Lockstep time-outs: a unit that went silent is gone.
            for (i, link) in links.iter_mut().enumerate() {
                if link.gone || answered(link) {
                    continue;
                }
                let silent = match link.last_heard {
                    Some(t) => t.elapsed() > UNIT_TIMEOUT,
                    None => wall_start.elapsed() > STARTUP_TIMEOUT,
                };
                if silent && !args.realtime {
                    warn!(unit = i, tick, "unit silent: its drives quick-stop");
                    link.gone = true;
                }
            }
            if links.iter().all(|l| l.gone) {
                break 'mission "every unit is gone".into();
            }
            let mut wait_for =
                RESEND.saturating_sub(last_send.map_or(Duration::ZERO, |t| t.elapsed()));
            if paced {
                wait_for = wait_for.min(due.saturating_duration_since(Instant::now()));
            }
            let wait = tokio::time::sleep(wait_for);
            tokio::select! {
                biased;
                why = signals.recv() => break 'mission why.into(),
                _ = wait => {}
                sample = commands.recv_async() => {
                    let Ok(sample) = sample else { break 'mission "the network closed".into() };
                    match SimCommand::decode(&sample.payload().to_bytes(), UNITS) {
                        Ok(c) => {
                            let link = &mut links[c.unit];
                            if link.command.is_none_or(|old| c.tick >= old.tick) && c.tick <= tick {
                                link.command = Some(c);
                                link.last_heard = Some(Instant::now());
                                if link.gone {
                                    info!(unit = c.unit, "unit answers again");
                                    link.gone = false;
                                }
                            }
                        }
                        Err(e) => {
                            dropped += 1;
                            warn!(error = %e, dropped, "dropped a command frame");
                        }
                    }
                }
            }
        }
        // Step with every unit's command; a gone unit's drives hold.
        let mut step = [UnitCommand::default(); UNITS];
        for (i, link) in links.iter().enumerate() {
            // Quick-stopped drives: wheels stopped, arm at its last command (as drives hold
            // their last setpoint when the master falls silent), or where it is if none came.
            step[i] = match link.command {
                Some(c) if !link.gone => c.command,
                Some(c) => moonhaul_coord::clamp::hold_command(&c.command),
                None => moonhaul_coord::clamp::anchor_command(&state.units[i].state),
            };
            if link.command.is_some_and(|c| c.grasp_open) && !gripper_open[i] {
                gripper_open[i] = true;
                env.release_grasp(i);
            }
        }
        env.step(&scene, &step);
        env.state_into(&scene, &mut state);
        tick += 1;
        let phases: Vec<Option<Phase>> = links
            .iter()
            .map(|l| l.command.filter(|_| !l.gone).map(|c| c.phase))
            .collect();
        log.write(&frame(tick, &state, &phases, &gripper_open))?;
        if !state.is_finite() {
            break 'mission "the simulation diverged".into();
        }
        began |= phases.iter().flatten().any(|p| *p != Phase::Idle);
        reached_place |= phases.iter().flatten().any(|p| *p == Phase::Place);
        let live_idle = phases.iter().flatten().all(|p| *p == Phase::Idle);
        let t_s = tick as f64 * period_s;
        if began && live_idle {
            let since = *ended_at_s.get_or_insert(t_s);
            if t_s - since >= SETTLE_S {
                break if reached_place {
                    "the mission ended after placing".into()
                } else {
                    "the mission stopped before placing".into()
                };
            }
        } else {
            ended_at_s = None;
        }
        if t_s >= args.max_seconds {
            break format!("the time limit ({} s)", args.max_seconds);
        }
    };
    info!(outcome = %outcome, ticks = tick, "world ends");
    log.finish()?;
    let _ = session.close().await;
    Ok(())
}

/// What unit `i`'s encoders and wrist-force estimate report: the truth through the training's
/// encoder model (`encoder_reading`, the `[sensing]` of configs/tasks.toml).
pub fn sense(
    state: &EnvState,
    i: usize,
    tick: u64,
    stamp_us: u64,
    tasks: &TaskConfig,
    rng: &mut ChaCha8Rng,
) -> SimSensed {
    let truth = &state.units[i];
    let sensed = encoder_reading(&truth.state, &tasks.sensing, rng);
    SimSensed {
        unit: i,
        tick,
        stamp_us,
        wheel_position_rad: sensed.wheels.position_rad,
        wheel_velocity_radps: sensed.wheels.velocity_radps,
        arm_position_rad: sensed.arm.position_rad,
        arm_velocity_radps: sensed.arm.velocity_radps,
        grasp_force_n: truth.grasp.force_n,
    }
}

fn frame(
    tick: u64,
    state: &EnvState,
    phases: &[Option<Phase>],
    gripper_open: &[bool; UNITS],
) -> WorldFrame {
    let p = &state.payload;
    let pose = |iso: &nalgebra::Isometry3<f64>| {
        let t = iso.translation.vector;
        let q = iso.rotation.coords;
        ([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
    };
    let (payload_position_m, payload_orientation_xyzw) = pose(&p.pose);
    let bases: Vec<_> = state
        .units
        .iter()
        .map(|u| {
            let b = &u.state.base_pose;
            let half = b.yaw_rad / 2.0;
            ([b.x_m, b.y_m, 0.0], [0.0, 0.0, half.sin(), half.cos()])
        })
        .collect();
    WorldFrame {
        tick,
        stamp_us: (state.time_s * 1e6).round() as u64,
        payload_position_m,
        payload_orientation_xyzw,
        payload_height_m: p.height_m,
        payload_tilt_deg: p.tilt_rad.to_degrees(),
        payload_ground_contact: p.ground_contact,
        base_position_m: bases.iter().map(|b| b.0).collect(),
        base_orientation_xyzw: bases.iter().map(|b| b.1).collect(),
        wheel_position_rad: state
            .units
            .iter()
            .map(|u| u.state.wheels.position_rad)
            .collect(),
        arm_position_rad: state
            .units
            .iter()
            .map(|u| u.state.arm.position_rad)
            .collect(),
        unit_phase: phases.to_vec(),
        grasp_closed: gripper_open.iter().map(|open| !open).collect(),
    }
}

/// The configs the world reads, which its log attaches beside the unit URDF: the simulator's,
/// the tasks', and the payload's URDF when it was given as a file.
fn log_inputs(args: &WorldArgs) -> Vec<PathBuf> {
    let mut files = vec![args.sim.clone(), args.tasks.clone()];
    if let PayloadArg::File(path) = &args.payload {
        files.push(path.clone());
    }
    files
}

/// Writes `value` as JSON, whole or not at all.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec_pretty(value).context("encoding JSON")?;
    moonhaul_core::atomic_file::write(path, &bytes)
        .with_context(|| format!("cannot write {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grasp the simulator broke (detached, the gripper never opened) is logged closed, so
    /// `moonhaul log` never reads a dropped payload as placed.
    #[test]
    fn a_broken_grasp_is_logged_closed_and_only_an_opened_gripper_as_released() {
        let state = EnvState::default();
        assert!(state.units.iter().all(|u| !u.grasp.attached));
        let f = frame(0, &state, &[None; UNITS], &[false, true]);
        assert_eq!(f.grasp_closed, [true, false]);
    }
}
