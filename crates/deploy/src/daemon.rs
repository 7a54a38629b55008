//! `moonhaul-unit`, the per-robot daemon: one [`Onboard`] tick per control period over a
//! unit-level hardware backend, peers and operator over zenoh, a mission log in MCAP.
//!
//! The loop runs on tokio. With `--hal mock`, `can` or `can-emulated` it ticks on a fixed-rate interval
//! (a late tick is counted as a deadline miss and the schedule skips ahead, never bursts); the
//! clock is the system's (team-synchronized, e.g. PTP). With `--hal sim` it ticks on each of the
//! simulated world's readings and the clock is the world's simulated time; in lockstep it also
//! waits (bounded) for its peers' messages of the previous tick and holds back any of the
//! current one, so the units' exchange does not depend on process scheduling. (The tick the
//! operator's start arrives on still does: trials of one seed differ from the start on.) SIGINT or SIGTERM ends in a hold: the hold command is written, the drives are
//! deactivated and the log is finished before the process exits.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::auth::KeyFile;
use moonhaul_coord::clamp::anchor_command;
use moonhaul_coord::message::{
    Body, FaultKind, MessageBounds, RejectCounts, Sender, ARENA_HALF_WIDTH_M,
};
use moonhaul_coord::{GateConfig, SyncConfig, Validator};
use moonhaul_core::input::{read_capped_text, MAX_URDF_BYTES};
use moonhaul_core::state::{Phase, PlanarPose};
use moonhaul_core::task_config::TaskConfig;
use moonhaul_core::unit::UnitSpec;
use moonhaul_hal::can::UnitCanConfig;
use moonhaul_hal::mock::MockConfig;
use moonhaul_hal::unit::{
    emulated_unit, kernel_unit, FaultInjection, InjectedFault, MockUnit, UnitHardware, UnitOutput,
    UnitReading, UNIT_JOINTS,
};
use tokio::sync::Notify;
use tracing::{info, warn};

use crate::cli_support::{load_policies, policy_file, wall_us, Signals};
use crate::mission_log::{LogInputs, UnitLog};
use crate::network::{self, Access, FrameQueue, Keys, Outbox, QueueCounts, Role};
use crate::record::TickRecord;
use crate::ros2::live::{LiveSettings, Ros2Publisher};
use crate::ros2::topics::default_namespace;
use crate::sim_link::{self, SimHardware, SimSensed};
use crate::tick::{Controller, Onboard, OnboardSettings};
use crate::unit_config::{check_endpoint, UnitConfig};
use moonhaul_core::scripted::MissionPlan;

/// Which hardware backend the daemon drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum HalKind {
    /// The unit's nine CiA 402 drives on a kernel CAN interface (SocketCAN), named by
    /// `--can-interface` (e.g. can0).
    Can,
    /// The same CiA 402 master over an in-memory bus of emulated drives: the CAN path without
    /// CAN hardware, with fault injection.
    CanEmulated,
    /// Mock drives that mirror their commands, with fault injection.
    Mock,
    /// One unit of a simulated world running in another process (`moonhaul mission world`).
    Sim,
}

/// A fault to inject at a given time, for tests and drills: `motor:3@2.5` (joint 3 at 2.5 s
/// after start), `emcy:0@1`, `heartbeat:8@4`, `nan:2@1` on the mock or emulated CAN drives;
/// `policy-nan@3` makes the policy's output non-finite; `drop-peers@3` drops all peer traffic
/// (a network partition) from then on; `absurd-state@3` makes this unit a key holder gone wrong
/// for [`ABSURD_STATE_S`]: its state messages, sealed with its genuine key, claim a base at
/// x = 1e308 m (its peers must hold on a named peer fault and take it back once it is sane).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Injection {
    pub at_s: f64,
    pub what: Injected,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Injected {
    Hardware(InjectedFault),
    PolicyNan,
    DropPeers,
    AbsurdState,
}

/// How long an `absurd-state` drill lasts.
pub const ABSURD_STATE_S: f64 = 1.0;
/// The base position an `absurd-state` drill announces: finite, far beyond any arena.
const ABSURD_X_M: f64 = 1e308;

impl std::str::FromStr for Injection {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "{s:?}: expected KIND[:JOINT]@SECONDS, KIND one of motor, emcy, heartbeat, nan, \
                 policy-nan, drop-peers, absurd-state"
            )
        };
        let (what, at) = s.split_once('@').ok_or_else(bad)?;
        let at_s: f64 = at.parse().map_err(|_| bad())?;
        if !(at_s.is_finite() && at_s >= 0.0) {
            return Err(bad());
        }
        let (kind, joint) = match what.split_once(':') {
            Some((k, j)) => {
                let joint = j.parse::<usize>().map_err(|_| bad())?;
                if joint >= UNIT_JOINTS {
                    return Err(format!(
                        "{s:?}: joint {joint} does not exist: a unit's joints are 0..{} (the \
                         two wheels, then the arm base to tip)",
                        UNIT_JOINTS - 1
                    ));
                }
                (k, Some(joint))
            }
            None => (what, None),
        };
        let what = match (kind, joint) {
            ("policy-nan", None) => Injected::PolicyNan,
            ("drop-peers", None) => Injected::DropPeers,
            ("absurd-state", None) => Injected::AbsurdState,
            ("motor", Some(joint)) => Injected::Hardware(InjectedFault::Motor { joint }),
            ("emcy", Some(joint)) => Injected::Hardware(InjectedFault::Emcy { joint }),
            ("heartbeat", Some(joint)) => {
                Injected::Hardware(InjectedFault::HeartbeatLoss { joint })
            }
            ("nan", Some(joint)) => Injected::Hardware(InjectedFault::SensorNan { joint }),
            _ => return Err(bad()),
        };
        Ok(Injection { at_s, what })
    }
}

