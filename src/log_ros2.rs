//! `moonhaul log ros2 INPUT --out BAG`: mission logs as rosbag2 bags (ROS 2 Jazzy, MCAP
//! storage), the topics a live unit publishes (`moonhaul_deploy::ros2::topics`) plus the
//! world's ground truth, so `ros2 bag play`, RViz and PlotJuggler replay a mission.
//!
//! INPUT is one of:
//! - a mission directory (`moonhaul mission sim --out DIR`): one bag per trial, at
//!   `BAG/<payload>/trial-<k>/`;
//! - one trial's folder (`world.mcap` and `unit-<i>.mcap`): one bag at `BAG`;
//! - one log file, a unit's or a world's: one bag at `BAG`.
//!
//! Every message is stamped, and logged in the bag, at its record's `stamp_us` (the team's
//! clock; the world's time in a simulated mission). `/tf_static` (one message for every unit)
//! and each `robot_description` are logged at the bag's first stamp.
//!
//! A log that cannot be read — not MCAP, a corrupt record, a record no mission writes — is an
//! error naming the file (and the record); nothing is written then. A log cut short (a killed
//! process's) is converted up to its last whole record, and said so. The bag is written into a
//! hidden sibling folder and renamed into place once complete: `BAG` never holds half a bag.
//! `BAG` must not exist unless `--force`, and never holds an input.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use moonhaul_deploy::mission_log::{
    read_attachments, read_unit_log_contents, read_world_log_contents, LogContents, LogEnd,
    LogError,
};
use moonhaul_deploy::record::{TickRecord, WorldFrame};
use moonhaul_deploy::ros2::msgs::{TfMessage, Time};
use moonhaul_deploy::ros2::{
    default_namespace, payload_pose, payload_topic, BagWriter, TopicId, UnitTopics,
};

use crate::log_cmd::{check_frame, check_ticks, find_trials};

/// Converts `input` into the bag (or bags) at `out`; prints what it wrote.
pub fn export(input: &Path, out: &Path, force: bool) -> Result<()> {
    let jobs = plan(input)?;
    check_output(input, out, force)?;
    let name = out
        .file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("--out {}: not a folder name", out.display()))?
        .to_owned();
    // Every log is read and checked before anything is written.
    let mut trials = Vec::with_capacity(jobs.len());
    for job in jobs {
        let logs = job.read()?;
        trials.push((job.subdir, logs));
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
        _ => PathBuf::from("."),
    };
    let staging = parent.join(format!(".tmp-{}-{name}", std::process::id()));
    let written = (|| -> Result<Vec<String>> {
        std::fs::create_dir(&staging)
            .with_context(|| format!("cannot create {}", staging.display()))?;
        let mut lines = Vec::new();
        for (subdir, logs) in &trials {
            let dir = staging.join(subdir);
            std::fs::create_dir_all(&dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
            let bag_name = if subdir.as_os_str().is_empty() {
                name.clone()
            } else {
                subdir
                    .file_name()
                    .and_then(|n| n.to_str())
                    .unwrap_or("bag")
                    .to_owned()
            };
            let summary = write_bag(&dir, &bag_name, logs)?;
            lines.push(format!("{}: {summary}", out.join(subdir).display()));
        }
        Ok(lines)
    })();
    let lines = match written.and_then(|lines| publish(&staging, out).map(|()| lines)) {
        Ok(lines) => lines,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
    };
    for line in lines {
        outln!("{line}")?;
    }
    Ok(())
}

/// One bag to write: where under `--out`, from which logs.
struct Job {
    /// Relative to `--out` (empty: `--out` itself).
    subdir: PathBuf,
    world: Option<PathBuf>,
    units: Vec<PathBuf>,
}

/// The logs of one bag, read and checked.
struct Logs {
    world: Option<(PathBuf, Vec<WorldFrame>)>,
    units: Vec<UnitLogData>,
}

struct UnitLogData {
    path: PathBuf,
    topics: UnitTopics,
    records: Vec<TickRecord>,
}

/// What to convert: the bags of a mission directory, a trial folder or a single log.
fn plan(input: &Path) -> Result<Vec<Job>> {
    let meta = std::fs::metadata(input)
        .with_context(|| format!("cannot read the input {}", input.display()))?;
    if meta.is_file() {
        // A world log or a unit log; which, its channels say.
        return Ok(vec![match read_world_log_contents(input) {
            Err(LogError::WrongKind { .. }) => Job {
                subdir: PathBuf::new(),
                world: None,
                units: vec![input.to_owned()],
            },
            _ => Job {
                subdir: PathBuf::new(),
                world: Some(input.to_owned()),
                units: Vec::new(),
            },
        }]);
    }
    if let Some(job) = trial_job(input, PathBuf::new())? {
        return Ok(vec![job]);
    }
    let mut jobs = Vec::new();
    for trial in find_trials(input)? {
        let folder = trial.log.parent().unwrap_or(input).to_owned();
        let subdir = PathBuf::from(&trial.payload).join(format!("trial-{}", trial.trial));
        jobs.extend(trial_job(&folder, subdir)?);
    }
    Ok(jobs)
}

