//! `moonhaul-train`: trains one policy with PPO from a `configs/train/*.toml` config.
//!
//! ```text
//! moonhaul-train --config configs/train/pendulum.toml [--out DIR] [--seed N] [--resume CKPT]
//!                [--time-limit-s S]
//! moonhaul-train --config CONFIG [--out DIR] --export-best
//! moonhaul-train --config configs/train/lift.toml --payload crate.urdf [...]
//! ```
//!
//! `--payload FILE` trains on a payload URDF (see `moonhaul_sim::scene` for what it must be)
//! instead of the sim config's payloads; the config is not changed, so `--resume` and
//! `--export-best` of such a run need the same `--payload` again.
//!
//! A config with `[warm_start]` first clones the scripted expert (DAgger, then the critic's
//! warm-up; `moonhaul_learn::distill`), shown round by round, then runs PPO from it.
//!
//! Ctrl-C stops after the current iteration (or warm-start round) and keeps a checkpoint of it;
//! a second Ctrl-C exits at once.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use moonhaul_core::input::{check_readable, MAX_CHECKPOINT_BYTES, MAX_URDF_BYTES};
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::trainer::{default_run_dir, export_checkpoint, train, Selection, TrainOptions};

/// A `--resume` checkpoint must be a regular file of sane size (not a folder, FIFO or device,
/// which would block or exhaust memory when read); returns its run folder,
/// `<run>/checkpoints/<file>` → `<run>`, or an error if it is not inside one.
fn check_resume(ckpt: &Path) -> Result<PathBuf> {
    check_readable(ckpt, MAX_CHECKPOINT_BYTES).context("--resume")?;
    let folder = ckpt.parent().filter(|p| !p.as_os_str().is_empty());
    match folder {
        Some(folder) if folder.file_name().is_some_and(|n| n == "checkpoints") => Ok(folder
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_owned()),
        _ => bail!(
            "--resume {}: not in a `<run>/checkpoints/` folder, so the run folder is unknown; \
             pass it with --out",
            ckpt.display()
        ),
    }
}

/// `--out` must be a folder or not exist yet.
fn check_out(out: &Path) -> Result<()> {
    if out.as_os_str().is_empty() {
        bail!("--out must not be empty");
    }
    if out.exists() && !out.is_dir() {
        bail!("--out {}: exists and is not a folder", out.display());
    }
    Ok(())
}