/// Which controller a unit flies.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ControllerKind {
    Learned,
    Scripted,
}

impl ControllerKind {
    /// The name on the command line and in a unit log's `controller` metadata.
    pub fn name(self) -> &'static str {
        match self {
            ControllerKind::Learned => "learned",
            ControllerKind::Scripted => "scripted",
        }
    }
}

/// `moonhaul-unit`'s command line.
#[derive(Debug, clap::Parser)]
#[command(
    name = "moonhaul-unit",
    version,
    about = "The per-robot moonhaul daemon"
)]
pub struct DaemonArgs {
    /// The unit config (TOML), e.g. configs/unit.toml.
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// Hardware backend.
    #[arg(long, value_enum)]
    pub hal: HalKind,
    /// With `--hal can`: the kernel CAN interface of the unit's drives (e.g. can0, vcan0).
    #[arg(long, value_name = "NAME", required_if_eq("hal", "can"))]
    pub can_interface: Option<String>,
    /// What drives the increments: the learned phase policies (the config's `policies`) or
    /// the scripted IK controller (the config's `mission` plan), through the same pipeline.
    #[arg(long, value_enum, default_value_t = ControllerKind::Learned)]
    pub controller: ControllerKind,
    /// The team's key file (`moonhaul keys generate`); kept outside the repository's configs.
    #[arg(long, value_name = "FILE")]
    pub keys: PathBuf,
    /// Overrides the config's unit index.
    #[arg(long)]
    pub unit_index: Option<usize>,
    /// Overrides the config's start pose: `x_m,y_m,yaw_rad`.
    #[arg(long, value_name = "X,Y,YAW", allow_hyphen_values = true)]
    pub start_pose: Option<String>,
    /// Overrides the config's zenoh endpoints to connect to (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Overrides the config's zenoh endpoints to listen on (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Publish the read-only ROS 2 topics (rmw_zenoh's wire format) on a session of their own
    /// to this endpoint, e.g. rmw_zenoh's router `tcp/localhost:7447` (repeatable; overrides
    /// `[ros2] endpoints` and turns `[ros2]` on).
    #[arg(long, value_name = "ENDPOINT")]
    pub ros2_connect: Vec<String>,
    /// Write the mission log (MCAP) here: never over one of the run's inputs (config, keys,
    /// policies, …), and over another existing file only with `--force`.
    #[arg(long, value_name = "FILE")]
    pub log: Option<PathBuf>,
    /// Replace an existing `--log` file.
    #[arg(long)]
    pub force: bool,
    /// With `--hal sim`: the world steps on the wall clock; do not wait for peers.
    #[arg(long)]
    pub realtime: bool,
    /// Add this offset to the unit's clock, ms (a drill for clock faults).
    #[arg(
        long,
        default_value_t = 0.0,
        allow_negative_numbers = true,
        value_name = "MS"
    )]
    pub clock_offset_ms: f64,
    /// Inject a fault (repeatable): see [`Injection`].
    #[arg(long, value_name = "KIND[:JOINT]@S")]
    pub inject: Vec<Injection>,
    /// With `--hal sim`: how long to wait for the world's first reading (its start-up and the
    /// zenoh connection on a loaded machine) before failing by name, s.
    #[arg(long, default_value_t = 60.0, value_name = "S")]
    pub world_wait_s: f64,
    /// Exit (in a hold) after this many seconds of unit time (of wall time while `--hal sim`
    /// has heard no world yet).
    #[arg(long, value_name = "S")]
    pub max_runtime_s: Option<f64>,
}

/// The mock backend of a unit config (`[mock]`): mirror drives with the grasp's load share,
/// activated by the caller.
pub fn mock_hardware(
    config: &UnitConfig,
    spec: &UnitSpec,
    period: Duration,
) -> Result<MockUnit, moonhaul_hal::HalError> {
    MockUnit::new(
        period,
        MockConfig::ideal(period),
        spec,
        &config.mock.arm_start_rad,
        config.mock.grasp_load_n,
    )
}

