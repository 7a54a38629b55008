//! A unit's log: one tick record per control tick.

use std::path::Path;
use std::sync::Arc;

use foxglove::RawChannel;

use super::file::LogFile;
use super::schema::tick_schema;
use super::topics::unit_topic;
use super::LogError;
use crate::record::TickRecord;

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
    /// [`FLUSH_PERIOD`](super::FLUSH_PERIOD) anyway).
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.file.flush()
    }

    /// Writes the summary and footer, flushes and syncs the file.
    pub fn finish(self) -> Result<(), LogError> {
        self.file.finish()
    }
}
