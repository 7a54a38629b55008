//! `metrics.csv`: one row per iteration, flushed as it is written so a crash or Ctrl-C loses
//! nothing, and read back when a run resumes (rows past the checkpoint are dropped, since the
//! resumed run recomputes them).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::runner::IterationStats;
use crate::LearnError;

pub const HEADER: &str = "iteration,env_steps,mean_return,mean_episode_length,eval_return,\
value_loss,surrogate_loss,entropy,mean_std,kl,lr,steps_per_s,mean_t_max,hold_fraction,\
mean_grasp_force_n,peak_grasp_force_n";

/// One iteration's figures; `None` is an empty CSV cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricsRow {
    pub iteration: usize,
    pub env_steps: u64,
    pub mean_return: Option<f64>,
    pub mean_episode_length: Option<f64>,
    /// Deterministic-policy mean return, on evaluation iterations only.
    pub eval_return: Option<f64>,
    pub value_loss: f64,
    pub surrogate_loss: f64,
    pub entropy: f64,
    pub mean_std: f64,
    pub kl: f64,
    pub lr: f64,
    pub steps_per_s: f64,
    /// The action pipeline over the iteration's rollout (phase tasks; empty for Pendulum):
    /// mean issued t_max per unit tick, fraction of unit ticks that held, and the mean and
    /// peak grasp force magnitude per unit, N.
    pub mean_t_max: Option<f64>,
    pub hold_fraction: Option<f64>,
    pub mean_grasp_force_n: Option<f64>,
    pub peak_grasp_force_n: Option<f64>,
}

impl MetricsRow {
    pub fn new(stats: &IterationStats, eval_return: Option<f64>) -> Self {
        MetricsRow {
            iteration: stats.progress.iteration,
            env_steps: stats.progress.env_steps,
            mean_return: stats.mean_return,
            mean_episode_length: stats.mean_episode_length,
            eval_return,
            value_loss: stats.update.value_loss,
            surrogate_loss: stats.update.surrogate_loss,
            entropy: stats.update.entropy,
            mean_std: stats.mean_std,
            kl: stats.update.kl,
            lr: stats.lr,
            steps_per_s: stats.steps_per_s,
            mean_t_max: stats.pipeline.and_then(|p| p.clamp.mean_t_max()),
            hold_fraction: stats.pipeline.and_then(|p| p.clamp.hold_fraction()),
            mean_grasp_force_n: stats.pipeline.and_then(|p| p.mean_grasp_force_n()),
            peak_grasp_force_n: stats.pipeline.and_then(|p| p.peak_grasp_force_n()),
        }
    }

    pub fn to_csv(&self) -> String {
        let opt = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
        format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.iteration,
            self.env_steps,
            opt(self.mean_return),
            opt(self.mean_episode_length),
            opt(self.eval_return),
            self.value_loss,
            self.surrogate_loss,
            self.entropy,
            self.mean_std,
            self.kl,
            self.lr,
            self.steps_per_s,
            opt(self.mean_t_max),
            opt(self.hold_fraction),
            opt(self.mean_grasp_force_n),
            opt(self.peak_grasp_force_n)
        )
    }

    pub fn parse(line: &str) -> Result<Self, String> {
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != HEADER.split(',').count() {
            return Err(format!(
                "{} columns, expected {}",
                cells.len(),
                HEADER.split(',').count()
            ));
        }
        let num = |i: usize| -> Result<f64, String> {
            cells[i]
                .parse()
                .map_err(|_| format!("column {} = {:?} is not a number", i + 1, cells[i]))
        };
        let opt = |i: usize| {
            if cells[i].is_empty() {
                Ok(None)
            } else {
                num(i).map(Some)
            }
        };
        let int = |i: usize| {
            cells[i]
                .parse::<u64>()
                .map_err(|_| format!("column {} = {:?} is not a count", i + 1, cells[i]))
        };
        Ok(MetricsRow {
            iteration: int(0)? as usize,
            env_steps: int(1)?,
            mean_return: opt(2)?,
            mean_episode_length: opt(3)?,
            eval_return: opt(4)?,
            value_loss: num(5)?,
            surrogate_loss: num(6)?,
            entropy: num(7)?,
            mean_std: num(8)?,
            kl: num(9)?,
            lr: num(10)?,
            steps_per_s: num(11)?,
            mean_t_max: opt(12)?,
            hold_fraction: opt(13)?,
            mean_grasp_force_n: opt(14)?,
            peak_grasp_force_n: opt(15)?,
        })
    }
}

