//! `metrics.csv`: one row per iteration, flushed as it is written so a crash or Ctrl-C loses
//! nothing, and read back when a run resumes (rows past the checkpoint are dropped, since the
//! resumed run recomputes them).
//!
//! A run with a warm start ([`crate::distill`]) begins with its rows, all at iteration 0 (they
//! come before PPO's first), in order: one per DAgger round (`bc_loss`, `dagger_beta`,
//! `expert_agreement` filled; no PPO losses), then one per critic warm-up iteration
//! (`value_loss` and `explained_variance`). The last of them carries the evaluation of the
//! warm actor. PPO rows fill `explained_variance` too: whether the critic keeps up.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::actor_critic::ActorCritic;
use crate::distill::{WarmStage, WarmStats};
use crate::gaussian;
use crate::runner::IterationStats;
use crate::LearnError;

pub const HEADER: &str = "iteration,env_steps,mean_return,mean_episode_length,eval_return,\
value_loss,surrogate_loss,entropy,mean_std,kl,lr,steps_per_s,mean_t_max,hold_fraction,\
mean_grasp_force_n,peak_grasp_force_n,bc_loss,dagger_beta,expert_agreement,explained_variance,\
bc_coef";

/// Columns every file has had since the action pipeline's were added. A file written before
/// later columns were (the warm start's, kickstarting's) has a prefix of [`HEADER`] with at
/// least these: it still resumes, its rows without the later columns.
const MIN_COLUMNS: usize = 16;

/// One iteration's figures; `None` is an empty CSV cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MetricsRow {
    /// PPO iterations completed; 0 for the warm start's rows.
    pub iteration: usize,
    pub env_steps: u64,
    pub mean_return: Option<f64>,
    pub mean_episode_length: Option<f64>,
    /// Deterministic-policy mean return, on evaluation iterations only.
    pub eval_return: Option<f64>,
    /// PPO's and the critic warm-up's value loss (none in a DAgger round).
    pub value_loss: Option<f64>,
    /// PPO only, as `kl`.
    pub surrogate_loss: Option<f64>,
    pub entropy: f64,
    pub mean_std: f64,
    pub kl: Option<f64>,
    pub lr: f64,
    pub steps_per_s: f64,
    /// The action pipeline over the iteration's rollout (phase tasks; empty for Pendulum):
    /// mean issued t_max per unit tick, fraction of unit ticks that held, and the mean and
    /// peak grasp force magnitude per unit, N.
    pub mean_t_max: Option<f64>,
    pub hold_fraction: Option<f64>,
    pub mean_grasp_force_n: Option<f64>,
    pub peak_grasp_force_n: Option<f64>,
    /// A DAgger round's behaviour-cloning loss: the mean squared error of the actor's mean to
    /// the expert's raw actions over the round's fit.
    pub bc_loss: Option<f64>,
    /// The share of rows the expert drove in the DAgger round.
    pub dagger_beta: Option<f64>,
    /// The share of the DAgger round's rows where the actor's mean was within
    /// [`crate::distill::AGREEMENT_TOLERANCE`] of the expert's action in every component.
    pub expert_agreement: Option<f64>,
    /// `1 − Var[returns − values] / Var[returns]` over the rollout, before its update.
    pub explained_variance: Option<f64>,
    /// A kickstarted PPO iteration's behaviour-cloning weight ([`crate::kickstart`]); its
    /// `bc_loss` and `expert_agreement` are then the update's and the rollout's.
    pub bc_coef: Option<f64>,
}

