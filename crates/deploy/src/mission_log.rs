//! Mission logs as MCAP, written through the Foxglove SDK so a mission replays in Foxglove
//! (3-D included), and read back — truncated ones too — by `moonhaul log summary` and the tests.
//!
//! Two kinds of log:
//!
//! - [`UnitLog`], one per unit: topic `/unit{i}/tick`, one [`TickRecord`] per control tick as
//!   JSON (with a JSON schema, so Foxglove lists and plots its fields).
//! - [`WorldLog`], one per simulated world: topic `/world/frame`, one [`WorldFrame`] per world
//!   step as JSON (the ground truth, like the paper's OptiTrack); `/tf` as foxglove
//!   `FrameTransforms` (`world` → `payload`, `world` → `base{i}`); and `/scene`, a foxglove
//!   `SceneUpdate` drawing the payload as a cube locked to the `payload` frame.
//!
//! The log time of every message is the record's `stamp_us` (the team's clock, the world's time
//! in a simulated mission), not the wall clock, so logs of one mission line up in Foxglove.
//!
//! # What a killed process leaves
//!
//! Each log has its own Foxglove [`Context`], so two logs in one process never see each other's
//! channels. The file is written in uncompressed chunks held in memory until complete
//! (`disable_seeking`: the writer never leaves a placeholder chunk header on disk to patch
//! later), and a background thread finishes the open chunk and flushes the file every
//! [`FLUSH_PERIOD`]. A process killed at any moment therefore leaves a valid MCAP prefix —
//! possibly ending in one partly written chunk and without the summary and footer — that loses
//! at most the records of the last flush period. [`read_unit_log`] and [`read_world_log`] return
//! every message of such a file up to the first incomplete record.
//!
//! Write errors of the SDK's sink are only logged by the SDK itself (`tracing`); the flush that
//! follows fails on the same file, so an I/O error surfaces here at the latest one flush period
//! later, from the next [`UnitLog::write`] or from `finish`.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{self, BufWriter, Read};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use foxglove::schemas::{
    Color, CubePrimitive, FrameTransform, FrameTransforms, Pose, Quaternion, SceneEntity,
    SceneUpdate, Timestamp, Vector3,
};
use foxglove::{Channel, Context, McapWriteOptions, McapWriterHandle, RawChannel, Schema};
use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use mcap::McapError;
use moonhaul_core::input::{check_readable, InputError};
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::record::{TickRecord, WorldFrame};
use moonhaul_coord::message::RejectCounts;

/// How often the open chunk is finished and the file flushed: what a killed process may lose.
pub const FLUSH_PERIOD: Duration = Duration::from_secs(1);

/// Largest log file read, bytes (2 GiB). A unit logs ~2 kB per tick, ~100 kB/s at 50 Hz: about
/// 5 h of one unit, far beyond a mission; a larger file is refused before anything is read
/// (every message is decoded into memory).
pub const MAX_LOG_BYTES: u64 = 2 << 30;

/// Largest single record (message, schema, or whole chunk) the reader accepts, bytes. Chunks
/// are closed at 1 MiB and every flush period; a longer length field is garbage, not a
/// truncated file.
const MAX_RECORD_BYTES: usize = 64 << 20;

/// The payload cube is re-sent this often (log time, µs) so Foxglove draws it wherever a replay
/// is started or seeked to, not only after the first message.
const SCENE_REPUBLISH_US: u64 = 1_000_000;

/// The MCAP profile: none of ROS 1/ROS 2; plain Foxglove JSON and protobuf channels.
const PROFILE: &str = "";

/// The topic of unit `unit`'s tick records.
pub fn unit_topic(unit: usize) -> String {
    format!("/unit{unit}/tick")
}

/// The topic of the world's ground-truth frames.
pub const WORLD_TOPIC: &str = "/world/frame";
/// The topic of the world's transforms (foxglove `FrameTransforms`).
pub const TF_TOPIC: &str = "/tf";
/// The topic of the 3-D scene (foxglove `SceneUpdate`).
pub const SCENE_TOPIC: &str = "/scene";
/// Frame names in `/tf` and `/scene`.
pub const WORLD_FRAME_ID: &str = "world";
pub const PAYLOAD_FRAME_ID: &str = "payload";

/// The frame of unit `unit`'s wheel base.
pub fn base_frame_id(unit: usize) -> String {
    format!("base{unit}")
}

/// Why a mission log could not be written or read; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("cannot create mission log {}: {error}", path.display())]
    Create { path: PathBuf, error: String },
    #[error("cannot write mission log {}: {error}", path.display())]
    Write { path: PathBuf, error: String },
    #[error(
        "mission log {}: frame of tick {tick} has {bases} base poses, {orientations} base \
         orientations and {phases} unit phases; the log is of a team of {units}",
        path.display()
    )]
    FrameShape {
        path: PathBuf,
        tick: u64,
        bases: usize,
        orientations: usize,
        phases: usize,
        units: usize,
    },
    #[error(transparent)]
    Input(#[from] InputError),
    // The I/O error is part of the message, not a `source`, so a chain prints it once.
    #[error("cannot read mission log {}: {error}", path.display())]
    Read { path: PathBuf, error: io::Error },
    #[error("{} is not a valid MCAP mission log: record {record}: {reason}", path.display())]
    Corrupt {
        path: PathBuf,
        /// 1-based index of the record (counting those inside chunks) at fault.
        record: usize,
        reason: String,
    },
    #[error(
        "mission log {}: message {message} on {topic} (record {record}) is not a {kind}: {error}",
        path.display()
    )]
    BadMessage {
        path: PathBuf,
        topic: String,
        /// 1-based index of the message on its topic.
        message: usize,
        record: usize,
        kind: &'static str,
        error: String,
    },
    #[error("{} is not a {kind} log: it has no {expected} channel (topics: {topics:?})", path.display())]
    WrongKind {
        path: PathBuf,
        kind: &'static str,
        expected: String,
        topics: Vec<String>,
    },
}

