//! Bus traffic in the can-utils `candump -L` log format, `(1700000000.123456) can0
//! 601#2B40600006000000`, so users inspect and replay it with the usual tools; a recording bus
//! decorator that logs everything the master sends and receives; and replay of a log into
//! emulated drives.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use moonhaul_core::input::{self, InputError, MAX_CANDUMP_BYTES};

use super::protocol::from_master;
use super::{BusError, CanBus, CanFrame};

/// Latest timestamp accepted in a log, seconds since the Unix epoch (year 2286): far beyond
/// any real recording, and small enough that time arithmetic on logged entries cannot
/// overflow.
pub const MAX_TIMESTAMP_S: u64 = 10_000_000_000;

/// Most frames a [`RecordingBus`] keeps by default. A `candump -L` line of an 11-bit frame on
/// an interface name of at most 15 bytes (Linux's limit) is at most 57 bytes, so a full
/// recording (≈ 4 M × 57 B ≈ 230 MB) still reads back under
/// [`MAX_CANDUMP_BYTES`]. One unit's bus at 50 Hz fills it in about 40 min.
pub const MAX_RECORDED_FRAMES: usize = 4_000_000;

/// Longest stretch of bus time [`replay`] reproduces (first to last entry): the virtual bus
/// steps its drives through every millisecond of it.
pub const MAX_REPLAY_SPAN: Duration = Duration::from_secs(3600);

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

/// Why a log file cannot be read: the file itself (missing, not a regular file, too large) or
/// one of its lines.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error(transparent)]
    Input(#[from] InputError),
    // The parse error is part of the message, not a `source`, so a chain prints it once.
    #[error("{}: {error}", path.display())]
    Parse { path: PathBuf, error: ParseError },
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

/// The value of a string of ASCII hex digits that is at most 8 digits long.
fn hex_u32(digits: &str) -> Option<u32> {
    (!digits.is_empty() && digits.len() <= 8 && digits.bytes().all(|b| b.is_ascii_hexdigit()))
        .then(|| u32::from_str_radix(digits, 16).ok())
        .flatten()
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
        if fields.next().is_some() {
            return Err("unexpected text after `id#data`".into());
        }
        let stamp = stamp
            .strip_prefix('(')
            .and_then(|s| s.strip_suffix(')'))
            .ok_or("timestamp not in parentheses")?;
        let (secs, micros) = stamp.split_once('.').ok_or("timestamp without '.'")?;
        if secs.is_empty() || !secs.bytes().all(|b| b.is_ascii_digit()) {
            return Err(format!("bad seconds {secs:?}"));
        }
        let secs = secs
            .parse::<u64>()
            .ok()
            .filter(|s| *s <= MAX_TIMESTAMP_S)
            .ok_or_else(|| format!("timestamp {secs} s is after {MAX_TIMESTAMP_S} s"))?;
        if micros.len() != 6 || !micros.bytes().all(|b| b.is_ascii_digit()) {
            return Err(format!("expected 6 digits of microseconds, got {micros:?}"));
        }
        let micros: u32 = micros
            .parse()
            .map_err(|_| format!("bad microseconds {micros:?}"))?;
        let (id, data) = frame.split_once('#').ok_or("frame without '#'")?;
        let id = match (id.len(), hex_u32(id)) {
            (3, Some(id)) => id,
            (8, Some(id)) if id > 0x1FFF_FFFF => {
                return Err(format!("identifier {id:08X} does not fit in 29 bits"))
            }
            (8, Some(_)) => {
                return Err(format!(
                    "identifier {id:?} is an extended 29-bit id; only 11-bit ids are supported"
                ))
            }
            _ => {
                return Err(format!(
                    "identifier {id:?} is not a 3-digit hex standard id"
                ))
            }
        };
        if data.starts_with(['#', 'R', 'r']) {
            return Err("CAN FD and remote frames are not supported".into());
        }
        if data.len() > 16 {
            return Err(format!("{} data bytes (at most 8)", data.len().div_ceil(2)));
        }
        if data.len() % 2 != 0 || !data.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!("data {data:?} is not whole hex bytes"));
        }
        // All ASCII, so every two-byte slice is on a character boundary.
        let bytes = (0..data.len())
            .step_by(2)
            .map(|i| {
                data.get(i..i + 2)
                    .and_then(|pair| u8::from_str_radix(pair, 16).ok())
            })
            .collect::<Option<Vec<u8>>>()
            .ok_or_else(|| format!("data {data:?} is not hex"))?;
        // `id` has three hex digits, so it fits in u16.
        let id = u16::try_from(id).map_err(|_| format!("identifier 0x{id:X} is too large"))?;
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
    parse_bytes(text.as_bytes())
}

