//! CI-sized lift training: a few iterations on a few worlds of the real lift task (domain
//! randomization on, the shipped reward and PPO settings) raise the deterministic evaluation
//! return on the same evaluation episodes, and the exported policy carries the observation
//! layout and its provenance. Not a full training (see `cargo xtask train-all`).

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use moonhaul_core::observation::check_layout;
use moonhaul_core::policy::Policy;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::metrics::MetricsRow;
use moonhaul_learn::trainer::{train, TrainOptions};

#[test]
fn a_few_lift_iterations_raise_the_evaluation_return() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml");
    let mut config = TrainConfig::load(path).unwrap();
    config.env.num_envs = 32;
    config.run.iterations = 40;
    config.run.eval_interval = 20;
    config.run.checkpoint_interval = 40;
    config.run.eval_episodes = 8;
    let dir = tempfile::tempdir().unwrap();
    let options = TrainOptions {
        run_dir: dir.path().join("run"),
        resume: None,
        stop: Arc::new(AtomicBool::new(false)),
        payload_file: None,
    };
    let mut evals = Vec::new();
    train(&config, &options, |row: &MetricsRow| {
        if let Some(r) = row.eval_return {
            evals.push(r);
        }
    })
    .unwrap();
    assert_eq!(evals.len(), 2, "{evals:?}");
    assert!(evals.iter().all(|r| r.is_finite() && *r < 0.0), "{evals:?}");
    assert!(evals[1] > evals[0], "no learning signal: {evals:?}");

    let policy = Policy::from_file(dir.path().join("run/policy.safetensors")).unwrap();
    let extra = &policy.metadata().extra;
    check_layout(extra).unwrap();
    for key in [
        "commit",
        "config_sha256",
        "seed",
        "env_steps",
        "wall_s",
        "eval_return",
    ] {
        assert!(extra.contains_key(key), "{key} missing: {extra:?}");
    }
}
