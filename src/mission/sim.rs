//! `moonhaul mission sim`: a simulated mission of real processes. For every payload and trial
//! it starts one world process (`moonhaul mission world`) and one `moonhaul-unit` per unit on
//! the sim-backed hardware, all talking only over zenoh on loopback, starts the mission as the
//! operator, waits for the world to end it, stops the units (SIGTERM: they hold and flush their
//! logs) and finally summarizes the ground truth (`moonhaul log summary`).
//!
//! Layout of `--out DIR`: `keys.toml` (the mission's key file, mode 0600, unless `--keys` names
//! one), `<payload>/trial-<k>/{world.mcap, unit-<i>.mcap, start.json, world.log, unit-<i>.log}`,
//! `summary.json`, `mission_profile.png`. None of them may be an input of the run, and none may
//! exist already unless `--force`: checked before anything starts.
//!
//! Every wait is bounded: the world's start-up, the units' first words, and each trial as a
//! whole ([`trial_wall_limit`]). SIGINT or SIGTERM is passed on to the world and every unit
//! (each holds and finishes its log), waited for (bounded, then killed), and ends the run with
//! an error; no process is left behind. Arguments, the key file and payload files are checked
//! here before any process starts, and a process that fails anyway is reported with the last
//! error line of its log.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::auth::KeyFile;
use moonhaul_deploy::cli_support::Signals;
use moonhaul_deploy::daemon::ControllerKind;
use moonhaul_deploy::network::free_loopback_port;
use moonhaul_sim::{SceneModel, SimConfig};

use super::operator::{self, Console};
use super::world::{check_max_seconds, StartInfo};
use crate::payload_arg::{self, PayloadArg};

#[derive(Debug, clap::Args)]
pub struct SimArgs {
    /// Payloads to carry, comma-separated: box, bricks, sledge, or payload URDFs.
    #[arg(long, value_delimiter = ',', default_value = "box")]
    pub payload: Vec<PayloadArg>,
    /// Trials per payload (the paper ran three).
    #[arg(long, default_value_t = 1)]
    pub trials: u32,
    /// Pace the world at the wall clock instead of lockstep.
    #[arg(long)]
    pub realtime: bool,
    /// Output folder.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Trial k of every payload runs the world seeded `seed + k`.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The unit config every unit runs (its index, start pose and endpoints are set per unit).
    #[arg(long, default_value = "configs/unit.toml", value_name = "FILE")]
    pub unit_config: PathBuf,
    /// An existing key file for the team; by default a fresh one is written to DIR/keys.toml.
    #[arg(long, value_name = "FILE")]
    pub keys: Option<PathBuf>,
    /// Longest mission, simulated seconds (at most an hour).
    #[arg(long, default_value_t = 90.0, value_name = "S")]
    pub max_seconds: f64,
    /// Replace the files of an earlier run in DIR (never an input of this one).
    #[arg(long)]
    pub force: bool,
    /// Extra arguments for unit i, e.g. `--unit-arg 1=--inject=motor:3@5` (repeatable): for
    /// fault drills.
    #[arg(long, value_name = "I=ARG")]
    pub unit_arg: Vec<String>,
    /// What each unit flies: the learned phase policies or the scripted IK controller, through
    /// the same gate, pipeline and clamp.
    #[arg(long, value_enum, default_value_t = ControllerKind::Learned)]
    pub controller: ControllerKind,
}

/// The daemon binary: beside this executable (cargo builds both into one folder), or
/// `MOONHAUL_UNIT_BIN`.
fn unit_binary() -> Result<PathBuf> {
    if let Some(path) = std::env::var_os("MOONHAUL_UNIT_BIN") {
        return Ok(PathBuf::from(path));
    }
    let exe = std::env::current_exe().context("locating this executable")?;
    let path = exe.with_file_name(format!("moonhaul-unit{}", std::env::consts::EXE_SUFFIX));
    if !path.is_file() {
        bail!(
            "{} not found: build it with `cargo build --release --bin moonhaul-unit`, or set \
             MOONHAUL_UNIT_BIN",
            path.display()
        );
    }
    Ok(path)
}

const SIGINT: i32 = 2;
const SIGTERM: i32 = 15;
/// How long a signalled process may take to hold and finish its log before it is killed.
const STOP_WAIT: Duration = Duration::from_secs(10);
/// How long the world may take to come up (its start file written).
const WORLD_UP_WAIT: Duration = Duration::from_secs(120);
/// How long the units may take to be heard by the operator console, none of them stopped.
const UNITS_HEARD_WAIT: Duration = Duration::from_secs(60);
/// Wall seconds a trial may take per simulated second of `--max-seconds`: a lockstep world on
/// a loaded machine runs a few times slower than real time, never twenty.
const WALL_PER_SIM_S: f64 = 20.0;

