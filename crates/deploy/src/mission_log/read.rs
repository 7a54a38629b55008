//! Reading mission logs back, truncated ones too.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{self, Read};
use std::path::Path;

use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use mcap::McapError;
use moonhaul_core::input::{check_readable, InputError};
use serde::de::DeserializeOwned;

use super::topics::WORLD_TOPIC;
use super::{LogError, MAX_LOG_BYTES};
use crate::record::{TickRecord, WorldFrame};

/// Largest single record (message, schema, or whole chunk) the reader accepts, bytes. Chunks
/// are closed at 1 MiB of records and every second; a longer length field is garbage, not a
/// truncated file.
const MAX_RECORD_BYTES: usize = 64 << 20;

/// What a reader got from a log: its records, in file order, how the file ended, and the
/// log's `moonhaul` metadata (`unit`, a unit log's `controller`, …; written before any record,
/// so a truncated log has it too; empty for a log without it).
#[derive(Debug, Clone, PartialEq)]
pub struct LogContents<T> {
    pub records: Vec<T>,
    pub end: LogEnd,
    pub metadata: BTreeMap<String, String>,
}

/// How a log file ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogEnd {
    /// At its footer: the writer finished the file.
    Finished,
    /// Without its footer: a killed writer's file, or a copy cut short. Every complete record
    /// was read; what follows the last one (at most the writer's last second of records, in its
    /// incomplete last chunk) could not be.
    Truncated {
        /// The size of the file, bytes.
        file_bytes: u64,
    },
}

/// Every tick record of a unit log (`/unit{i}/tick`), in file order. A truncated log (a killed
/// daemon's) gives every record up to its first incomplete one.
pub fn read_unit_log(path: &Path) -> Result<Vec<TickRecord>, LogError> {
    read_unit_log_contents(path).map(|c| c.records)
}

/// As [`read_unit_log`], saying whether the file was whole.
pub fn read_unit_log_contents(path: &Path) -> Result<LogContents<TickRecord>, LogError> {
    read_json_topic(path, MAX_LOG_BYTES, &TopicFilter::unit())
}

/// Every ground-truth frame of a world log (`/world/frame`), in file order. A truncated log
/// gives every frame up to its first incomplete record.
pub fn read_world_log(path: &Path) -> Result<Vec<WorldFrame>, LogError> {
    read_world_log_contents(path).map(|c| c.records)
}

/// As [`read_world_log`], saying whether the file was whole.
pub fn read_world_log_contents(path: &Path) -> Result<LogContents<WorldFrame>, LogError> {
    read_json_topic(path, MAX_LOG_BYTES, &TopicFilter::world())
}

/// The attachments of a log (the files it was recorded with) as (name, bytes), in file order,
/// by the rules of the readers above.
pub fn read_attachments(path: &Path) -> Result<LogContents<(String, Vec<u8>)>, LogError> {
    let mut out = Vec::new();
    let (end, metadata) = read_records(path, MAX_LOG_BYTES, |_, record| {
        if let Record::Attachment { header, data, .. } = record {
            out.push((header.name, data.into_owned()));
        }
        Ok(())
    })?;
    Ok(LogContents {
        records: out,
        end,
        metadata,
    })
}

/// Which channels a reader decodes, and what to call them in errors.
pub(super) struct TopicFilter {
    /// The kind of log, for errors: "unit", "world".
    kind: &'static str,
    /// The topic as the user knows it, for errors.
    expected: &'static str,
    /// The Rust type its messages decode into, for errors.
    type_name: &'static str,
    matches: fn(&str) -> bool,
}

impl TopicFilter {
    pub(super) fn unit() -> Self {
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

    pub(super) fn world() -> Self {
        Self {
            kind: "world",
            expected: WORLD_TOPIC,
            type_name: "WorldFrame",
            matches: |topic| topic == WORLD_TOPIC,
        }
    }
}

/// Reads the JSON messages of the channels `filter` picks, by the rules of [`read_records`].
/// Beyond those, a message on an undeclared channel, a wanted channel that is not JSON, or a
/// message that does not decode is an error naming the file, the record and the message.
pub(super) fn read_json_topic<T: DeserializeOwned>(
    path: &Path,
    max_bytes: u64,
    filter: &TopicFilter,
) -> Result<LogContents<T>, LogError> {
    let corrupt = |record: usize, reason: String| LogError::Corrupt {
        path: path.to_owned(),
        record,
        reason,
    };
    // Channel id → its topic if the filter wants it.
    let mut channels: HashMap<u16, Option<String>> = HashMap::new();
    let mut topics: Vec<String> = Vec::new();
    let mut out = Vec::new();
    let (end, metadata) = read_records(path, max_bytes, |record, parsed| {
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
                    let value =
                        serde_json::from_slice(&data).map_err(|e| LogError::BadMessage {
                            path: path.to_owned(),
                            topic: topic.clone(),
                            message: out.len() + 1,
                            record,
                            kind: filter.type_name,
                            error: e.to_string(),
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
        Ok(())
    })?;
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
    Ok(LogContents {
        records: out,
        end,
        metadata,
    })
}

/// Streams the records of the MCAP file at `path` (those inside chunks included, decompressed)
/// to `visit` with their 1-based index; refuses a file larger than `max_bytes` or one that is
/// not a regular file before reading. Returns how the file ended and its `moonhaul` metadata.
///
/// A file that ends inside a record, or without its footer, is taken as truncated (what a
/// killed writer leaves) and every complete record of it visited. Anything else that is wrong is
/// garbage and an error naming the file and the record: bad magic, a record or chunk longer
/// than [`MAX_RECORD_BYTES`], a chunk whose CRC does not match or that does not decompress, or
/// a record that does not parse.
fn read_records(
    path: &Path,
    max_bytes: u64,
    mut visit: impl FnMut(usize, Record<'_>) -> Result<(), LogError>,
) -> Result<(LogEnd, BTreeMap<String, String>), LogError> {
    let file_bytes = check_readable(path, max_bytes)?;
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
    let mut record = 0usize;
    let mut read_total = 0u64;
    let mut footer = false;
    let mut metadata = BTreeMap::new();
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
                footer |= matches!(parsed, Record::Footer(_));
                if let Record::Metadata(m) = &parsed {
                    if m.name == "moonhaul" {
                        metadata.extend(m.metadata.clone());
                    }
                }
                visit(record, parsed)?;
            }
        }
    }
    let end = if footer {
        LogEnd::Finished
    } else {
        LogEnd::Truncated {
            file_bytes: read_total.max(file_bytes),
        }
    };
    Ok((end, metadata))
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
