//! Bus traffic in the can-utils `candump -L` log format, `(1700000000.123456) can0
//! 601#2B40600006000000`, so users inspect and replay it with the usual tools; a recording bus
//! decorator that logs everything the master sends and receives; and replay of a log into
//! emulated drives.

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use super::protocol::from_master;
use super::{BusError, CanBus, CanFrame};

/// One logged frame. `time` is absolute (seconds since the Unix epoch when recorded live).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogEntry {
    pub time: Duration,
    pub interface: String,
    pub frame: CanFrame,
}

/// Why a log line cannot be read; `line` is 1-based.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("candump log line {line}: {reason}")]
pub struct ParseError {
    pub line: usize,
    pub reason: String,
}

impl std::fmt::Display for LogEntry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "({}.{:06}) {} {:03X}#",
            self.time.as_secs(),
            self.time.subsec_micros(),
            self.interface,
            self.frame.id()
        )?;
        self.frame
            .data()
            .iter()
            .try_for_each(|b| write!(f, "{b:02X}"))
    }
}

impl std::str::FromStr for LogEntry {
    type Err = String;

    /// Parses one line; only classic 11-bit data frames (what CANopen uses) are accepted.
    fn from_str(line: &str) -> Result<Self, String> {
        let mut fields = line.split_whitespace();
        let (Some(stamp), Some(interface), Some(frame)) =
            (fields.next(), fields.next(), fields.next())
        else {
            return Err("expected `(seconds.micros) interface id#data`".into());
        };
        let stamp = stamp
            .strip_prefix('(')
            .and_then(|s| s.strip_suffix(')'))
            .ok_or("timestamp not in parentheses")?;
        let (secs, micros) = stamp.split_once('.').ok_or("timestamp without '.'")?;
        let secs: u64 = secs.parse().map_err(|_| format!("bad seconds {secs:?}"))?;
        if micros.len() != 6 || !micros.bytes().all(|b| b.is_ascii_digit()) {
            return Err(format!("expected 6 digits of microseconds, got {micros:?}"));
        }
        let micros: u32 = micros
            .parse()
            .map_err(|_| format!("bad microseconds {micros:?}"))?;
        let (id, data) = frame.split_once('#').ok_or("frame without '#'")?;
        if id.len() != 3 || !id.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("identifier {id:?} is not a 3-digit standard id"));
        }
        if data.starts_with(['#', 'R', 'r']) {
            return Err("CAN FD and remote frames are not supported".into());
        }
        let id = u16::from_str_radix(id, 16).map_err(|_| format!("bad identifier {id:?}"))?;
        if data.len() % 2 != 0 || !data.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("data {data:?} is not whole hex bytes"));
        }
        let bytes = (0..data.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&data[i..i + 2], 16))
            .collect::<Result<Vec<u8>, _>>()
            .map_err(|_| format!("data {data:?} is not hex"))?;
        let frame = CanFrame::new(id, &bytes).map_err(|e| e.to_string())?;
        Ok(LogEntry {
            time: Duration::new(secs, micros * 1000),
            interface: interface.to_owned(),
            frame,
        })
    }
}

/// Parses a whole log; blank lines are skipped.
pub fn parse(text: &str) -> Result<Vec<LogEntry>, ParseError> {
    text.lines()
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty())
        .map(|(i, line)| {
            line.parse().map_err(|reason| ParseError {
                line: i + 1,
                reason,
            })
        })
        .collect()
}

/// Writes a log whole or not at all ([`moonhaul_core::atomic_file`]): a reader never sees
/// half a log.
pub fn write_file(path: &Path, entries: &[LogEntry]) -> std::io::Result<()> {
    let write_log = |temp: &Path| {
        let mut out = std::io::BufWriter::new(std::fs::File::create(temp)?);
        for entry in entries {
            writeln!(out, "{entry}")?;
        }
        out.flush()
    };
    moonhaul_core::atomic_file::write_with(path, write_log, |e| e)
}

/// A bus decorator that logs every frame sent and received, stamped `epoch + bus time`.
pub struct RecordingBus<B> {
    inner: B,
    epoch: Duration,
    log: Vec<LogEntry>,
}

impl<B: CanBus> RecordingBus<B> {
    /// `epoch`: the wall-clock time of bus time zero, since the Unix epoch.
    pub fn new(inner: B, epoch: Duration) -> Self {
        RecordingBus {
            inner,
            epoch,
            log: Vec::new(),
        }
    }

    pub fn log(&self) -> &[LogEntry] {
        &self.log
    }