/// The longest a trial of `max_seconds` may take on the wall clock, start-up included, before
/// its processes are stopped and the trial fails by name.
pub fn trial_wall_limit(max_seconds: f64) -> Duration {
    WORLD_UP_WAIT + UNITS_HEARD_WAIT + Duration::from_secs_f64(max_seconds * WALL_PER_SIM_S)
}

/// A child process; its log file holds its stdout and stderr.
struct Proc {
    name: String,
    log: PathBuf,
    child: Child,
}

impl Proc {
    fn spawn(name: &str, mut command: Command, log: &Path) -> Result<Proc> {
        let file = std::fs::File::create(log)
            .with_context(|| format!("cannot create {}", log.display()))?;
        let child = command
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .with_context(|| format!("starting the {name}"))?;
        Ok(Proc {
            name: name.to_owned(),
            log: log.to_owned(),
            child,
        })
    }

    fn signal(&self, sig: i32) {
        // SAFETY-free: `kill` via the command line keeps this crate free of libc bindings.
        let _ = Command::new("kill")
            .arg(format!("-{sig}"))
            .arg(self.child.id().to_string())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
    }

    /// Its exit status, if it has exited.
    fn exited(&mut self) -> Result<Option<std::process::ExitStatus>> {
        self.child
            .try_wait()
            .with_context(|| format!("watching the {}", self.name))
    }

    /// Waits until `deadline`; then SIGKILL.
    fn wait_until(&mut self, deadline: Instant) -> Result<std::process::ExitStatus> {
        loop {
            if let Some(status) = self.exited()? {
                return Ok(status);
            }
            if Instant::now() >= deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                bail!(
                    "the {} did not exit within {:?} of its signal; killed",
                    self.name,
                    STOP_WAIT
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Why it failed, for a message: its exit status and the last error line of its log.
    fn failure(&self, status: std::process::ExitStatus) -> String {
        match last_error(&self.log) {
            Some(line) => format!("the {} exited ({status}): {line}", self.name),
            None => format!(
                "the {} exited ({status}); see {}",
                self.name,
                self.log.display()
            ),
        }
    }
}

/// The last `error: …` line a moonhaul process wrote to its log (both binaries end a failed
/// run with one), read from the log's last 64 KiB.
fn last_error(log: &Path) -> Option<String> {
    use std::io::{Read, Seek, SeekFrom};
    const TAIL: u64 = 64 * 1024;
    let mut file = std::fs::File::open(log).ok()?;
    let len = file.metadata().ok()?.len();
    file.seek(SeekFrom::Start(len.saturating_sub(TAIL))).ok()?;
    let mut tail = Vec::new();
    file.take(TAIL).read_to_end(&mut tail).ok()?;
    String::from_utf8_lossy(&tail)
        .lines()
        .rev()
        .find_map(|l| l.strip_prefix("error: ").map(str::to_owned))
}

/// A trial's processes. Dropped on any early return (an error, a signal), it stops them the
/// way a finished trial does: SIGTERM, so each holds and finishes its log, then waits
/// (bounded) and kills what is left. No process outlives the launcher's run.
#[derive(Default)]
struct Procs(Vec<Proc>);

impl Procs {
    /// Sends `sig` to every process still running, then waits for each, [`STOP_WAIT`] in all.
    /// Returns each one's success, in order.
    fn stop(&mut self, sig: i32) -> Vec<bool> {
        for p in &mut self.0 {
            if matches!(p.exited(), Ok(None)) {
                p.signal(sig);
            }
        }
        let deadline = Instant::now() + STOP_WAIT;
        self.0
            .iter_mut()
            .map(|p| match p.wait_until(deadline) {
                Ok(status) => status.success(),
                Err(e) => {
                    eprintln!("mission sim: {e:#}");
                    false
                }
            })
            .collect()
    }
}

impl Drop for Procs {
    fn drop(&mut self) {
        self.stop(SIGTERM);
    }
}

/// Sleeps `d`, unless a signal comes first: then it is passed on to `procs` (each holds and
/// finishes its log; waited for, bounded) and the run ends with an error.
async fn pause(signals: &mut Signals, procs: &mut Procs, d: Duration) -> Result<()> {
    tokio::select! {
        biased;
        why = signals.recv() => Err(interrupt(why, procs)),
        _ = tokio::time::sleep(d) => Ok(()),
    }
}

/// Passes the signal `why` on to `procs`, waits for them, and says so.
fn interrupt(why: &'static str, procs: &mut Procs) -> anyhow::Error {
    procs.stop(if why == "SIGINT" { SIGINT } else { SIGTERM });
    anyhow::anyhow!("interrupted by {why}: passed on to the world and the units, which stopped")
}

/// How one trial went, as the launcher saw it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TrialRun {
    pub payload: String,
    pub trial: u32,
    pub dir: PathBuf,
    pub wall_s: f64,
    pub world_ok: bool,
    pub units_ok: Vec<bool>,
}

/// Everything a trial needs that the whole run shares.
struct Launch<'a> {
    args: &'a SimArgs,
    exe: PathBuf,
    unit_bin: PathBuf,
    keys: PathBuf,
    unit_config: moonhaul_deploy::unit_config::UnitConfig,
    /// Per unit, the extra arguments of `--unit-arg`.
    unit_args: Vec<Vec<String>>,
}

/// The files one trial writes in `dir`, for a team of `team_size`.
fn trial_outputs(dir: &Path, team_size: usize) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = ["world.mcap", "world.log", "start.json"]
        .iter()
        .map(|f| dir.join(f))
        .collect();
    for i in 0..team_size {
        files.push(dir.join(format!("unit-{i}.mcap")));
        files.push(dir.join(format!("unit-{i}.log")));
    }
    files
}