/// The job of a trial folder: its `world.mcap` and `unit-<i>.mcap`; `None` when it holds none.
fn trial_job(folder: &Path, subdir: PathBuf) -> Result<Option<Job>> {
    let world = folder.join("world.mcap");
    let mut units: Vec<(usize, PathBuf)> = Vec::new();
    let entries = std::fs::read_dir(folder)
        .with_context(|| format!("cannot read the folder {}", folder.display()))?;
    for entry in entries {
        let entry = entry.with_context(|| format!("cannot read {}", folder.display()))?;
        let name = entry.file_name();
        let index = name
            .to_str()
            .and_then(|n| n.strip_prefix("unit-")?.strip_suffix(".mcap")?.parse().ok());
        if let Some(i) = index {
            units.push((i, entry.path()));
        }
    }
    units.sort();
    let world = world.is_file().then_some(world);
    if world.is_none() && units.is_empty() {
        return Ok(None);
    }
    Ok(Some(Job {
        subdir,
        world,
        units: units.into_iter().map(|(_, p)| p).collect(),
    }))
}

impl Job {
    fn read(&self) -> Result<Logs> {
        let world = match &self.world {
            Some(path) => {
                let contents = read_world_log_contents(path)?;
                let frames = checked_frames(path, contents)?;
                Some((path.clone(), frames))
            }
            None => None,
        };
        let mut units = Vec::with_capacity(self.units.len());
        for path in &self.units {
            units.push(read_unit(path)?);
        }
        Ok(Logs { world, units })
    }
}

fn note_truncation<T>(path: &Path, contents: &LogContents<T>, what: &str) {
    if let LogEnd::Truncated { file_bytes } = contents.end {
        eprintln!(
            "note: {} ends without its footer ({file_bytes} bytes: a killed writer, or a copy \
             cut short): converted its {} {what}; its incomplete last chunk could not be read",
            path.display(),
            contents.records.len()
        );
    }
}

fn checked_frames(path: &Path, contents: LogContents<WorldFrame>) -> Result<Vec<WorldFrame>> {
    note_truncation(path, &contents, "frames");
    if let Some(first) = contents.records.first() {
        let team = first.base_position_m.len();
        for (k, f) in contents.records.iter().enumerate() {
            check_frame(f, team).map_err(|why| {
                anyhow::anyhow!(
                    "{}: frame {} (tick {}, stamped {} µs): {why}",
                    path.display(),
                    k + 1,
                    f.tick,
                    f.stamp_us
                )
            })?;
        }
    }
    Ok(contents.records)
}

/// A unit log: its records, checked, and the topics of the unit model it carries.
fn read_unit(path: &Path) -> Result<UnitLogData> {
    let contents = read_unit_log_contents(path)?;
    note_truncation(path, &contents, "ticks");
    let Some(first) = contents.records.first() else {
        bail!(
            "{} holds no tick record: nothing to convert",
            path.display()
        );
    };
    let unit = first.unit;
    check_ticks(unit, &contents.records)
        .map_err(|why| anyhow::anyhow!("{}: {why}", path.display()))?;
    let attachments = read_attachments(path)?;
    let Some((name, urdf)) = attachments.records.first() else {
        bail!(
            "{} carries no unit URDF (a unit log attaches the URDF it ran with first)",
            path.display()
        );
    };
    let urdf = std::str::from_utf8(urdf)
        .map_err(|_| anyhow::anyhow!("{}: attachment {name} is not UTF-8 text", path.display()))?;
    let topics = UnitTopics::new(urdf, &default_namespace(unit)).map_err(|why| {
        anyhow::anyhow!(
            "{}: attachment {name} is not a unit URDF: {why}",
            path.display()
        )
    })?;
    Ok(UnitLogData {
        path: path.to_owned(),
        topics,
        records: contents.records,
    })
}

/// A record's stamp as a ROS time, or an error naming the file and record.
fn ros_time(path: &Path, what: &str, index: usize, stamp_us: u64) -> Result<Time> {
    Time::from_us(stamp_us).with_context(|| {
        format!(
            "{}: {what} {} is stamped {stamp_us} µs, past what a ROS time (int32 seconds) holds",
            path.display(),
            index + 1
        )
    })
}