#[derive(Debug, Parser)]
#[command(
    version,
    about = "Train a moonhaul policy with PPO (rsl_rl-faithful, libtorch)"
)]
struct Args {
    /// Training config, e.g. configs/train/pendulum.toml.
    #[arg(long)]
    config: PathBuf,
    /// Run folder [default: the resumed checkpoint's run folder, else runs/<run.name>].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Overrides `run.seed`.
    #[arg(long)]
    seed: Option<u64>,
    /// Overrides `run.iterations`; 0 runs a config's `[warm_start]` alone, its cloned expert
    /// exported as the run's policy.
    #[arg(long, value_name = "N")]
    iterations: Option<usize>,
    /// Continue from this checkpoint (`<run>/checkpoints/iter_NNNNNN.safetensors`).
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Wall-time budget, s: stop after the iteration that passes it, as Ctrl-C does (keeping a
    /// checkpoint and exporting the policy).
    #[arg(long)]
    time_limit_s: Option<f64>,
    /// Train nothing: export the best evaluated checkpoint of the finished run in --out (or
    /// runs/<run.name>) as best_policy.safetensors.
    #[arg(long, conflicts_with_all = ["resume", "time_limit_s"])]
    export_best: bool,
    /// Train nothing: export iteration N's checkpoint of the finished run in --out (or
    /// runs/<run.name>) as policy_iter_NNNNNN.safetensors (0: a warm start's cloned expert),
    /// to select checkpoints by another measure, such as `moonhaul eval`'s deployed missions.
    #[arg(long, value_name = "N", conflicts_with_all = ["resume", "time_limit_s", "export_best"])]
    export_iteration: Option<usize>,
    /// Payload URDF every training world carries, replacing the sim config's payloads (one
    /// link `payload`, one <box> collision, long side along x). Give it again to --resume or
    /// --export-best such a run.
    #[arg(long, value_name = "FILE")]
    payload: Option<PathBuf>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let mut config = TrainConfig::load(&args.config)
        .with_context(|| format!("loading training config {}", args.config.display()))?;
    if let Some(seed) = args.seed {
        config.run.seed = seed;
    }
    if let Some(iterations) = args.iterations {
        if iterations == 0 && config.warm_start.is_none() {
            bail!(
                "--iterations 0 runs the warm start alone, and {} has no [warm_start]",
                args.config.display()
            );
        }
        config.run.iterations = iterations;
    }
    let resume_dir = args.resume.as_deref().map(check_resume).transpose()?;
    // Before the run folder exists; the sim checks the payload convention itself.
    if let Some(payload) = &args.payload {
        check_readable(payload, MAX_URDF_BYTES).context("--payload")?;
    }
    let run_dir = match (&args.out, resume_dir) {
        (Some(out), _) => {
            check_out(out)?;
            out.clone()
        }
        (None, Some(dir)) => dir,
        (None, None) => default_run_dir(&config.run.name)
            .with_context(|| format!("training config {}", args.config.display()))?,
    };

    let selection = match (args.export_best, args.export_iteration) {
        (true, _) => Some(Selection::BestEvaluation),
        (false, Some(i)) => Some(Selection::Iteration(i)),
        (false, None) => None,
    };
    if let Some(selection) = selection {
        let exported = export_checkpoint(&config, &run_dir, selection, args.payload.as_deref())
            .with_context(|| format!("exporting a checkpoint of {}", run_dir.display()))?;
        let eval = exported
            .eval_return
            .map_or("not evaluated".to_string(), |e| {
                format!("evaluation return {e:.1}")
            });
        writeln!(
            std::io::stdout().lock(),
            "iteration {}, {eval}\npolicy     {}",
            exported.iteration,
            exported.policy.display()
        )
        .context("cannot write to stdout")?;
        return Ok(());
    }

    let stop = Arc::new(AtomicBool::new(false));
    let handler_flag = Arc::clone(&stop);
    ctrlc::set_handler(move || {
        if handler_flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("\nstopping after this iteration (Ctrl-C again to abort)");
    })
    .context("installing the Ctrl-C handler")?;
    if let Some(limit) = args.time_limit_s {
        if !(limit.is_finite() && limit > 0.0) {
            bail!("--time-limit-s {limit}: must be a positive number of seconds");
        }
        let budget_flag = Arc::clone(&stop);
        let budget = std::time::Duration::from_secs_f64(limit.min(1e9));
        std::thread::spawn(move || {
            std::thread::sleep(budget);
            budget_flag.store(true, Ordering::SeqCst);
        });
    }

    let bar = ProgressBar::new(config.run.iterations as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{bar:30} it {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .context("progress bar template")?,
    );
    let options = TrainOptions {
        run_dir: run_dir.clone(),
        resume: args.resume.clone(),
        stop,
        payload_file: args.payload.clone(),
    };
    let mut last_eval = None;
    let (mut dagger_rounds, mut critic_rounds) = (0, 0);
    let summary = train(&config, &options, |row| {
        let fmt = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.1}"));
        let fmt3 = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.3}"));
        last_eval = row.eval_return.or(last_eval);
        bar.set_position(row.iteration as u64);
        let clamp = match (row.mean_t_max, row.hold_fraction, row.mean_grasp_force_n) {
            (Some(t), Some(h), Some(f)) => {
                format!(
                    " | t_max {t:.3} | holds {:.1} % | grasp {f:.0} N",
                    h * 100.0
                )
            }
            _ => String::new(),
        };
        let warm = config.warm_start.as_ref();
        let message = match (row.iteration, row.bc_loss, warm) {
            // The warm start's rows, before PPO's first iteration (see moonhaul_learn::distill).
            (0, Some(bc_loss), Some(warm)) => {
                dagger_rounds += 1;
                format!(
                    "warm start: DAgger round {dagger_rounds}/{} | beta {:.2} | bc loss {bc_loss:.4} \
                     | expert agreement {} % | return {}{clamp}",
                    warm.rounds,
                    row.dagger_beta.unwrap_or(f64::NAN),
                    fmt(row.expert_agreement.map(|a| a * 100.0)),
                    fmt(row.mean_return),
                )
            }
            (0, None, Some(warm)) => {
                critic_rounds += 1;
                format!(
                    "warm start: critic {critic_rounds}/{} | explained variance {} | value loss \
                     {} | return {} | eval {}",
                    warm.critic_warmup_iterations,
                    fmt3(row.explained_variance),
                    fmt3(row.value_loss),
                    fmt(row.mean_return),
                    fmt(last_eval),
                )
            }
            _ => format!(
                "{:.0} steps/s | return {} | eval {} | kl {} | ev {} | lr {:.1e}{clamp}",
                row.steps_per_s,
                fmt(row.mean_return),
                fmt(last_eval),
                row.kl.map_or("-".to_string(), |kl| format!("{kl:.4}")),
                fmt3(row.explained_variance),
                row.lr
            ),
        };
        bar.set_message(message);
    })
    .with_context(|| {
        format!(
            "training {} into {}",
            args.config.display(),
            run_dir.display()
        )
    })?;
    bar.finish();

    let mut out = std::io::stdout().lock();
    writeln!(
        out,
        "{} after {} iterations, {} env steps, {:.1} s: eval return {}",
        if summary.stopped { "stopped" } else { "done" },
        summary.progress.iteration,
        summary.progress.env_steps,
        summary.wall_s,
        summary
            .eval_return
            .map_or("n/a".into(), |r| format!("{r:.1}"))
    )
    .context("cannot write to stdout")?;
    writeln!(out, "checkpoint {}", summary.last_checkpoint.display())
        .context("cannot write to stdout")?;
    writeln!(out, "policy     {}", summary.policy.display()).context("cannot write to stdout")?;
    Ok(())
}
