//! A rosbag2 bag as ROS 2 Jazzy's `ros2 bag record` writes one with its MCAP storage: a folder
//! holding `<folder name>_0.mcap` (profile `ros2`, one `ros2msg` schema per message type, `cdr`
//! channels carrying their offered QoS and type hash, zstd chunks) and `metadata.yaml`
//! (rosbag2 metadata version 9, the same text also inside the MCAP as its `rosbag2` metadata
//! record), so `ros2 bag info`, `ros2 bag play`, PlotJuggler and `rosbags` open it.
//!
//! The writer fills the folder it is given; publishing it whole (a temporary folder renamed
//! into place) is the caller's.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, Metadata};
use mcap::{Compression, WriteOptions};
use serde::Serialize;

use super::msgs::encode_cdr;
use super::topics::{Durability, Qos, Topic};

/// rosbag2's metadata version that Jazzy writes.
pub const METADATA_VERSION: u32 = 9;
/// The ROS distribution the type hashes and the metadata format are Jazzy's.
pub const ROS_DISTRO: &str = "jazzy";

/// Why a bag could not be written; names the file.
#[derive(Debug, thiserror::Error)]
#[error("cannot write the bag file {}: {error}", path.display())]
pub struct BagError {
    pub path: PathBuf,
    pub error: String,
}

/// A topic's place in the bag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TopicId(usize);

struct BagTopic {
    topic: Topic,
    channel: u16,
    count: u64,
}

/// Writes one bag into an empty folder.
pub struct BagWriter {
    mcap_path: PathBuf,
    metadata_path: PathBuf,
    file_name: String,
    writer: mcap::Writer<BufWriter<File>>,
    schemas: BTreeMap<&'static str, u16>,
    topics: Vec<BagTopic>,
    /// (first, last) log time written, ns.
    span_ns: Option<(u64, u64)>,
    buf: Vec<u8>,
}

impl BagWriter {
    /// Starts a bag named `name` (the folder's final name: rosbag2 names the MCAP file after
    /// it) in the existing folder `dir`.
    pub fn create(dir: &Path, name: &str) -> Result<Self, BagError> {
        let file_name = format!("{name}_0.mcap");
        let mcap_path = dir.join(&file_name);
        let fail = |error: String| BagError {
            path: mcap_path.clone(),
            error,
        };
        let file = File::create_new(&mcap_path).map_err(|e| fail(e.to_string()))?;
        let writer = WriteOptions::new()
            .profile("ros2")
            .library(concat!("moonhaul ", env!("CARGO_PKG_VERSION")))
            .compression(Some(Compression::Zstd))
            .create(BufWriter::new(file))
            .map_err(|e| fail(e.to_string()))?;
        Ok(BagWriter {
            metadata_path: dir.join("metadata.yaml"),
            mcap_path,
            file_name,
            writer,
            schemas: BTreeMap::new(),
            topics: Vec::new(),
            span_ns: None,
            buf: Vec::with_capacity(4096),
        })
    }

    /// Adds `topic` (each name once; a second call for the same name returns the first).
    pub fn add_topic(&mut self, topic: &Topic) -> Result<TopicId, BagError> {
        if let Some(k) = self.topics.iter().position(|t| t.topic.name == topic.name) {
            return Ok(TopicId(k));
        }
        let ros_type = topic.ros_type;
        let schema = match self.schemas.get(ros_type.name) {
            Some(&id) => id,
            None => {
                let id = self
                    .writer
                    .add_schema(ros_type.name, "ros2msg", ros_type.definition().as_bytes())
                    .map_err(|e| self.error(e))?;
                self.schemas.insert(ros_type.name, id);
                id
            }
        };
        let metadata = BTreeMap::from([
            (
                "offered_qos_profiles".to_owned(),
                qos_yaml(&topic.qos, 0).trim_end().to_owned(),
            ),
            ("topic_type_hash".to_owned(), ros_type.hash.to_owned()),
        ]);
        let channel = self
            .writer
            .add_channel(schema, &topic.name, "cdr", &metadata)
            .map_err(|e| self.error(e))?;
        self.topics.push(BagTopic {
            topic: topic.clone(),
            channel,
            count: 0,
        });
        Ok(TopicId(self.topics.len() - 1))
    }

    /// Writes `message` on `topic` at log time `log_time_ns` (ns; the message's stamp).
    pub fn write<T: Serialize>(
        &mut self,
        topic: TopicId,
        log_time_ns: u64,
        message: &T,
    ) -> Result<(), BagError> {
        encode_cdr(message, &mut self.buf).map_err(|e| self.error(e))?;
        let Some(entry) = self.topics.get_mut(topic.0) else {
            return Err(BagError {
                path: self.mcap_path.clone(),
                error: format!("no topic {} in this bag", topic.0),
            });
        };
        entry.count += 1;
        let header = MessageHeader {
            channel_id: entry.channel,
            // rosbag2 numbers nothing; a wrapped count is only a label.
            sequence: entry.count as u32,
            log_time: log_time_ns,
            publish_time: log_time_ns,
        };
        self.writer
            .write_to_known_channel(&header, &self.buf)
            .map_err(|e| BagError {
                path: self.mcap_path.clone(),
                error: e.to_string(),
            })?;
        self.span_ns = Some(match self.span_ns {
            None => (log_time_ns, log_time_ns),
            Some((a, b)) => (a.min(log_time_ns), b.max(log_time_ns)),
        });
        Ok(())
    }