/// One unit's mission log: `/unit{i}/tick`, one [`TickRecord`] per control tick.
pub struct UnitLog {
    file: LogFile,
    ticks: Arc<RawChannel>,
    /// The encoded record, reused so steady-state logging allocates little.
    buf: Vec<u8>,
}

impl UnitLog {
    /// Creates (or replaces) the log of unit `unit` at `path`.
    pub fn create(path: &Path, unit: usize) -> Result<UnitLog, LogError> {
        let file = LogFile::create(path, &[("unit", unit.to_string())])?;
        let ticks = file.json_channel(&unit_topic(unit), "moonhaul.TickRecord", &tick_schema())?;
        Ok(UnitLog {
            file,
            ticks,
            buf: Vec::with_capacity(4096),
        })
    }

    /// Logs one tick at its `stamp_us`. Fails if a flush of an earlier record failed.
    pub fn write(&mut self, r: &TickRecord) -> Result<(), LogError> {
        self.file.check()?;
        self.file
            .log_json(&self.ticks, r, r.stamp_us, &mut self.buf)
    }

    /// Finishes the open chunk and flushes the file now (the background flush does it every
    /// [`FLUSH_PERIOD`] anyway).
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.file.flush()
    }

    /// Writes the summary and footer, flushes and syncs the file.
    pub fn finish(self) -> Result<(), LogError> {
        self.file.finish()
    }
}

/// The world's mission log: ground truth on `/world/frame`, and `/tf` and `/scene` for 3-D.
pub struct WorldLog {
    file: LogFile,
    frames: Arc<RawChannel>,
    tf: Channel<FrameTransforms>,
    scene: Channel<SceneUpdate>,
    payload_size_m: [f64; 3],
    units: usize,
    /// Log time of the last scene update, µs (`None`: none sent yet).
    scene_sent_us: Option<u64>,
    buf: Vec<u8>,
}

impl WorldLog {
    /// Creates (or replaces) the world log at `path` for a payload of `payload_size_m` (the
    /// box that Foxglove draws, centered on the payload pose) carried by `units` units.
    pub fn create(
        path: &Path,
        payload_size_m: [f64; 3],
        units: usize,
    ) -> Result<WorldLog, LogError> {
        let size = payload_size_m.map(|s| format!("{s}"));
        let file = LogFile::create(
            path,
            &[
                ("units", units.to_string()),
                ("payload_size_m", size.join(",")),
            ],
        )?;
        let frames = file.json_channel(WORLD_TOPIC, "moonhaul.WorldFrame", &world_schema())?;
        let tf = file.context.channel_builder(TF_TOPIC).build();
        let scene = file.context.channel_builder(SCENE_TOPIC).build();
        Ok(WorldLog {
            file,
            frames,
            tf,
            scene,
            payload_size_m,
            units,
            scene_sent_us: None,
            buf: Vec::with_capacity(1024),
        })
    }

    /// Logs one world step at its `stamp_us`: the frame, its transforms and, the first time and
    /// every second after, the payload cube. Refuses a frame whose per-unit vectors do not
    /// match the team size the log was created for.
    pub fn write(&mut self, f: &WorldFrame) -> Result<(), LogError> {
        self.file.check()?;
        let units = self.units;
        if f.base_position_m.len() != units
            || f.base_orientation_xyzw.len() != units
            || f.unit_phase.len() != units
        {
            return Err(LogError::FrameShape {
                path: self.file.path.clone(),
                tick: f.tick,
                bases: f.base_position_m.len(),
                orientations: f.base_orientation_xyzw.len(),
                phases: f.unit_phase.len(),
                units,
            });
        }
        self.file
            .log_json(&self.frames, f, f.stamp_us, &mut self.buf)?;
        let log_time_ns = log_time_ns(f.stamp_us);
        let stamp = timestamp(f.stamp_us);
        let transform = |child: String, p: &[f64; 3], q: &[f64; 4]| FrameTransform {
            timestamp: Some(stamp),
            parent_frame_id: WORLD_FRAME_ID.to_owned(),
            child_frame_id: child,
            translation: Some(vector(p)),
            rotation: Some(quaternion(q)),
        };
        let mut transforms = Vec::with_capacity(1 + units);
        transforms.push(transform(
            PAYLOAD_FRAME_ID.to_owned(),
            &f.payload_position_m,
            &f.payload_orientation_xyzw,
        ));
        for (i, (p, q)) in f
            .base_position_m
            .iter()
            .zip(&f.base_orientation_xyzw)
            .enumerate()
        {
            transforms.push(transform(base_frame_id(i), p, q));
        }
        self.tf
            .log_with_time(&FrameTransforms { transforms }, log_time_ns);
        let due = match self.scene_sent_us {
            None => true,
            Some(sent) => f.stamp_us < sent || f.stamp_us - sent >= SCENE_REPUBLISH_US,
        };
        if due {
            self.scene
                .log_with_time(&payload_scene(self.payload_size_m, stamp), log_time_ns);
            self.scene_sent_us = Some(f.stamp_us);
        }
        Ok(())
    }

    /// Finishes the open chunk and flushes the file now.
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.file.flush()
    }

    /// Writes the summary and footer, flushes and syncs the file.
    pub fn finish(self) -> Result<(), LogError> {
        self.file.finish()
    }
}

