//! One evaluation episode as a CSV: a header line ([`HEADER`]) and one line per control-tick
//! sample ([`EpisodeRow`]), comma-separated, no quoting. `phase` is the phase's lowercase name,
//! `ground_contact` is `0` or `1`, every other field a decimal number written so that it reads
//! back to the same `f64`.
//!
//! What [`read_csv`] accepts is exactly what [`write_csv`] writes: every number finite, `t_s`
//! strictly increasing, tilt within 0–180° and grasp forces non-negative (both are magnitudes).
//! A file breaking a rule is refused with its path, line and column, so a hand-edited or
//! truncated file never yields metrics silently.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{anyhow, Context, Result};
use moonhaul_core::state::Phase;

/// Largest episode CSV accepted, bytes: ~200 bytes a row, so over 300 000 samples (an hour at
/// 100 Hz), far above any episode.
pub const MAX_EPISODE_CSV_BYTES: u64 = 64 << 20;

/// The column names, in file order.
pub const COLUMNS: [&str; 13] = [
    "t_s",
    "phase",
    "goal_height_m",
    "payload_height_m",
    "payload_tilt_deg",
    "payload_vx_mps",
    "payload_vy_mps",
    "payload_vz_mps",
    "command_vx_mps",
    "command_vy_mps",
    "ground_contact",
    "grasp_force_1_n",
    "grasp_force_2_n",
];

/// The first line of every episode CSV.
pub const HEADER: &str = "t_s,phase,goal_height_m,payload_height_m,payload_tilt_deg,\
payload_vx_mps,payload_vy_mps,payload_vz_mps,command_vx_mps,command_vy_mps,ground_contact,\
grasp_force_1_n,grasp_force_2_n";

/// One sample of an evaluation episode; the fields are the CSV columns, in order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeRow {
    /// Episode time, s.
    pub t_s: f64,
    /// The active mission phase.
    pub phase: Phase,
    /// Target payload height h* of the phase, m.
    pub goal_height_m: f64,
    /// Payload bottom-face height above the ground, m (0 resting on flat ground).
    pub payload_height_m: f64,
    /// Angle between the payload's up axis and world up, degrees (0–180).
    pub payload_tilt_deg: f64,
    /// Payload linear velocity, world frame, m/s.
    pub payload_vx_mps: f64,
    pub payload_vy_mps: f64,
    pub payload_vz_mps: f64,
    /// Commanded planar payload velocity v_cmd, world frame, m/s.
    pub command_vx_mps: f64,
    pub command_vy_mps: f64,
    /// Whether the payload touches the ground.
    pub ground_contact: bool,
    /// Grasp force magnitude of unit 1 and unit 2, N (about 0 once released).
    pub grasp_force_1_n: f64,
    pub grasp_force_2_n: f64,
}

/// A rule a row breaks: the column at fault and why.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RowFault {
    pub column: &'static str,
    pub reason: String,
}

impl EpisodeRow {
    /// The numeric columns with their names, in file order.
    fn numbers(&self) -> [(&'static str, f64); 11] {
        [
            ("t_s", self.t_s),
            ("goal_height_m", self.goal_height_m),
            ("payload_height_m", self.payload_height_m),
            ("payload_tilt_deg", self.payload_tilt_deg),
            ("payload_vx_mps", self.payload_vx_mps),
            ("payload_vy_mps", self.payload_vy_mps),
            ("payload_vz_mps", self.payload_vz_mps),
            ("command_vx_mps", self.command_vx_mps),
            ("command_vy_mps", self.command_vy_mps),
            ("grasp_force_1_n", self.grasp_force_1_n),
            ("grasp_force_2_n", self.grasp_force_2_n),
        ]
    }

    /// Checks the rules of the [module docs](self); `previous_t_s` is the time of the row
    /// before, if any. Shared by the reader, the writer and the metrics, so all three agree.
    pub(crate) fn check(&self, previous_t_s: Option<f64>) -> Result<(), RowFault> {
        let fault = |column, reason: String| Err(RowFault { column, reason });
        for (column, value) in self.numbers() {
            if !value.is_finite() {
                return fault(column, format!("{value} is not a finite number"));
            }
        }
        if !(0.0..=180.0).contains(&self.payload_tilt_deg) {
            let tilt = self.payload_tilt_deg;
            return fault("payload_tilt_deg", format!("{tilt} is outside 0–180°"));
        }
        for (column, force) in [
            ("grasp_force_1_n", self.grasp_force_1_n),
            ("grasp_force_2_n", self.grasp_force_2_n),
        ] {
            if force < 0.0 {
                return fault(column, format!("{force} is negative (a force magnitude)"));
            }
        }
        match previous_t_s {
            Some(previous) if self.t_s <= previous => fault(
                "t_s",
                format!("{} does not increase (previous row: {previous})", self.t_s),
            ),
            _ => Ok(()),
        }
    }

    fn write_line(&self, out: &mut String) {
        // `{}` of f64 is the shortest decimal that parses back to the same value.
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.t_s,
            self.phase.name(),
            self.goal_height_m,
            self.payload_height_m,
            self.payload_tilt_deg,
            self.payload_vx_mps,
            self.payload_vy_mps,
            self.payload_vz_mps,
            self.command_vx_mps,
            self.command_vy_mps,
            u8::from(self.ground_contact),
            self.grasp_force_1_n,
            self.grasp_force_2_n,
        );
    }