    /// Messages written so far on `topic`.
    pub fn count(&self, topic: TopicId) -> u64 {
        self.topics.get(topic.0).map_or(0, |t| t.count)
    }

    /// Finishes the MCAP file (with the metadata inside it) and writes `metadata.yaml`, both
    /// synced to disk.
    pub fn finish(mut self) -> Result<(), BagError> {
        let info = self.metadata_body();
        self.writer
            .write_metadata(&Metadata {
                name: "rosbag2".to_owned(),
                metadata: BTreeMap::from([
                    ("ROS_DISTRO".to_owned(), ROS_DISTRO.to_owned()),
                    ("serialized_metadata".to_owned(), info.clone()),
                ]),
            })
            .map_err(|e| self.error(e))?;
        self.writer.finish().map_err(|e| self.error(e))?;
        let file = self
            .writer
            .into_inner()
            .into_inner()
            .map_err(|e| BagError {
                path: self.mcap_path.clone(),
                error: e.error().to_string(),
            })?;
        file.sync_all().map_err(|e| BagError {
            path: self.mcap_path.clone(),
            error: e.to_string(),
        })?;
        let mut text = String::from("rosbag2_bagfile_information:\n");
        for line in info.lines() {
            let _ = writeln!(text, "  {line}");
        }
        let meta_error = |e: std::io::Error| BagError {
            path: self.metadata_path.clone(),
            error: e.to_string(),
        };
        let mut out = File::create_new(&self.metadata_path).map_err(meta_error)?;
        out.write_all(text.as_bytes()).map_err(meta_error)?;
        out.sync_all().map_err(meta_error)
    }

    /// The body of rosbag2's `rosbag2_bagfile_information`, version 9.
    fn metadata_body(&self) -> String {
        let (start, end) = self.span_ns.unwrap_or((0, 0));
        let duration = end - start;
        let total: u64 = self.topics.iter().map(|t| t.count).sum();
        let mut y = String::new();
        let _ = writeln!(y, "version: {METADATA_VERSION}");
        let _ = writeln!(y, "storage_identifier: mcap");
        let _ = writeln!(y, "duration:\n  nanoseconds: {duration}");
        let _ = writeln!(y, "starting_time:\n  nanoseconds_since_epoch: {start}");
        let _ = writeln!(y, "message_count: {total}");
        let _ = writeln!(y, "topics_with_message_count:");
        for t in &self.topics {
            let _ = writeln!(y, "  - topic_metadata:");
            let _ = writeln!(y, "      name: {}", t.topic.name);
            let _ = writeln!(y, "      type: {}", t.topic.ros_type.name);
            let _ = writeln!(y, "      serialization_format: cdr");
            let _ = writeln!(y, "      offered_qos_profiles:");
            y.push_str(&qos_yaml(&t.topic.qos, 8));
            let _ = writeln!(y, "      type_description_hash: {}", t.topic.ros_type.hash);
            let _ = writeln!(y, "    message_count: {}", t.count);
        }
        let _ = writeln!(y, "compression_format: \"\"");
        let _ = writeln!(y, "compression_mode: \"\"");
        let _ = writeln!(y, "relative_file_paths:\n  - {}", self.file_name);
        let _ = writeln!(y, "files:");
        let _ = writeln!(y, "  - path: {}", self.file_name);
        let _ = writeln!(
            y,
            "    starting_time:\n      nanoseconds_since_epoch: {start}"
        );
        let _ = writeln!(y, "    duration:\n      nanoseconds: {duration}");
        let _ = writeln!(y, "    message_count: {total}");
        let _ = writeln!(y, "custom_data: ~");
        let _ = writeln!(y, "ros_distro: {ROS_DISTRO}");
        y
    }

    fn error(&self, e: impl ToString) -> BagError {
        BagError {
            path: self.mcap_path.clone(),
            error: e.to_string(),
        }
    }
}

/// rmw's infinite duration as rosbag2 writes it: (sec, nsec) of i64::MAX ns.
const INFINITE: (i64, i64) = (9_223_372_036, 854_775_807);

/// A one-profile list of offered QoS as rosbag2 version 9 writes it (names, not numbers),
/// indented by `indent` spaces.
fn qos_yaml(qos: &Qos, indent: usize) -> String {
    let pad = " ".repeat(indent);
    let durability = match qos.durability {
        Durability::Volatile => "volatile",
        Durability::TransientLocal => "transient_local",
    };
    let (s, ns) = INFINITE;
    let mut y = String::new();
    let _ = writeln!(y, "{pad}- history: keep_last");
    let _ = writeln!(y, "{pad}  depth: {}", qos.depth);
    let _ = writeln!(y, "{pad}  reliability: reliable");
    let _ = writeln!(y, "{pad}  durability: {durability}");
    for key in ["deadline", "lifespan"] {
        let _ = writeln!(y, "{pad}  {key}:\n{pad}    sec: {s}\n{pad}    nsec: {ns}");
    }
    let _ = writeln!(y, "{pad}  liveliness: automatic");
    let _ = writeln!(
        y,
        "{pad}  liveliness_lease_duration:\n{pad}    sec: {s}\n{pad}    nsec: {ns}"
    );
    let _ = writeln!(y, "{pad}  avoid_ros_namespace_conventions: false");
    y
}