/// The payload as a cube in its own frame, locked to it so it follows `/tf`.
fn payload_scene(size_m: [f64; 3], stamp: Timestamp) -> SceneUpdate {
    SceneUpdate {
        deletions: Vec::new(),
        entities: vec![SceneEntity {
            timestamp: Some(stamp),
            frame_id: PAYLOAD_FRAME_ID.to_owned(),
            id: "payload".to_owned(),
            // No lifetime: the entity stays until replaced by the next update.
            lifetime: None,
            frame_locked: true,
            cubes: vec![CubePrimitive {
                pose: Some(Pose {
                    position: Some(Vector3::default()),
                    orientation: Some(Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: 0.0,
                        w: 1.0,
                    }),
                }),
                size: Some(vector(&size_m)),
                color: Some(Color {
                    r: 0.85,
                    g: 0.55,
                    b: 0.2,
                    a: 0.9,
                }),
            }],
            ..Default::default()
        }],
    }
}

fn vector(v: &[f64; 3]) -> Vector3 {
    Vector3 {
        x: v[0],
        y: v[1],
        z: v[2],
    }
}

fn quaternion(q: &[f64; 4]) -> Quaternion {
    Quaternion {
        x: q[0],
        y: q[1],
        z: q[2],
        w: q[3],
    }
}

/// MCAP log time, ns since the epoch of the log's clock, from a record's stamp in µs.
fn log_time_ns(stamp_us: u64) -> u64 {
    stamp_us.saturating_mul(1000)
}

/// A foxglove timestamp from µs (saturating beyond the year 2106).
fn timestamp(stamp_us: u64) -> Timestamp {
    let sec = u32::try_from(stamp_us / 1_000_000).unwrap_or(u32::MAX);
    // < 10⁹, fits u32.
    let nsec = ((stamp_us % 1_000_000) * 1000) as u32;
    Timestamp::new_checked(sec, nsec).unwrap_or(Timestamp::MAX)
}

/// The file, its context and writer, and the thread that flushes it every [`FLUSH_PERIOD`].
struct LogFile {
    path: PathBuf,
    // Field order matters for drop: the flusher stops before the writer finishes, and the
    // writer finishes before the context (which holds its channels) goes.
    flusher: Option<Flusher>,
    writer: Arc<McapWriterHandle<BufWriter<File>>>,
    context: Arc<Context>,
}

/// The background flush: stops when its sender is dropped.
struct Flusher {
    stop: Option<mpsc::Sender<()>>,
    thread: Option<JoinHandle<()>>,
    /// The first flush error, reported by the next write.
    error: Arc<Mutex<Option<String>>>,
}

impl Drop for Flusher {
    fn drop(&mut self) {
        self.stop.take();
        if let Some(thread) = self.thread.take() {
            // A panic in the flusher is already reported by the thread; nothing to add here.
            let _ = thread.join();
        }
    }
}

impl LogFile {
    fn create(path: &Path, metadata: &[(&str, String)]) -> Result<Self, LogError> {
        let create_error = |error: String| LogError::Create {
            path: path.to_owned(),
            error,
        };
        // A log is replaced like any output, but only if it is a regular file: never through a
        // symlink, never into a FIFO or device (the check and the open are not atomic; a log
        // folder is not expected to be shared with an adversary).
        match std::fs::symlink_metadata(path) {
            Ok(m) if !m.file_type().is_file() => {
                return Err(create_error("it exists and is not a regular file".into()))
            }
            Ok(_) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(create_error(e.to_string())),
        }
        let file = File::create(path).map_err(|e| create_error(e.to_string()))?;
        let context = Context::new();
        let options = McapWriteOptions::new()
            .profile(PROFILE)
            .compression(None)
            .use_chunks(true)
            // Whole chunks are written at once: no placeholder header on disk if killed.
            .disable_seeking(true);
        let writer = context
            .mcap_writer_with_options(options)
            .create(BufWriter::new(file))
            .map_err(|e| create_error(e.to_string()))?;
        let metadata: BTreeMap<String, String> = metadata
            .iter()
            .map(|(k, v)| ((*k).to_owned(), v.clone()))
            .collect();
        writer
            .write_metadata("moonhaul", metadata)
            .and_then(|()| writer.flush())
            .map_err(|e| create_error(e.to_string()))?;
        let writer = Arc::new(writer);
        let flusher = Flusher::spawn(path, Arc::clone(&writer)).map_err(create_error)?;
        Ok(Self {
            path: path.to_owned(),
            flusher: Some(flusher),
            writer,
            context,
        })
    }

    fn json_channel(
        &self,
        topic: &str,
        schema_name: &str,
        schema: &serde_json::Value,
    ) -> Result<Arc<RawChannel>, LogError> {
        let schema = serde_json::to_vec(schema).map_err(|e| LogError::Create {
            path: self.path.clone(),
            error: format!("schema of {topic}: {e}"),
        })?;
        self.context
            .channel_builder(topic)
            .message_encoding("json")
            .schema(Schema::new(schema_name, "jsonschema", schema))
            .build_raw()
            .map_err(|e| LogError::Create {
                path: self.path.clone(),
                error: format!("channel {topic}: {e}"),
            })
    }

    /// Reports the background flush's first error, if any.
    fn check(&self) -> Result<(), LogError> {
        let Some(flusher) = &self.flusher else {
            return Ok(());
        };
        let error = flusher
            .error
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .clone();
        match error {
            Some(error) => Err(LogError::Write {
                path: self.path.clone(),
                error,
            }),
            None => Ok(()),
        }
    }

    fn log_json<T: Serialize>(
        &self,
        channel: &RawChannel,
        value: &T,
        stamp_us: u64,
        buf: &mut Vec<u8>,
    ) -> Result<(), LogError> {
        buf.clear();
        serde_json::to_writer(&mut *buf, value).map_err(|e| LogError::Write {
            path: self.path.clone(),
            error: format!("encoding a message for {}: {e}", channel.topic()),
        })?;
        channel.log_with_meta(
            buf,
            foxglove::PartialMetadata::with_log_time(log_time_ns(stamp_us)),
        );
        Ok(())
    }

