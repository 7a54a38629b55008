//! `moonhaul can`: CAN bus tools. `emulate` runs the CiA 402 master against a unit's nine
//! emulated drives on the virtual bus, so a user sees (and can replay with can-utils) exactly
//! what the master will send before connecting real motors.

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context, Result};
use moonhaul_core::config;
use moonhaul_core::overwrite::RunInputs;
use moonhaul_core::state::{ARM_JOINTS, WHEEL_JOINTS};
use moonhaul_hal::can::cia402::Cia402State;
use moonhaul_hal::can::{candump, RecordingBus, UnitCanConfig};
use moonhaul_hal::{emulated_unit_on, ArmDrive, Drive, WheelDrive};

#[derive(clap::Subcommand)]
pub enum CanCommand {
    /// Bring up a unit's nine emulated CiA 402 drives on a virtual bus, run the master through
    /// start-up, enable every drive, run a short wheel-velocity and arm-position pattern,
    /// disable them and print a summary; optionally record all traffic as a candump log.
    Emulate {
        /// Unit CAN drive config (TOML), e.g. configs/unit_can.toml.
        #[arg(long, value_name = "FILE")]
        unit: PathBuf,
        /// Duration of the motion pattern, in simulated seconds (the run itself takes far less):
        /// at least one control cycle (the control period the unit config names), at most
        /// 600 s and 100000 control cycles.
        #[arg(
            long,
            allow_negative_numbers = true,
            default_value_t = 2.0,
            value_name = "S"
        )]
        seconds: f64,
        /// Write all bus traffic to this file in candump -L format
        /// (`(seconds.micros) can0 601#2B40600006000000`); written whole or not at all, and
        /// only over a regular file (never over a directory, FIFO or device).
        #[arg(long, value_name = "FILE")]
        record: Option<PathBuf>,
        /// Replace an existing `--record` file (never the unit's config or model).
        #[arg(long, requires = "record")]
        force: bool,
    },
}

pub fn run(cmd: CanCommand) -> Result<()> {
    match cmd {
        CanCommand::Emulate {
            unit,
            seconds,
            record,
            force,
        } => emulate(&unit, seconds, record.as_deref(), force),
    }
}

/// Wheel velocity amplitude of the pattern, rad/s, and arm joint amplitude, rad: small enough
/// for any joint range, large enough to show in the log.
const WHEEL_AMPLITUDE_RADPS: f64 = 1.0;
const ARM_AMPLITUDE_RAD: f64 = 0.2;

/// Longest motion pattern, simulated seconds: ten minutes of traffic, a log of ~37 MB at 50 Hz.
const MAX_PATTERN_S: f64 = 600.0;
/// Most control cycles of a pattern, whatever the unit's SYNC period: ~30 frames a cycle keep
/// even the longest run well inside the recording limit
/// ([`candump::MAX_RECORDED_FRAMES`]) and a few seconds of wall time.
const MAX_CYCLES: f64 = 100_000.0;