    /// Parses one data line (without its line ending).
    fn parse(line: &str) -> Result<Self, LineFault> {
        if line.is_empty() {
            return Err(LineFault::new(COLUMNS[0], "empty line".into()));
        }
        let fields: Vec<&str> = line.split(',').collect();
        check_count(fields.len(), |i| fields[i])?;
        let number = |i: usize| -> Result<f64, LineFault> {
            fields[i]
                .parse()
                .map_err(|_| LineFault::new(COLUMNS[i], format!("{:?} is not a number", fields[i])))
        };
        let phase = fields[1]
            .parse::<Phase>()
            .map_err(|e| LineFault::new(COLUMNS[1], e.to_string()))?;
        let ground_contact = match fields[10] {
            "0" => false,
            "1" => true,
            other => {
                let reason = format!("{other:?} is neither 0 nor 1");
                return Err(LineFault::new(COLUMNS[10], reason));
            }
        };
        Ok(Self {
            t_s: number(0)?,
            phase,
            goal_height_m: number(2)?,
            payload_height_m: number(3)?,
            payload_tilt_deg: number(4)?,
            payload_vx_mps: number(5)?,
            payload_vy_mps: number(6)?,
            payload_vz_mps: number(7)?,
            command_vx_mps: number(8)?,
            command_vy_mps: number(9)?,
            ground_contact,
            grasp_force_1_n: number(11)?,
            grasp_force_2_n: number(12)?,
        })
    }
}

/// What is wrong on one line: the column (a name, or a position past the last one) and why.
#[derive(Debug)]
struct LineFault {
    column: String,
    reason: String,
}

impl LineFault {
    fn new(column: &str, reason: String) -> Self {
        Self {
            column: column.to_owned(),
            reason,
        }
    }
}

/// Refuses a line of `count` fields unless it has one per column; `field(i)` is field i.
fn check_count<'a>(count: usize, field: impl Fn(usize) -> &'a str) -> Result<(), LineFault> {
    let expected = COLUMNS.len();
    if count < expected {
        let reason = format!("missing (the line has {count} of {expected} fields)");
        return Err(LineFault::new(COLUMNS[count], reason));
    }
    if count > expected {
        let column = format!("{} (after {})", expected + 1, COLUMNS[expected - 1]);
        let reason = format!(
            "extra field {:?} (the line has {count} fields, expected {expected})",
            field(expected)
        );
        return Err(LineFault { column, reason });
    }
    Ok(())
}

fn check_header(line: &str) -> Result<(), LineFault> {
    let names: Vec<&str> = line.split(',').collect();
    for (name, expected) in names.iter().zip(COLUMNS) {
        if *name != expected {
            let reason = format!("header has {name:?} here; expected the header {HEADER:?}");
            return Err(LineFault::new(expected, reason));
        }
    }
    check_count(names.len(), |i| names[i]).map_err(|fault| LineFault {
        reason: format!("{} in the header; expected {HEADER:?}", fault.reason),
        ..fault
    })
}