fn trial_dir(out: &Path, payload: &PayloadArg, trial: u32) -> PathBuf {
    out.join(payload.name()).join(format!("trial-{trial}"))
}

/// `--unit-arg I=ARG` values per unit of a team of `team_size`.
fn unit_args(values: &[String], team_size: usize) -> Result<Vec<Vec<String>>> {
    let mut per_unit = vec![Vec::new(); team_size];
    for value in values {
        let Some((index, arg)) = value.split_once('=') else {
            bail!("--unit-arg {value:?}: expected I=ARG, e.g. 1=--inject=motor:3@5");
        };
        let i: usize = index
            .parse()
            .map_err(|_| anyhow::anyhow!("--unit-arg {value:?}: {index:?} is not a unit index"))?;
        let Some(args) = per_unit.get_mut(i) else {
            bail!(
                "--unit-arg {value:?}: there is no unit {i}; the team of {} has units 0 to {}",
                team_size,
                team_size - 1
            );
        };
        args.push(arg.to_owned());
    }
    Ok(per_unit)
}

pub async fn run(args: SimArgs) -> Result<Vec<TrialRun>> {
    // First: from now on a signal is passed on to the processes, never leaving them behind.
    let mut signals = Signals::install()?;
    if args.trials == 0 || args.trials > 100 {
        bail!("--trials {}: must be 1 to 100", args.trials);
    }
    if args.payload.is_empty() {
        bail!("--payload: name at least one payload");
    }
    check_max_seconds(args.max_seconds)?;
    let Some(last_seed) = args.seed.checked_add(u64::from(args.trials - 1)) else {
        bail!(
            "--seed {} with --trials {}: trial k runs seed + k, which overflows 2^64 - 1",
            args.seed,
            args.trials
        );
    };
    let unit_config = moonhaul_deploy::unit_config::UnitConfig::from_file(&args.unit_config)?;
    let unit_args = unit_args(&args.unit_arg, unit_config.team_size)?;
    // What the world will refuse, refused here with its reason before anything starts.
    let mut scene = SceneModel::new(
        SimConfig::load(WORLD_SIM_CONFIG).context("cannot load the simulator config")?,
    )
    .context("cannot build the simulated scene")?;
    let mut inputs = unit_config.inputs(&args.unit_config);
    inputs
        .add("simulator config", WORLD_SIM_CONFIG)
        .add("task config", WORLD_TASK_CONFIG);
    for payload in &args.payload {
        payload_arg::resolve(&mut scene, payload)?;
        if let PayloadArg::File(path) = payload {
            inputs.add("payload", path);
        }
    }
    if let Some(keys) = &args.keys {
        KeyFile::load(keys)?
            .check_matches(&unit_config.team_settings())
            .with_context(|| {
                format!(
                    "--keys {} does not fit the unit config {}",
                    keys.display(),
                    args.unit_config.display()
                )
            })?;
        inputs.add("key file", keys);
    }
    let out_file = |f: &str| args.out.join(f);
    let mut outputs = vec![out_file("summary.json"), out_file("mission_profile.png")];
    if args.keys.is_none() {
        outputs.push(out_file("keys.toml"));
    }
    for payload in &args.payload {
        for trial in 0..args.trials {
            outputs.extend(trial_outputs(
                &trial_dir(&args.out, payload, trial),
                unit_config.team_size,
            ));
        }
    }
    for output in &outputs {
        inputs.check_output("--out", output, args.force)?;
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("--out {}: cannot create the folder", args.out.display()))?;
    let keys_path = match &args.keys {
        Some(p) => p.clone(),
        None => {
            let path = out_file("keys.toml");
            KeyFile::generate(&unit_config.team, unit_config.team_size, 1)?
                .write_new(&path, true)?;
            path
        }
    };
    let launch = Launch {
        args: &args,
        exe: std::env::current_exe().context("locating this executable")?,
        unit_bin: unit_binary()?,
        keys: keys_path,
        unit_config,
        unit_args,
    };
    let mut runs = Vec::new();
    for payload in &args.payload {
        for trial in 0..args.trials {
            let name = payload.name();
            let dir = trial_dir(&args.out, payload, trial);
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
            eprintln!("mission sim: {name}, trial {trial} → {}", dir.display());
            let started = Instant::now();
            // No wrap: checked against the last trial's seed above.
            let seed = last_seed - u64::from(args.trials - 1 - trial);
            let (world_ok, units_ok) = trial_run(&launch, &mut signals, payload, seed, &dir)
                .await
                .with_context(|| format!("{name} trial {trial} ({})", dir.display()))?;
            eprintln!(
                "mission sim: {name}, trial {trial} done in {:.1} s of wall time",
                started.elapsed().as_secs_f64()
            );
            runs.push(TrialRun {
                payload: name,
                trial,
                dir,
                wall_s: started.elapsed().as_secs_f64(),
                world_ok,
                units_ok,
            });
        }
    }
    Ok(runs)
}

