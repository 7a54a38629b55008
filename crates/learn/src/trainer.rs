//! A training run on disk: the run folder, its resolved config, `metrics.csv`, plots,
//! periodic checkpoints, resume, a clean stop, and the exported policy.
//!
//! ```text
//! <run>/config.toml                         the resolved config (after --seed)
//! <run>/metrics.csv                         one row per iteration (and warm-start round)
//! <run>/return.png, <run>/entropy.png       learning curves
//! <run>/checkpoints/iter_NNNNNN.safetensors checkpoints (see crate::checkpoint)
//! <run>/policy.safetensors                  the actor as an onboard policy file
//! <run>/best_policy.safetensors             --export-best (export_checkpoint)
//! <run>/policy_iter_NNNNNN.safetensors      --export-iteration N (export_checkpoint)
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use moonhaul_core::policy::Policy;
use moonhaul_core::state::Phase;
use moonhaul_env::export::policy_provenance;

use crate::actor_critic::ActorCritic;
use crate::checkpoint::{self, write_atomic};
use crate::config::TrainConfig;
use crate::distill;
use crate::env::VecEnv;
use crate::export::export_policy;
use crate::metrics::{MetricsLog, MetricsRow};
use crate::plot::plot_curves;
use crate::ppo::Ppo;
use crate::provenance;
use crate::runner::{eval_seed, evaluate, Progress, Runner};
use crate::task::make_env;
use crate::LearnError;

#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub run_dir: PathBuf,
    /// Checkpoint to continue from (written by a run of the same config).
    pub resume: Option<PathBuf>,
    /// Set (e.g. by a Ctrl-C handler) to stop after the current iteration, keeping a
    /// checkpoint of it.
    pub stop: Arc<AtomicBool>,
    /// A payload URDF every world carries instead of the sim config's payloads (see
    /// [`make_env`]); recorded in the exported policy as `payload_file`.
    pub payload_file: Option<PathBuf>,
}

#[derive(Debug, Clone)]
pub struct TrainSummary {
    pub progress: Progress,
    /// The last deterministic evaluation, if any ran.
    pub eval_return: Option<f64>,
    pub last_checkpoint: PathBuf,
    pub policy: PathBuf,
    /// Whether the run ended on the stop flag before `run.iterations`.
    pub stopped: bool,
    pub wall_s: f64,
}

/// Longest run name accepted, bytes: the run folder's name, well under any file system's
/// limit on one path component (255 bytes).
pub const MAX_RUN_NAME_BYTES: usize = 128;

/// The default run folder, `runs/<name>`, for a run name that is one plain folder name: not
/// empty, not `.`/`..` or containing `..`, no `/`, `\` or control characters, and at most
/// [`MAX_RUN_NAME_BYTES`] long, so the run can never land outside `runs/`.
pub fn default_run_dir(name: &str) -> Result<PathBuf, LearnError> {
    let reason = if name.is_empty() {
        Some("is empty".to_owned())
    } else if name.len() > MAX_RUN_NAME_BYTES {
        Some(format!(
            "is {} bytes long, more than {MAX_RUN_NAME_BYTES}",
            name.len()
        ))
    } else if name.contains("..") || name == "." {
        Some(format!("{name:?} may not be `.` or contain `..`"))
    } else if name.contains(['/', '\\']) || name.chars().any(char::is_control) {
        Some(format!(
            "{name:?} may not contain `/`, `\\` or control characters"
        ))
    } else {
        None
    };
    match reason {
        Some(reason) => Err(LearnError::InvalidConfig {
            field: "run.name".into(),
            reason: format!("must be one plain folder name: {reason}"),
        }),
        None => Ok(Path::new("runs").join(name)),
    }
}

/// Creates the run folder and its `checkpoints/`; an existing path that is not a folder is
/// an error naming it, not a confusing failure further down.
fn prepare_run_dir(dir: &Path) -> Result<PathBuf, LearnError> {
    if dir.exists() && !dir.is_dir() {
        return Err(LearnError::Io {
            path: dir.to_owned(),
            source: std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "the run folder exists and is not a folder",
            ),
        });
    }
    let checkpoints = dir.join("checkpoints");
    std::fs::create_dir_all(&checkpoints).map_err(LearnError::io(&checkpoints))?;
    Ok(checkpoints)
}