/// The open `metrics.csv` and every row of the run so far (for the plots).
#[derive(Debug)]
pub struct MetricsLog {
    path: PathBuf,
    file: BufWriter<File>,
    rows: Vec<MetricsRow>,
}

impl MetricsLog {
    /// Starts `path` afresh, or with `resume_at = Some(i)` keeps its rows up to iteration `i`.
    pub fn open(path: &Path, resume_at: Option<usize>) -> Result<Self, LearnError> {
        let rows = match resume_at {
            Some(last) if path.exists() => read_rows(path)?
                .into_iter()
                .filter(|r| r.iteration <= last)
                .collect(),
            _ => Vec::new(),
        };
        let mut file = BufWriter::new(File::create(path).map_err(LearnError::io(path))?);
        let mut text = format!("{HEADER}\n");
        rows.iter()
            .for_each(|r| text.push_str(&format!("{}\n", r.to_csv())));
        file.write_all(text.as_bytes())
            .and_then(|()| file.flush())
            .map_err(LearnError::io(path))?;
        Ok(MetricsLog {
            path: path.to_path_buf(),
            file,
            rows,
        })
    }

    pub fn append(&mut self, row: MetricsRow) -> Result<(), LearnError> {
        writeln!(self.file, "{}", row.to_csv())
            .and_then(|()| self.file.flush())
            .map_err(LearnError::io(&self.path))?;
        self.rows.push(row);
        Ok(())
    }

    pub fn rows(&self) -> &[MetricsRow] {
        &self.rows
    }
}

/// Every row of a run's `metrics.csv`.
pub fn read_rows(path: &Path) -> Result<Vec<MetricsRow>, LearnError> {
    let bad = |line: usize, reason: String| LearnError::Metrics {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let text =
        moonhaul_core::input::read_capped_text(path, moonhaul_core::input::MAX_RUN_LOG_BYTES)?;
    let mut lines = text.lines();
    if lines.next() != Some(HEADER) {
        return Err(bad(1, "header differs from this build's columns".into()));
    }
    lines
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| MetricsRow::parse(l).map_err(|e| bad(i + 2, e)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_resume_drops_later_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let row = |i: usize, eval: Option<f64>| MetricsRow {
            iteration: i,
            env_steps: 64 * i as u64,
            mean_return: (i > 1).then_some(-1234.5),
            mean_episode_length: (i > 1).then_some(200.0),
            eval_return: eval,
            value_loss: 0.1,
            surrogate_loss: -0.01,
            entropy: 1.4,
            mean_std: 0.9,
            kl: 0.008,
            lr: 1e-3,
            steps_per_s: 5000.0,
            mean_t_max: (i > 2).then_some(0.875),
            hold_fraction: (i > 2).then_some(0.03125),
            mean_grasp_force_n: (i > 2).then_some(41.5),
            peak_grasp_force_n: (i > 2).then_some(97.25),
        };
        let mut log = MetricsLog::open(&path, None).unwrap();
        for i in 1..=4 {
            log.append(row(i, (i % 2 == 0).then_some(-300.25))).unwrap();
        }
        drop(log);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.lines().nth(1).unwrap().starts_with("1,64,,,,"));
        let log = MetricsLog::open(&path, Some(2)).unwrap();
        assert_eq!(log.rows(), &[row(1, None), row(2, Some(-300.25))]);
        assert_eq!(std::fs::read_to_string(&path).unwrap().lines().count(), 3);
        // The pipeline columns round-trip too (row 3 carries them).
        let mut log = MetricsLog::open(&path, Some(2)).unwrap();
        log.append(row(3, None)).unwrap();
        assert_eq!(read_rows(&path).unwrap()[2], row(3, None));
    }
}
