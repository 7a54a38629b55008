//! `moonhaul log summary DIR`: the paper's hardware metrics ("Evaluation on Hardware") from the
//! ground truth of a mission directory, per trial and as mean ± 1σ per payload beside the
//! paper's figures, and the full-mission height profile.
//!
//! A mission directory (`moonhaul mission sim --out DIR`) holds `DIR/<payload>/trial-<k>/`
//! with `world.mcap` (the world's ground truth, like the paper's OptiTrack) and one
//! `unit-<i>.mcap` per unit. The metrics come from `world.mcap` alone: they are what an external
//! tracker measures, and the phase is the one the units reported to the world with their
//! commands (unit 0's, or any unit's when unit 0 sent none that step, or the last known). The
//! unit logs, where present, add what the clamp did and why a stopped mission stopped: only a
//! unit knows its own latched stop.
//!
//! # The metrics, and the choices the paper leaves open
//!
//! Times are from the trial's first Lift frame; heights are of the payload's underside above
//! the ground beneath it.
//!
//! - **Steady transport height**: the mean height over the transport phase without its first
//!   [`STEADY_SKIP_FRACTION`] (25 %). The paper does not define its window; its hardware lift
//!   took 20–30 s to converge, so the start of transport may still be settling.
//! - **Time to 95 %**: from the first Lift frame until the height first reaches
//!   [`RISE_FRACTION`] (0.95) × the steady height.
//! - **Final settled height**: the mean height over the last [`SETTLE_WINDOW_S`] (1 s) of the
//!   trial, after the phase returned to Idle following Place (only the part after Idle if that
//!   is shorter); if the mission never got there, the last second of the trial, flagged.
//! - **Phase durations** of Lift, Transport and Place, each from its first frame to the first
//!   frame of another phase (or the end of the log).
//! - **Completed**: the phases went Lift → Transport → Place → Idle in order; otherwise the
//!   reason (held in a phase until the log ended, or stopped to Idle in the middle). For a
//!   stop, the unit logs name the unit and its reason (`stop` in the JSON): the first unit that
//!   stopped on its own while a phase ran (a stop it raised — its own fault, a stale or refused
//!   peer, an agreement timeout — not one it heard from a peer or the operator), and what every
//!   other unit stopped for.
//!
//! Per payload: mean ± sample standard deviation (n − 1; 0 for a single trial) over the trials
//! that have the metric. Outputs `DIR/summary.json` (the `--json` output) and
//! `DIR/mission_profile.png`, published together.
//!
//! # Partial and damaged logs
//!
//! A log without its footer (a killed world, a copy cut short) is summarized from every frame
//! it holds — all but at most its last second — and says so. A frame stamped before the
//! previous one or more than [`MAX_FRAME_GAP_S`] after it (a clock jump: the mission's real
//! span ends there) is left out and named. A value no mission can have logged is an error for
//! its trial, naming the file, the frame and the field ([`check_frame`]): a non-finite number,
//! a payload height outside [`PAYLOAD_HEIGHT_RANGE_M`], a position beyond
//! [`MAX_WORLD_EXTENT_M`], a tilt outside 0–180°, an orientation that is not a unit
//! quaternion, a team whose size changes between frames, a tick that does not advance, or a
//! log spanning more than the longest mission a world runs ([`MAX_MISSION_S`]). So is a world
//! log none of whose frames carries a unit's phase: its phases cannot be timed. A trial that
//! cannot be summarized (an unreadable log, no frames, no lift) is named with the reason and
//! the others are still summarized; only when none can be is it an error.
//!
//! The unit logs expected are `unit-0.mcap` … one per unit of the world log's team. One that
//! is missing, damaged, of another kind, of another unit, or holding an impossible tick record
//! ([`check_tick`]: a t_max outside [0, 1], a negative or non-finite tracking d, time or ticks
//! running backwards) is left out of the clamp figures and the stop's reason, and named; so is
//! a `unit-<i>.mcap` beyond the team. Each trial's `unread` lists what was not read, in
//! `summary.json` and below the table.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_coord::message::{FaultKind, StopReason};
use moonhaul_coord::HoldReason;
use moonhaul_core::state::Phase;
use moonhaul_deploy::mission_log::{read_unit_log_contents, read_world_log_contents, LogEnd};
use moonhaul_deploy::record::{TickRecord, WorldFrame};
use plotters::prelude::*;

use moonhaul_coord::auth::MAX_KEY_FILE_UNITS;

use crate::mission::world::MAX_MISSION_S;
use serde::Serialize;

/// Fraction of the transport phase left out, at its start, of the steady-height mean.
pub const STEADY_SKIP_FRACTION: f64 = 0.25;
/// Fraction of the steady height whose first crossing ends the rise time.
pub const RISE_FRACTION: f64 = 0.95;
/// Length of the final-settled-height window, s.
pub const SETTLE_WINDOW_S: f64 = 1.0;
/// The reference height of the paper's hardware mission profile (its dashed line), m.
pub const REFERENCE_HEIGHT_M: f64 = 0.30;
/// Step of the common time grid the profile figure averages trials on, s.
const GRID_STEP_S: f64 = 0.1;
/// Most points of that grid: past [`GRID_STEP_S`] × this (2.8 h) the step grows instead.
const MAX_GRID_POINTS: usize = 100_000;
/// A frame stamped more than this after the previous frame read is beyond the mission's real
/// span (a clock jump, a corrupt stamp) and left out, s. The world logs every control step
/// (20 ms); a tracker silent this long has lost the mission.
pub const MAX_FRAME_GAP_S: f64 = 10.0;
/// Heights of a payload's underside above the ground beneath it that a mission can log, m:
/// below, more than a settling payload sinks into regolith or a tilted one reaches under its
/// footprint's centre; above, several times what any arm lifts (the paper's 0.75 m).
pub const PAYLOAD_HEIGHT_RANGE_M: (f64, f64) = (-0.5, 5.0);
/// Farthest a payload or base can be from the world's origin along any axis, m: the paper's
/// missions span metres; a coordinate beyond this is a corrupt log, not a long drive.
pub const MAX_WORLD_EXTENT_M: f64 = 10_000.0;
/// Deviation of a logged orientation's norm from 1 that is still a rotation (the world writes
/// unit quaternions; float rounding is ~1e-7).
const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

#[derive(clap::Subcommand)]
pub enum LogCommand {
    /// The paper's hardware metrics (steady transport height, time to 95 %, final settled
    /// height, phase durations, completion) of every trial in a mission directory, and mean ±
    /// 1σ per payload beside the paper's figures; writes DIR/summary.json and
    /// DIR/mission_profile.png.
    Summary {
        /// A mission directory: DIR/<payload>/trial-<k>/world.mcap (`moonhaul mission sim
        /// --out DIR`).
        dir: PathBuf,
        /// Print the summary as JSON (what summary.json holds) instead of tables.
        #[arg(long)]
        json: bool,
    },
    /// Mission logs as ROS 2 (Jazzy) rosbag2 bags with MCAP storage: per unit
    /// /<ns>/joint_states, /tf, /tf_static, /<ns>/robot_description, /diagnostics, and the
    /// world's /ground_truth/payload; for `ros2 bag play`, RViz, PlotJuggler.
    Ros2 {
        /// A mission directory (one bag per trial, at BAG/<payload>/trial-<k>/), one trial's
        /// folder, or one unit or world log (.mcap).
        input: PathBuf,
        /// The bag folder to write (must not exist unless --force).
        #[arg(long, value_name = "BAG")]
        out: PathBuf,
        /// Replace an existing BAG (never one that holds the input).
        #[arg(long)]
        force: bool,
    },
}

pub fn run(cmd: LogCommand) -> Result<()> {
    match cmd {
        LogCommand::Summary { dir, json } => summarize(&dir, json),
        LogCommand::Ros2 { input, out, force } => crate::log_ros2::export(&input, &out, force),
    }
}

/// Summarizes the mission directory `dir`: prints tables (or the JSON with `json`) and writes
/// `dir/summary.json` and `dir/mission_profile.png`.
pub fn summarize(dir: &Path, json: bool) -> Result<()> {
    let trials = find_trials(dir)?;
    let mut metrics = Vec::with_capacity(trials.len());
    let mut skipped = Vec::new();
    let mut profiles: BTreeMap<String, Vec<Profile>> = BTreeMap::new();
    for trial in &trials {
        let log = trial.log.display().to_string();
        let WorldTrial {
            samples,
            mut unread,
            team,
        } = match read_trial(&trial.log) {
            Ok(read) => read,
            Err(e) => {
                skipped.push(SkippedTrial {
                    payload: trial.payload.clone(),
                    trial: trial.trial,
                    log,
                    reason: format!("{e:#}"),
                });
                continue;
            }
        };
        let folder = trial.log.parent().unwrap_or(Path::new("."));
        let UnitLogs {
            clamp,
            stop,
            controller,
        } = read_unit_logs(folder, team, &mut unread);
        let m = match trial_metrics(&samples, stop.as_ref()) {
            Ok(m) => m,
            Err(e) => {
                let mut reason = format!("cannot summarize: {e:#}");
                for note in &unread {
                    let _ = write!(reason, "; {note}");
                }
                skipped.push(SkippedTrial {
                    payload: trial.payload.clone(),
                    trial: trial.trial,
                    log,
                    reason,
                });
                continue;
            }
        };
        profiles
            .entry(trial.payload.clone())
            .or_default()
            .push(Profile::new(&samples, &m));
        metrics.push(TrialSummary {
            payload: trial.payload.clone(),
            trial: trial.trial,
            log,
            metrics: m,
            stop,
            clamp,
            controller,
            unread,
        });
    }
    if metrics.is_empty() {
        let mut why = format!("no trial of {} could be summarized:", dir.display());
        for s in &skipped {
            let _ = write!(why, "\n  {}: {}", s.log, s.reason);
        }
        bail!(why);
    }
    let summary = Summary::new(dir, metrics, skipped);
    let text = serde_json::to_string_pretty(&summary).context("encoding the summary")?;
    write_outputs(dir, &text, &summary, &profiles)?;
    if json {
        outln!("{text}")?;
    } else {
        outln!("{}", summary.table())?;
        outln!(
            "wrote {} and {}",
            dir.join("summary.json").display(),
            dir.join("mission_profile.png").display()
        )?;
    }
    Ok(())
}