/// `rows × steps_per_env × width`, the size of the largest rollout tensor, or an error if it
/// does not fit in a tensor dimension product (i64). `rows` is `config.env.num_envs` before
/// the env exists, then the env's agent rows (several per world for some tasks).
fn rollout_size(config: &TrainConfig, rows: usize, width: usize) -> Result<i64, LearnError> {
    let steps = config.env.steps_per_env;
    rows.checked_mul(steps)
        .and_then(|batch| batch.checked_mul(width.max(1)))
        .and_then(|size| i64::try_from(size).ok())
        .ok_or_else(|| LearnError::InvalidConfig {
            field: "env.num_envs".into(),
            reason: format!(
                "{rows} env rows × steps_per_env {steps} × {width} values per step overflows"
            ),
        })
}

/// What every exported policy records about where it came from: `moonhaul-train`'s own
/// entries under the identity every trainer's file carries
/// ([`moonhaul_env::export::policy_provenance`]).
fn provenance_extra(
    config: &TrainConfig,
    env: &dyn VecEnv,
    commit: String,
    progress: Progress,
    eval_return: Option<f64>,
    payload_file: Option<&Path>,
) -> Result<(Phase, BTreeMap<String, String>), LearnError> {
    let mut extra = BTreeMap::from([
        ("created_by".to_string(), "moonhaul-train".to_string()),
        ("train_run".into(), config.run.name.clone()),
        ("seed".into(), config.run.seed.to_string()),
        ("iteration".into(), progress.iteration.to_string()),
        ("env_steps".into(), progress.env_steps.to_string()),
    ]);
    if let Some(r) = eval_return {
        extra.insert("eval_return".into(), r.to_string());
    }
    Ok(policy_provenance(config, env, commit, payload_file, extra)?)
}

/// The policy of a finished run's best evaluated checkpoint.
#[derive(Debug, Clone)]
pub struct Exported {
    pub policy: PathBuf,
    pub iteration: usize,
    /// The checkpoint's evaluation return (`None`: that iteration was not evaluated).
    pub eval_return: Option<f64>,
}

/// Which checkpoint of a run [`export_checkpoint`] exports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Selection {
    /// The highest deterministic evaluation return of the run: PPO's last iterate is not its
    /// best when training oscillates, and the evaluation episodes are the same every time, so
    /// their return ranks checkpoints fairly.
    BestEvaluation,
    /// This iteration's checkpoint (iteration 0 of a warm-started run: the cloned expert), for
    /// a selection by another measure, such as missions flown through the deployed stack.
    Iteration(usize),
}

/// Exports the `selection` checkpoint of the run in `run_dir` (trained with `config`) as
/// `<run>/best_policy.safetensors` (best evaluation) or `<run>/policy_iter_NNNNNN.safetensors`.
/// Records the source commit of the run's own `policy.safetensors` and `train_compute_s`:
/// rollout and update time up to that iteration (from `metrics.csv`, evaluations excluded).
/// A run trained on a payload file needs the same `payload_file`
/// ([`TrainOptions::payload_file`]): its grasp sets the action map.
pub fn export_checkpoint(
    config: &TrainConfig,
    run_dir: &Path,
    selection: Selection,
    payload_file: Option<&Path>,
) -> Result<Exported, LearnError> {
    let rows = crate::metrics::read_rows(&run_dir.join("metrics.csv"))?;
    let (iteration, eval_return) = match selection {
        Selection::BestEvaluation => rows
            .iter()
            .filter_map(|r| r.eval_return.map(|e| (r.iteration, e)))
            .filter(|(i, _)| checkpoint_path(run_dir, *i).is_file())
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, e)| (i, Some(e)))
            .ok_or_else(|| LearnError::Checkpoint {
                path: run_dir.join("checkpoints"),
                reason: "no evaluated iteration has a checkpoint".into(),
            })?,
        Selection::Iteration(i) => (
            i,
            rows.iter()
                .filter(|r| r.iteration == i)
                .find_map(|r| r.eval_return),
        ),
    };
    let env = make_env(config, 1, payload_file)?;
    let policy = ActorCritic::new(
        env.obs_dim(),
        env.critic_obs_dim(),
        env.action_dim(),
        &config.policy,
    );
    let mut ppo = Ppo::new(
        policy,
        config.ppo.clone(),
        config.env.steps_per_env,
        env.num_envs(),
    );
    let ckpt = checkpoint_path(run_dir, iteration);
    let progress = checkpoint::load(&ckpt, &mut ppo, config.run.task)?;
    let last = Policy::from_file(run_dir.join("policy.safetensors")).ok();
    let commit = last
        .and_then(|p| p.metadata().extra.get("commit").cloned())
        .unwrap_or_else(provenance::commit);
    let (phase, mut extra) = provenance_extra(
        config,
        env.as_ref(),
        commit,
        progress,
        eval_return,
        payload_file,
    )?;
    let (mut compute_s, mut previous) = (0.0, 0);
    for r in &rows {
        let samples = r.env_steps.saturating_sub(previous);
        previous = r.env_steps;
        if r.iteration <= iteration && r.steps_per_s > 0.0 {
            compute_s += samples as f64 / r.steps_per_s;
        }
    }
    extra.insert("train_compute_s".into(), format!("{compute_s:.0}"));
    let (selected, file) = match selection {
        Selection::BestEvaluation => (
            "best evaluation return of the run".to_string(),
            "best_policy.safetensors".to_string(),
        ),
        Selection::Iteration(i) => (
            format!("iteration {i}"),
            format!("policy_iter_{i:06}.safetensors"),
        ),
    };
    extra.insert("selected".into(), selected);
    let exported = export_policy(
        ppo.policy(),
        phase,
        &env.action_scale(),
        &env.action_offset(),
        extra,
    )?;
    let path = run_dir.join(file);
    exported.write_file(&path)?;
    Ok(Exported {
        policy: path,
        iteration,
        eval_return,
    })
}