    fn flush(&self) -> Result<(), LogError> {
        self.check()?;
        self.writer.flush().map_err(|e| LogError::Write {
            path: self.path.clone(),
            error: e.to_string(),
        })
    }

    fn finish(self) -> Result<(), LogError> {
        self.check()?;
        let LogFile {
            path,
            flusher,
            writer,
            context,
        } = self;
        // Stop the flusher first: it holds the other reference to the writer.
        drop(flusher);
        let write_error = |error: String| LogError::Write {
            path: path.clone(),
            error,
        };
        let writer = Arc::try_unwrap(writer)
            .map_err(|_| write_error("the writer is still shared".into()))?;
        let file = writer
            .close()
            .map_err(|e| write_error(e.to_string()))?
            .into_inner()
            .map_err(|e| write_error(e.error().to_string()))?;
        drop(context);
        file.sync_all().map_err(|e| write_error(e.to_string()))
    }
}

impl Flusher {
    fn spawn(path: &Path, writer: Arc<McapWriterHandle<BufWriter<File>>>) -> Result<Self, String> {
        let (stop, stopped) = mpsc::channel::<()>();
        let error = Arc::new(Mutex::new(None));
        let first_error = Arc::clone(&error);
        let name = format!(
            "log-flush {}",
            path.file_name().map_or("".into(), |n| n.to_string_lossy())
        );
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || loop {
                match stopped.recv_timeout(FLUSH_PERIOD) {
                    Err(RecvTimeoutError::Timeout) => {
                        if let Err(e) = writer.flush() {
                            let mut slot = first_error.lock().unwrap_or_else(|p| p.into_inner());
                            slot.get_or_insert_with(|| e.to_string());
                        }
                    }
                    // Stopped (the sender is dropped): the owner finishes the file.
                    Ok(()) | Err(RecvTimeoutError::Disconnected) => return,
                }
            })
            .map_err(|e| format!("cannot start the flush thread: {e}"))?;
        Ok(Self {
            stop: Some(stop),
            thread: Some(thread),
            error,
        })
    }
}

/// Every tick record of a unit log (`/unit{i}/tick`), in file order. A truncated log (a killed
/// daemon's) gives every record up to its first incomplete one.
pub fn read_unit_log(path: &Path) -> Result<Vec<TickRecord>, LogError> {
    read_json_topic(path, MAX_LOG_BYTES, &TopicFilter::unit())
}

/// Every ground-truth frame of a world log (`/world/frame`), in file order. A truncated log
/// gives every frame up to its first incomplete record.
pub fn read_world_log(path: &Path) -> Result<Vec<WorldFrame>, LogError> {
    read_json_topic(path, MAX_LOG_BYTES, &TopicFilter::world())
}

/// Which channels a reader decodes, and what to call them in errors.
struct TopicFilter {
    /// The kind of log, for errors: "unit", "world".
    kind: &'static str,
    /// The topic as the user knows it, for errors.
    expected: &'static str,
    /// The Rust type its messages decode into, for errors.
    type_name: &'static str,
    matches: fn(&str) -> bool,
}

impl TopicFilter {
    fn unit() -> Self {
        Self {
            kind: "unit",
            expected: "/unit{i}/tick",
            type_name: "TickRecord",
            matches: |topic| {
                topic
                    .strip_prefix("/unit")
                    .and_then(|rest| rest.strip_suffix("/tick"))
                    .is_some_and(|i| !i.is_empty() && i.bytes().all(|b| b.is_ascii_digit()))
            },
        }
    }

    fn world() -> Self {
        Self {
            kind: "world",
            expected: WORLD_TOPIC,
            type_name: "WorldFrame",
            matches: |topic| topic == WORLD_TOPIC,
        }
    }
}

/// Reads the JSON messages of the channels `filter` picks, with the rules of the readers above;
/// refuses a file larger than `max_bytes` or one that is not a regular file before reading.
///
/// A file that ends inside a record is taken as truncated (what a killed writer leaves) and its
/// complete prefix returned. Anything else that is wrong is garbage and an error naming the file
/// and the record: bad magic, a record or chunk longer than [`MAX_RECORD_BYTES`], a chunk whose
/// CRC does not match, a record that does not parse, a message on an undeclared channel, or a
/// message that does not decode.
fn read_json_topic<T: DeserializeOwned>(
    path: &Path,
    max_bytes: u64,
    filter: &TopicFilter,
) -> Result<Vec<T>, LogError> {
    check_readable(path, max_bytes)?;
    let read_error = |error| LogError::Read {
        path: path.to_owned(),
        error,
    };
    let corrupt = |record: usize, reason: String| LogError::Corrupt {
        path: path.to_owned(),
        record,
        reason,
    };
    let mut input = File::open(path).map_err(read_error)?.take(max_bytes + 1);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            // A truncated file has no end magic; a whole one ends at its footer either way.
            .with_skip_end_magic(true)
            // A chunk is checked whole before any of its records is trusted.
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    );
    // Channel id → its topic if the filter wants it.
    let mut channels: HashMap<u16, Option<String>> = HashMap::new();
    let mut topics: Vec<String> = Vec::new();
    let mut out = Vec::new();
    let mut record = 0usize;
    let mut read_total = 0u64;
    while let Some(event) = reader.next_event() {
        let event = match event {
            Ok(event) => event,
            // The file ends inside a record: a killed writer's last, incomplete chunk.
            Err(McapError::UnexpectedEof) => break,
            Err(e) => return Err(corrupt(record + 1, e.to_string())),
        };
        match event {
            LinearReadEvent::ReadRequest(need) => {
                let n = read_some(&mut input, reader.insert(need)).map_err(read_error)?;
                read_total += n as u64;
                if read_total > max_bytes {
                    return Err(InputError::TooLarge {
                        path: path.to_owned(),
                        max_bytes,
                    }
                    .into());
                }
                reader.notify_read(n);
            }
            LinearReadEvent::Record { opcode, data } => {
                record += 1;
                let parsed =
                    mcap::parse_record(opcode, data).map_err(|e| corrupt(record, e.to_string()))?;
                match parsed {
                    Record::Channel(channel) => {
                        let wanted = (filter.matches)(&channel.topic);
                        if wanted && channel.message_encoding != "json" {
                            return Err(corrupt(
                                record,
                                format!(
                                    "channel {} has message encoding {:?}, not json",
                                    channel.topic, channel.message_encoding
                                ),
                            ));
                        }
                        if !topics.contains(&channel.topic) {
                            topics.push(channel.topic.clone());
                        }
                        channels.insert(channel.id, wanted.then_some(channel.topic));
                    }
                    Record::Message { header, data } => match channels.get(&header.channel_id) {
                        Some(Some(topic)) => {
                            let value = serde_json::from_slice(&data).map_err(|e| {
                                LogError::BadMessage {
                                    path: path.to_owned(),
                                    topic: topic.clone(),
                                    message: out.len() + 1,
                                    record,
                                    kind: filter.type_name,
                                    error: e.to_string(),
                                }
                            })?;
                            out.push(value);
                        }
                        Some(None) => {}
                        None => {
                            return Err(corrupt(
                                record,
                                format!(
                                    "message on channel {}, which was never declared",
                                    header.channel_id
                                ),
                            ))
                        }
                    },
                    _ => {}
                }
            }
        }
    }
    // A file of another kind (a unit log given as the world log); one cut before its first
    // channel is just empty.
    if !topics.is_empty() && !topics.iter().any(|t| (filter.matches)(t)) {
        return Err(LogError::WrongKind {
            path: path.to_owned(),
            kind: filter.kind,
            expected: filter.expected.to_owned(),
            topics,
        });
    }
    Ok(out)
}