    pub fn inner(&self) -> &B {
        &self.inner
    }

    pub fn inner_mut(&mut self) -> &mut B {
        &mut self.inner
    }

    fn record(&mut self, frame: &CanFrame) {
        self.log.push(LogEntry {
            time: self.epoch + self.inner.now(),
            interface: self.inner.name().to_owned(),
            frame: *frame,
        });
    }
}

impl<B: CanBus> CanBus for RecordingBus<B> {
    fn name(&self) -> &str {
        self.inner.name()
    }

    fn now(&self) -> Duration {
        self.inner.now()
    }

    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.inner.send(frame)?;
        self.record(frame);
        Ok(())
    }

    fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError> {
        let frame = self.inner.recv_until(deadline)?;
        if let Some(frame) = &frame {
            self.record(frame);
        }
        Ok(frame)
    }
}

/// Replays the master's frames of a log (NMT, SYNC, RPDOs, SDO requests) into `bus` at their
/// logged times, relative to the first entry, and returns what the bus answered, stamped on
/// the same time base. On a [`super::VirtualBus`] with freshly powered-up drives this
/// reproduces the drives' side of the recording.
pub fn replay(entries: &[LogEntry], bus: &mut dyn CanBus) -> Result<Vec<LogEntry>, BusError> {
    let Some(first) = entries.first() else {
        return Ok(Vec::new());
    };
    let offset = bus.now();
    let mut answers = Vec::new();
    let mut collect = |bus: &mut dyn CanBus, until: Duration| -> Result<(), BusError> {
        while let Some(frame) = bus.recv_until(until)? {
            answers.push(LogEntry {
                time: first.time + bus.now().saturating_sub(offset),
                interface: first.interface.clone(),
                frame,
            });
        }
        Ok(())
    };
    for entry in entries.iter().filter(|e| from_master(e.frame.id())) {
        collect(bus, offset + entry.time.saturating_sub(first.time))?;
        bus.send(&entry.frame)?;
    }
    let last = entries.last().map_or(first.time, |e| e.time);
    collect(bus, offset + last.saturating_sub(first.time))?;
    Ok(answers)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn the_issue_example_round_trips() {
        let line = "(1700000000.123456) can0 601#2B40600006000000";
        let entry: LogEntry = line.parse().unwrap();
        assert_eq!(entry.time, Duration::new(1_700_000_000, 123_456_000));
        assert_eq!(entry.frame.id(), 0x601);
        assert_eq!(entry.frame.data(), [0x2B, 0x40, 0x60, 0, 6, 0, 0, 0]);
        assert_eq!(entry.to_string(), line);
        let empty: LogEntry = "(1.000001) vcan0 080#".parse().unwrap();
        assert_eq!(empty.to_string(), "(1.000001) vcan0 080#");
    }

    #[test]
    fn bad_lines_name_their_number() {
        let text = "(1.000000) can0 080#\n\n(1.000000) can0 12345678#00\n";
        let err = parse(text).unwrap_err();
        assert_eq!(err.line, 3);
        for bad in [
            "(1.0) can0 080#",
            "1.000000 can0 080#",
            "(1.000000) can0 080#0",
            "(1.000000) can0 080#GG",
            "(1.000000) can0 123#R",
            "(1.000000) can0 123##1",
            "(1.000000) can0 800#",
            "(1.000000) can0 080#000000000000000000",
            "(1.000000) can0",
        ] {
            assert!(bad.parse::<LogEntry>().is_err(), "{bad}");
        }
    }

    #[test]
    fn written_files_parse_back_and_leave_no_partial() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bus.log");
        let entries = parse("(5.000000) can0 080#\n(5.001000) can0 181#3702E8030000\n").unwrap();
        write_file(&path, &entries).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(parse(&text).unwrap(), entries);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        assert!(write_file(&dir.path().join("missing/bus.log"), &entries).is_err());
    }

    proptest! {
        #[test]
        fn parsing_arbitrary_lines_never_panics(line in "\\PC{0,60}") {
            let _ = line.parse::<LogEntry>();
        }

        #[test]
        fn formatted_entries_parse_back(secs in 0u64..4_000_000_000, micros in 0u32..1_000_000,
                                        id in 0u16..=0x7FF, data in proptest::collection::vec(any::<u8>(), 0..=8)) {
            let entry = LogEntry {
                time: Duration::new(secs, micros * 1000),
                interface: "can0".into(),
                frame: CanFrame::new(id, &data).unwrap(),
            };
            prop_assert_eq!(entry.to_string().parse::<LogEntry>(), Ok(entry));
        }
    }
}