pub fn checkpoint_path(run_dir: &Path, iteration: usize) -> PathBuf {
    run_dir
        .join("checkpoints")
        .join(format!("iter_{iteration:06}.safetensors"))
}

/// Trains `config` into `options.run_dir`, calling `on_iteration` after every iteration.
///
/// A config with `[warm_start]` first runs it ([`crate::distill`]) unless the run is resumed:
/// its rounds are rows of iteration 0 (`on_iteration` sees them too), the warm actor is
/// evaluated and checkpointed as iteration 0, and PPO continues from it. A stop during the
/// warm start ends the run after the round with that checkpoint of the partly warm actor; a
/// resume from it continues with PPO.
pub fn train(
    config: &TrainConfig,
    options: &TrainOptions,
    mut on_iteration: impl FnMut(&MetricsRow),
) -> Result<TrainSummary, LearnError> {
    let start = Instant::now();
    // The source the run starts from, before anyone edits the tree during a long run.
    let commit = provenance::commit();
    let dir = &options.run_dir;
    // Before anything is allocated from it or written: the rollout batch must be countable.
    rollout_size(config, config.env.num_envs, 1)?;
    prepare_run_dir(dir)?;

    let threads = i32::try_from(config.run.threads).unwrap_or(i32::MAX);
    tch::set_num_threads(threads);
    tch::manual_seed(config.run.seed as i64);
    let task = config.run.task;
    let payload_file = options.payload_file.as_deref();
    let mut env = make_env(config, config.env.num_envs, payload_file)?;
    let mut eval_env = make_env(config, config.run.eval_episodes, payload_file)?;
    let (obs_dim, critic_obs_dim) = (env.obs_dim(), env.critic_obs_dim());
    let action_dim = env.action_dim();
    rollout_size(
        config,
        env.num_envs(),
        obs_dim.max(critic_obs_dim).max(action_dim),
    )?;
    let policy = ActorCritic::new(obs_dim, critic_obs_dim, action_dim, &config.policy);
    // Sized by the env's rows, not `config.env.num_envs` (worlds): see `crate::env`.
    let mut ppo = Ppo::new(
        policy,
        config.ppo.clone(),
        config.env.steps_per_env,
        env.num_envs(),
    );
    let mut progress = match &options.resume {
        Some(path) => checkpoint::load(path, &mut ppo, task)?,
        None => Progress::default(),
    };
    // Only once the checkpoint to resume proved usable: a failed resume leaves the run's
    // resolved config as it was.
    write_atomic(&dir.join("config.toml"), config.to_toml().as_bytes())?;
    let mut metrics = MetricsLog::open(
        &dir.join("metrics.csv"),
        options.resume.as_ref().map(|_| progress.iteration),
    )?;
    let mut eval_return = metrics.rows().iter().rev().find_map(|r| r.eval_return);
    let mut last_checkpoint = None;
    let mut stopped = false;
    if let (Some(warm), None) = (&config.warm_start, &options.resume) {
        let rounds = warm.rounds + warm.critic_warmup_iterations;
        let mut done = 0;
        let completed = distill::warm_start(
            config,
            env.as_mut(),
            ppo.policy_mut(),
            || options.stop.load(Ordering::SeqCst),
            |stats, policy| {
                done += 1;
                progress.env_steps += stats.env_steps;
                let mut row =
                    MetricsRow::warm(stats, progress.env_steps, policy, warm.learning_rate);
                if done == rounds {
                    let seed = eval_seed(config.run.seed);
                    row.eval_return = Some(evaluate(eval_env.as_mut(), policy, seed)?);
                    eval_return = row.eval_return;
                }
                metrics.append(row)?;
                on_iteration(&row);
                Ok(())
            },
        )?;
        stopped = !completed;
        if completed {
            let path = checkpoint_path(dir, progress.iteration);
            checkpoint::save(&path, &ppo, progress, task)?;
            last_checkpoint = Some(path);
            plot_curves(dir, metrics.rows())?;
        }
    }
    let mut runner = Runner::new(config, env, eval_env, ppo, progress)?;
    if let Some(kickstart) = &config.kickstart {
        runner = runner.with_kickstart(kickstart.clone());
    }
    while !stopped && runner.progress().iteration < config.run.iterations {
        if options.stop.load(Ordering::SeqCst) {
            stopped = true;
            break;
        }
        let stats = runner.iterate()?;
        let it = stats.progress.iteration;
        let last = it == config.run.iterations;
        let eval = if it % config.run.eval_interval == 0 || last {
            Some(runner.evaluate()?)
        } else {
            None
        };
        eval_return = eval.or(eval_return);
        let row = MetricsRow::new(&stats, eval);
        metrics.append(row)?;
        on_iteration(&row);
        if eval.is_some() {
            plot_curves(dir, metrics.rows())?;
        }
        if it % config.run.checkpoint_interval == 0 || last {
            let path = checkpoint_path(dir, it);
            checkpoint::save(&path, runner.ppo(), stats.progress, task)?;
            last_checkpoint = Some(path);
        }
    }
    let progress = runner.progress();
    // A stop between periodic checkpoints still leaves one of the last completed iteration.
    let last_checkpoint = match last_checkpoint {
        Some(path) if path == checkpoint_path(dir, progress.iteration) => path,
        _ => {
            let path = checkpoint_path(dir, progress.iteration);
            checkpoint::save(&path, runner.ppo(), progress, task)?;
            path
        }
    };
    plot_curves(dir, metrics.rows())?;

    let env = runner.env();
    let (phase, mut extra) =
        provenance_extra(config, env, commit, progress, eval_return, payload_file)?;
    if let Some(last) = metrics.rows().last() {
        if let Some(r) = last.mean_return {
            extra.insert("final_mean_return".into(), r.to_string());
        }
        if let Some(l) = last.mean_episode_length {
            extra.insert("final_mean_episode_length".into(), l.to_string());
        }
    }
    // This session's wall time; a resumed run's earlier sessions are in its metrics.csv.
    extra.insert(
        "wall_s".into(),
        format!("{:.0}", start.elapsed().as_secs_f64()),
    );
    let exported = export_policy(
        runner.ppo().policy(),
        phase,
        &env.action_scale(),
        &env.action_offset(),
        extra,
    )?;
    let policy = dir.join("policy.safetensors");
    exported.write_file(&policy)?;
    Ok(TrainSummary {
        progress,
        eval_return,
        last_checkpoint,
        policy,
        stopped,
        wall_s: start.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_names_that_leave_runs_are_refused() {
        assert_eq!(
            default_run_dir("pendulum-2").unwrap(),
            Path::new("runs/pendulum-2")
        );
        let long = "x".repeat(MAX_RUN_NAME_BYTES + 1);
        for bad in [
            "", ".", "..", "a..b", "../x", "a/b", "/abs", "a\\b", "a\nb", &long,
        ] {
            let err = default_run_dir(bad).unwrap_err();
            assert!(
                matches!(&err, LearnError::InvalidConfig { field, .. } if field == "run.name"),
                "{bad:?}: {err}"
            );
        }
        assert!(default_run_dir(&"x".repeat(MAX_RUN_NAME_BYTES)).is_ok());
    }

    #[test]
    fn a_run_folder_that_is_a_file_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("run");
        std::fs::write(&file, "").unwrap();
        let err = prepare_run_dir(&file).unwrap_err();
        assert!(
            matches!(&err, LearnError::Io { path, .. } if path == &file),
            "{err}"
        );
        assert!(prepare_run_dir(&dir.path().join("new")).unwrap().is_dir());
    }
}