/// One `read` that retries when interrupted; 0 only at the end of the file.
fn read_some(input: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    loop {
        match input.read(buf) {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            other => return other,
        }
    }
}

/// JSON Schema (draft 2020-12) of [`TickRecord`] as serde writes it, for Foxglove's field list.
/// A test keeps its property names equal to the struct's fields.
fn tick_schema() -> serde_json::Value {
    use serde_json::json;
    let number = json!({ "type": "number" });
    let uint = json!({ "type": "integer", "minimum": 0 });
    let numbers = |n: usize| json!({ "type": "array", "items": { "type": "number" }, "minItems": n, "maxItems": n });
    let command = json!({
        "type": "object",
        "properties": {
            "wheel_velocity_radps": numbers(2),
            "arm_position_rad": numbers(7),
        }
    });
    let joints = |n: usize| {
        json!({
            "type": "object",
            "properties": { "position_rad": numbers(n), "velocity_radps": numbers(n) }
        })
    };
    let state = json!({
        "type": "object",
        "properties": {
            "wheels": joints(2),
            "arm": joints(7),
            "base_pose": {
                "type": "object",
                "properties": { "x_m": number, "y_m": number, "yaw_rad": number }
            },
            "base_velocity": {
                "type": "object",
                "properties": { "forward_mps": number, "yaw_rate_radps": number }
            }
        }
    });
    // The reject counters follow the struct (coord adds reasons as the protocol grows).
    let counts: serde_json::Map<String, serde_json::Value> =
        match serde_json::to_value(RejectCounts::default()) {
            Ok(serde_json::Value::Object(fields)) => {
                fields.into_iter().map(|(k, _)| (k, uint.clone())).collect()
            }
            _ => serde_json::Map::new(),
        };
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "moonhaul.TickRecord",
        "description": "One control tick of one unit (moonhaul-deploy record::TickRecord).",
        "type": "object",
        "properties": {
            "unit": uint,
            "tick": uint,
            "stamp_us": uint,
            "phase": phase_schema(),
            "hold": {
                "description": "Why the clamp held (null: it issued T(t_max)).",
                "type": ["string", "object", "null"]
            },
            "t_max": number,
            "distance": {
                "type": ["object", "null"],
                "properties": {
                    "value": number,
                    "binding": { "type": "object", "description": "{\"arm\": i} or {\"base\": i}" }
                }
            },
            "tracking_d": {
                "description": "This unit's d(U_{k-1}, Y_k) in tolerance units.",
                "type": ["number", "null"]
            },
            "sensed": state,
            "payload_height_estimate_m": { "type": ["number", "null"] },
            "press_m": {
                "description": "The largest height of a unit's sensed over its commanded end effector, the touchdown signal, m.",
                "type": ["number", "null"]
            },
            "goal_distance_m": number,
            "team_sensed": { "type": "array", "items": state.clone() },
            "team_previous": { "type": "array", "items": command.clone() },
            "grasp_force_n": { "type": ["number", "null"] },
            "grasp_open": { "type": "boolean" },
            "target": command,
            "issued": command,
            "peer_age_us": {
                "type": "array",
                "items": { "type": ["integer", "null"], "minimum": 0 }
            },
            "fault": { "type": ["string", "null"] },
            "rejected": { "type": "object", "properties": counts },
            "deadline_misses": uint,
            "work_us": uint,
        }
    })
}