/// One trial's world log.
pub(crate) struct TrialDir {
    pub(crate) payload: String,
    pub(crate) trial: u32,
    /// The trial's `world.mcap`.
    pub(crate) log: PathBuf,
}

/// The trials of `dir` in payload order (sledge, box, bricks as in the paper, then others by
/// name) and trial number. Folders starting with `.` are skipped; every other folder is a
/// payload and must hold `trial-<k>` folders, each with its `world.mcap`.
pub(crate) fn find_trials(dir: &Path) -> Result<Vec<TrialDir>> {
    let subdirs = |path: &Path| -> Result<Vec<(String, PathBuf)>> {
        let mut out = Vec::new();
        let entries = std::fs::read_dir(path)
            .with_context(|| format!("cannot read the mission directory {}", path.display()))?;
        for entry in entries {
            let entry = entry.with_context(|| format!("cannot read {}", path.display()))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let is_dir = entry
                .file_type()
                .with_context(|| format!("cannot read {}", entry.path().display()))?
                .is_dir();
            if is_dir && !name.starts_with('.') {
                out.push((name, entry.path()));
            }
        }
        Ok(out)
    };
    let mut payloads = subdirs(dir)?;
    payloads.sort_by_key(|(name, _)| (paper_rank(name), name.clone()));
    let mut trials = Vec::new();
    for (payload, path) in payloads {
        let mut found: Vec<(u32, PathBuf)> = subdirs(&path)?
            .into_iter()
            .filter_map(|(name, p)| {
                let k = name.strip_prefix("trial-")?.parse().ok()?;
                Some((k, p))
            })
            .collect();
        if found.is_empty() {
            bail!(
                "{} has no trial-<k> folders (a mission directory holds <payload>/trial-<k>/world.mcap)",
                path.display()
            );
        }
        found.sort();
        for (trial, trial_dir) in found {
            let log = trial_dir.join("world.mcap");
            if !log.exists() {
                bail!(
                    "{} is missing (the trial's ground-truth log)",
                    log.display()
                );
            }
            trials.push(TrialDir {
                payload: payload.clone(),
                trial,
                log,
            });
        }
    }
    if trials.is_empty() {
        bail!(
            "{} holds no trials (expected <payload>/trial-<k>/world.mcap)",
            dir.display()
        );
    }
    Ok(trials)
}

/// The paper's hardware figures for one payload: mean and 1σ over its three trials.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PaperFigures {
    pub mass_kg: f64,
    pub steady_height_mm: [f64; 2],
    pub time_to_95_s: [f64; 2],
    pub settled_height_mm: [f64; 2],
}

/// The paper's "Evaluation on Hardware" results, by our payload names.
fn paper_figures(payload: &str) -> Option<PaperFigures> {
    let figures = |mass_kg, steady, rise, settled| PaperFigures {
        mass_kg,
        steady_height_mm: steady,
        time_to_95_s: rise,
        settled_height_mm: settled,
    };
    match payload {
        "sledge" => Some(figures(5.3, [272.6, 3.8], [21.02, 0.61], [8.1, 0.7])),
        "box" => Some(figures(7.5, [243.0, 5.5], [30.42, 0.76], [8.0, 1.0])),
        "bricks" => Some(figures(9.5, [209.1, 7.8], [31.18, 0.56], [12.1, 1.0])),
        _ => None,
    }
}

/// The paper's order of payloads (by mass); others after them.
fn paper_rank(payload: &str) -> u8 {
    match payload {
        "sledge" => 0,
        "box" => 1,
        "bricks" => 2,
        _ => 3,
    }
}

/// A world log as the metrics read it.
struct WorldTrial {
    samples: Vec<Sample>,
    /// What of it could not be read: its truncation, the frames left out.
    unread: Vec<String>,
    /// Units in the team, from its frames.
    team: usize,
}

/// The samples of the world log at `path`. An error when the log cannot be read, yields no
/// frame or holds one no mission can have logged.
fn read_trial(path: &Path) -> Result<WorldTrial> {
    let contents = read_world_log_contents(path)?;
    let mut unread = Vec::new();
    let truncated = match contents.end {
        LogEnd::Finished => None,
        LogEnd::Truncated { file_bytes } => Some(format!(
            "{} ends without its footer ({file_bytes} bytes: a killed writer, or a copy cut \
             short): read {} frames; its incomplete last chunk (at most a second) could not be",
            path.display(),
            contents.records.len()
        )),
    };
    let samples = match samples(&contents.records) {
        Ok((samples, left_out)) => {
            unread.extend(truncated);
            unread.extend(left_out);
            samples
        }
        Err(e) => {
            let e = match truncated {
                Some(t) => e.context(t),
                None => e,
            };
            // The trial's record names the log.
            return Err(e);
        }
    };
    let team = contents.records[0].base_position_m.len();
    Ok(WorldTrial {
        samples,
        unread,
        team,
    })
}

/// One frame of a trial as the metrics see it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Sample {
    /// Time since the log's first frame, s.
    t_s: f64,
    height_m: f64,
    phase: Phase,
    /// Every grasp is open: the payload was let go.
    released: bool,
}

/// Frames of one kind left out of a trial: how many, and the first.
#[derive(Default)]
struct LeftOut {
    count: usize,
    /// (tick, stamp µs) of the first.
    first: Option<(u64, u64)>,
}

impl LeftOut {
    fn add(&mut self, f: &WorldFrame) {
        self.count += 1;
        self.first.get_or_insert((f.tick, f.stamp_us));
    }

    fn note(&self, why: &str) -> Option<String> {
        let (tick, stamp_us) = self.first?;
        Some(format!(
            "{} frame{} {why} left out (the first: tick {tick}, stamped {stamp_us} µs)",
            self.count,
            if self.count == 1 { "" } else { "s" }
        ))
    }
}

/// The samples of `frames`: time from the first frame, the reported phase (unit 0's, else any
/// unit's, else the last one known; Idle before any); and what was left out, named: frames
/// stamped before the previous one read or more than [`MAX_FRAME_GAP_S`] after it. An error
/// for a log without frames, a frame [`check_frame`] refuses, ticks that do not advance, a
/// span beyond [`MAX_MISSION_S`], or a log in which no unit's phase was ever recorded.
fn samples(frames: &[WorldFrame]) -> Result<(Vec<Sample>, Vec<String>)> {
    let Some(first) = frames.first() else {
        bail!("empty log: no ground-truth frames");
    };
    let team = first.base_position_m.len();
    let max_gap_us = (MAX_FRAME_GAP_S * 1e6) as u64;
    let (mut backwards, mut beyond) = (LeftOut::default(), LeftOut::default());
    let mut phase = Phase::Idle;
    let mut any_phase = false;
    let mut last: Option<&WorldFrame> = None;
    let mut out = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let at = || {
            format!(
                "frame {} (tick {}, stamped {} µs)",
                k + 1,
                f.tick,
                f.stamp_us
            )
        };
        let last_us = last.map_or(first.stamp_us, |l| l.stamp_us);
        if f.stamp_us < last_us {
            backwards.add(f);
            continue;
        }
        if f.stamp_us - last_us > max_gap_us {
            beyond.add(f);
            continue;
        }
        check_frame(f, team).map_err(|why| anyhow::anyhow!("{}: {why}", at()))?;
        if let Some(l) = last.filter(|l| f.tick <= l.tick) {
            bail!(
                "{}: its tick does not advance past the frame before's ({}): the world logs \
                 each control step once",
                at(),
                l.tick
            );
        }
        let t_s = (f.stamp_us - first.stamp_us) as f64 * 1e-6;
        if t_s > MAX_MISSION_S + MAX_FRAME_GAP_S {
            bail!(
                "{}: {t_s:.1} s after the first frame, beyond the longest mission a world \
                 runs ({MAX_MISSION_S} s)",
                at()
            );
        }
        last = Some(f);
        let reported = f
            .unit_phase
            .first()
            .copied()
            .flatten()
            .or_else(|| f.unit_phase.iter().find_map(|p| *p));
        if let Some(p) = reported {
            phase = p;
            any_phase = true;
        }
        out.push(Sample {
            t_s,
            height_m: f.payload_height_m,
            phase,
            released: !f.grasp_closed.iter().any(|closed| *closed),
        });
    }
    if !any_phase {
        bail!(
            "none of its {} frames carries a unit's phase (every unit_phase is empty or null): \
             the world did not record the phases the units reported, so they cannot be timed",
            out.len()
        );
    }
    let beyond_why = format!(
        "stamped more than {MAX_FRAME_GAP_S} s after the frame before (beyond the mission's span)"
    );
    let left_out = [
        backwards.note("stamped before the frame before"),
        beyond.note(&beyond_why),
    ]
    .into_iter()
    .flatten()
    .collect();
    Ok((out, left_out))
}