fn parse_pose(text: &str) -> Result<PlanarPose> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--start-pose {text:?}: expected x_m,y_m,yaw_rad"))?;
    match v[..] {
        [x_m, y_m, yaw_rad]
            if [x_m, y_m].iter().all(|c| c.abs() <= ARENA_HALF_WIDTH_M)
                && yaw_rad.abs() <= std::f64::consts::TAU =>
        {
            Ok(PlanarPose { x_m, y_m, yaw_rad })
        }
        _ => bail!(
            "--start-pose {text:?}: expected x_m,y_m,yaw_rad with x and y within \
             ±{ARENA_HALF_WIDTH_M} m (the arena peers hold messages to) and |yaw| ≤ 2π"
        ),
    }
}

/// The daemon's hardware: one backend, with what only some backends have.
enum Hardware {
    Mock(Box<MockUnit>),
    Can(Box<dyn CanUnit>),
    Sim(Box<SimHardware>),
}

/// The CAN master, on a kernel interface or the emulated bus, as the daemon uses it.
trait CanUnit: UnitHardware + FaultInjection {}
impl<T: UnitHardware + FaultInjection> CanUnit for T {}

impl Hardware {
    fn unit(&mut self) -> &mut dyn UnitHardware {
        match self {
            Hardware::Mock(m) => m.as_mut(),
            Hardware::Can(c) => c.as_mut(),
            Hardware::Sim(s) => s.as_mut(),
        }
    }

    fn inject(&mut self, fault: InjectedFault) -> Result<(), moonhaul_hal::HalError> {
        match self {
            Hardware::Mock(m) => m.inject(fault),
            Hardware::Can(c) => c.inject(fault),
            Hardware::Sim(_) => Err(moonhaul_hal::HalError::Bus {
                bus: "sim".into(),
                reason: format!("cannot inject {fault} into the simulated world's drives"),
            }),
        }
    }
}

/// The configs a run reads, which its log attaches (beside the URDF): the unit config, the
/// control rate, gate, clamp and tasks, the CAN drives' with a CAN backend, the scripted
/// plan with the scripted controller. Never the key file.
fn log_inputs(args: &DaemonArgs, config: &UnitConfig) -> Vec<PathBuf> {
    let mut files = vec![
        args.config.clone(),
        config.control.clone(),
        config.gate.clone(),
        config.sync.clone(),
        config.tasks.clone(),
    ];
    if matches!(args.hal, HalKind::Can | HalKind::CanEmulated) {
        files.push(config.can.clone());
    }
    if args.controller == ControllerKind::Scripted {
        files.push(config.mission.clone());
    }
    files
}

fn offset_us(t_us: u64, offset_ms: f64) -> u64 {
    let off = (offset_ms * 1e3).round() as i64;
    t_us.saturating_add_signed(off)
}

/// With `--hal sim`: how long the world's link may stay silent once it spoke. A live world
/// re-sends its reading every 50 ms while it waits for the units, so silence means it is gone.
pub const WORLD_SILENCE: Duration = Duration::from_secs(10);