/// JSON Schema of [`WorldFrame`]; a test keeps its property names equal to the struct's fields.
fn world_schema() -> serde_json::Value {
    use serde_json::json;
    let number = json!({ "type": "number" });
    let uint = json!({ "type": "integer", "minimum": 0 });
    let numbers = |n: usize| json!({ "type": "array", "items": { "type": "number" }, "minItems": n, "maxItems": n });
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "moonhaul.WorldFrame",
        "description": "One world step: ground truth (moonhaul-deploy record::WorldFrame).",
        "type": "object",
        "properties": {
            "tick": uint,
            "stamp_us": uint,
            "payload_position_m": numbers(3),
            "payload_orientation_xyzw": numbers(4),
            "payload_height_m": number,
            "payload_tilt_deg": number,
            "payload_ground_contact": { "type": "boolean" },
            "base_position_m": { "type": "array", "items": numbers(3) },
            "base_orientation_xyzw": { "type": "array", "items": numbers(4) },
            "unit_phase": {
                "type": "array",
                "items": { "anyOf": [phase_schema(), { "type": "null" }] }
            },
            "grasp_closed": { "type": "array", "items": { "type": "boolean" } },
        }
    })
}

fn phase_schema() -> serde_json::Value {
    serde_json::json!({ "type": "string", "enum": ["idle", "lift", "transport", "place"] })
}

#[cfg(test)]
mod tests {
    use super::*;
    use moonhaul_coord::HoldReason;
    use moonhaul_core::stacked::{StackedDistance, Subsystem};
    use moonhaul_core::state::{Phase, UnitCommand, UnitState};
    use std::collections::BTreeSet;
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    use std::time::Instant;

    fn tick(unit: usize, tick: u64) -> TickRecord {
        let mut sensed = UnitState::default();
        sensed.base_pose.x_m = tick as f64 * 0.01;
        sensed.arm.position_rad[3] = 0.25;
        let mut issued = UnitCommand::default();
        issued.arm_position_rad[1] = -0.5 + tick as f64 * 1e-3;
        TickRecord {
            unit,
            tick,
            stamp_us: tick * 20_000,
            phase: if tick < 10 { Phase::Idle } else { Phase::Lift },
            hold: (tick % 3 == 0).then_some(HoldReason::NoAdmissibleStep),
            t_max: 0.75,
            distance: Some(StackedDistance {
                value: 0.4,
                binding: Subsystem::Base(1),
            }),
            tracking_d: (tick > 1).then_some(0.1),
            sensed,
            payload_height_estimate_m: (tick > 10).then_some(0.01 * tick as f64),
            press_m: Some(-0.001),
            goal_distance_m: 2.0,
            team_sensed: vec![sensed, UnitState::default()],
            team_previous: vec![issued, UnitCommand::default()],
            grasp_force_n: Some(12.5),
            grasp_open: false,
            target: issued,
            issued,
            peer_age_us: vec![None, Some(20_000)],
            fault: (tick == 7).then(|| "drive 3: following error".into()),
            rejected: RejectCounts {
                stale: tick / 5,
                ..Default::default()
            },
            deadline_misses: 1,
            work_us: 350,
        }
    }

    fn frame(tick: u64, units: usize) -> WorldFrame {
        let t = tick as f64 * 0.02;
        WorldFrame {
            tick,
            stamp_us: tick * 20_000,
            payload_position_m: [0.1 * t, 0.0, 0.2 + 0.01 * t],
            payload_orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            payload_height_m: 0.01 * t,
            payload_tilt_deg: 0.5,
            payload_ground_contact: tick == 0,
            base_position_m: (0..units).map(|i| [0.1 * t, i as f64 - 0.5, 0.1]).collect(),
            base_orientation_xyzw: vec![[0.0, 0.0, 0.0, 1.0]; units],
            unit_phase: (0..units)
                .map(|i| (i == 0).then_some(Phase::Lift))
                .collect(),
            grasp_closed: vec![true; units],
        }
    }

    /// Topic → (message encoding, schema name, messages as (log time ns, bytes)) of a finished
    /// file, through the mcap crate's strict reader.
    type Messages = BTreeMap<String, (String, String, Vec<(u64, Vec<u8>)>)>;

    fn messages(path: &Path) -> Messages {
        let bytes = std::fs::read(path).unwrap();
        let mut out = Messages::new();
        for message in mcap::MessageStream::new(&bytes).unwrap() {
            let message = message.unwrap();
            let entry = out.entry(message.channel.topic.clone()).or_insert_with(|| {
                (
                    message.channel.message_encoding.clone(),
                    message
                        .channel
                        .schema
                        .as_ref()
                        .map_or(String::new(), |s| s.name.clone()),
                    Vec::new(),
                )
            });
            entry.2.push((message.log_time, message.data.into_owned()));
        }
        out
    }