impl MetricsRow {
    pub fn new(stats: &IterationStats, eval_return: Option<f64>) -> Self {
        MetricsRow {
            iteration: stats.progress.iteration,
            env_steps: stats.progress.env_steps,
            mean_return: stats.mean_return,
            mean_episode_length: stats.mean_episode_length,
            eval_return,
            value_loss: Some(stats.update.value_loss),
            surrogate_loss: Some(stats.update.surrogate_loss),
            entropy: stats.update.entropy,
            mean_std: stats.mean_std,
            kl: Some(stats.update.kl),
            lr: stats.lr,
            steps_per_s: stats.steps_per_s,
            mean_t_max: stats.pipeline.and_then(|p| p.clamp.mean_t_max()),
            hold_fraction: stats.pipeline.and_then(|p| p.clamp.hold_fraction()),
            mean_grasp_force_n: stats.pipeline.and_then(|p| p.mean_grasp_force_n()),
            peak_grasp_force_n: stats.pipeline.and_then(|p| p.peak_grasp_force_n()),
            bc_loss: stats.kickstart.map(|k| k.bc_loss),
            dagger_beta: None,
            expert_agreement: stats.kickstart.map(|k| k.expert_agreement),
            explained_variance: stats.update.explained_variance,
            bc_coef: stats.kickstart.map(|k| k.coef),
        }
    }

    /// A warm-start row: `env_steps` counts every transition of the run so far, `policy` is
    /// the policy after the round (its std and entropy), `lr` the warm start's rate.
    pub fn warm(stats: &WarmStats, env_steps: u64, policy: &ActorCritic, lr: f64) -> Self {
        let std = policy.std();
        let (value_loss, explained_variance, dagger) = match stats.stage {
            WarmStage::Dagger {
                beta,
                bc_loss,
                expert_agreement,
            } => (None, None, Some((bc_loss, beta, expert_agreement))),
            WarmStage::Critic {
                value_loss,
                explained_variance,
            } => (Some(value_loss), explained_variance, None),
        };
        MetricsRow {
            iteration: 0,
            env_steps,
            mean_return: stats.mean_return,
            mean_episode_length: stats.mean_episode_length,
            eval_return: None,
            value_loss,
            surrogate_loss: None,
            entropy: gaussian::entropy(&std).double_value(&[]),
            mean_std: std.mean(tch::Kind::Float).double_value(&[]),
            kl: None,
            lr,
            steps_per_s: stats.steps_per_s,
            mean_t_max: stats.pipeline.and_then(|p| p.clamp.mean_t_max()),
            hold_fraction: stats.pipeline.and_then(|p| p.clamp.hold_fraction()),
            mean_grasp_force_n: stats.pipeline.and_then(|p| p.mean_grasp_force_n()),
            peak_grasp_force_n: stats.pipeline.and_then(|p| p.peak_grasp_force_n()),
            bc_loss: dagger.map(|d| d.0),
            dagger_beta: dagger.map(|d| d.1),
            expert_agreement: dagger.map(|d| d.2),
            explained_variance,
            bc_coef: None,
        }
    }

    pub fn to_csv(&self) -> String {
        let opt = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
        [
            self.iteration.to_string(),
            self.env_steps.to_string(),
            opt(self.mean_return),
            opt(self.mean_episode_length),
            opt(self.eval_return),
            opt(self.value_loss),
            opt(self.surrogate_loss),
            self.entropy.to_string(),
            self.mean_std.to_string(),
            opt(self.kl),
            self.lr.to_string(),
            self.steps_per_s.to_string(),
            opt(self.mean_t_max),
            opt(self.hold_fraction),
            opt(self.mean_grasp_force_n),
            opt(self.peak_grasp_force_n),
            opt(self.bc_loss),
            opt(self.dagger_beta),
            opt(self.expert_agreement),
            opt(self.explained_variance),
            opt(self.bc_coef),
        ]
        .join(",")
    }

    /// One line of a file with this build's [`HEADER`].
    pub fn parse(line: &str) -> Result<Self, String> {
        Self::parse_columns(line, HEADER.split(',').count())
    }