/// Runs the daemon until a signal, `--max-runtime-s` or a lost world; every exit path after
/// the start-up holds and finishes the log.
pub async fn run(args: DaemonArgs) -> Result<()> {
    // First: a signal from now on ends in a hold with a finished log (it waits for the loop).
    let mut signals = Signals::install()?;
    let started = tokio::time::Instant::now();
    // A drill offset beyond an hour is a typo, not a clock fault.
    if !(args.clock_offset_ms.is_finite() && args.clock_offset_ms.abs() <= 3.6e6) {
        bail!(
            "--clock-offset-ms {}: must be a finite offset of at most an hour",
            args.clock_offset_ms
        );
    }
    // Beyond a year a runtime limit is a typo (and would overflow the wall-clock deadline).
    if let Some(m) = args.max_runtime_s {
        if !(m.is_finite() && m > 0.0 && m <= 3.2e7) {
            bail!("--max-runtime-s {m}: must be a positive number of seconds, at most a year");
        }
    }
    if !(args.world_wait_s.is_finite() && args.world_wait_s > 0.0 && args.world_wait_s <= 3600.0) {
        bail!(
            "--world-wait-s {}: must be a positive number of seconds, at most an hour",
            args.world_wait_s
        );
    }
    let mut config = UnitConfig::from_file(&args.config)?;
    if let Some(i) = args.unit_index {
        config.unit_index = i;
        config
            .team_settings()
            .validate()
            .with_context(|| format!("--unit-index {i}"))?;
    }
    if let Some(pose) = &args.start_pose {
        config.start_pose = parse_pose(pose)?;
    }
    let mut net = config.network.clone();
    if !args.connect.is_empty() {
        net.connect = args.connect.clone();
    }
    if !args.listen.is_empty() {
        net.listen = args.listen.clone();
    }
    for (list, listen, flag) in [
        (&net.connect, false, "--connect"),
        (&net.listen, true, "--listen"),
    ] {
        for endpoint in list {
            check_endpoint(endpoint, listen)
                .map_err(|reason| anyhow::anyhow!("{flag} {endpoint:?}: {reason}"))?;
        }
    }
    let mut ros2 = config.ros2.clone();
    if !args.ros2_connect.is_empty() {
        ros2.enabled = true;
        ros2.endpoints = args.ros2_connect.clone();
        for endpoint in &ros2.endpoints {
            check_endpoint(endpoint, false)
                .map_err(|reason| anyhow::anyhow!("--ros2-connect {endpoint:?}: {reason}"))?;
        }
    }
    if config.team_size > 1 && net.connect.is_empty() && net.listen.is_empty() {
        bail!(
            "{}: [network] connect and listen are empty and no --connect or --listen was given: \
             unit {} could never reach the other {} of its team",
            args.config.display(),
            config.unit_index,
            config.team_size - 1
        );
    }
    if let Some(log) = &args.log {
        let mut inputs = config.inputs(&args.config);
        inputs.add("key file", &args.keys);
        inputs.check_output("--log", log, args.force)?;
    }
    let settings = config.team_settings();
    let unit = settings.unit_index;
    let keys = KeyFile::load(&args.keys)?;
    keys.check_matches(&settings)
        .with_context(|| format!("key file {}", args.keys.display()))?;
    let sealer = keys.sealer(Sender::Unit(unit))?;
    let spec = UnitSpec::from_file(&config.urdf)
        .with_context(|| format!("unit model {}", config.urdf.display()))?;
    config.check_against_model(&args.config, &spec)?;
    let validator = Validator::new(&settings, &keys, MessageBounds::of_unit(&spec))?;
    let gate = GateConfig::from_file(&config.gate)?;
    let sync = SyncConfig::from_file(&config.sync)?;
    let tasks = TaskConfig::load(&config.tasks)?;
    let controller = match args.controller {
        ControllerKind::Learned => Controller::Learned(Box::new(load_policies(&config.policies)?)),
        ControllerKind::Scripted => Controller::Scripted(MissionPlan::load(&config.mission)?),
    };
    let period = Duration::from_micros(settings.control_period_us);
    if args.can_interface.is_some() && args.hal != HalKind::Can {
        bail!("--can-interface applies to --hal can only");
    }
    let mut hardware = match args.hal {
        HalKind::Mock => Hardware::Mock(Box::new(mock_hardware(&config, &spec, period)?)),
        HalKind::Can => {
            let can = UnitCanConfig::from_file(&config.can)?;
            let Some(interface) = args.can_interface.as_deref() else {
                bail!("--hal can needs --can-interface NAME (e.g. can0)");
            };
            Hardware::Can(Box::new(kernel_unit(&can, interface).with_context(
                || format!("bringing up the unit's CAN drives on {interface}"),
            )?))
        }
        HalKind::CanEmulated => {
            let can = UnitCanConfig::from_file(&config.can)?;
            Hardware::Can(Box::new(
                emulated_unit(&can).context("bringing up the unit's emulated CAN drives")?,
            ))
        }
        HalKind::Sim => Hardware::Sim(Box::new(SimHardware::new(unit))),
    };
    let mut log = match &args.log {
        Some(path) => Some(UnitLog::create(
            path,
            unit,
            &LogInputs::read(&config.urdf, &log_inputs(&args, &config))?.flown_by(
                args.controller.name(),
                &match args.controller {
                    ControllerKind::Learned => [Phase::Lift, Phase::Transport, Phase::Place]
                        .map(|phase| policy_file(&config.policies, phase))
                        .to_vec(),
                    ControllerKind::Scripted => Vec::new(),
                },
            )?,
        )?),
        None => None,
    };
    let access = Access::new(&keys, Role::Unit(unit))
        .with_context(|| format!("key file {}", args.keys.display()))?;
    let session = network::open(&net, &access).await?;
    let links = Links::open(
        &session,
        &validator,
        &settings.team,
        settings.team_size,
        args.hal,
    )
    .await?;

    // Read-only ROS 2 topics, on a session of their own (never the team's).
    let ros2 = match ros2.enabled {
        true => {
            let urdf = read_capped_text(&config.urdf, MAX_URDF_BYTES)?;
            let live = LiveSettings {
                domain_id: ros2.domain_id,
                namespace: ros2
                    .namespace
                    .clone()
                    .unwrap_or_else(|| default_namespace(unit)),
                connect: ros2.endpoints.clone(),
            };
            let publisher = Ros2Publisher::start(&live, &urdf, settings.team_size)
                .await
                .context("starting the ROS 2 topics")?;
            info!(unit, namespace = %live.namespace, domain = live.domain_id, endpoints = ?live.connect, "ROS 2 topics up");
            Some(publisher)
        }
        false => None,
    };

    hardware
        .unit()
        .activate()
        .context("activating the drives")?;
    // Sequence numbers start at the unit's clock at boot (message.rs's convention). On the
    // simulated world the clock is the world's time, which a unit only learns at its first
    // reading: it starts from 0 and the first message takes the clock then.
    let boot_us = match args.hal {
        HalKind::Sim => 0,
        HalKind::Mock | HalKind::Can | HalKind::CanEmulated => {
            offset_us(wall_us(), args.clock_offset_ms)
        }
    };
    let mut onboard = Onboard::new(
        OnboardSettings {
            spec,
            team: settings.clone(),
            gate,
            sync,
            tasks,
            start_pose: config.start_pose,
        },
        controller,
        boot_us,
    )?;
    info!(unit, hal = ?args.hal, team = %settings.team, "unit daemon up");

    let mut interval = tokio::time::interval(period);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // Before the world's first reading, `--max-runtime-s` counts wall time from start-up.
    let mut world = WorldWatch {
        last_frame: None,
        first_by: started + Duration::from_secs_f64(args.world_wait_s),
        first_wait_s: args.world_wait_s,
        key: Keys::new(&settings.team).sim_sensed(unit),
        runtime_by: args
            .max_runtime_s
            .map(|m| started + Duration::from_secs_f64(m)),
    };
    let mut reading = UnitReading::default();
    let mut record = TickRecord::for_team(settings.team_size);
    let mut frame = Vec::with_capacity(1024);
    let mut start_us: Option<u64> = None;
    let mut pending = args.inject.clone();
    let mut drop_peers = false;
    let mut absurd_until_s: Option<f64> = None;
    let mut deadline_misses = 0u64;
    let mut report = Report::default();
    let lockstep = args.hal == HalKind::Sim && !args.realtime;
    let mut inbox = Inbox {
        validator,
        lockstep,
        deferred: Vec::new(),
    };
    let stop: Stop = loop {
        // Wait for the tick: the interval, or the world's next reading. A signal comes first.
        let wake = tokio::select! {
            biased;
            why = signals.recv() => Wake::Stop(Stop::Signal(why)),
            w = next_tick(&mut interval, links.sensed.as_ref(), &mut hardware, unit, &mut world) => w,
        };
        let now_us = match wake {
            Wake::Stop(why) => break why,
            Wake::Skip => continue,
            Wake::Tick(t_us) => offset_us(t_us, args.clock_offset_ms),
        };
        let work_start = Instant::now();
        let t0 = *start_us.get_or_insert(now_us);
        let elapsed_s = now_us.saturating_sub(t0) as f64 * 1e-6;
        if args.max_runtime_s.is_some_and(|m| elapsed_s >= m) {
            break Stop::RuntimeLimit;
        }
        // Injections due.
        let mut k = 0;
        while k < pending.len() {
            if pending[k].at_s <= elapsed_s {
                let due = pending.swap_remove(k);
                warn!(unit, at_s = due.at_s, what = ?due.what, "injecting a fault");
                match due.what {
                    Injected::Hardware(f) => {
                        if let Err(e) = hardware.inject(f) {
                            warn!(unit, error = %e, "injection refused");
                        }
                    }
                    Injected::PolicyNan => onboard.inject_policy_nan(),
                    Injected::DropPeers => drop_peers = true,
                    Injected::AbsurdState => absurd_until_s = Some(due.at_s + ABSURD_STATE_S),
                }
            } else {
                k += 1;
            }
        }
        inbox.release(&mut onboard, now_us);
        if lockstep {
            wait_for_peers(
                &links,
                &mut inbox,
                &mut onboard,
                now_us,
                &settings,
                drop_peers,
            )
            .await;
        }
        let read = hardware.unit().read(&mut reading);
        if let Err(e) = &read {
            warn!(unit, error = %e, "hardware read failed");
        }
        if let Some(e) = hardware.unit().fault() {
            if onboard.fault().is_none() {
                warn!(unit, error = %e, "drive fault");
            }
            onboard.latch_fault(FaultKind::Drive, "drive fault");
        }
        for queue in &links.peers {
            drain(queue, &mut inbox, &mut onboard, now_us, drop_peers);
        }
        drain(&links.operator, &mut inbox, &mut onboard, now_us, false);
        let before = onboard.phase();
        let rejected = links.rejections(&inbox.validator);
        let out = onboard.tick(
            now_us,
            read.is_ok().then_some(&reading),
            &rejected,
            &mut record,
        );
        let output = out.output;
        let absurd;
        let message = if absurd_until_s.is_some_and(|until| elapsed_s < until) {
            // A drill only: the copy costs an allocation per tick while it lasts.
            let mut tampered = out.message.clone();
            if let Body::Unit(tick) = &mut tampered.body {
                tick.state.base_pose.x_m = ABSURD_X_M;
            }
            absurd = tampered;
            &absurd
        } else {
            out.message
        };
        let sealed = sealer.seal_into(message, &mut frame);
        inbox.validator.set_mission(onboard.mission());
        if let Hardware::Sim(hw) = &mut hardware {
            hw.set_phase(record.phase);
        }
        if let Err(e) = hardware.unit().write(&output) {
            warn!(unit, error = %e, "hardware write failed");
            onboard.latch_fault(FaultKind::Drive, "hardware write failed");
        }
        if let (Hardware::Sim(hw), Some(commands)) = (&mut hardware, &links.commands) {
            if let Some(c) = hw.take_command() {
                commands.send(&sim_link::encode(&c));
            }
        }
        match sealed {
            Ok(()) => links.state.send(&frame),
            Err(e) => warn!(unit, error = %e, "state message not sent"),
        }
        if record.phase != before {
            info!(unit, from = %before, to = %record.phase, t_s = elapsed_s, "phase");
        }
        report.tick(unit, &inbox.validator, &links);
        let work = work_start.elapsed();
        if args.hal != HalKind::Sim && work > period {
            deadline_misses += 1;
        }
        record.deadline_misses = deadline_misses;
        record.work_us = work.as_micros() as u64;
        if let Some(log) = &mut log {
            if let Err(e) = log.write(&record) {
                warn!(unit, error = %e, "mission log write failed");
            }
        }
        if let Some(ros2) = &ros2 {
            ros2.offer(&record);
        }
    };
    info!(
        unit,
        reason = %stop,
        "stopping: holding and flushing the log"
    );
    report.totals(unit, &inbox.validator, &links);
    // The hold: wheels stopped, arm at its last command (a loaded arm stays where it is), or at
    // its sensed position if no command was issued yet; then torque off.
    let mut hold = UnitReading::default();
    if hardware.unit().read(&mut hold).is_ok() {
        let command = onboard.hold_command().unwrap_or_else(|| {
            let mut s = moonhaul_core::state::UnitState::default();
            s.arm.position_rad = hold.arm.position_rad;
            anchor_command(&s)
        });
        let _ = hardware.unit().write(&UnitOutput {
            command,
            grasp_open: record.grasp_open,
        });
        if let (Hardware::Sim(hw), Some(commands)) = (&mut hardware, &links.commands) {
            if let Some(c) = hw.take_command() {
                commands.send(&sim_link::encode(&c));
            }
        }
    }
    links.close().await;
    if let Err(e) = hardware.unit().deactivate() {
        warn!(unit, error = %e, "deactivating the drives");
    }
    if let Some(log) = log {
        log.finish().context("finishing the mission log")?;
    }
    if let Some(ros2) = ros2 {
        let (dropped, failed) = ros2.counts();
        info!(
            unit,
            dropped, failed, "ROS 2 totals: ticks not published, samples not sent"
        );
        ros2.close().await;
    }
    let _ = session.close().await;
    info!(unit, "unit daemon down");
    match stop {
        Stop::WorldLost(why) => bail!("{why}"),
        Stop::Signal(_) | Stop::RuntimeLimit => Ok(()),
    }
}

