//! `moonhaul-train`: trains one policy with PPO from a `configs/train/*.toml` config.
//!
//! ```text
//! moonhaul-train --config configs/train/pendulum.toml [--out DIR] [--seed N] [--resume CKPT]
//! ```
//!
//! Ctrl-C stops after the current iteration and keeps a checkpoint of it; a second Ctrl-C
//! exits at once.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::trainer::{train, TrainOptions};

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
    /// Continue from this checkpoint (`<run>/checkpoints/iter_NNNNNN.safetensors`).
    #[arg(long)]
    resume: Option<PathBuf>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let mut config = TrainConfig::load(&args.config)
        .with_context(|| format!("loading training config {}", args.config.display()))?;
    if let Some(seed) = args.seed {
        config.run.seed = seed;
    }
    let run_dir = match (&args.out, &args.resume) {
        (Some(out), _) => out.clone(),
        // <run>/checkpoints/<file> -> <run>
        (None, Some(ckpt)) => ckpt
            .parent()
            .and_then(|p| p.parent())
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(".")),
        (None, None) => PathBuf::from("runs").join(&config.run.name),
    };

    let stop = Arc::new(AtomicBool::new(false));
    let handler_flag = Arc::clone(&stop);
    ctrlc::set_handler(move || {
        if handler_flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
        eprintln!("\nstopping after this iteration (Ctrl-C again to abort)");
    })
    .context("installing the Ctrl-C handler")?;

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
    };
    let mut last_eval = None;
    let summary = train(&config, &options, |row| {
        let fmt = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.1}"));
        last_eval = row.eval_return.or(last_eval);
        bar.set_position(row.iteration as u64);
        bar.set_message(format!(
            "{:.0} steps/s | return {} | eval {} | kl {:.4} | lr {:.1e}",
            row.steps_per_s,
            fmt(row.mean_return),
            fmt(last_eval),
            row.kl,
            row.lr
        ));
    })
    .with_context(|| {
        format!(
            "training {} into {}",
            args.config.display(),
            run_dir.display()
        )
    })?;
    bar.finish();

    println!(
        "{} after {} iterations, {} env steps, {:.1} s: eval return {}",
        if summary.stopped { "stopped" } else { "done" },
        summary.progress.iteration,
        summary.progress.env_steps,
        summary.wall_s,
        summary
            .eval_return
            .map_or("n/a".into(), |r| format!("{r:.1}"))
    );
    println!("checkpoint {}", summary.last_checkpoint.display());
    println!("policy     {}", summary.policy.display());
    Ok(())
}
