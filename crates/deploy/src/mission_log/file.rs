//! One MCAP file written through the Foxglove SDK: its own context, channels, metadata, the
//! background flush, and the finish that writes the summary and footer.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use foxglove::{
    Context, McapAttachment, McapCompression, McapWriteOptions, McapWriterHandle, RawChannel,
    Schema,
};
use serde::Serialize;

use super::flusher::Flusher;
use super::inputs::LogInputs;
use super::{LogError, FLUSH_PERIOD};

/// The MCAP profile: none of ROS 1/ROS 2; plain Foxglove JSON and protobuf channels.
const PROFILE: &str = "";

/// MCAP log time, ns since the epoch of the log's clock, from a record's stamp in µs.
pub(super) fn log_time_ns(stamp_us: u64) -> u64 {
    stamp_us.saturating_mul(1000)
}

/// The most log time one chunk spans, µs: a chunk is finished before a record stamped this much
/// after the chunk's first one, so a log cut anywhere (a killed writer's, or a copy cut short)
/// keeps every record but those of its last second of log time, however fast it was written (a
/// simulated world runs faster than the wall clock that [`FLUSH_PERIOD`] counts).
const CHUNK_SPAN_US: u64 = FLUSH_PERIOD.as_micros() as u64;

/// The file, its context and writer, and the thread that flushes it every [`FLUSH_PERIOD`].
pub(super) struct LogFile {
    pub(super) path: PathBuf,
    // Field order matters for drop: the flusher stops before the writer finishes, and the
    // writer finishes before the context (which holds its channels) goes.
    flusher: Option<Flusher>,
    writer: Arc<McapWriterHandle<BufWriter<File>>>,
    pub(super) context: Arc<Context>,
    /// The stamp of the open chunk's first record, µs (`None`: none since the last chunk).
    chunk_start_us: Option<u64>,
}

impl LogFile {
    /// Creates the file with its `metadata` and the attachments of `inputs`.
    pub(super) fn create(
        path: &Path,
        metadata: &[(&str, String)],
        inputs: &LogInputs,
    ) -> Result<Self, LogError> {
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
            // Foxglove and the mcap crate (the readers here) decompress zstd chunks; the JSON
            // records shrink about tenfold.
            .compression(Some(McapCompression::Zstd))
            // Compressed on the writing thread, as written: no worker threads beside a control
            // loop, and a chunk is whole when it is finished.
            .compression_threads(0)
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
            .map_err(|e| create_error(e.to_string()))?;
        for a in &inputs.attachments {
            writer
                .attach(&McapAttachment {
                    log_time: 0,
                    create_time: a.modified_ns,
                    name: a.name.clone(),
                    media_type: a.media_type.to_owned(),
                    data: a.data.as_slice().into(),
                })
                .map_err(|e| create_error(format!("attaching {}: {e}", a.name)))?;
        }
        writer.flush().map_err(|e| create_error(e.to_string()))?;
        let writer = Arc::new(writer);
        let flusher = Flusher::spawn(path, Arc::clone(&writer)).map_err(create_error)?;
        Ok(Self {
            path: path.to_owned(),
            flusher: Some(flusher),
            writer,
            context,
            chunk_start_us: None,
        })
    }

    /// Called before the records stamped `stamp_us` are logged: finishes the open chunk if
    /// they would stretch it past [`CHUNK_SPAN_US`] (or its stamps run backwards).
    pub(super) fn start_records(&mut self, stamp_us: u64) -> Result<(), LogError> {
        match self.chunk_start_us {
            Some(start) if stamp_us >= start && stamp_us - start < CHUNK_SPAN_US => Ok(()),
            Some(_) => {
                self.chunk_start_us = Some(stamp_us);
                self.flush()
            }
            None => {
                self.chunk_start_us = Some(stamp_us);
                Ok(())
            }
        }
    }

    pub(super) fn json_channel(
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
    pub(super) fn check(&self) -> Result<(), LogError> {
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

    pub(super) fn log_json<T: Serialize>(
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

    pub(super) fn flush(&self) -> Result<(), LogError> {
        self.check()?;
        self.writer.flush().map_err(|e| LogError::Write {
            path: self.path.clone(),
            error: e.to_string(),
        })
    }

    pub(super) fn finish(self) -> Result<(), LogError> {
        self.check()?;
        let LogFile {
            path,
            flusher,
            writer,
            context,
            ..
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