/// Why the loop ended: a signal or the runtime limit (a clean exit), or a lost world (an
/// error, after the same hold and finished log).
enum Stop {
    Signal(&'static str),
    RuntimeLimit,
    WorldLost(String),
}

impl std::fmt::Display for Stop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Stop::Signal(s) => f.write_str(s),
            Stop::RuntimeLimit => f.write_str("the runtime limit"),
            Stop::WorldLost(why) => f.write_str(why),
        }
    }
}

/// What ends a wait for the next tick.
enum Wake {
    /// Tick at this clock reading, µs (before the drill offset).
    Tick(u64),
    /// Nothing to do (a malformed or repeated reading).
    Skip,
    Stop(Stop),
}

/// The bounds of a wait on the simulated world's link.
struct WorldWatch {
    /// When the link last delivered a frame; `None` before the first.
    last_frame: Option<tokio::time::Instant>,
    /// The first reading must come by then (`--world-wait-s` after start-up).
    first_by: tokio::time::Instant,
    first_wait_s: f64,
    /// The world's reading key, for the error that names it.
    key: String,
    /// `--max-runtime-s` in wall time, which holds until the world's clock takes over.
    runtime_by: Option<tokio::time::Instant>,
}

impl WorldWatch {
    /// Why the world's link counts as lost once its deadline passed (formatted only then: the
    /// wait runs every tick).
    fn lost(&self) -> String {
        match self.last_frame {
            Some(_) => format!(
                "the simulated world fell silent: no frame on {} for {} s",
                self.key,
                WORLD_SILENCE.as_secs()
            ),
            None => format!(
                "no reading from the simulated world on {} within {} s of start-up \
                 (--world-wait-s): is `moonhaul mission world` running and reachable at this \
                 unit's --connect endpoints?",
                self.key, self.first_wait_s
            ),
        }
    }
}