/// Why `f` cannot be a frame of a mission of `team` units (the log's first frame's), naming
/// the field; `Ok` when every value is one a world can log.
pub(crate) fn check_frame(f: &WorldFrame, team: usize) -> Result<(), String> {
    if !(1..=MAX_KEY_FILE_UNITS).contains(&team) {
        return Err(format!(
            "the log's team has {team} units (a team has 1 to {MAX_KEY_FILE_UNITS})"
        ));
    }
    let per_unit = [
        ("base_position_m", f.base_position_m.len(), false),
        (
            "base_orientation_xyzw",
            f.base_orientation_xyzw.len(),
            false,
        ),
        ("unit_phase", f.unit_phase.len(), false),
        ("grasp_closed", f.grasp_closed.len(), false),
        // Absent from logs written before joints were recorded.
        ("wheel_position_rad", f.wheel_position_rad.len(), true),
        ("arm_position_rad", f.arm_position_rad.len(), true),
    ];
    for (field, len, may_be_absent) in per_unit {
        if len != team && !(may_be_absent && len == 0) {
            return Err(format!(
                "{field} has {len} entries; the log's team has {team} units"
            ));
        }
    }
    let (low, high) = PAYLOAD_HEIGHT_RANGE_M;
    let h = f.payload_height_m;
    if !(low..=high).contains(&h) {
        return Err(format!(
            "payload_height_m {h:?} is not a height a payload can be at ({low} to {high} m)"
        ));
    }
    let tilt = f.payload_tilt_deg;
    if !(0.0..=180.0).contains(&tilt) {
        return Err(format!(
            "payload_tilt_deg {tilt:?} is not a tilt from upright (0 to 180°)"
        ));
    }
    // (field, base index: `None` for the payload's); the name is written only when refused.
    let name = |field: &str, base: Option<usize>| match base {
        Some(i) => format!("{field}[{i}]"),
        None => field.to_owned(),
    };
    let positions = std::iter::once(("payload_position_m", None, &f.payload_position_m)).chain(
        (f.base_position_m.iter().enumerate()).map(|(i, p)| ("base_position_m", Some(i), p)),
    );
    for (field, base, p) in positions {
        if !p.iter().all(|c| c.abs() <= MAX_WORLD_EXTENT_M) {
            return Err(format!(
                "{} {p:?} is not a position in the world (each coordinate within \
                 ±{MAX_WORLD_EXTENT_M} m)",
                name(field, base)
            ));
        }
    }
    let orientations = std::iter::once((
        "payload_orientation_xyzw",
        None,
        &f.payload_orientation_xyzw,
    ))
    .chain(
        (f.base_orientation_xyzw.iter().enumerate())
            .map(|(i, q)| ("base_orientation_xyzw", Some(i), q)),
    );
    for (field, base, q) in orientations {
        let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        // NaN fails the range check too.
        if !(1.0 - QUATERNION_NORM_TOLERANCE..=1.0 + QUATERNION_NORM_TOLERANCE).contains(&norm) {
            return Err(format!(
                "{} {q:?} is not a rotation (a unit quaternion; its norm is {norm:?})",
                name(field, base)
            ));
        }
    }
    let joints = (f
        .wheel_position_rad
        .iter()
        .map(|j| ("wheel_position_rad", &j[..])))
    .chain(
        f.arm_position_rad
            .iter()
            .map(|j| ("arm_position_rad", &j[..])),
    );
    for (field, j) in joints {
        if !j.iter().all(|q| q.is_finite()) {
            return Err(format!("{field} {j:?} is not finite"));
        }
    }
    Ok(())
}

/// When each phase of the mission began, on the log's clock (s).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PhaseStarts {
    pub lift_s: f64,
    pub transport_s: Option<f64>,
    pub place_s: Option<f64>,
    /// Back to Idle after Place: the mission completed.
    pub idle_s: Option<f64>,
}

/// The metrics of one trial (the module docs define them).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrialMetrics {
    /// Length of the log, s.
    pub duration_s: f64,
    pub phase_starts: PhaseStarts,
    /// `None` when the mission never reached transport (or it was too short to average).
    pub steady_height_mm: Option<f64>,
    /// `None` without a steady height or when the height never reached 95 % of it.
    pub time_to_95_s: Option<f64>,
    pub settled_height_mm: f64,
    /// False when the settled height is of the trial's last second because the mission never
    /// returned to Idle after Place.
    pub settled_after_idle: bool,
    pub lift_s: f64,
    pub transport_s: Option<f64>,
    pub place_s: Option<f64>,
    pub completed: bool,
    /// Why the mission did not complete.
    pub incomplete: Option<String>,
}

/// The trial metrics of `samples` (non-empty, time non-decreasing); an error if no unit ever
/// reported Lift. `stop`, from the unit logs, says why a stopped mission stopped.
fn trial_metrics(samples: &[Sample], stop: Option<&TrialStop>) -> Result<TrialMetrics> {
    let Some(lift_at) = samples.iter().position(|s| s.phase == Phase::Lift) else {
        bail!("no unit ever reported the lift phase: the mission never started");
    };
    let end_s = samples.last().map_or(0.0, |s| s.t_s);
    const ORDER: [Phase; 4] = [Phase::Lift, Phase::Transport, Phase::Place, Phase::Idle];
    let mut starts = [Some(samples[lift_at].t_s), None, None, None];
    let mut stage = 0;
    // (the phase it was in, the phase it went to, when), if the order broke.
    let mut broke: Option<(Phase, Phase, f64)> = None;
    for s in &samples[lift_at..] {
        if stage == ORDER.len() - 1 {
            break;
        }
        if s.phase == ORDER[stage] {
            continue;
        }
        if s.phase == ORDER[stage + 1] {
            stage += 1;
            starts[stage] = Some(s.t_s);
        } else {
            broke = Some((ORDER[stage], s.phase, s.t_s));
            break;
        }
    }
    // Each phase ends where the next began, where the order broke, or at the end of the log.
    let span = |i: usize| -> Option<(f64, f64)> {
        let start = starts[i]?;
        let end = starts[i + 1].or(broke.map(|b| b.2)).unwrap_or(end_s);
        Some((start, end))
    };
    let (lift_start, lift_end) = span(0).unwrap_or((samples[lift_at].t_s, end_s));
    let transport = span(1);
    let place = span(2);
    // Back in Idle after Place is a completion only if the payload was let go: a safety stop
    // during the placement also ends in Idle, with the grasps still closed.
    let released = samples.last().is_some_and(|s| s.released);
    let completed = starts[3].is_some() && released;
    let why = stop.map(TrialStop::words);
    let incomplete = if completed {
        None
    } else if let (Some(at), false) = (starts[3], released) {
        Some(match &why {
            Some(why) => format!("stopped during place at {at:.2} s, grasps still closed: {why}"),
            None => format!(
                "stopped during place at {at:.2} s (phase went to idle, grasps still closed)"
            ),
        })
    } else if let Some((from, to, at)) = broke {
        Some(match (to, &why) {
            (Phase::Idle, Some(why)) => {
                format!("stopped during {} at {at:.2} s: {why}", from.name())
            }
            (Phase::Idle, None) => format!(
                "stopped during {} at {at:.2} s (phase went to idle)",
                from.name()
            ),
            _ => format!("left {} for {} at {at:.2} s", from.name(), to.name()),
        })
    } else {
        let held = format!(
            "held in {} until the log ended at {end_s:.2} s",
            ORDER[stage].name()
        );
        Some(match &why {
            Some(why) => format!("{held}; {why}"),
            None => held,
        })
    };

    let mean_height = |from_s: f64, to_s: f64, include_end: bool| -> Option<f64> {
        let (sum, n) = samples
            .iter()
            .filter(|s| s.t_s >= from_s && (s.t_s < to_s || (include_end && s.t_s <= to_s)))
            .fold((0.0, 0usize), |(sum, n), s| (sum + s.height_m, n + 1));
        (n > 0).then(|| sum / n as f64)
    };
    let steady_m = transport.and_then(|(start, end)| {
        let from = start + STEADY_SKIP_FRACTION * (end - start);
        // A transport that ran to the end of the log includes the last frame.
        mean_height(from, end, starts[2].is_none() && broke.is_none())
    });
    let time_to_95_s = steady_m.and_then(|steady| {
        samples[lift_at..]
            .iter()
            .find(|s| s.height_m >= RISE_FRACTION * steady)
            .map(|s| s.t_s - lift_start)
    });
    let settle_from = (end_s - SETTLE_WINDOW_S).max(starts[3].unwrap_or(f64::NEG_INFINITY));
    let settled_m =
        mean_height(settle_from, end_s, true).unwrap_or(samples[samples.len() - 1].height_m);
    Ok(TrialMetrics {
        duration_s: end_s,
        phase_starts: PhaseStarts {
            lift_s: lift_start,
            transport_s: starts[1],
            place_s: starts[2],
            idle_s: starts[3],
        },
        steady_height_mm: steady_m.map(|h| h * 1e3),
        time_to_95_s,
        settled_height_mm: settled_m * 1e3,
        settled_after_idle: starts[3].is_some(),
        lift_s: lift_end - lift_start,
        transport_s: transport.map(|(s, e)| e - s),
        place_s: place.map(|(s, e)| e - s),
        completed,
        incomplete,
    })
}

/// Mean and sample standard deviation over `n` values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stat {
    pub mean: f64,
    /// Sample standard deviation (n − 1); 0 for one value.
    pub std: f64,
    pub n: usize,
}