/// Refuses a `--record` target that the log could not replace: a directory, FIFO or device
/// (renaming over it would fail after the whole run, or silently replace the FIFO), a path
/// without a file name, or a folder that does not exist or is not writable. Checked before
/// the run so a bad path fails at once and nothing is written.
fn check_record_path(path: &Path) -> Result<()> {
    if path.file_name().is_none() {
        bail!("--record {}: not a file name", path.display());
    }
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    match std::fs::metadata(folder) {
        Ok(meta) if meta.is_dir() => {}
        Ok(_) => bail!(
            "--record {}: {} is not a folder",
            path.display(),
            folder.display()
        ),
        Err(e) => bail!(
            "--record {}: folder {}: {e}",
            path.display(),
            folder.display()
        ),
    }
    match std::fs::metadata(path) {
        Ok(meta) if !meta.is_file() => bail!(
            "--record {}: exists and is not a regular file (a directory, FIFO or device)",
            path.display()
        ),
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => bail!("--record {}: {e}", path.display()),
    }
    // The log is written to a temporary sibling and renamed: probe that the folder takes one.
    let probe = folder.join(format!(".moonhaul-record-probe-{}", std::process::id()));
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .with_context(|| {
            format!(
                "--record {}: cannot create files in {}",
                path.display(),
                folder.display()
            )
        })?;
    // Best effort: the probe is empty and hidden.
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

fn emulate(unit: &Path, seconds: f64, record: Option<&Path>, force: bool) -> Result<()> {
    if !(seconds.is_finite() && seconds > 0.0 && seconds <= MAX_PATTERN_S) {
        bail!("--seconds must be a number of seconds in (0, {MAX_PATTERN_S}], got {seconds:?}");
    }
    if let Some(path) = record {
        check_record_path(path)?;
    }
    let config = UnitCanConfig::from_file(unit)?;
    if let Some(path) = record {
        let mut inputs = RunInputs::new();
        inputs
            .add("CAN config", unit)
            .add("control config", config::resolve(unit, &config.control))
            .add("unit model", &config.unit_urdf);
        inputs.check_output("--record", path, force)?;
    }
    let period_s = config.sync_period_s;
    let cycles = (seconds / period_s).round();
    if cycles.is_nan() || cycles < 1.0 {
        bail!(
            "--seconds {seconds:?} is shorter than one control cycle ({period_s:?} s, the \
             control period of {})",
            unit.display()
        );
    }
    if cycles > MAX_CYCLES {
        bail!(
            "--seconds {seconds:?} at the {period_s:?} s SYNC period of {} is {cycles} control \
             cycles, more than the {MAX_CYCLES} allowed",
            unit.display()
        );
    }
    // In 1..=MAX_CYCLES, so the conversion is exact.
    let cycles = cycles as u64;
    // Bus time zero is "now", so the log's timestamps read as wall-clock times.
    let epoch = Duration::from_secs(
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default()
            .as_secs(),
    );
    let mut master = emulated_unit_on(&config, |bus| RecordingBus::new(bus, epoch))
        .context("start-up failed")?;
    master.enable().context("enabling the drives failed")?;
    let enabled = master
        .drive_states()
        .filter(|(_, s)| *s == Some(Cia402State::OperationEnabled))
        .count();
    let arm_start = master.read_arm()?.position_rad;
    for k in 1..=cycles {
        // One full sine period over the run: starts and ends at rest, at the start pose.
        let phase = (TAU * k as f64 / cycles as f64).sin();
        let wheels: [f64; WHEEL_JOINTS] = [
            WHEEL_AMPLITUDE_RADPS * phase,
            -WHEEL_AMPLITUDE_RADPS * phase,
        ];
        let arm: [f64; ARM_JOINTS] =
            std::array::from_fn(|j| arm_start[j] + ARM_AMPLITUDE_RAD * phase);
        master.command_velocity(&wheels)?;
        master.command_position(&arm)?;
        master
            .sync()
            .with_context(|| format!("control cycle {k} failed"))?;
    }
    let wheels = master.read_wheels()?;
    let arm = master.read_arm()?;
    master.shut_down().context("disabling the drives failed")?;

    let stats = master.stats();
    let frames = master.bus().log().len();
    if let Some(path) = record {
        candump::write_file(path, master.bus().log())
            .with_context(|| format!("cannot write candump log {}", path.display()))?;
    }
    outln!(
        "unit {} on virtual bus {}: {} drives, {} enabled, {} control cycles of {} ms",
        unit.display(),
        config.interface,
        config.drives().count(),
        enabled,
        stats.cycles,
        period_s * 1e3
    )?;
    outln!(
        "frames: {frames} ({} sent, {} received){}",
        stats.frames_sent,
        stats.frames_received,
        record.map_or(String::new(), |p| format!(", recorded to {}", p.display()))
    )?;
    outln!("final positions (rad):")?;
    let positions = wheels.position_rad.iter().chain(&arm.position_rad);
    for (drive, position) in config.drives().zip(positions) {
        outln!(
            "  {:<20} node {:>3}  {:+.4}",
            drive.joint,
            drive.node_id,
            position
        )?;
    }
    Ok(())
}