    #[test]
    fn unit_log_round_trips_with_its_stamps_as_log_time() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("unit-1.mcap");
        let records: Vec<TickRecord> = (1..=60).map(|k| tick(1, k)).collect();
        let mut log = UnitLog::create(&path, 1).unwrap();
        for r in &records {
            log.write(r).unwrap();
        }
        log.finish().unwrap();
        assert_eq!(read_unit_log(&path).unwrap(), records);

        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.ends_with(mcap::MAGIC), "finished file has its footer");
        let topics = messages(&path);
        assert_eq!(topics.keys().collect::<Vec<_>>(), ["/unit1/tick"]);
        let (encoding, schema, msgs) = &topics["/unit1/tick"];
        assert_eq!(
            (encoding.as_str(), schema.as_str()),
            ("json", "moonhaul.TickRecord")
        );
        let times: Vec<u64> = msgs.iter().map(|m| m.0).collect();
        let expected: Vec<u64> = records.iter().map(|r| r.stamp_us * 1000).collect();
        assert_eq!(times, expected);
    }

    #[test]
    fn schemas_name_every_field() {
        let keys = |v: serde_json::Value| -> BTreeSet<String> {
            v.as_object().unwrap().keys().cloned().collect()
        };
        let properties = |schema: serde_json::Value| keys(schema["properties"].clone());
        let record = serde_json::to_value(tick(0, 3)).unwrap();
        assert_eq!(properties(tick_schema()), keys(record.clone()));
        assert_eq!(
            keys(tick_schema()["properties"]["rejected"]["properties"].clone()),
            keys(record["rejected"].clone())
        );
        assert_eq!(
            properties(world_schema()),
            keys(serde_json::to_value(frame(3, 2)).unwrap())
        );
    }

    #[test]
    fn truncated_log_gives_its_complete_prefix() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("unit-0.mcap");
        let records: Vec<TickRecord> = (1..=120).map(|k| tick(0, k)).collect();
        let mut log = UnitLog::create(&path, 0).unwrap();
        for chunk in records.chunks(10) {
            for r in chunk {
                log.write(r).unwrap();
            }
            log.flush().unwrap();
        }
        log.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let cut_path = dir.path().join("cut.mcap");
        let mut last = 0;
        let mut partial = BTreeSet::new();
        let step = (bytes.len() / 500).max(1);
        for cut in (0..bytes.len()).step_by(step).chain([bytes.len() - 1]) {
            std::fs::write(&cut_path, &bytes[..cut]).unwrap();
            let got = read_unit_log(&cut_path)
                .unwrap_or_else(|e| panic!("cut at {cut} of {}: {e}", bytes.len()));
            assert_eq!(got[..], records[..got.len()], "cut at {cut}");
            assert!(
                got.len() >= last,
                "cut at {cut}: fewer records than a shorter cut"
            );
            last = got.len();
            partial.insert(got.len());
        }
        assert_eq!(last, records.len(), "all records come before the summary");
        // Every flushed chunk becomes readable on its own.
        for n in (10..=120).step_by(10) {
            assert!(
                partial.contains(&n),
                "no cut gave the first {n} records: {partial:?}"
            );
        }
    }

    /// Set in the child process of `killed_writer_loses_at_most_the_last_second`: where it
    /// writes its log.
    const CHILD_LOG_ENV: &str = "MOONHAUL_TEST_KILLED_LOG";

    /// The writer `killed_writer_loses_at_most_the_last_second` SIGKILLs: logs a record every
    /// 10 ms and prints each one's tick once written, for up to a minute.
    #[test]
    #[ignore = "the child of killed_writer_loses_at_most_the_last_second"]
    fn killed_writer_child() {
        let Some(path) = std::env::var_os(CHILD_LOG_ENV) else {
            return;
        };
        let mut log = UnitLog::create(Path::new(&path), 0).unwrap();
        let start = Instant::now();
        let mut k = 0;
        while start.elapsed() < Duration::from_secs(60) {
            k += 1;
            log.write(&tick(0, k)).unwrap();
            println!("wrote {k}");
            std::thread::sleep(Duration::from_millis(10));
        }
        log.finish().unwrap();
    }

    #[test]
    fn killed_writer_loses_at_most_the_last_second() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("unit-0.mcap");
        let mut child = Command::new(std::env::current_exe().unwrap())
            .args([
                "mission_log::tests::killed_writer_child",
                "--exact",
                "--ignored",
                "--nocapture",
                "--test-threads=1",
            ])
            .env(CHILD_LOG_ENV, &path)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(k) = line.strip_prefix("wrote ").and_then(|k| k.parse().ok()) {
                    let _ = tx.send((k, Instant::now()));
                }
            }
        });
        let mut written: Vec<(u64, Instant)> = Vec::new();
        loop {
            let next = rx.recv_timeout(Duration::from_secs(60));
            let Ok(next) = next else {
                let _ = child.kill();
                panic!("the child stopped writing: {next:?}");
            };
            written.push(next);
            if next.1 - written[0].1 >= Duration::from_secs(3) {
                break;
            }
        }
        let killed_at = Instant::now();
        child.kill().unwrap();
        child.wait().unwrap();

        // Written more than a flush period (plus scheduling slack on a loaded machine) before
        // the kill: these must have reached the file.
        let old = written
            .iter()
            .filter(|(_, at)| *at + FLUSH_PERIOD + Duration::from_millis(500) <= killed_at)
            .map(|(k, _)| *k)
            .max()
            .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(
            !bytes.ends_with(mcap::MAGIC),
            "a killed writer leaves no footer"
        );
        let records = read_unit_log(&path).unwrap();
        let ticks: Vec<u64> = records.iter().map(|r| r.tick).collect();
        assert_eq!(ticks, (1..=ticks.len() as u64).collect::<Vec<_>>());
        assert!(
            ticks.len() as u64 >= old,
            "{} records read back; {old} were written over 1.5 s before the kill",
            ticks.len()
        );
        assert_eq!(
            records[..],
            (1..=ticks.len() as u64)
                .map(|k| tick(0, k))
                .collect::<Vec<_>>()[..]
        );
    }

    fn error_text(result: Result<Vec<TickRecord>, LogError>) -> String {
        result.map(|r| r.len()).unwrap_err().to_string()
    }

    #[test]
    fn garbage_is_an_error_naming_the_file_and_record() {
        let dir = tempfile::tempdir().unwrap();
        let name = |p: &Path| p.display().to_string();

        let random = dir.path().join("random.mcap");
        std::fs::write(
            &random,
            (0..4000u32)
                .map(|i| (i * 7919 % 251) as u8)
                .collect::<Vec<_>>(),
        )
        .unwrap();
        let e = error_text(read_unit_log(&random));
        assert!(e.contains(&name(&random)) && e.contains("record 1"), "{e}");

        // A byte changed inside a chunk: its CRC no longer matches.
        let path = dir.path().join("unit-0.mcap");
        let mut log = UnitLog::create(&path, 0).unwrap();
        for k in 1..=20 {
            log.write(&tick(0, k)).unwrap();
        }
        log.finish().unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        let at = bytes
            .windows(12)
            .position(|w| w == b"\"grasp_open\"")
            .unwrap();
        bytes[at + 1] = b'G';
        let flipped = dir.path().join("flipped.mcap");
        std::fs::write(&flipped, &bytes).unwrap();
        let e = error_text(read_unit_log(&flipped));
        assert!(e.contains(&name(&flipped)) && e.contains("CRC"), "{e}");

        // Valid MCAP, but the message is not a TickRecord.
        let bogus = dir.path().join("bogus.mcap");
        {
            let context = Context::new();
            let writer = context
                .mcap_writer()
                .create(BufWriter::new(File::create(&bogus).unwrap()))
                .unwrap();
            let channel = context
                .channel_builder("/unit0/tick")
                .message_encoding("json")
                .build_raw()
                .unwrap();
            channel.log(br#"{"unit": 0}"#);
            writer.close().unwrap();
        }
        let e = error_text(read_unit_log(&bogus));
        assert!(
            e.contains(&name(&bogus)) && e.contains("message 1 on /unit0/tick"),
            "{e}"
        );

        // Not a regular file; larger than the cap.
        let e = error_text(read_unit_log(dir.path()));
        assert!(e.contains("not a regular file"), "{e}");
        let e = read_json_topic::<TickRecord>(&path, 100, &TopicFilter::unit())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&name(&path)) && e.contains("larger than 100 bytes"),
            "{e}"
        );
    }

    #[test]
    fn a_log_of_the_other_kind_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let unit = dir.path().join("unit-0.mcap");
        let mut log = UnitLog::create(&unit, 0).unwrap();
        log.write(&tick(0, 1)).unwrap();
        log.finish().unwrap();
        let world = dir.path().join("world.mcap");
        let mut log = WorldLog::create(&world, [0.4, 0.3, 0.2], 2).unwrap();
        log.write(&frame(0, 2)).unwrap();
        log.finish().unwrap();
        let e = read_world_log(&unit).unwrap_err().to_string();
        assert!(
            e.contains("is not a world log") && e.contains("/unit0/tick"),
            "{e}"
        );
        let e = error_text(read_unit_log(&world));
        assert!(e.contains("is not a unit log"), "{e}");
    }

    #[test]
    fn world_log_round_trips_and_draws_in_3d() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("world.mcap");
        let size = [0.6, 0.4, 0.3];
        // 2.5 s of frames at 50 Hz.
        let frames: Vec<WorldFrame> = (0..125).map(|k| frame(k, 2)).collect();
        let mut log = WorldLog::create(&path, size, 2).unwrap();
        for f in &frames {
            log.write(f).unwrap();
        }
        let e = log.write(&frame(200, 3)).unwrap_err().to_string();
        assert!(e.contains("team of 2") && e.contains("tick 200"), "{e}");
        log.finish().unwrap();
        assert_eq!(read_world_log(&path).unwrap(), frames);

        let topics = messages(&path);
        assert_eq!(
            topics.keys().collect::<Vec<_>>(),
            [SCENE_TOPIC, TF_TOPIC, WORLD_TOPIC]
        );
        let (encoding, schema, tf) = &topics[TF_TOPIC];
        assert_eq!(
            (encoding.as_str(), schema.as_str()),
            ("protobuf", "foxglove.FrameTransforms")
        );
        assert_eq!(tf.len(), frames.len());
        let (time, data) = &tf[100];
        assert_eq!(*time, frames[100].stamp_us * 1000);
        let decoded = <FrameTransforms as foxglove::Decode>::decode(&data[..]).unwrap();
        let children: Vec<&str> = decoded
            .transforms
            .iter()
            .map(|t| t.child_frame_id.as_str())
            .collect();
        assert_eq!(children, ["payload", "base0", "base1"]);
        assert!(decoded
            .transforms
            .iter()
            .all(|t| t.parent_frame_id == "world"));
        let p = decoded.transforms[0].translation.unwrap();
        assert_eq!([p.x, p.y, p.z], frames[100].payload_position_m);
        let b = decoded.transforms[2].translation.unwrap();
        assert_eq!([b.x, b.y, b.z], frames[100].base_position_m[1]);

        // The cube at start and once a second after: 0, 1, 2 s.
        let (_, schema, scene) = &topics[SCENE_TOPIC];
        assert_eq!(schema, "foxglove.SceneUpdate");
        let times: Vec<u64> = scene.iter().map(|m| m.0).collect();
        assert_eq!(times, [0, 1_000_000_000, 2_000_000_000]);
        let update = <SceneUpdate as foxglove::Decode>::decode(&scene[0].1[..]).unwrap();
        let entity = &update.entities[0];
        assert_eq!(entity.frame_id, "payload");
        assert!(entity.frame_locked);
        let s = entity.cubes[0].size.unwrap();
        assert_eq!([s.x, s.y, s.z], size);
    }

    #[test]
    fn two_logs_in_one_process_do_not_mix() {
        let dir = tempfile::tempdir().unwrap();
        let paths = [
            dir.path().join("unit-0.mcap"),
            dir.path().join("unit-1.mcap"),
        ];
        let mut logs = [
            UnitLog::create(&paths[0], 0).unwrap(),
            UnitLog::create(&paths[1], 1).unwrap(),
        ];
        for k in 1..=30 {
            for (unit, log) in logs.iter_mut().enumerate() {
                log.write(&tick(unit, k)).unwrap();
            }
        }
        for log in logs {
            log.finish().unwrap();
        }
        for (unit, path) in paths.iter().enumerate() {
            let records = read_unit_log(path).unwrap();
            assert_eq!(records, (1..=30).map(|k| tick(unit, k)).collect::<Vec<_>>());
            let topics = messages(path);
            assert_eq!(topics.keys().collect::<Vec<_>>(), [&unit_topic(unit)]);
        }
    }

    #[test]
    fn refuses_to_write_through_a_non_file() {
        let dir = tempfile::tempdir().unwrap();
        let e = UnitLog::create(dir.path(), 0).err().unwrap().to_string();
        assert!(e.contains("not a regular file"), "{e}");
    }
}