impl Stat {
    /// `None` for no values.
    fn of(values: impl IntoIterator<Item = f64>) -> Option<Stat> {
        let values: Vec<f64> = values.into_iter().collect();
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let std = if n > 1 {
            (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
        } else {
            0.0
        };
        Some(Stat { mean, std, n })
    }
}

#[derive(Debug, Serialize)]
struct TrialSummary {
    payload: String,
    trial: u32,
    log: String,
    #[serde(flatten)]
    metrics: TrialMetrics,
    /// Why the mission stopped, from the units' logs: the first unit that stopped on its own
    /// while a phase ran, and every unit's stop; `None` when no unit stopped (or the trial
    /// folder has no unit logs).
    stop: Option<TrialStop>,
    /// What the synchronization clamp did, from the units' logs (`unit-<i>.mcap` beside the
    /// world log); `None` when the trial folder has none.
    clamp: Option<ClampStats>,
    /// What flew the units, from their logs' `controller` metadata: `scripted`, `learned`, or
    /// each unit's (`unit 0 learned, unit 1 scripted`) when they differ; `None` when no unit
    /// log says.
    controller: Option<String>,
    /// What of the trial's logs could not be read: truncation, frames left out, unit logs.
    unread: Vec<String>,
}

/// A trial that could not be summarized, and why.
#[derive(Debug, Serialize)]
struct SkippedTrial {
    payload: String,
    trial: u32,
    log: String,
    reason: String,
}

/// The clamp over one trial's ticks that ran a phase policy (every unit pooled).
#[derive(Debug, Clone, Copy, Serialize)]
struct ClampStats {
    /// Ticks whose committed phase had a policy and no hold was requested.
    policy_ticks: u64,
    /// Mean t_max over them.
    mean_t_max: f64,
    /// Fraction issued less than the full step (t_max < 1).
    clamped_fraction: f64,
    /// Fraction where no step was admissible (the hold of eq. t_max's empty set).
    held_fraction: f64,
}

/// What a trial's unit logs say.
struct UnitLogs {
    /// `None` when the trial folder has no unit log.
    clamp: Option<ClampStats>,
    stop: Option<TrialStop>,
    controller: Option<String>,
}

/// Reads the unit logs of a trial folder of a team of `team` units (`unit-<i>.mcap`, i <
/// `team`), one at a time; what of them could not be read is added to `unread`, and a log that
/// is missing, unreadable or holds an impossible record is left out. A folder without any unit
/// log (ground truth alone) has no clamp figures and no notes.
fn read_unit_logs(folder: &Path, team: usize, unread: &mut Vec<String>) -> UnitLogs {
    const LEFT_OUT: &str = "left out of the clamp figures and the stop's reason";
    let mut tally = moonhaul_coord::ClampTally::default();
    let mut any = false;
    let mut stops = Vec::new();
    let paths: Vec<PathBuf> = (0..team)
        .map(|i| folder.join(format!("unit-{i}.mcap")))
        .collect();
    let strangers = strangers(folder, team);
    if strangers.is_empty() && !paths.iter().any(|p| p.exists()) {
        return UnitLogs {
            clamp: None,
            stop: None,
            controller: None,
        };
    }
    let mut controllers = Vec::new();
    for (i, path) in paths.iter().enumerate() {
        if !path.exists() {
            unread.push(format!(
                "{} is missing: unit {i} is {LEFT_OUT}",
                path.display()
            ));
            continue;
        }
        let contents = match read_unit_log_contents(path) {
            Ok(contents) => contents,
            Err(e) => {
                unread.push(format!("{e}: {LEFT_OUT}"));
                continue;
            }
        };
        if let Err(why) = check_ticks(i, &contents.records) {
            unread.push(format!("{}: {why}: {LEFT_OUT}", path.display()));
            continue;
        }
        if let LogEnd::Truncated { file_bytes } = contents.end {
            unread.push(format!(
                "{} ends without its footer ({file_bytes} bytes): read {} ticks",
                path.display(),
                contents.records.len()
            ));
        }
        any = true;
        if let Some(c) = contents.metadata.get("controller") {
            controllers.push((i, c.clone()));
        }
        for r in &contents.records {
            let running =
                r.phase.has_policy() && matches!(r.hold, None | Some(HoldReason::NoAdmissibleStep));
            if running {
                tally.record(r.t_max, r.hold);
            }
        }
        stops.extend(UnitStop::first(i, &contents.records));
    }
    unread.extend(strangers);
    UnitLogs {
        clamp: any.then(|| ClampStats {
            policy_ticks: tally.ticks,
            mean_t_max: tally.mean_t_max().unwrap_or(0.0),
            clamped_fraction: tally.clamped_fraction().unwrap_or(0.0),
            held_fraction: tally.no_step_fraction().unwrap_or(0.0),
        }),
        stop: TrialStop::of(stops),
        controller: agreed_controller(controllers),
    }
}

/// The controller every unit flew (unit index, name), or each unit's when they differ.
fn agreed_controller(per_unit: Vec<(usize, String)>) -> Option<String> {
    let (_, first) = per_unit.first()?;
    if per_unit.iter().all(|(_, c)| c == first) {
        return Some(first.clone());
    }
    let each: Vec<String> = per_unit
        .iter()
        .map(|(i, c)| format!("unit {i} {c}"))
        .collect();
    Some(each.join(", "))
}

/// The `unit-<i>.mcap` files of `folder` whose unit is not one of the team's, named.
fn strangers(folder: &Path, team: usize) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(folder) else {
        return Vec::new();
    };
    let mut out: Vec<(usize, String)> = entries
        .flatten()
        .filter_map(|e| {
            let name = e.file_name().into_string().ok()?;
            let i: usize = name
                .strip_prefix("unit-")?
                .strip_suffix(".mcap")?
                .parse()
                .ok()?;
            (i >= team).then(|| {
                let why = format!(
                    "{} is not read: the world log's team has {team} units (0 to {})",
                    e.path().display(),
                    team - 1
                );
                (i, why)
            })
        })
        .collect();
    out.sort();
    out.into_iter().map(|(_, why)| why).collect()
}

/// Why `records` cannot be unit `unit`'s log, naming the record and field: a record of
/// another unit, a t_max outside [0, 1], a tracking d that is negative or not finite, ticks
/// that do not advance or a clock that runs backwards.
pub(crate) fn check_ticks(unit: usize, records: &[TickRecord]) -> Result<(), String> {
    let mut last: Option<&TickRecord> = None;
    for (k, r) in records.iter().enumerate() {
        let problem = if r.unit != unit {
            Some(format!(" is unit {}'s, not unit {unit}'s", r.unit))
        } else if !(0.0..=1.0).contains(&r.t_max) {
            Some(format!(": t_max {:?} is outside [0, 1]", r.t_max))
        } else if let Some(d) = r.tracking_d.filter(|d| !(d.is_finite() && *d >= 0.0)) {
            Some(format!(": tracking_d {d:?} is not a distance"))
        } else {
            match last {
                Some(l) if r.tick <= l.tick => Some(format!(
                    ": its tick does not advance past the record before's ({})",
                    l.tick
                )),
                Some(l) if r.stamp_us < l.stamp_us => Some(format!(
                    ": stamped before the record before ({} µs)",
                    l.stamp_us
                )),
                _ => None,
            }
        };
        if let Some(problem) = problem {
            return Err(format!(
                "record {} (tick {}, stamped {} µs){problem}",
                k + 1,
                r.tick,
                r.stamp_us
            ));
        }
        last = Some(r);
    }
    Ok(())
}

/// One unit's first safety stop while a phase ran, from its log.
#[derive(Debug, Clone, PartialEq, Serialize)]
struct UnitStop {
    unit: usize,
    /// The phase it was in when it stopped.
    phase: Phase,
    /// The unit's clock at the stop (the world's time in a simulated mission), µs.
    stamp_us: u64,
    /// The stop as the log records it (the tick's `hold`, `safety_stop`).
    cause: StopReason,
    /// The latched fault's description (the record's `fault`), for a stop on the unit's own
    /// fault.
    fault: Option<String>,
    /// The stop in words, e.g. "latched a tracking fault (drives did not reach …)" or
    /// "stopped because unit 1 announced a stop".
    reason: String,
}

impl UnitStop {
    /// The first tick of `records` (unit `unit`'s log) that holds on a safety stop while the
    /// unit was in a phase, or stopped out of one (the stop's own tick may already be Idle).
    /// Stops in Idle (waiting for a peer before the start) are not the mission's.
    fn first(unit: usize, records: &[TickRecord]) -> Option<UnitStop> {
        let mut last = Phase::Idle;
        for (k, r) in records.iter().enumerate() {
            if let Some(HoldReason::SafetyStop(cause)) = r.hold {
                let phase = if r.phase == Phase::Idle {
                    last
                } else {
                    r.phase
                };
                if phase != Phase::Idle {
                    // The fault is recorded from the tick it latched on; it may be this one's
                    // successor when the stop came first.
                    let fault = matches!(cause, StopReason::Fault(_))
                        .then(|| records[k..].iter().find_map(|r| r.fault.as_deref()))
                        .flatten()
                        .map(str::to_owned);
                    return Some(UnitStop {
                        unit,
                        phase,
                        stamp_us: r.stamp_us,
                        cause,
                        reason: stop_words(cause, fault.as_deref()),
                        fault,
                    });
                }
            }
            last = r.phase;
        }
        None
    }
}

