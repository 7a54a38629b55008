//! CI-sized training run: a few Pendulum iterations write every file with finite metrics, and a
//! resumed run continues from the checkpoint.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use moonhaul_core::policy::Policy;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::metrics::{MetricsRow, HEADER};
use moonhaul_learn::trainer::{checkpoint_path, export_checkpoint, train, Selection, TrainOptions};

fn tiny_config() -> TrainConfig {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../configs/train/pendulum.toml"
    );
    let mut c = TrainConfig::load(path).unwrap();
    c.run.iterations = 4;
    c.run.eval_interval = 2;
    c.run.checkpoint_interval = 2;
    c.run.eval_episodes = 4;
    c.env.num_envs = 8;
    c.env.steps_per_env = 50;
    c.ppo.epochs = 2;
    c.ppo.minibatches = 4;
    c
}

fn rows(dir: &std::path::Path) -> Vec<MetricsRow> {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(HEADER));
    lines.map(|l| MetricsRow::parse(l).unwrap()).collect()
}

#[test]
fn trains_writes_everything_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let stop = Arc::new(AtomicBool::new(false));
    let mut config = tiny_config();
    config.run.iterations = 2;
    let options = TrainOptions {
        run_dir: run.clone(),
        resume: None,
        stop: stop.clone(),
        payload_file: None,
    };
    let mut seen = 0;
    let summary = train(&config, &options, |_| seen += 1).unwrap();
    assert_eq!(
        (seen, summary.progress.iteration, summary.progress.env_steps),
        (2, 2, 800)
    );
    assert!(!summary.stopped);
    for file in [
        "config.toml",
        "metrics.csv",
        "return.png",
        "entropy.png",
        "policy.safetensors",
    ] {
        assert!(run.join(file).is_file(), "{file} missing");
    }
    assert_eq!(summary.last_checkpoint, checkpoint_path(&run, 2));
    assert!(summary.last_checkpoint.is_file());
    assert_eq!(TrainConfig::load(run.join("config.toml")).unwrap(), config);
    let first = rows(&run);
    assert_eq!(first.len(), 2);
    assert!(first[0].eval_return.is_none() && first[1].eval_return.is_some());
    for r in &first {
        // Every PPO row has its losses (only warm-start rows leave them empty).
        for v in [
            r.value_loss,
            r.surrogate_loss,
            Some(r.entropy),
            Some(r.mean_std),
            r.kl,
            Some(r.lr),
            Some(r.steps_per_s),
        ] {
            assert!(v.is_some_and(f64::is_finite), "{r:?}");
        }
        assert!(r.bc_loss.is_none() && r.dagger_beta.is_none(), "{r:?}");
    }
    let policy = Policy::from_file(&summary.policy).unwrap();
    assert_eq!((policy.obs_dim(), policy.action_dim()), (3, 1));
    assert_eq!(
        policy.metadata().extra.get("task").map(String::as_str),
        Some("pendulum-v1")
    );

    // Resume to 4 iterations: keeps the first rows, continues counting.
    let config = tiny_config();
    let options = TrainOptions {
        run_dir: run.clone(),
        resume: Some(summary.last_checkpoint),
        stop,
        payload_file: None,
    };
    let resumed = train(&config, &options, |_| {}).unwrap();
    assert_eq!(
        (resumed.progress.iteration, resumed.progress.env_steps),
        (4, 1600)
    );
    let all = rows(&run);
    assert_eq!(
        all.iter().map(|r| r.iteration).collect::<Vec<_>>(),
        vec![1, 2, 3, 4]
    );
    assert_eq!(&all[..2], &first[..]);
    assert!(checkpoint_path(&run, 4).is_file());
}

#[test]
fn stop_flag_ends_after_the_iteration_and_keeps_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let stop = Arc::new(AtomicBool::new(false));
    let options = TrainOptions {
        run_dir: run.clone(),
        resume: None,
        stop: stop.clone(),
        payload_file: None,
    };
    // As the Ctrl-C handler does, mid-run: after iteration 1 (checkpoints are every 2).
    let summary = train(&tiny_config(), &options, |_| {
        stop.store(true, Ordering::SeqCst)
    })
    .unwrap();
    assert!(summary.stopped);
    assert_eq!(summary.progress.iteration, 1);
    assert_eq!(summary.last_checkpoint, checkpoint_path(&run, 1));
    assert!(summary.last_checkpoint.is_file() && summary.policy.is_file());
    assert_eq!(rows(&run).len(), 1);
}

#[test]
fn the_best_evaluated_checkpoint_is_exported_with_its_provenance() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let config = tiny_config();
    let options = TrainOptions {
        run_dir: run.clone(),
        resume: None,
        stop: Arc::new(AtomicBool::new(false)),
        payload_file: None,
    };
    train(&config, &options, |_| {}).unwrap();
    let evaluated: Vec<(usize, f64)> = rows(&run)
        .iter()
        .filter_map(|r| r.eval_return.map(|e| (r.iteration, e)))
        .collect();
    let (iteration, eval_return) = evaluated
        .iter()
        .copied()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    let best = export_checkpoint(&config, &run, Selection::BestEvaluation, None).unwrap();
    assert_eq!(
        (best.iteration, best.eval_return),
        (iteration, Some(eval_return))
    );
    let policy = Policy::from_file(&best.policy).unwrap();
    let extra = &policy.metadata().extra;
    assert_eq!(extra["iteration"], iteration.to_string());
    assert_eq!(extra["selected"], "best evaluation return of the run");
    for key in ["commit", "config_sha256", "train_compute_s", "env_steps"] {
        assert!(extra.contains_key(key), "{key}: {extra:?}");
    }
    // Any checkpointed iteration, by number, with its own provenance.
    let last = rows(&run).last().unwrap().iteration;
    let chosen = export_checkpoint(&config, &run, Selection::Iteration(last), None).unwrap();
    assert_eq!(chosen.iteration, last);
    assert!(chosen
        .policy
        .ends_with(format!("policy_iter_{last:06}.safetensors")));
    let policy = Policy::from_file(&chosen.policy).unwrap();
    assert_eq!(policy.metadata().extra["iteration"], last.to_string());
    assert_eq!(
        policy.metadata().extra["selected"],
        format!("iteration {last}")
    );
    // One without a checkpoint is refused, naming the missing file.
    let missing = export_checkpoint(&config, &run, Selection::Iteration(last + 1), None)
        .unwrap_err()
        .to_string();
    assert!(
        missing.contains(&format!("iter_{:06}", last + 1)),
        "{missing}"
    );
    // A run without a checkpoint of any evaluated iteration has nothing to export.
    std::fs::remove_dir_all(run.join("checkpoints")).unwrap();
    assert!(export_checkpoint(&config, &run, Selection::BestEvaluation, None).is_err());
}