/// The simulator and task configs the world runs on (its defaults, which `mission sim` keeps).
const WORLD_SIM_CONFIG: &str = "configs/sim.toml";
const WORLD_TASK_CONFIG: &str = "configs/tasks.toml";

async fn trial_run(
    launch: &Launch<'_>,
    signals: &mut Signals,
    payload: &PayloadArg,
    seed: u64,
    dir: &Path,
) -> Result<(bool, Vec<bool>)> {
    let args = launch.args;
    let unit_config = &launch.unit_config;
    let wall_by = Instant::now() + trial_wall_limit(args.max_seconds);
    let port = free_loopback_port().context("finding a free loopback port")?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let start_file = dir.join("start.json");
    let _ = std::fs::remove_file(&start_file);
    let payload_text = match payload {
        PayloadArg::Named(_) => payload.name(),
        PayloadArg::File(path) => path.display().to_string(),
    };
    let mut world_cmd = Command::new(&launch.exe);
    world_cmd
        .args(["mission", "world", "--payload", &payload_text])
        .args(["--seed", &seed.to_string()])
        .args(["--team", &unit_config.team])
        .arg("--keys")
        .arg(&launch.keys)
        .args(["--listen", &endpoint])
        .args(["--sim", WORLD_SIM_CONFIG, "--tasks", WORLD_TASK_CONFIG])
        .arg("--log")
        .arg(dir.join("world.mcap"))
        .arg("--start-file")
        .arg(&start_file)
        .args(["--max-seconds", &args.max_seconds.to_string()]);
    if args.realtime {
        world_cmd.arg("--realtime");
    }
    if args.force {
        world_cmd.arg("--force");
    }
    // procs[0] is the world, procs[1 + i] unit i.
    let mut procs = Procs::default();
    procs
        .0
        .push(Proc::spawn("world", world_cmd, &dir.join("world.log"))?);
    let deadline = Instant::now() + WORLD_UP_WAIT;
    let start: StartInfo = loop {
        if let Ok(bytes) = std::fs::read(&start_file) {
            break serde_json::from_slice(&bytes)
                .with_context(|| format!("reading {}", start_file.display()))?;
        }
        if let Some(status) = procs.0[0].exited()? {
            bail!("{} before it was up", procs.0[0].failure(status));
        }
        if Instant::now() >= deadline {
            bail!("the world was not up within {} s", WORLD_UP_WAIT.as_secs());
        }
        pause(signals, &mut procs, Duration::from_millis(50)).await?;
    };
    if start.start_pose.len() != unit_config.team_size {
        bail!(
            "the world has {} units, the unit config's team {}",
            start.start_pose.len(),
            unit_config.team_size
        );
    }
    for (i, pose) in start.start_pose.iter().enumerate() {
        let mut cmd = Command::new(&launch.unit_bin);
        cmd.arg("--config")
            .arg(&args.unit_config)
            .args(["--hal", "sim"])
            .args([
                "--controller",
                match args.controller {
                    ControllerKind::Learned => "learned",
                    ControllerKind::Scripted => "scripted",
                },
            ])
            .arg("--keys")
            .arg(&launch.keys)
            .args(["--unit-index", &i.to_string()])
            .arg(format!(
                "--start-pose={},{},{}",
                pose.x_m, pose.y_m, pose.yaw_rad
            ))
            .args(["--connect", &endpoint])
            .args(["--listen", "tcp/127.0.0.1:0"])
            .arg("--log")
            .arg(dir.join(format!("unit-{i}.mcap")));
        if args.realtime {
            cmd.arg("--realtime");
        }
        if args.force {
            cmd.arg("--force");
        }
        cmd.args(&launch.unit_args[i]);
        procs.0.push(Proc::spawn(
            &format!("unit {i}"),
            cmd,
            &dir.join(format!("unit-{i}.log")),
        )?);
    }
    // The operator: wait until every unit is heard and none reports a safety stop (each
    // stops until it hears its peers), then start.
    let mut console = Console::open(&launch.keys, std::slice::from_ref(&endpoint)).await?;
    let heard_by = Instant::now() + UNITS_HEARD_WAIT;
    let mut world_ended = false;
    while !world_ended && (!console.all_heard() || console.first_stopped().is_some()) {
        tokio::select! {
            biased;
            why = signals.recv() => return Err(interrupt(why, &mut procs)),
            _ = console.listen(Duration::from_millis(100)) => {}
        }
        if Instant::now() >= heard_by {
            if let (true, Some((unit, reason))) = (console.all_heard(), console.first_stopped()) {
                bail!(
                    "unit {unit} still reported a safety stop ({reason:?}) {} s after start-up; \
                     see the unit-*.log in {}",
                    UNITS_HEARD_WAIT.as_secs(),
                    dir.display()
                );
            }
            bail!(
                "only {} of {} units were heard within {} s; see the unit-*.log in {}",
                console.units.len(),
                console.team_size(),
                UNITS_HEARD_WAIT.as_secs(),
                dir.display()
            );
        }
        for (k, p) in procs.0.iter_mut().enumerate() {
            if let Some(status) = p.exited()? {
                // The world's own end (its --max-seconds) with every unit heard but never
                // settled: a team that never starts, which the summary reports.
                if k == 0 && console.all_heard() {
                    world_ended = true;
                    break;
                }
                bail!("{} before the mission started", p.failure(status));
            }
        }
    }
    if world_ended {
        eprintln!("mission sim: the world ended before the team settled to start");
    }
    // The start, unless the world ends first (its --max-seconds, a team that never starts).
    if !world_ended {
        let start = operator::start(&mut console, Duration::from_secs(20));
        tokio::pin!(start);
        loop {
            tokio::select! {
                biased;
                why = signals.recv() => return Err(interrupt(why, &mut procs)),
                started = &mut start => {
                    if let Err(e) = started {
                        eprintln!("mission sim: {e:#}");
                    }
                    break;
                }
                _ = tokio::time::sleep(Duration::from_millis(50)) => {
                    if procs.0[0].exited()?.is_some() {
                        eprintln!("mission sim: the world ended before the team started");
                        break;
                    }
                }
            }
        }
    }
    // The world ends the mission; keep draining the console meanwhile.
    let world_status = loop {
        if let Some(status) = procs.0[0].exited()? {
            break status;
        }
        if Instant::now() >= wall_by {
            bail!(
                "the trial ran past its bound of {} s of wall time ({} x --max-seconds {} plus \
                 start-up); its processes were stopped",
                trial_wall_limit(args.max_seconds).as_secs(),
                WALL_PER_SIM_S,
                args.max_seconds
            );
        }
        console.poll();
        pause(signals, &mut procs, Duration::from_millis(50)).await?;
    };
    console.close().await;
    let world = procs.0.remove(0);
    let units_ok = procs.stop(SIGTERM);
    for (p, ok) in procs.0.iter_mut().zip(&units_ok) {
        if !ok {
            if let Ok(Some(status)) = p.exited() {
                eprintln!("mission sim: {}", p.failure(status));
            }
        }
    }
    let world_ok = world_status.success();
    if !world_ok {
        eprintln!("mission sim: {}", world.failure(world_status));
    }
    Ok((world_ok, units_ok))
}