/// A stop in words, as the unit that took it would say it (after "unit N ").
fn stop_words(cause: StopReason, fault: Option<&str>) -> String {
    match cause {
        StopReason::Fault(kind) => {
            let kind = match kind {
                FaultKind::Drive => "drive",
                FaultKind::Sensor => "sensor",
                FaultKind::Policy => "policy",
                FaultKind::Tracking => "tracking",
            };
            match fault {
                Some(what) => format!("latched a {kind} fault ({what})"),
                None => format!("latched a {kind} fault"),
            }
        }
        StopReason::Operator => "stopped on the operator's command".into(),
        StopReason::PeerStop { unit } => format!("stopped because unit {unit} announced a stop"),
        StopReason::PeerStale { unit } => format!(
            "stopped because unit {unit} went stale (nothing fresh from it within the \
             staleness bound)"
        ),
        StopReason::PeerRejected { unit } => format!(
            "stopped because unit {unit}'s messages were refused (out of physical bounds or \
             not finite)"
        ),
        StopReason::PhaseTimeout => {
            "stopped because a phase change stayed pending past the agreement window".into()
        }
        StopReason::PhaseMismatch { unit } => {
            format!("stopped because unit {unit} reported a phase the barrier cannot explain")
        }
    }
}

/// Why a trial's mission stopped: the unit that stopped first on its own (a stop it raised,
/// not one it heard from a peer or the operator, which name their origin anyway), else the
/// first to stop; and each unit's own first stop.
#[derive(Debug, Clone, PartialEq, Serialize)]
struct TrialStop {
    #[serde(flatten)]
    first: UnitStop,
    /// Every unit's first stop (the first's included), in unit order.
    units: Vec<UnitStop>,
}

impl TrialStop {
    /// From each unit's first stop (in unit order); `None` when no unit stopped.
    fn of(stops: Vec<UnitStop>) -> Option<TrialStop> {
        let earliest = |raised: bool| {
            stops
                .iter()
                .filter(|s| !raised || s.cause.announce())
                .min_by_key(|s| (s.stamp_us, s.unit))
        };
        let first = earliest(true).or_else(|| earliest(false))?.clone();
        Some(TrialStop {
            first,
            units: stops,
        })
    }

    /// "unit 1 latched a tracking fault (…); unit 0 stopped because unit 1 announced a stop":
    /// the first stop, then the others.
    fn words(&self) -> String {
        let mut words = format!("unit {} {}", self.first.unit, self.first.reason);
        for s in self.units.iter().filter(|s| s.unit != self.first.unit) {
            let _ = write!(words, "; unit {} {}", s.unit, s.reason);
        }
        words
    }
}

#[derive(Debug, Serialize)]
struct PayloadSummary {
    payload: String,
    trials: usize,
    completed: usize,
    steady_height_mm: Option<Stat>,
    time_to_95_s: Option<Stat>,
    settled_height_mm: Option<Stat>,
    lift_s: Option<Stat>,
    transport_s: Option<Stat>,
    place_s: Option<Stat>,
    /// The paper's hardware figures for this payload, if it is one of the paper's.
    paper: Option<PaperFigures>,
}

/// How the metrics were computed, recorded beside them.
#[derive(Debug, Serialize)]
struct Method {
    steady_skip_fraction: f64,
    rise_fraction: f64,
    settle_window_s: f64,
    reference_height_m: f64,
    times_from: &'static str,
    phase_source: &'static str,
}

#[derive(Debug, Serialize)]
struct Summary {
    dir: String,
    method: Method,
    trials: Vec<TrialSummary>,
    /// Trials that could not be summarized.
    skipped: Vec<SkippedTrial>,
    payloads: Vec<PayloadSummary>,
}

impl Summary {
    fn new(dir: &Path, trials: Vec<TrialSummary>, skipped: Vec<SkippedTrial>) -> Self {
        let mut names: Vec<&str> = Vec::new();
        for t in &trials {
            if !names.contains(&t.payload.as_str()) {
                names.push(&t.payload);
            }
        }
        let payloads = names
            .iter()
            .map(|name| {
                let of = |f: fn(&TrialMetrics) -> Option<f64>| {
                    Stat::of(
                        trials
                            .iter()
                            .filter(|t| t.payload == *name)
                            .filter_map(|t| f(&t.metrics)),
                    )
                };
                let mine = trials.iter().filter(|t| t.payload == *name);
                PayloadSummary {
                    payload: (*name).to_owned(),
                    trials: mine.clone().count(),
                    completed: mine.filter(|t| t.metrics.completed).count(),
                    steady_height_mm: of(|m| m.steady_height_mm),
                    time_to_95_s: of(|m| m.time_to_95_s),
                    settled_height_mm: of(|m| Some(m.settled_height_mm)),
                    lift_s: of(|m| Some(m.lift_s)),
                    transport_s: of(|m| m.transport_s),
                    place_s: of(|m| m.place_s),
                    paper: paper_figures(name),
                }
            })
            .collect();
        Summary {
            dir: dir.display().to_string(),
            method: Method {
                steady_skip_fraction: STEADY_SKIP_FRACTION,
                rise_fraction: RISE_FRACTION,
                settle_window_s: SETTLE_WINDOW_S,
                reference_height_m: REFERENCE_HEIGHT_M,
                times_from: "durations and time to 95 % from the first lift frame; \
                             phase_starts on the log's clock from its first frame",
                phase_source: "unit 0's reported phase, else any unit's, else the last known",
            },
            trials,
            skipped,
            payloads,
        }
    }

    /// Per-trial rows, then per-payload mean ± 1σ beside the paper's hardware figures.
    fn table(&self) -> String {
        let opt =
            |v: Option<f64>, digits: usize| v.map_or("—".to_owned(), |v| format!("{v:.digits$}"));
        let stat = |s: &Option<Stat>, digits: usize| {
            s.map_or("—".to_owned(), |s| {
                format!("{:.digits$} ± {:.digits$}", s.mean, s.std)
            })
        };
        let paper = |p: Option<[f64; 2]>, digits: usize| {
            p.map_or("—".to_owned(), |[m, s]| {
                format!("{m:.digits$} ± {s:.digits$}")
            })
        };
        let mut out = String::new();
        let _ = writeln!(
            out,
            "{:<22} {:>11} {:>9} {:>12} {:>8} {:>13} {:>9}  completed",
            "trial",
            "steady (mm)",
            "t95 (s)",
            "settled (mm)",
            "lift (s)",
            "transport (s)",
            "place (s)"
        );
        for t in &self.trials {
            let m = &t.metrics;
            let settled = format!(
                "{:.1}{}",
                m.settled_height_mm,
                if m.settled_after_idle { "" } else { "*" }
            );
            let _ = writeln!(
                out,
                "{:<22} {:>11} {:>9} {:>12} {:>8.2} {:>13} {:>9}  {}",
                format!("{}/trial-{}", t.payload, t.trial),
                opt(m.steady_height_mm, 1),
                opt(m.time_to_95_s, 2),
                settled,
                m.lift_s,
                opt(m.transport_s, 2),
                opt(m.place_s, 2),
                match &m.incomplete {
                    None => "yes".to_owned(),
                    Some(why) => format!("no: {why}"),
                }
            );
        }
        for t in &self.trials {
            for note in &t.unread {
                let _ = writeln!(out, "{}/trial-{}: {note}", t.payload, t.trial);
            }
        }
        for s in &self.skipped {
            let _ = writeln!(
                out,
                "{}/trial-{}: not summarized: {}",
                s.payload, s.trial, s.reason
            );
        }
        if self.trials.iter().any(|t| !t.metrics.settled_after_idle) {
            let _ = writeln!(
                out,
                "* never returned to idle after place: the last {SETTLE_WINDOW_S} s of the trial"
            );
        }
        let _ = writeln!(
            out,
            "\nmean ± 1σ per payload (sample std over trials), beside the paper's hardware results\n\
             {:<14} {:>5} {:>17} {:>17} {:>15} {:>15} {:>15} {:>15} {:>14} {:>16} {:>14}",
            "payload",
            "n",
            "steady (mm)",
            "paper",
            "t95 (s)",
            "paper",
            "settled (mm)",
            "paper",
            "lift (s)",
            "transport (s)",
            "place (s)"
        );
        for p in &self.payloads {
            let figures = p.paper;
            let name = match figures {
                Some(f) => format!("{} {:.1} kg", p.payload, f.mass_kg),
                None => p.payload.clone(),
            };
            let _ = writeln!(
                out,
                "{:<14} {:>5} {:>17} {:>17} {:>15} {:>15} {:>15} {:>15} {:>14} {:>16} {:>14}",
                name,
                format!("{}/{}", p.completed, p.trials),
                stat(&p.steady_height_mm, 1),
                paper(figures.map(|f| f.steady_height_mm), 1),
                stat(&p.time_to_95_s, 2),
                paper(figures.map(|f| f.time_to_95_s), 2),
                stat(&p.settled_height_mm, 1),
                paper(figures.map(|f| f.settled_height_mm), 1),
                stat(&p.lift_s, 2),
                stat(&p.transport_s, 2),
                stat(&p.place_s, 2),
            );
        }
        let _ = write!(
            out,
            "n: completed/trials. steady: mean over transport without its first {:.0} %; \
             t95: first lift frame to {:.0} % of steady; settled: last {SETTLE_WINDOW_S} s after \
             idle.",
            STEADY_SKIP_FRACTION * 100.0,
            RISE_FRACTION * 100.0
        );
        if self.trials.iter().any(|t| t.clamp.is_some()) {
            let _ = write!(
                out,
                "\n\nsynchronization clamp, from the unit logs (ticks running a phase policy, all \
                 units)\n{:<22} {:>12} {:>11} {:>14} {:>12}  controller",
                "trial", "policy ticks", "mean t_max", "clamped (t<1)", "no step"
            );
            for t in &self.trials {
                if let Some(c) = &t.clamp {
                    let _ = write!(
                        out,
                        "\n{:<22} {:>12} {:>11.3} {:>13.1}% {:>11.1}%  {}",
                        format!("{}/trial-{}", t.payload, t.trial),
                        c.policy_ticks,
                        c.mean_t_max,
                        c.clamped_fraction * 100.0,
                        c.held_fraction * 100.0,
                        t.controller.as_deref().unwrap_or("unknown")
                    );
                }
            }
        }
        out
    }
}