/// The next tick: the interval's, or the world's next reading (the newest one waiting), within
/// the bounds of `world`.
async fn next_tick(
    interval: &mut tokio::time::Interval,
    sensed: Option<&(Arc<FrameQueue>, Arc<Notify>)>,
    hardware: &mut Hardware,
    unit: usize,
    world: &mut WorldWatch,
) -> Wake {
    let Some((queue, ready)) = sensed else {
        interval.tick().await;
        return Wake::Tick(wall_us());
    };
    let deadline = world
        .last_frame
        .map_or(world.first_by, |t| t + WORLD_SILENCE);
    let runtime_by = world.runtime_by.filter(|_| world.last_frame.is_none());
    tokio::select! {
        biased;
        heard = tokio::time::timeout_at(deadline, ready.notified()) => {
            if heard.is_err() {
                return Wake::Stop(Stop::WorldLost(world.lost()));
            }
        }
        _ = tokio::time::sleep_until(runtime_by.unwrap_or(deadline)), if runtime_by.is_some() => {
            return Wake::Stop(Stop::RuntimeLimit);
        }
    }
    world.last_frame = Some(tokio::time::Instant::now());
    // Drain to the newest reading: a unit never ticks on old news.
    let mut newest: Option<SimSensed> = None;
    queue.drain(
        |sample| match SimSensed::decode(&sample.payload().to_bytes(), unit) {
            Ok(m) if newest.is_none_or(|n| m.tick >= n.tick) => newest = Some(m),
            Ok(_) => {}
            Err(e) => warn!(unit, error = %e, "dropped a sim link frame"),
        },
    );
    let Some(newest) = newest else {
        return Wake::Skip;
    };
    let Hardware::Sim(hw) = hardware else {
        return Wake::Skip;
    };
    if hw.latest().is_some_and(|l| l.tick >= newest.tick) {
        // The world re-sends a reading until every unit answered it.
        return Wake::Skip;
    }
    hw.deliver(newest);
    Wake::Tick(newest.stamp_us)
}