    /// One line of a file whose first `columns` columns are [`HEADER`]'s: the later ones read
    /// as empty.
    fn parse_columns(line: &str, columns: usize) -> Result<Self, String> {
        let mut cells: Vec<&str> = line.split(',').collect();
        if cells.len() != columns {
            return Err(format!("{} columns, expected {columns}", cells.len()));
        }
        cells.resize(HEADER.split(',').count(), "");
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
            value_loss: opt(5)?,
            surrogate_loss: opt(6)?,
            entropy: num(7)?,
            mean_std: num(8)?,
            kl: opt(9)?,
            lr: num(10)?,
            steps_per_s: num(11)?,
            mean_t_max: opt(12)?,
            hold_fraction: opt(13)?,
            mean_grasp_force_n: opt(14)?,
            peak_grasp_force_n: opt(15)?,
            bc_loss: opt(16)?,
            dagger_beta: opt(17)?,
            expert_agreement: opt(18)?,
            explained_variance: opt(19)?,
            bc_coef: opt(20)?,
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
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let columns = header.len();
    if columns < MIN_COLUMNS || !HEADER.split(',').take(columns).eq(header) {
        return Err(bad(1, "header differs from this build's columns".into()));
    }
    lines
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| MetricsRow::parse_columns(l, columns).map_err(|e| bad(i + 2, e)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(i: usize, eval: Option<f64>) -> MetricsRow {
        MetricsRow {
            iteration: i,
            env_steps: 64 * i as u64,
            mean_return: (i > 1).then_some(-1234.5),
            mean_episode_length: (i > 1).then_some(200.0),
            eval_return: eval,
            value_loss: Some(0.1),
            surrogate_loss: Some(-0.01),
            entropy: 1.4,
            mean_std: 0.9,
            kl: Some(0.008),
            lr: 1e-3,
            steps_per_s: 5000.0,
            mean_t_max: (i > 2).then_some(0.875),
            hold_fraction: (i > 2).then_some(0.03125),
            mean_grasp_force_n: (i > 2).then_some(41.5),
            peak_grasp_force_n: (i > 2).then_some(97.25),
            bc_loss: None,
            dagger_beta: None,
            expert_agreement: None,
            explained_variance: (i > 2).then_some(0.625),
            bc_coef: None,
        }
    }

    #[test]
    fn rows_round_trip_and_resume_drops_later_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
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

    #[test]
    fn warm_start_rows_round_trip_and_survive_a_resume_at_zero() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let dagger = MetricsRow {
            value_loss: None,
            surrogate_loss: None,
            kl: None,
            bc_loss: Some(0.0625),
            dagger_beta: Some(0.5),
            expert_agreement: Some(0.25),
            explained_variance: None,
            ..row(0, None)
        };
        let critic = MetricsRow {
            surrogate_loss: None,
            kl: None,
            explained_variance: Some(-0.5),
            env_steps: 100,
            ..row(0, Some(-50.5))
        };
        let mut log = MetricsLog::open(&path, None).unwrap();
        for r in [dagger, critic, row(1, None)] {
            log.append(r).unwrap();
        }
        drop(log);
        assert_eq!(read_rows(&path).unwrap(), [dagger, critic, row(1, None)]);
        // Resumed from the checkpoint written after the warm start: its rows stay.
        let log = MetricsLog::open(&path, Some(0)).unwrap();
        assert_eq!(log.rows(), &[dagger, critic]);
    }

    #[test]
    fn kickstart_rows_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let kick = MetricsRow {
            bc_loss: Some(0.125),
            expert_agreement: Some(0.75),
            bc_coef: Some(0.5),
            ..row(3, None)
        };
        MetricsLog::open(&path, None).unwrap().append(kick).unwrap();
        assert_eq!(read_rows(&path).unwrap(), [kick]);
    }

    #[test]
    fn a_file_from_before_the_warm_start_columns_still_resumes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let old = row(1, Some(-3.5));
        let cells: Vec<String> = old.to_csv().split(',').take(16).map(String::from).collect();
        let header: Vec<&str> = HEADER.split(',').take(16).collect();
        std::fs::write(
            &path,
            format!("{}\n{}\n", header.join(","), cells.join(",")),
        )
        .unwrap();
        let read = read_rows(&path).unwrap();
        assert_eq!(
            read,
            [MetricsRow {
                explained_variance: None,
                ..old
            }]
        );
        // A line with the new columns under the old header is refused, by line.
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str(&format!("{}\n", row(2, None).to_csv()));
        std::fs::write(&path, text).unwrap();
        let err = read_rows(&path).unwrap_err().to_string();
        assert!(err.contains(":3:") && err.contains("21 columns"), "{err}");
    }
}