/// Writes `rows` to `path` atomically (a reader sees the old file or the new one), creating
/// missing parent folders. Rows that [`read_csv`] would refuse are refused first, before the
/// file is touched.
pub fn write_csv(path: &Path, rows: &[EpisodeRow]) -> Result<()> {
    let mut previous = None;
    for (i, row) in rows.iter().enumerate() {
        row.check(previous).map_err(|f| {
            anyhow!(
                "refusing to write {}: line {} (row {i}), column {}: {}",
                path.display(),
                i + 2,
                f.column,
                f.reason
            )
        })?;
        previous = Some(row.t_s);
    }
    let mut text = String::with_capacity(HEADER.len() + 1 + 200 * rows.len());
    text.push_str(HEADER);
    text.push('\n');
    for row in rows {
        row.write_line(&mut text);
    }
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create folder {}", parent.display()))?;
    }
    moonhaul_core::atomic_file::write(path, text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Reads an episode CSV written by [`write_csv`] (or by hand, following the
/// [module docs](self)); the file is size-capped at [`MAX_EPISODE_CSV_BYTES`]. Every error
/// names the file, the line and the column.
pub fn read_csv(path: &Path) -> Result<Vec<EpisodeRow>> {
    let text = moonhaul_core::input::read_capped_text(path, MAX_EPISODE_CSV_BYTES)?;
    parse(&text).map_err(|(line, fault)| {
        anyhow!(
            "{}: line {line}, column {}: {}",
            path.display(),
            fault.column,
            fault.reason
        )
    })
}

/// Parses a whole file; an error carries its 1-based line number.
fn parse(text: &str) -> Result<Vec<EpisodeRow>, (usize, LineFault)> {
    let mut lines = text.lines();
    check_header(lines.next().unwrap_or("")).map_err(|f| (1, f))?;
    let mut rows: Vec<EpisodeRow> = Vec::new();
    for (i, line) in lines.enumerate() {
        let line_number = i + 2;
        let row = EpisodeRow::parse(line).map_err(|f| (line_number, f))?;
        row.check(rows.last().map(|r| r.t_s))
            .map_err(|f| (line_number, LineFault::new(f.column, f.reason)))?;
        rows.push(row);
    }
    Ok(rows)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A held, level, motionless sample at time `t_s`; tests change the fields they need.
    pub(crate) fn sample(t_s: f64) -> EpisodeRow {
        EpisodeRow {
            t_s,
            phase: Phase::Lift,
            goal_height_m: 0.3,
            payload_height_m: 0.0,
            payload_tilt_deg: 0.0,
            payload_vx_mps: 0.0,
            payload_vy_mps: 0.0,
            payload_vz_mps: 0.0,
            command_vx_mps: 0.0,
            command_vy_mps: 0.0,
            ground_contact: false,
            grasp_force_1_n: 20.0,
            grasp_force_2_n: 20.0,
        }
    }

    fn awkward_rows() -> Vec<EpisodeRow> {
        Phase::ALL
            .into_iter()
            .enumerate()
            .map(|(i, phase)| EpisodeRow {
                t_s: 0.1 * i as f64 + 0.2,
                phase,
                goal_height_m: 0.1 + 0.2,
                payload_height_m: -1e-300,
                payload_tilt_deg: 180.0 / 7.0,
                payload_vx_mps: 1e21,
                payload_vy_mps: -0.0,
                payload_vz_mps: std::f64::consts::PI,
                command_vx_mps: f64::MIN_POSITIVE,
                command_vy_mps: -123456.789,
                ground_contact: i % 2 == 1,
                grasp_force_1_n: 0.0,
                grasp_force_2_n: 5e-324,
            })
            .collect()
    }

    fn bits(row: &EpisodeRow) -> Vec<u64> {
        row.numbers().iter().map(|(_, v)| v.to_bits()).collect()
    }

    #[test]
    fn header_is_the_columns() {
        assert_eq!(HEADER, COLUMNS.join(","));
    }

    #[test]
    fn round_trips_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("new").join("folder").join("lift_0.csv");
        let rows = awkward_rows();
        write_csv(&path, &rows).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.lines().next(), Some(HEADER));
        assert!(
            text.contains(",transport,") && text.contains(",1,0,"),
            "{text}"
        );
        let back = read_csv(&path).unwrap();
        assert_eq!(back.len(), rows.len());
        for (a, b) in rows.iter().zip(&back) {
            assert_eq!((a.phase, a.ground_contact), (b.phase, b.ground_contact));
            assert_eq!(bits(a), bits(b));
        }
        // No rows: the header alone, read back as no rows.
        write_csv(&path, &[]).unwrap();
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            format!("{HEADER}\n")
        );
        assert!(read_csv(&path).unwrap().is_empty());
        // CRLF line endings and a missing final newline read the same.
        let crlf = format!("{HEADER}\r\n0,place,0,0.01,1,0,0,-0.03,0,0,1,0,0");
        std::fs::write(&path, crlf).unwrap();
        let rows = read_csv(&path).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].phase, Phase::Place);
        assert!(rows[0].ground_contact);
    }

    #[test]
    fn write_refuses_rows_read_would_refuse() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.csv");
        let nan = EpisodeRow {
            payload_vz_mps: f64::NAN,
            ..sample(0.0)
        };
        let err = write_csv(&path, &[sample(0.0), sample(0.5), nan]).unwrap_err();
        let message = err.to_string();
        assert!(message.contains("bad.csv"), "{message}");
        assert!(
            message.contains("line 4 (row 2), column payload_vz_mps"),
            "{message}"
        );
        assert!(!path.exists());
        let err = write_csv(&path, &[sample(1.0), sample(1.0)]).unwrap_err();
        assert!(
            err.to_string().contains("line 3 (row 1), column t_s"),
            "{err}"
        );
        assert!(!path.exists());
    }

    /// Writes `text` as an episode CSV and returns the error reading it gives.
    fn read_error(text: &str) -> String {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("episode.csv");
        std::fs::write(&path, text).unwrap();
        let message = read_csv(&path).unwrap_err().to_string();
        assert!(
            message.starts_with(&format!("{}: line ", path.display())),
            "{message}"
        );
        message
    }

    #[test]
    fn malformed_files_name_file_line_and_column() {
        let good = "0,lift,0.3,0.01,2,0,0,0.1,0,0,0,20,20";
        let file = |body: &[&str]| format!("{HEADER}\n{}\n", body.join("\n"));
        let cases: Vec<(String, &str)> = vec![
            (String::new(), "line 1, column t_s"),
            (
                HEADER.replace("payload_tilt_deg", "tilt"),
                "line 1, column payload_tilt_deg",
            ),
            (
                format!("{HEADER},extra\n"),
                "line 1, column 14 (after grasp_force_2_n)",
            ),
            (
                HEADER.replace(",grasp_force_2_n", ""),
                "line 1, column grasp_force_2_n",
            ),
            (
                file(&[good, &format!("{good},7")]),
                "line 3, column 14 (after grasp_force_2_n)",
            ),
            (
                file(&[good, "0.5,lift,0.3,0.01"]),
                "line 3, column payload_tilt_deg: missing",
            ),
            (
                file(&[&good.replacen("0.01", "nan", 1)]),
                "line 2, column payload_height_m",
            ),
            (
                file(&[&good.replacen("0.1", "inf", 1)]),
                "line 2, column payload_vz_mps",
            ),
            (
                file(&[&good.replacen("0.01", "1cm", 1)]),
                "line 2, column payload_height_m",
            ),
            (
                file(&[&good.replace("lift", "hover")]),
                "line 2, column phase: unknown phase",
            ),
            (
                file(&[&good.replace(",0,20,", ",true,20,")]),
                "line 2, column ground_contact",
            ),
            (
                file(&[good, good]),
                "line 3, column t_s: 0 does not increase",
            ),
            (file(&[good, "", good]), "line 3, column t_s: empty line"),
            (
                file(&[&good.replacen(",2,", ",-1,", 1)]),
                "line 2, column payload_tilt_deg",
            ),
            (
                file(&[&good.replacen(",20,", ",-3,", 1)]),
                "line 2, column grasp_force_1_n",
            ),
        ];
        for (text, expected) in cases {
            let message = read_error(&text);
            assert!(
                message.contains(expected),
                "{expected:?} not in {message:?}"
            );
        }
    }

    #[test]
    fn non_files_and_oversized_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let err = read_csv(dir.path()).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        let err = read_csv(&dir.path().join("absent.csv"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("absent.csv"), "{err}");
    }
}