/// A trial's height over time since its first Lift frame, and its phase boundaries on that
/// clock, for the profile figure.
struct Profile {
    /// (t since first lift s, height m), t ≥ 0.
    points: Vec<(f64, f64)>,
    transport_s: Option<f64>,
    place_s: Option<f64>,
    idle_s: Option<f64>,
}

impl Profile {
    fn new(samples: &[Sample], m: &TrialMetrics) -> Self {
        let t0 = m.phase_starts.lift_s;
        Profile {
            points: samples
                .iter()
                .filter(|s| s.t_s >= t0)
                .map(|s| (s.t_s - t0, s.height_m))
                .collect(),
            transport_s: m.phase_starts.transport_s.map(|t| t - t0),
            place_s: m.phase_starts.place_s.map(|t| t - t0),
            idle_s: m.phase_starts.idle_s.map(|t| t - t0),
        }
    }

    /// Height at `t_s` by linear interpolation; `None` outside the trial.
    fn at(&self, t_s: f64) -> Option<f64> {
        let i = self.points.partition_point(|p| p.0 < t_s);
        let after = *self.points.get(i)?;
        if after.0 == t_s || i == 0 {
            return (after.0 == t_s).then_some(after.1);
        }
        let before = self.points[i - 1];
        let w = (t_s - before.0) / (after.0 - before.0);
        Some(before.1 + w * (after.1 - before.1))
    }
}

/// The mean of `profiles` on a grid of [`GRID_STEP_S`] (or coarser, at most
/// [`MAX_GRID_POINTS`]) from the first Lift frame to the end of the longest; where some trials
/// have ended, the mean of those still running.
fn mean_profile(profiles: &[Profile]) -> Vec<(f64, f64)> {
    let end = profiles
        .iter()
        .filter_map(|p| p.points.last().map(|q| q.0))
        .fold(0.0, f64::max);
    let step = GRID_STEP_S.max(end / MAX_GRID_POINTS as f64);
    let steps = ((end / step).floor() as usize).min(MAX_GRID_POINTS);
    (0..=steps)
        .filter_map(|k| {
            let t = k as f64 * step;
            let (sum, n) = profiles
                .iter()
                .filter_map(|p| p.at(t))
                .fold((0.0, 0usize), |(s, n), h| (s + h, n + 1));
            (n > 0).then(|| (t, sum / n as f64))
        })
        .collect()
}

/// Writes `summary.json` and `mission_profile.png` as one group: a reader never sees a new
/// summary beside an old figure.
fn write_outputs(
    dir: &Path,
    json: &str,
    summary: &Summary,
    profiles: &BTreeMap<String, Vec<Profile>>,
) -> Result<()> {
    let json_path = dir.join("summary.json");
    let png_path = dir.join("mission_profile.png");
    let cannot_write = |path: &Path| format!("cannot write {}", path.display());
    let mut outputs = moonhaul_core::atomic_file::Group::new(|path: &Path, e: std::io::Error| {
        anyhow::Error::new(e).context(cannot_write(path))
    });
    outputs.stage(&json_path, |temp| {
        std::fs::write(temp, format!("{json}\n")).with_context(|| cannot_write(&json_path))
    })?;
    outputs.stage(&png_path, |temp| {
        profile_figure(temp, summary, profiles).with_context(|| cannot_write(&png_path))
    })?;
    outputs.publish()
}

const COLORS: [RGBColor; 4] = [BLUE, RED, RGBColor(0, 140, 0), RGBColor(150, 0, 150)];