/// Frames one peer may have waiting between two ticks: it sends one a tick, so this covers a
/// stall of several ticks; older news than that is worth nothing.
const PEER_QUEUE_FRAMES: usize = 8;
/// Operator frames waiting between two ticks: commands are rare; a burst beyond this is a
/// flood, of which the newest are kept.
const OPERATOR_QUEUE_FRAMES: usize = 16;
/// The world's readings waiting: only the newest is used.
const SENSED_QUEUE_FRAMES: usize = 4;
/// How long the hold command at shutdown may take to go out.
const LAST_COMMAND_WAIT: Duration = Duration::from_millis(200);

/// The daemon's network I/O: one receive queue per peer (a flood on one key cannot push out
/// another's frames), one for the operator, one for the world's readings with `--hal sim`, and
/// the outboxes of its own state and drive commands. Its own publications never reach it.
struct Links {
    peers: Vec<Arc<FrameQueue>>,
    peer_ready: Arc<Notify>,
    operator: Arc<FrameQueue>,
    sensed: Option<(Arc<FrameQueue>, Arc<Notify>)>,
    state: Outbox,
    commands: Option<Outbox>,
    /// Kept for their callbacks; dropping one undeclares it.
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
}

impl Links {
    /// `validator`: this unit's, whose stateless half admits frames to the peer and operator
    /// queues.
    async fn open(
        session: &zenoh::Session,
        validator: &Validator,
        team: &str,
        team_size: usize,
        hal: HalKind,
    ) -> Result<Links> {
        let unit = validator.unit().unwrap_or(usize::MAX);
        let keys = Keys::new(team);
        let mut subscribers = Vec::new();
        let peer_ready = Arc::new(Notify::new());
        let mut peers = Vec::new();
        for peer in (0..team_size).filter(|&j| j != unit) {
            let queue = FrameQueue::new(PEER_QUEUE_FRAMES, Arc::clone(&peer_ready));
            let admission = validator.admission(Sender::Unit(peer));
            subscribers.push(
                network::subscribe(session, keys.unit_state(peer), &queue, Some(admission)).await?,
            );
            peers.push(queue);
        }
        let operator = FrameQueue::new(OPERATOR_QUEUE_FRAMES, Arc::new(Notify::new()));
        let admission = validator.admission(Sender::Operator);
        subscribers
            .push(network::subscribe(session, keys.operator(), &operator, Some(admission)).await?);
        let state =
            Outbox::spawn(network::control_publisher(session, keys.unit_state(unit)).await?);
        let (sensed, commands) = if hal == HalKind::Sim {
            let ready = Arc::new(Notify::new());
            let queue = FrameQueue::new(SENSED_QUEUE_FRAMES, Arc::clone(&ready));
            subscribers
                .push(network::subscribe(session, keys.sim_sensed(unit), &queue, None).await?);
            let commands = network::control_publisher(session, keys.sim_command(unit)).await?;
            (Some((queue, ready)), Some(Outbox::spawn(commands)))
        } else {
            (None, None)
        };
        Ok(Links {
            peers,
            peer_ready,
            operator,
            sensed,
            state,
            commands,
            _subscribers: subscribers,
        })
    }

    /// The frames the peer and operator queues refused on arrival, by reason.
    fn refused_on_arrival(&self) -> RejectCounts {
        let mut total = self.operator.refused();
        for q in &self.peers {
            total.add(&q.refused());
        }
        total
    }

    /// Every rejection by reason: the validator's and the arrival checks'.
    fn rejections(&self, validator: &Validator) -> RejectCounts {
        let mut total = self.refused_on_arrival();
        total.add(validator.counts());
        total
    }

    /// Every receive queue's counts, summed.
    fn received(&self) -> QueueCounts {
        let mut total = self.operator.counts();
        for q in &self.peers {
            total += q.counts();
        }
        if let Some((q, _)) = &self.sensed {
            total += q.counts();
        }
        total
    }