/// Writes the bag of `logs` into `dir`; returns a one-line summary.
fn write_bag(dir: &Path, name: &str, logs: &Logs) -> Result<String> {
    // Everything in stamp order: (stamp µs, source: 0 world, 1 + i unit i, record index).
    let mut order: Vec<(u64, usize, usize)> = Vec::new();
    if let Some((_, frames)) = &logs.world {
        order.extend(frames.iter().enumerate().map(|(k, f)| (f.stamp_us, 0, k)));
    }
    for (i, u) in logs.units.iter().enumerate() {
        order.extend(
            u.records
                .iter()
                .enumerate()
                .map(|(k, r)| (r.stamp_us, i + 1, k)),
        );
    }
    order.sort_unstable();
    let Some(&(start_us, _, _)) = order.first() else {
        bail!("the logs hold no record: nothing to convert");
    };
    let first_log = logs
        .units
        .first()
        .map(|u| u.path.as_path())
        .or(logs.world.as_ref().map(|(p, _)| p.as_path()))
        .unwrap_or(Path::new("."));
    let start = ros_time(first_log, "record", 0, start_us)?;
    let start_ns = start_us * 1000;

    let mut bag = BagWriter::create(dir, name)?;
    let payload = match &logs.world {
        Some(_) => Some(bag.add_topic(&payload_topic())?),
        None => None,
    };
    struct UnitIds {
        joint_states: TopicId,
        tf: TopicId,
        diagnostics: TopicId,
    }
    let mut ids = Vec::with_capacity(logs.units.len());
    let mut tf_static = TfMessage::default();
    let mut tf_static_id = None;
    for u in &logs.units {
        let t = &u.topics;
        ids.push(UnitIds {
            joint_states: bag.add_topic(&t.joint_states)?,
            tf: bag.add_topic(&t.tf)?,
            diagnostics: bag.add_topic(&t.diagnostics)?,
        });
        let description = bag.add_topic(&t.robot_description)?;
        bag.write(description, start_ns, &t.robot_description())?;
        tf_static_id = Some(bag.add_topic(&t.tf_static)?);
        tf_static.transforms.extend(t.tf_static(start));
    }
    if let Some(id) = tf_static_id {
        bag.write(id, start_ns, &tf_static)?;
    }
    for (stamp_us, source, k) in order {
        let log_ns = stamp_us * 1000;
        if source == 0 {
            if let (Some((path, frames)), Some(id)) = (&logs.world, payload) {
                let stamp = ros_time(path, "frame", k, stamp_us)?;
                bag.write(id, log_ns, &payload_pose(&frames[k], stamp))?;
            }
            continue;
        }
        let (u, id) = (&logs.units[source - 1], &ids[source - 1]);
        let r = &u.records[k];
        let stamp = ros_time(&u.path, "record", k, stamp_us)?;
        bag.write(id.joint_states, log_ns, &u.topics.joint_state(r, stamp))?;
        bag.write(id.tf, log_ns, &u.topics.tf(r, stamp))?;
        bag.write(id.diagnostics, log_ns, &u.topics.diagnostics(r, stamp))?;
    }
    let mut summary = Vec::new();
    for (u, id) in logs.units.iter().zip(&ids) {
        summary.push(format!(
            "{} joint_states of {}",
            bag.count(id.joint_states),
            u.topics.namespace()
        ));
    }
    if let Some(id) = payload {
        summary.push(format!("{} ground-truth poses", bag.count(id)));
    }
    bag.finish()?;
    Ok(summary.join(", "))
}

/// Refuses an output that exists (unless `force`) or that holds the input.
fn check_output(input: &Path, out: &Path, force: bool) -> Result<()> {
    let input = input
        .canonicalize()
        .with_context(|| format!("cannot resolve {}", input.display()))?;
    if let Ok(out_real) = out.canonicalize() {
        if input.starts_with(&out_real) {
            bail!(
                "--out {}: it holds the input {}; refusing to write over an input",
                out.display(),
                input.display()
            );
        }
        if !force {
            bail!(
                "--out {}: it exists; pass --force to replace it",
                out.display()
            );
        }
        if !out_real.is_dir() {
            bail!("--out {}: exists and is not a folder", out.display());
        }
    } else if std::fs::symlink_metadata(out).is_ok() {
        bail!("--out {}: a link to nothing; refusing it", out.display());
    }
    Ok(())
}

/// Renames the complete `staging` folder to `out`, replacing an old `out` only once the new one
/// is whole.
fn publish(staging: &Path, out: &Path) -> Result<()> {
    if std::fs::symlink_metadata(out).is_ok() {
        let old = staging.with_file_name(format!(
            "{}-old",
            staging
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or(".tmp")
        ));
        std::fs::rename(out, &old)
            .with_context(|| format!("cannot move the old {} aside", out.display()))?;
        if let Err(e) = std::fs::rename(staging, out) {
            let _ = std::fs::rename(&old, out);
            return Err(e).with_context(|| format!("cannot rename the bag to {}", out.display()));
        }
        std::fs::remove_dir_all(&old)
            .with_context(|| format!("cannot remove the replaced {}", old.display()))?;
        return Ok(());
    }
    std::fs::rename(staging, out)
        .with_context(|| format!("cannot rename the bag to {}", out.display()))
}
