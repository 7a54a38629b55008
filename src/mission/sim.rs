//! `moonhaul mission sim`: a simulated mission of real processes. For every payload and trial
//! it starts one world process (`moonhaul mission world`) and one `moonhaul-unit` per unit on
//! the sim-backed hardware, all talking only over zenoh on loopback, starts the mission as the
//! operator, waits for the world to end it, stops the units (SIGTERM: they hold and flush their
//! logs) and finally summarizes the ground truth (`moonhaul log summary`).
//!
//! Layout of `--out DIR`: `keys.toml` (the mission's key file, mode 0600, unless `--keys` names
//! one), `<payload>/trial-<k>/{world.mcap, unit-<i>.mcap, start.json, world.log, unit-<i>.log}`,
//! `summary.json`, `mission_profile.png`.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use moonhaul_coord::auth::KeyFile;
use moonhaul_deploy::daemon::ControllerKind;
use moonhaul_deploy::network::free_loopback_port;

use super::operator::{self, Console};
use super::world::StartInfo;
use crate::payload_arg::PayloadArg;

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
    /// Longest mission, simulated seconds.
    #[arg(long, default_value_t = 90.0, value_name = "S")]
    pub max_seconds: f64,
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

/// A child process that is killed if it is still running when dropped.
struct Proc {
    name: String,
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
            child,
        })
    }

    fn signal(&self, sig: i32) {
        // SAFETY-free: `kill` via the command line keeps this crate free of libc bindings.
        let _ = Command::new("kill")
            .arg(format!("-{sig}"))
            .arg(self.child.id().to_string())
            .status();
    }

    /// Waits up to `timeout`; then SIGKILL.
    fn wait(&mut self, timeout: Duration) -> Result<std::process::ExitStatus> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if Instant::now() >= deadline {
                let _ = self.child.kill();
                let _ = self.child.wait();
                bail!(
                    "the {} did not exit within {:?}; killed",
                    self.name,
                    timeout
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
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

pub async fn run(args: SimArgs) -> Result<Vec<TrialRun>> {
    if args.trials == 0 || args.trials > 100 {
        bail!("--trials {}: must be 1 to 100", args.trials);
    }
    if args.payload.is_empty() {
        bail!("--payload: name at least one payload");
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("--out {}: cannot create the folder", args.out.display()))?;
    let unit_config = moonhaul_deploy::unit_config::UnitConfig::from_file(&args.unit_config)?;
    let keys_path = match &args.keys {
        Some(p) => p.clone(),
        None => {
            let path = args.out.join("keys.toml");
            KeyFile::generate(&unit_config.team, unit_config.team_size, 1)?
                .write_new(&path, true)?;
            path
        }
    };
    let unit_bin = unit_binary()?;
    let exe = std::env::current_exe().context("locating this executable")?;
    let mut runs = Vec::new();
    for payload in &args.payload {
        for trial in 0..args.trials {
            let name = payload.name();
            let dir = args.out.join(&name).join(format!("trial-{trial}"));
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
            eprintln!("mission sim: {name}, trial {trial} → {}", dir.display());
            let started = Instant::now();
            let (world_ok, units_ok) = trial_run(
                &args,
                &exe,
                &unit_bin,
                &keys_path,
                &unit_config,
                payload,
                args.seed + u64::from(trial),
                &dir,
            )
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

#[allow(clippy::too_many_arguments)]
async fn trial_run(
    args: &SimArgs,
    exe: &Path,
    unit_bin: &Path,
    keys: &Path,
    unit_config: &moonhaul_deploy::unit_config::UnitConfig,
    payload: &PayloadArg,
    seed: u64,
    dir: &Path,
) -> Result<(bool, Vec<bool>)> {
    let port = free_loopback_port().context("finding a free loopback port")?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let start_file = dir.join("start.json");
    let _ = std::fs::remove_file(&start_file);
    let payload_text = match payload {
        PayloadArg::Shipped(kind) => kind.name().to_owned(),
        PayloadArg::File(path) => path.display().to_string(),
    };
    let mut world_cmd = Command::new(exe);
    world_cmd
        .args(["mission", "world", "--payload", &payload_text])
        .args(["--seed", &seed.to_string()])
        .args(["--team", &unit_config.team])
        .args(["--listen", &endpoint])
        .arg("--log")
        .arg(dir.join("world.mcap"))
        .arg("--start-file")
        .arg(&start_file)
        .args(["--max-seconds", &args.max_seconds.to_string()]);
    if args.realtime {
        world_cmd.arg("--realtime");
    }
    let mut world = Proc::spawn("world", world_cmd, &dir.join("world.log"))?;
    let deadline = Instant::now() + Duration::from_secs(120);
    let start: StartInfo = loop {
        if let Ok(bytes) = std::fs::read(&start_file) {
            break serde_json::from_slice(&bytes)
                .with_context(|| format!("reading {}", start_file.display()))?;
        }
        if let Some(status) = world.child.try_wait()? {
            bail!(
                "the world exited ({status}) before it was up; see {}",
                dir.join("world.log").display()
            );
        }
        if Instant::now() >= deadline {
            bail!("the world was not up within 120 s");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    if start.start_pose.len() != unit_config.team_size {
        bail!(
            "the world has {} units, the unit config's team {}",
            start.start_pose.len(),
            unit_config.team_size
        );
    }
    let mut units = Vec::new();
    for (i, pose) in start.start_pose.iter().enumerate() {
        let mut cmd = Command::new(unit_bin);
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
            .arg(keys)
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
        for extra in &args.unit_arg {
            match extra.split_once('=') {
                Some((unit, arg)) if unit.parse::<usize>().ok() == Some(i) => {
                    cmd.arg(arg);
                }
                Some((unit, _)) if unit.parse::<usize>().is_ok() => {}
                _ => bail!("--unit-arg {extra:?}: expected I=ARG"),
            }
        }
        units.push(Proc::spawn(
            &format!("unit {i}"),
            cmd,
            &dir.join(format!("unit-{i}.log")),
        )?);
    }
    // The operator: wait for every unit, then start.
    let mut console = Console::open(keys, std::slice::from_ref(&endpoint)).await?;
    let heard_by = Instant::now() + Duration::from_secs(60);
    while !console.all_heard() {
        console.listen(Duration::from_millis(100)).await;
        if Instant::now() >= heard_by {
            bail!(
                "only {} of {} units were heard within 60 s; see the unit-*.log in {}",
                console.units.len(),
                console.team_size(),
                dir.display()
            );
        }
        if let Some(status) = world.child.try_wait()? {
            bail!("the world exited early ({status})");
        }
        for (i, unit) in units.iter_mut().enumerate() {
            if let Some(status) = unit.child.try_wait()? {
                bail!(
                    "unit {i} exited ({status}) before the mission started; see {}",
                    dir.join(format!("unit-{i}.log")).display()
                );
            }
        }
    }
    if let Err(e) = operator::start(&mut console, Duration::from_secs(20)).await {
        eprintln!("mission sim: {e:#}");
    }
    // The world ends the mission; keep draining the console meanwhile.
    let world_status = loop {
        if let Some(status) = world.child.try_wait()? {
            break status;
        }
        console.poll();
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    console.close().await;
    let mut units_ok = Vec::new();
    for unit in &mut units {
        unit.signal(15);
    }
    for unit in &mut units {
        units_ok.push(match unit.wait(Duration::from_secs(10)) {
            Ok(status) => status.success(),
            Err(e) => {
                eprintln!("mission sim: {e:#}");
                false
            }
        });
    }
    let world_ok = world_status.success();
    if !world_ok {
        eprintln!(
            "mission sim: the world exited with {world_status}; see {}",
            dir.join("world.log").display()
        );
    }
    Ok((world_ok, units_ok))
}