/// [`parse`] for raw bytes: a line that is not UTF-8 is an error naming that line.
pub fn parse_bytes(bytes: &[u8]) -> Result<Vec<LogEntry>, ParseError> {
    let mut lines: Vec<&[u8]> = bytes.split(|b| *b == b'\n').collect();
    // A final newline ends the last line; it does not start another.
    if lines.last().is_some_and(|l| l.is_empty()) {
        lines.pop();
    }
    lines
        .into_iter()
        .enumerate()
        .map(|(i, line)| (i + 1, line.strip_suffix(b"\r").unwrap_or(line)))
        .filter(|(_, line)| !line.trim_ascii().is_empty())
        .map(|(number, line)| {
            let error = |reason| ParseError {
                line: number,
                reason,
            };
            let text = std::str::from_utf8(line).map_err(|e| {
                error(format!(
                    "not valid UTF-8 text (byte {} of the line)",
                    e.valid_up_to() + 1
                ))
            })?;
            text.parse().map_err(error)
        })
        .collect()
}

/// Reads and parses a log file of at most [`MAX_CANDUMP_BYTES`]; anything else at `path`
/// (a directory, a FIFO, a device) is refused before it is opened.
pub fn read_file(path: &Path) -> Result<Vec<LogEntry>, ReadError> {
    let bytes = input::read_capped(path, MAX_CANDUMP_BYTES)?;
    parse_bytes(&bytes).map_err(|error| ReadError::Parse {
        path: path.to_owned(),
        error,
    })
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

/// A bus decorator that logs every frame sent and received, stamped `epoch + bus time`. The
/// log holds at most a fixed number of frames ([`MAX_RECORDED_FRAMES`] unless set with
/// [`RecordingBus::with_limit`]); once it is full, sending and receiving fail with a bus
/// error instead of growing memory without bound (no frame is ever sent unrecorded).
pub struct RecordingBus<B> {
    inner: B,
    epoch: Duration,
    log: Vec<LogEntry>,
    max_frames: usize,
}

impl<B: CanBus> RecordingBus<B> {
    /// `epoch`: the wall-clock time of bus time zero, since the Unix epoch.
    pub fn new(inner: B, epoch: Duration) -> Self {
        Self::with_limit(inner, epoch, MAX_RECORDED_FRAMES)
    }

    /// [`RecordingBus::new`] keeping at most `max_frames` frames.
    pub fn with_limit(inner: B, epoch: Duration, max_frames: usize) -> Self {
        RecordingBus {
            inner,
            epoch,
            log: Vec::new(),
            max_frames,
        }
    }

    pub fn log(&self) -> &[LogEntry] {
        &self.log
    }

    /// Most frames the log keeps.
    pub fn max_frames(&self) -> usize {
        self.max_frames
    }

    pub fn inner(&self) -> &B {
        &self.inner
    }

    pub fn inner_mut(&mut self) -> &mut B {
        &mut self.inner
    }

    fn check_room(&self) -> Result<(), BusError> {
        if self.log.len() < self.max_frames {
            Ok(())
        } else {
            Err(BusError::Io {
                bus: self.inner.name().to_owned(),
                reason: format!("recording is full ({} frames)", self.max_frames),
            })
        }
    }

    fn record(&mut self, frame: &CanFrame) {
        self.log.push(LogEntry {
            time: self.epoch.saturating_add(self.inner.now()),
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
        self.check_room()?;
        self.inner.send(frame)?;
        self.record(frame);
        Ok(())
    }

    fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError> {
        self.check_room()?;
        let frame = self.inner.recv_until(deadline)?;
        if let Some(frame) = &frame {
            self.record(frame);
        }
        Ok(frame)
    }
}

/// Why a log cannot be replayed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ReplayError {
    #[error("the log spans {span:?} of bus time, more than the {max:?} a replay reproduces")]
    TooLong { span: Duration, max: Duration },
    #[error(transparent)]
    Bus(#[from] BusError),
}

/// Replays the master's frames of a log (NMT, SYNC, RPDOs, SDO requests) into `bus` at their
/// logged times, relative to the first entry, and returns what the bus answered, stamped on
/// the same time base. On a [`super::VirtualBus`] with freshly powered-up drives this
/// reproduces the drives' side of the recording. Logs spanning more than
/// [`MAX_REPLAY_SPAN`] are refused (a virtual bus would step through all of it).
pub fn replay(entries: &[LogEntry], bus: &mut dyn CanBus) -> Result<Vec<LogEntry>, ReplayError> {
    let Some(first) = entries.first() else {
        return Ok(Vec::new());
    };
    let span = entries
        .iter()
        .map(|e| e.time.saturating_sub(first.time))
        .max()
        .unwrap_or_default();
    if span > MAX_REPLAY_SPAN {
        return Err(ReplayError::TooLong {
            span,
            max: MAX_REPLAY_SPAN,
        });
    }
    let offset = bus.now();
    let mut answers = Vec::new();
    let mut collect = |bus: &mut dyn CanBus, until: Duration| -> Result<(), BusError> {
        while let Some(frame) = bus.recv_until(until)? {
            answers.push(LogEntry {
                time: first.time.saturating_add(bus.now().saturating_sub(offset)),
                interface: first.interface.clone(),
                frame,
            });
        }
        Ok(())
    };
    for entry in entries.iter().filter(|e| from_master(e.frame.id())) {
        collect(
            bus,
            offset.saturating_add(entry.time.saturating_sub(first.time)),
        )?;
        bus.send(&entry.frame)?;
    }
    let last = entries.last().map_or(first.time, |e| e.time);
    collect(bus, offset.saturating_add(last.saturating_sub(first.time)))?;
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

    /// Every class of malformed line is an error that names the line and says what is wrong.
    #[test]
    fn each_malformed_class_is_named() {
        let cases: &[(&[u8], &str)] = &[
            (b"(1.000000) can0 080#0G", "not whole hex bytes"),
            (b"(1.000000) can0 080#0", "not whole hex bytes"),
            (
                b"(1.000000) can0 080#\xc3\xa9\xc3\xa9",
                "not whole hex bytes",
            ),
            (
                b"(1.000000) can0 080#000102030405060708",
                "9 data bytes (at most 8)",
            ),
            (
                b"(1.000000) can0 080#00010203040506070809AABB",
                "12 data bytes",
            ),
            (b"(1.000000) can0 0G0#", "not a 3-digit hex standard id"),
            (b"(1.000000) can0 #00", "not a 3-digit hex standard id"),
            (b"(1.000000) can0 1234#00", "not a 3-digit hex standard id"),
            (b"(1.000000) can0 800#", "does not fit in 11 bits"),
            (b"(1.000000) can0 12345678#00", "extended 29-bit id"),
            (b"(1.000000) can0 FFFFFFFF#00", "does not fit in 29 bits"),
            (
                b"(1.000000) can0 123456789#00",
                "not a 3-digit hex standard id",
            ),
            (
                b"(1.000000) can0",
                "expected `(seconds.micros) interface id#data`",
            ),
            (b"(1.000000)", "expected"),
            (b"(1.000000) can0 080", "frame without '#'"),
            (b"(1.000000) can0 080# 00", "unexpected text"),
            (b"(1) can0 080#", "timestamp without '.'"),
            (b"1.000000) can0 080#", "timestamp not in parentheses"),
            (b"(.000000) can0 080#", "bad seconds"),
            (b"(+1.000000) can0 080#", "bad seconds"),
            (b"(-1.000000) can0 080#", "bad seconds"),
            (b"(1.00000a) can0 080#", "6 digits of microseconds"),
            (b"(10000000001.000000) can0 080#", "is after 10000000000 s"),
            (
                b"(99999999999999999999999999.000000) can0 080#",
                "is after 10000000000 s",
            ),
            (b"(1.000000) can\xff0 080#", "not valid UTF-8"),
            (b"\xfe\xff", "not valid UTF-8"),
        ];
        for (line, reason) in cases {
            let text = [b"(1.000000) can0 080#\n\n".as_slice(), line, b"\n"].concat();
            let err = parse_bytes(&text).unwrap_err();
            assert_eq!(err.line, 3, "{}", String::from_utf8_lossy(line));
            assert!(
                err.to_string().starts_with("candump log line 3: ") && err.reason.contains(reason),
                "{}: {err}",
                String::from_utf8_lossy(line)
            );
        }
        // CRLF line ends and a missing final newline are fine; the latest timestamp is too.
        let ok = parse_bytes(b"(1.000000) can0 080#\r\n(10000000000.999999) can0 7FF#01").unwrap();
        assert_eq!(ok[1].time, Duration::new(MAX_TIMESTAMP_S, 999_999_000));
    }

    #[test]
    fn read_file_caps_the_file_and_names_path_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bus.log");
        std::fs::write(&path, b"(1.000000) can0 080#\n(2.000000) can0 080#\xff\n").unwrap();
        let err = read_file(&path).unwrap_err();
        let message = err.to_string();
        assert!(
            matches!(&err, ReadError::Parse { error, .. } if error.line == 2)
                && message.contains("bus.log")
                && message.contains("line 2"),
            "{message}"
        );
        std::fs::write(&path, "(1.000000) can0 080#\n").unwrap();
        assert_eq!(read_file(&path).unwrap().len(), 1);
        let not_a_file = read_file(dir.path()).unwrap_err();
        assert!(
            matches!(not_a_file, ReadError::Input(InputError::NotAFile { .. })),
            "{not_a_file}"
        );
        assert!(matches!(
            read_file(&dir.path().join("absent.log")),
            Err(ReadError::Input(InputError::Io { .. }))
        ));
    }

    /// A bus that answers nothing and whose clock jumps to every deadline.
    struct Silent(Duration);

    impl CanBus for Silent {
        fn name(&self) -> &str {
            "vcan0"
        }
        fn now(&self) -> Duration {
            self.0
        }
        fn send(&mut self, _: &CanFrame) -> Result<(), BusError> {
            Ok(())
        }
        fn recv_until(&mut self, deadline: Duration) -> Result<Option<CanFrame>, BusError> {
            self.0 = self.0.max(deadline);
            Ok(None)
        }
    }

    #[test]
    fn the_recording_is_bounded() {
        let mut bus = RecordingBus::with_limit(Silent(Duration::ZERO), Duration::MAX, 3);
        let sync = CanFrame::new(0x080, &[]).unwrap();
        for _ in 0..3 {
            bus.send(&sync).unwrap();
        }
        let err = bus.send(&sync).unwrap_err();
        assert!(
            err.to_string().contains("recording is full (3 frames)"),
            "{err}"
        );
        assert!(bus.recv_until(Duration::from_secs(1)).is_err());
        assert_eq!(bus.log().len(), 3);
        // An epoch near the end of time saturates instead of overflowing.
        assert_eq!(bus.log()[0].time, Duration::MAX);
        assert_eq!(
            RecordingBus::new(Silent(Duration::ZERO), Duration::ZERO).max_frames(),
            MAX_RECORDED_FRAMES
        );
    }

    #[test]
    fn replay_refuses_logs_longer_than_its_span() {
        let log = parse(&format!(
            "(1.000000) can0 080#\n({}.000000) can0 080#\n",
            MAX_TIMESTAMP_S
        ))
        .unwrap();
        let err = replay(&log, &mut Silent(Duration::ZERO)).unwrap_err();
        assert!(matches!(err, ReplayError::TooLong { .. }), "{err}");
        let short =
            parse("(5.000000) can0 080#\n(3.000000) can0 080#\n(6.000000) can0 080#\n").unwrap();
        assert_eq!(replay(&short, &mut Silent(Duration::ZERO)), Ok(Vec::new()));
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
        fn parsing_arbitrary_bytes_never_panics(
            bytes in proptest::collection::vec(any::<u8>(), 0..200)
        ) {
            let _ = parse_bytes(&bytes);
        }

        #[test]
        fn parsing_near_miss_lines_never_panics(
            line in "\\([0-9+.-]{0,22}\\) [a-z0-9]{1,4} [0-9A-Fa-fxR#]{0,24}"
        ) {
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