/// The paper's full-mission figure: mean payload height per payload over mission time, the
/// phases shaded from the mean phase boundaries over all trials, the 0.30 m reference dashed.
fn profile_figure(
    path: &Path,
    summary: &Summary,
    profiles: &BTreeMap<String, Vec<Profile>>,
) -> Result<()> {
    moonhaul_core::plot_font::register().map_err(anyhow::Error::msg)?;
    let family = moonhaul_core::plot_font::FAMILY;
    // Curves in the summary's payload order.
    let curves: Vec<(&str, Vec<(f64, f64)>)> = summary
        .payloads
        .iter()
        .filter_map(|p| {
            let trials = profiles.get(&p.payload)?;
            Some((p.payload.as_str(), mean_profile(trials)))
        })
        .collect();
    let all: Vec<&Profile> = profiles.values().flatten().collect();
    let mean_of =
        |f: fn(&Profile) -> Option<f64>| Stat::of(all.iter().filter_map(|p| f(p))).map(|s| s.mean);
    let x_max = curves
        .iter()
        .flat_map(|c| c.1.last().map(|p| p.0))
        .fold(1.0, f64::max);
    let y_max = curves
        .iter()
        .flat_map(|c| c.1.iter().map(|p| p.1))
        .fold(REFERENCE_HEIGHT_M, f64::max)
        * 1.15;
    let y_min = curves
        .iter()
        .flat_map(|c| c.1.iter().map(|p| p.1))
        .fold(0.0, f64::min);

    let root = BitMapBackend::new(path, (1400, 700)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Full mission profile: mean payload height over trials",
            (family, 24),
        )
        .margin(16)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..x_max, y_min..y_max)?;
    chart
        .configure_mesh()
        .x_desc("mission time since lift start (s)")
        .y_desc("payload height (m)")
        .label_style((family, 15))
        .axis_desc_style((family, 16))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;

    // Phase spans from the mean boundaries; each ends where the next begins, or at the end.
    let transport = mean_of(|p| p.transport_s);
    let place = mean_of(|p| p.place_s);
    let idle = mean_of(|p| p.idle_s);
    let spans = [
        (
            "lift",
            Some(0.0),
            transport.or(Some(x_max)),
            RGBColor(255, 236, 204),
        ),
        (
            "transport",
            transport,
            place.or(Some(x_max)),
            RGBColor(214, 234, 248),
        ),
        (
            "place",
            place,
            idle.or(Some(x_max)),
            RGBColor(220, 240, 220),
        ),
    ];
    for (name, start, end, color) in spans {
        let (Some(start), Some(end)) = (start, end) else {
            continue;
        };
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(start, y_min), (end.min(x_max), y_max)],
                // Translucent, so the grid shows through.
                color.mix(0.75).filled(),
            )))?
            .label(format!("{name} (mean span)"))
            .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 18, y + 6)], color.filled()));
    }
    chart
        .draw_series(DashedLineSeries::new(
            [(0.0, REFERENCE_HEIGHT_M), (x_max, REFERENCE_HEIGHT_M)],
            10,
            6,
            BLACK.stroke_width(2),
        ))?
        .label(format!("{REFERENCE_HEIGHT_M:.2} m reference"))
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.stroke_width(2)));
    for ((name, points), color) in curves.iter().zip(COLORS.iter().cycle()) {
        let color = *color;
        let n = profiles.get(*name).map_or(0, Vec::len);
        let label = match paper_figures(name) {
            Some(f) => format!("{name} {:.1} kg (mean of {n})", f.mass_kg),
            None => format!("{name} (mean of {n})"),
        };
        chart
            .draw_series(LineSeries::new(
                points.iter().copied(),
                color.stroke_width(2),
            ))?
            .label(label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        // Below the transport plateau, clear of the curves and the reference line.
        .position(SeriesLabelPosition::LowerMiddle)
        .label_font((family, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples every 20 ms of `(until_s, phase)` segments, heights from `height(t)`.
    fn trial(segments: &[(f64, Phase)], height: impl Fn(f64) -> f64) -> Vec<Sample> {
        let end = segments.last().unwrap().0;
        let n = (end / 0.02).round() as usize;
        (0..=n)
            .map(|k| {
                let t = k as f64 * 0.02;
                let phase = segments
                    .iter()
                    .find(|(until, _)| t < *until - 1e-9)
                    .map_or(segments.last().unwrap().1, |s| s.1);
                // The grasps open once Idle follows Place.
                let released = phase == Phase::Idle
                    && segments
                        .iter()
                        .any(|(until, p)| *p == Phase::Place && *until <= t + 1e-9);
                Sample {
                    t_s: t,
                    height_m: height(t),
                    phase,
                    released,
                }
            })
            .collect()
    }

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    /// Idle 2 s, lift 2–32 s, transport 32–72 s, place 72–82 s, idle to 85 s.
    const MISSION: [(f64, Phase); 5] = [
        (2.0, Phase::Idle),
        (32.0, Phase::Lift),
        (72.0, Phase::Transport),
        (82.0, Phase::Place),
        (85.0, Phase::Idle),
    ];

    #[test]
    fn steady_height_rise_time_and_settled_height_of_a_known_profile() {
        // A linear ramp from 0 at lift start to 0.25 m at 27 s, flat (with a bump early in
        // transport that the 25 % skip leaves out), then down to 8 mm.
        let height = |t: f64| {
            if t < 2.0 {
                0.0
            } else if t < 27.0 {
                0.25 * (t - 2.0) / 25.0
            } else if t < 72.0 {
                if (32.0..40.0).contains(&t) {
                    0.20
                } else {
                    0.25
                }
            } else if t < 80.0 {
                0.25 - (0.25 - 0.008) * (t - 72.0) / 8.0
            } else {
                0.008
            }
        };
        let m = trial_metrics(&trial(&MISSION, height), None).unwrap();
        assert!(m.completed && m.incomplete.is_none(), "{m:?}");
        assert!(close(m.steady_height_mm.unwrap(), 250.0, 1e-9), "{m:?}");
        // 0.95 × 0.25 m is reached 0.95 × 25 s = 23.75 s into the ramp (the 20 ms grid).
        assert!(close(m.time_to_95_s.unwrap(), 23.76, 0.011), "{m:?}");
        assert!(
            close(m.settled_height_mm, 8.0, 1e-9) && m.settled_after_idle,
            "{m:?}"
        );
        assert!(close(m.lift_s, 30.0, 1e-9), "{m:?}");
        assert!(close(m.transport_s.unwrap(), 40.0, 1e-9), "{m:?}");
        assert!(close(m.place_s.unwrap(), 10.0, 1e-9), "{m:?}");
        assert_eq!(m.phase_starts.lift_s, 2.0);
        assert!(close(m.phase_starts.idle_s.unwrap(), 82.0, 1e-9));
    }

    #[test]
    fn steady_height_leaves_out_the_first_quarter_of_transport() {
        // Transport 32–72 s: heights 0.1 m for the first 10 s, 0.3 m after.
        let height = |t: f64| if t < 42.0 { 0.1 } else { 0.3 };
        let m = trial_metrics(&trial(&MISSION, height), None).unwrap();
        assert!(close(m.steady_height_mm.unwrap(), 300.0, 1e-9), "{m:?}");
    }

    #[test]
    fn a_stop_during_place_with_the_grasps_closed_is_not_completed() {
        let mut samples = trial(&MISSION, |_| 0.2);
        for s in &mut samples {
            s.released = false;
        }
        let m = trial_metrics(&samples, None).unwrap();
        assert!(!m.completed, "{m:?}");
        let why = m.incomplete.as_deref().unwrap();
        assert!(
            why.contains("stopped during place") && why.contains("closed"),
            "{why}"
        );
    }

    #[test]
    fn a_mission_held_in_transport_is_not_completed() {
        let segments = [
            (1.0, Phase::Idle),
            (20.0, Phase::Lift),
            (60.0, Phase::Transport),
        ];
        let m =
            trial_metrics(&trial(&segments, |t| if t < 1.0 { 0.0 } else { 0.2 }), None).unwrap();
        assert!(!m.completed, "{m:?}");
        let why = m.incomplete.as_deref().unwrap();
        assert!(why.contains("held in transport"), "{why}");
        assert_eq!(m.place_s, None);
        assert!(close(m.transport_s.unwrap(), 40.0, 1e-9), "{m:?}");
        // The steady window runs to the log's last frame.
        assert!(close(m.steady_height_mm.unwrap(), 200.0, 1e-9), "{m:?}");
        // Settled height: the last second, flagged.
        assert!(!m.settled_after_idle);
        assert!(close(m.settled_height_mm, 200.0, 1e-9));
    }

    #[test]
    fn a_stop_in_lift_is_reported_and_has_no_steady_height() {
        let segments = [(1.0, Phase::Idle), (10.0, Phase::Lift), (20.0, Phase::Idle)];
        let m = trial_metrics(&trial(&segments, |_| 0.05), None).unwrap();
        assert!(!m.completed);
        let why = m.incomplete.as_deref().unwrap();
        assert!(why.contains("stopped during lift at 10.00 s"), "{why}");
        assert!(close(m.lift_s, 9.0, 1e-9), "{m:?}");
        assert_eq!(
            (m.steady_height_mm, m.time_to_95_s, m.transport_s),
            (None, None, None)
        );
    }

    /// A unit's log: `(stamp µs, phase, hold, fault)` per tick.
    fn unit_log(
        unit: usize,
        ticks: &[(u64, Phase, Option<StopReason>, Option<&'static str>)],
    ) -> Vec<TickRecord> {
        ticks
            .iter()
            .map(|&(stamp_us, phase, stop, fault)| {
                let mut r = TickRecord::for_team(2);
                r.unit = unit;
                r.stamp_us = stamp_us;
                r.phase = phase;
                r.hold = stop.map(HoldReason::SafetyStop);
                r.fault = fault.map(Into::into);
                r
            })
            .collect()
    }

    const TRACKING: &str = "drives did not reach their command within hold.tracking_stop_ticks";

    /// Unit 1 latches a tracking fault in transport (its description recorded from the next
    /// tick); unit 0, which waited for its peer before the start, stops on unit 1's
    /// announcement a tick later.
    fn tracking_stop_logs() -> [Vec<TickRecord>; 2] {
        let stale = Some(StopReason::PeerStale { unit: 1 });
        let heard = Some(StopReason::PeerStop { unit: 1 });
        let own = Some(StopReason::Fault(FaultKind::Tracking));
        [
            unit_log(
                0,
                &[
                    (0, Phase::Idle, stale, None),
                    (20, Phase::Idle, None, None),
                    (40, Phase::Lift, None, None),
                    (60, Phase::Transport, None, None),
                    (80, Phase::Transport, None, None),
                    (100, Phase::Idle, heard, None),
                ],
            ),
            unit_log(
                1,
                &[
                    (40, Phase::Lift, None, None),
                    (60, Phase::Transport, None, None),
                    (80, Phase::Transport, own, None),
                    (100, Phase::Idle, own, Some(TRACKING)),
                ],
            ),
        ]
    }

    #[test]
    fn a_stop_names_the_unit_that_raised_it_and_what_the_others_heard() {
        let [u0, u1] = tracking_stop_logs();
        let stops = [UnitStop::first(0, &u0), UnitStop::first(1, &u1)];
        // The wait for a peer before the start is not the mission's stop.
        let heard = stops[0].clone().unwrap();
        assert_eq!((heard.phase, heard.stamp_us), (Phase::Transport, 100));
        let stop = TrialStop::of(stops.into_iter().flatten().collect()).unwrap();
        assert_eq!(
            (stop.first.unit, stop.first.phase, stop.first.stamp_us),
            (1, Phase::Transport, 80)
        );
        assert_eq!(stop.first.fault.as_deref(), Some(TRACKING));
        assert_eq!(
            stop.words(),
            format!(
                "unit 1 latched a tracking fault ({TRACKING}); unit 0 stopped because unit 1 \
                 announced a stop"
            )
        );
        let json = serde_json::to_value(&stop).unwrap();
        assert_eq!(json["unit"], 1);
        assert_eq!(json["phase"], "transport");
        assert_eq!(json["cause"]["fault"], "tracking");
        assert_eq!(json["units"][0]["cause"]["peer_stop"]["unit"], 1);

        // The world log saw the team go from transport to idle.
        let mission = [
            (1.0, Phase::Idle),
            (10.0, Phase::Lift),
            (20.0, Phase::Transport),
            (25.0, Phase::Idle),
        ];
        let m = trial_metrics(&trial(&mission, |_| 0.2), Some(&stop)).unwrap();
        let why = m.incomplete.unwrap();
        assert!(
            why.starts_with("stopped during transport at 20.00 s: unit 1 latched a tracking fault")
                && why.ends_with("unit 0 stopped because unit 1 announced a stop"),
            "{why}"
        );
        // A stop in place: idle with the grasps closed.
        let mut samples = trial(&MISSION, |_| 0.2);
        samples.iter_mut().for_each(|s| s.released = false);
        let why = trial_metrics(&samples, Some(&stop))
            .unwrap()
            .incomplete
            .unwrap();
        assert!(
            why.starts_with("stopped during place at 82.00 s, grasps still closed: unit 1 latched"),
            "{why}"
        );
    }

    #[test]
    fn a_stop_only_heard_is_named_when_its_origin_left_no_log() {
        // Unit 0's peer went silent (its log is lost): unit 0 raised the stop itself. A peer's
        // stop heard earlier on a skewed clock does not outrank it either.
        let stale = StopReason::PeerStale { unit: 1 };
        let raised = unit_log(
            0,
            &[
                (40, Phase::Lift, None, None),
                (60, Phase::Idle, Some(stale), None),
            ],
        );
        let heard = unit_log(
            2,
            &[
                (40, Phase::Lift, None, None),
                (
                    50,
                    Phase::Idle,
                    Some(StopReason::PeerStop { unit: 0 }),
                    None,
                ),
            ],
        );
        let stops = [UnitStop::first(0, &raised), UnitStop::first(2, &heard)];
        let stop = TrialStop::of(stops.iter().flatten().cloned().collect()).unwrap();
        assert_eq!((stop.first.unit, stop.first.cause), (0, stale));
        assert!(stop.first.reason.contains("unit 1 went stale"), "{stop:?}");
        // Only a heard stop: it is the one named.
        let stop = TrialStop::of(vec![stops[1].clone().unwrap()]).unwrap();
        assert_eq!(
            stop.words(),
            "unit 2 stopped because unit 0 announced a stop"
        );
        // No stop while a phase ran: nothing to name.
        let waiting = unit_log(0, &[(0, Phase::Idle, Some(stale), None)]);
        assert_eq!(UnitStop::first(0, &waiting), None);
        assert_eq!(TrialStop::of(Vec::new()), None);
    }

    #[test]
    fn a_trial_without_lift_is_an_error() {
        let samples = trial(&[(5.0, Phase::Idle)], |_| 0.0);
        let e = trial_metrics(&samples, None).unwrap_err().to_string();
        assert!(e.contains("no unit ever reported the lift phase"), "{e}");
    }

    fn frame(tick: u64, phases: Vec<Option<Phase>>) -> WorldFrame {
        WorldFrame {
            tick,
            stamp_us: 1_000_000 + tick * 20_000,
            payload_position_m: [0.0; 3],
            payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            payload_height_m: 0.1,
            payload_tilt_deg: 0.0,
            payload_ground_contact: false,
            base_position_m: vec![[0.0; 3]; 2],
            base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; 2],
            wheel_position_rad: vec![[0.0; 2]; 2],
            arm_position_rad: vec![[0.0; 7]; 2],
            unit_phase: phases,
            grasp_closed: vec![true; 2],
        }
    }

    #[test]
    fn phase_is_unit_0s_else_any_units_else_the_last_known() {
        let frames = [
            frame(0, vec![None, None]),
            frame(1, vec![None, Some(Phase::Lift)]),
            frame(2, vec![None, None]),
            frame(3, vec![Some(Phase::Transport), Some(Phase::Lift)]),
        ];
        let (s, left_out) = samples(&frames).unwrap();
        assert!(left_out.is_empty(), "{left_out:?}");
        let phases: Vec<Phase> = s.iter().map(|s| s.phase).collect();
        assert_eq!(
            phases,
            [Phase::Idle, Phase::Lift, Phase::Lift, Phase::Transport]
        );
        assert!(close(s[3].t_s, 0.06, 1e-12));
        assert!(samples(&[]).unwrap_err().to_string().contains("empty log"));
    }

    #[test]
    fn frames_outside_the_missions_span_are_left_out_and_named() {
        let mut frames: Vec<WorldFrame> = (0..10)
            .map(|k| frame(k, vec![Some(Phase::Lift); 2]))
            .collect();
        frames[2].stamp_us = 0;
        frames[4].stamp_us = u64::MAX / 2;
        frames[5].stamp_us = u64::MAX;
        let (s, left_out) = samples(&frames).unwrap();
        assert_eq!(s.len(), 7);
        assert!(close(s.last().unwrap().t_s, 0.18, 1e-12), "{s:?}");
        assert_eq!(left_out.len(), 2, "{left_out:?}");
        assert!(left_out[0].contains("1 frame stamped before") && left_out[0].contains("tick 2"));
        assert!(
            left_out[1].contains("2 frames stamped more than") && left_out[1].contains("tick 4"),
            "{left_out:?}"
        );
    }

    /// Every class of value no world can log, in the middle of a good log: an error naming the
    /// frame and the field, never a summary (a height of 1e300 once averaged to `inf`).
    #[test]
    fn an_impossible_frame_value_is_an_error_naming_the_frame_and_field() {
        type Bend = fn(&mut WorldFrame);
        let cases: [(&str, Bend); 15] = [
            ("payload_height_m", |f| f.payload_height_m = 1e300),
            ("payload_height_m", |f| f.payload_height_m = -3.0),
            ("payload_height_m", |f| f.payload_height_m = f64::NAN),
            ("payload_tilt_deg", |f| f.payload_tilt_deg = 400.0),
            ("payload_tilt_deg", |f| f.payload_tilt_deg = f64::INFINITY),
            ("payload_position_m", |f| f.payload_position_m[1] = 1e9),
            ("payload_position_m", |f| f.payload_position_m[2] = f64::NAN),
            ("base_position_m[1]", |f| f.base_position_m[1][0] = -1e7),
            ("payload_orientation_xyzw", |f| {
                f.payload_orientation_xyzw = [0.0, 0.0, 0.0, 2.0]
            }),
            ("base_orientation_xyzw[0]", |f| {
                f.base_orientation_xyzw[0] = [0.0; 4]
            }),
            ("arm_position_rad", |f| f.arm_position_rad[1][3] = f64::NAN),
            ("wheel_position_rad", |f| {
                f.wheel_position_rad[0][1] = f64::INFINITY
            }),
            ("unit_phase has 3 entries", |f| f.unit_phase.push(None)),
            ("grasp_closed has 1 entries", |f| {
                f.grasp_closed.pop();
            }),
            ("tick does not advance", |f| f.tick = 3),
        ];
        for (named, bend) in cases {
            let mut frames: Vec<WorldFrame> = (0..10)
                .map(|k| frame(k, vec![Some(Phase::Lift); 2]))
                .collect();
            // Frames after a huge stamp are stamped before it: the last one is bent.
            bend(&mut frames[9]);
            let e = samples(&frames).map(|_| ()).unwrap_err().to_string();
            assert!(
                e.contains(named) && e.contains("frame 10 (tick"),
                "{named}: {e}"
            );
        }
        // Stamps 9 s apart (each within the gap a frame may follow the one before by) add up
        // to a span no world runs: the frame past it is named.
        let long: Vec<WorldFrame> = (0..500)
            .map(|k| {
                let mut f = frame(k, vec![Some(Phase::Lift); 2]);
                f.stamp_us = k * 9_000_000;
                f
            })
            .collect();
        let e = samples(&long).map(|_| ()).unwrap_err().to_string();
        assert!(
            e.contains("frame 403 (tick 402") && e.contains("longest mission"),
            "{e}"
        );
        assert!(samples(&long[..400]).is_ok());
    }

    #[test]
    fn a_world_log_without_unit_phases_says_so() {
        let frames: Vec<WorldFrame> = (0..10).map(|k| frame(k, vec![None, None])).collect();
        let e = samples(&frames).map(|_| ()).unwrap_err().to_string();
        assert!(
            e.contains("none of its 10 frames carries a unit's phase")
                && !e.contains("never started"),
            "{e}"
        );
        let frames: Vec<WorldFrame> = (0..10).map(|k| frame(k, Vec::new())).collect();
        let e = samples(&frames).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("unit_phase has 0 entries"), "{e}");
    }

    #[test]
    fn an_impossible_tick_record_names_its_record_and_field() {
        let good = |unit| {
            unit_log(
                unit,
                &[
                    (0, Phase::Lift, None, None),
                    (20, Phase::Lift, None, None),
                    (40, Phase::Transport, None, None),
                ],
            )
            .into_iter()
            .enumerate()
            .map(|(k, mut r)| {
                r.tick = k as u64 + 1;
                r.t_max = 1.0;
                r.tracking_d = Some(0.2);
                r
            })
            .collect::<Vec<_>>()
        };
        assert_eq!(check_ticks(1, &good(1)), Ok(()));
        type Bend = fn(&mut [TickRecord]);
        let cases: [(&str, Bend); 7] = [
            ("is unit 0's, not unit 1's", |r| r[1].unit = 0),
            ("t_max 7.0 is outside", |r| r[2].t_max = 7.0),
            ("t_max NaN is outside", |r| r[2].t_max = f64::NAN),
            ("t_max -0.5 is outside", |r| r[2].t_max = -0.5),
            ("tracking_d -1.0 is not", |r| r[2].tracking_d = Some(-1.0)),
            ("tick does not advance", |r| r[2].tick = 2),
            ("stamped before the record before", |r| r[2].stamp_us = 10),
        ];
        for (named, bend) in cases {
            let mut records = good(1);
            bend(&mut records);
            let e = check_ticks(1, &records).unwrap_err();
            assert!(e.contains(named) && e.contains("record "), "{named}: {e}");
        }
    }

    #[test]
    fn the_profile_grid_is_bounded_whatever_the_span() {
        let profile = |points: Vec<(f64, f64)>| Profile {
            points,
            transport_s: None,
            place_s: None,
            idle_s: None,
        };
        let long = profile(vec![(0.0, 0.0), (1e12, 1.0)]);
        let mean = mean_profile(&[long]);
        assert!(mean.len() <= MAX_GRID_POINTS + 1, "{}", mean.len());
        assert!(close(mean.last().unwrap().0, 1e12, 1.0));
    }

    #[test]
    fn stats_use_the_sample_deviation() {
        let s = Stat::of([1.0, 2.0, 3.0]).unwrap();
        assert!(close(s.mean, 2.0, 1e-12) && close(s.std, 1.0, 1e-12) && s.n == 3);
        let one = Stat::of([4.0]).unwrap();
        assert_eq!((one.mean, one.std), (4.0, 0.0));
        assert_eq!(Stat::of([]), None);
    }

    #[test]
    fn profiles_average_on_a_common_grid() {
        let profile = |points: Vec<(f64, f64)>| Profile {
            points,
            transport_s: None,
            place_s: None,
            idle_s: None,
        };
        let a = profile(vec![(0.0, 0.0), (1.0, 1.0)]);
        let b = profile(vec![(0.0, 1.0), (0.5, 1.0)]);
        assert_eq!(a.at(0.25), Some(0.25));
        assert_eq!(b.at(0.75), None);
        let mean = mean_profile(&[a, b]);
        assert_eq!(mean.len(), 11);
        assert!(close(mean[2].1, (0.2 + 1.0) / 2.0, 1e-12), "{mean:?}");
        // After b ends, only a.
        assert!(close(mean[8].1, 0.8, 1e-12), "{mean:?}");
    }
}