    /// Lets the last frames go out (bounded), then stops publishing.
    async fn close(self) {
        if let Some(commands) = self.commands {
            commands.close(LAST_COMMAND_WAIT).await;
        }
        self.state.close(LAST_COMMAND_WAIT).await;
    }
}

/// How often the daemon's log reports refused frames while more keep coming.
const REPORT_PERIOD: Duration = Duration::from_secs(1);

/// The log's account of refused frames: the validator's rejections (with their reasons) and
/// the queues' drops and oversize frames, when they grew, at most once per [`REPORT_PERIOD`];
/// and the totals at the end.
#[derive(Default)]
struct Report {
    rejected: u64,
    refused: u64,
    last: Option<Instant>,
}

impl Report {
    fn tick(&mut self, unit: usize, validator: &Validator, links: &Links) {
        let counts = links.rejections(validator);
        let rejected = counts.total();
        let net = links.received();
        if rejected == self.rejected && net.refused() == self.refused {
            return;
        }
        if self.last.is_some_and(|t| t.elapsed() < REPORT_PERIOD) {
            return;
        }
        self.last = Some(Instant::now());
        self.rejected = rejected;
        self.refused = net.refused();
        warn!(
            unit,
            rejected,
            ?counts,
            dropped = net.dropped,
            oversize = net.oversize,
            "frames refused"
        );
    }

    fn totals(&self, unit: usize, validator: &Validator, links: &Links) {
        let net = links.received();
        let state = links.state.counts();
        let counts = links.rejections(validator);
        info!(
            unit,
            received = net.received,
            rejected = counts.total(),
            ?counts,
            dropped = net.dropped,
            oversize = net.oversize,
            published = state.sent,
            superseded = state.superseded,
            publish_failed = state.failed,
            "network totals"
        );
    }
}

/// Validates and takes in every frame waiting in `queue` (none when `drop`: a drilled
/// partition).
fn drain(queue: &FrameQueue, inbox: &mut Inbox, onboard: &mut Onboard, now_us: u64, drop: bool) {
    queue.drain(|sample| {
        if !drop {
            take(sample, inbox, onboard, now_us);
        }
    });
}

fn take(sample: &zenoh::sample::Sample, inbox: &mut Inbox, onboard: &mut Onboard, now_us: u64) {
    // The queue refused anything over the frame cap, so this copy (if the payload is not
    // contiguous) is bounded.
    let bytes = sample.payload().to_bytes();
    match inbox.validator.receive_frame(&bytes, now_us) {
        // Lockstep: a peer's message of this very tick waits for the next one, so what a unit
        // sees never depends on which process the scheduler ran first (operator commands act
        // at once).
        Ok(envelope)
            if inbox.lockstep
                && matches!(envelope.sender, Sender::Unit(_))
                && envelope.stamp_us >= now_us =>
        {
            inbox.deferred.push(envelope)
        }
        Ok(envelope) => onboard.receive(&envelope),
        Err(rejection) => {
            tracing::debug!(unit = onboard.unit(), %rejection, "rejected");
            onboard.reject(&rejection);
        }
    }
}

/// The receiving side of the daemon: the validator, and in lockstep the peers' messages held
/// for the next tick.
struct Inbox {
    validator: Validator,
    lockstep: bool,
    deferred: Vec<moonhaul_coord::message::Envelope>,
}

impl Inbox {
    /// Takes in the held messages older than `now_us`.
    fn release(&mut self, onboard: &mut Onboard, now_us: u64) {
        self.deferred.retain(|e| {
            let due = e.stamp_us < now_us;
            if due {
                onboard.receive(e);
            }
            !due
        });
    }
}

/// Lockstep only: waits (at most a second of wall time) until every peer's message of
/// the previous tick is in, taking them in as they come; a silent peer is then judged by the
/// staleness rule on message stamps, like any other.
async fn wait_for_peers(
    links: &Links,
    inbox: &mut Inbox,
    onboard: &mut Onboard,
    now_us: u64,
    team: &moonhaul_coord::TeamSettings,
    drop: bool,
) {
    // Long enough for a loaded machine to deliver a live peer's message (waiting costs nothing
    // then); a dead peer makes each of the few ticks before its staleness stop wait this long.
    const PEER_WAIT: Duration = Duration::from_secs(1);
    if drop {
        return;
    }
    // A peer already stale (dead, or on a clock far off: a clock drill) has been judged by the
    // staleness rule; waiting for it would stretch every tick to PEER_WAIT.
    if !onboard.peers_heard_since(now_us.saturating_sub(team.staleness_us())) {
        return;
    }
    let wanted = now_us.saturating_sub(team.control_period_us);
    let deadline = tokio::time::Instant::now() + PEER_WAIT;
    loop {
        for queue in &links.peers {
            queue.drain(|sample| take(sample, inbox, onboard, now_us));
        }
        if onboard.peers_heard_since(wanted) {
            return;
        }
        if tokio::time::timeout_at(deadline, links.peer_ready.notified())
            .await
            .is_err()
        {
            return;
        }
    }
}
