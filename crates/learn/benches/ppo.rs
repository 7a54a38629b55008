//! PPO throughput at the lift task's sizes: our side of the PPO side-by-side benchmark against
//! rsl_rl 5.5.1 (`bench/rsl_rl_ppo.py`, which takes the same flags and prints the same fields).
//!
//! ```text
//! cargo xtask cargo bench -p moonhaul-learn --bench ppo -- [--config configs/train/lift.toml]
//!     [--rows 4096] [--steps 24] [--obs 61] [--critic-obs 81] [--actions 9]
//!     [--rounds 3] [--warmup 1] [--threads 2] [--seed 0] [--human]
//! ```
//!
//! Networks, epochs, minibatches and every PPO hyperparameter come from the config (the lift
//! config by default); rows, steps and widths are flags. Each round runs `steps` rollout steps on
//! random observations and rewards, then one update, and prints one JSON line:
//!
//! - `update_samples_per_s`: rows × steps / the wall time of [`Ppo::update`] (last value, GAE,
//!   epochs × minibatches gradient steps). rsl_rl's figure times `alg.update()` only; its
//!   `compute_returns` (last value + GAE, a few ms) is outside it, and its normalizer refresh
//!   inside it; ours refreshes the normalizers per rollout step instead (in `step_ms_per_step`).
//! - `act_ms_per_step`: mean wall time of [`ActorCritic::act`] per step (actor and critic
//!   forward with their normalizers, Gaussian sample, log-prob, mean and std): what rsl_rl's
//!   `alg.act(obs)` computes.
//! - `step_ms_per_step`: [`Ppo::act_and_store`] minus the environment's closure: act, the
//!   normalizer updates and the storage add (rsl_rl: `alg.act` + `alg.process_env_step`).
//!
//! Asserts nothing; figures are only meaningful as ratios against the other side run
//! alternately on the same machine.

use std::time::Instant;

use moonhaul_learn::actor_critic::ActorCritic;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::ppo::{EnvAnswer, Ppo};
use tch::{Device, Kind, Tensor};

struct Args {
    config: String,
    rows: i64,
    steps: usize,
    obs: i64,
    critic_obs: i64,
    actions: i64,
    rounds: usize,
    warmup: usize,
    threads: i32,
    seed: i64,
    human: bool,
}

fn parse_args() -> Args {
    let mut a = Args {
        config: concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml").into(),
        rows: 4096,
        steps: 24,
        obs: moonhaul_core::observation::ACTOR_OBS_DIM as i64,
        critic_obs: moonhaul_sim::task::CRITIC_OBS_DIM as i64,
        actions: 9,
        rounds: 3,
        warmup: 1,
        threads: 2,
        seed: 0,
        human: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().unwrap_or_else(|| panic!("{flag} needs a value"));
        let num = |v: String| -> i64 { v.parse().unwrap_or_else(|_| panic!("bad number {v}")) };
        match flag.as_str() {
            // `cargo bench` passes `--bench` to harness-less benches.
            "--bench" => {}
            "--human" => a.human = true,
            "--config" => a.config = value(),
            "--rows" => a.rows = num(value()),
            "--steps" => a.steps = num(value()) as usize,
            "--obs" => a.obs = num(value()),
            "--critic-obs" => a.critic_obs = num(value()),
            "--actions" => a.actions = num(value()),
            "--rounds" => a.rounds = num(value()) as usize,
            "--warmup" => a.warmup = num(value()) as usize,
            "--threads" => a.threads = num(value()) as i32,
            "--seed" => a.seed = num(value()),
            other => panic!("unknown flag {other} (see the doc comment of benches/ppo.rs)"),
        }
    }
    a
}

fn main() {
    let a = parse_args();
    let config = TrainConfig::load(&a.config).expect("training config");
    tch::set_num_threads(a.threads);
    tch::manual_seed(a.seed);
    let (n, steps) = (a.rows, a.steps);
    let policy = ActorCritic::new(
        a.obs as usize,
        a.critic_obs as usize,
        a.actions as usize,
        &config.policy,
    );
    let mut ppo = Ppo::new(policy, config.ppo.clone(), steps, n as usize);
    let opts = (Kind::Float, Device::Cpu);
    if a.human {
        eprintln!(
            "# moonhaul: rows {n} x steps {steps}, obs {}, critic obs {}, actions {}, actor {:?} \
             critic {:?}, {} epochs x {} minibatches, {} threads",
            a.obs,
            a.critic_obs,
            a.actions,
            config.policy.actor_hidden,
            config.policy.critic_hidden,
            config.ppo.epochs,
            config.ppo.minibatches,
            tch::get_num_threads()
        );
    }
    let mut obs = Tensor::randn([n, a.obs], opts);
    let mut critic_obs = Tensor::randn([n, a.critic_obs], opts);
    for round in 0..a.warmup + a.rounds {
        let (mut act_s, mut step_s) = (0.0, 0.0);
        for _ in 0..steps {
            let t = Instant::now();
            let sample = ppo.policy().act(&obs, &critic_obs);
            act_s += t.elapsed().as_secs_f64();
            drop(sample);
            let mut env_s = 0.0;
            let t = Instant::now();
            let answer = ppo
                .act_and_store(&obs, &critic_obs, |_| {
                    let t = Instant::now();
                    let answer = EnvAnswer {
                        next_obs: Tensor::randn([n, a.obs], opts),
                        next_critic_obs: Tensor::randn([n, a.critic_obs], opts),
                        rewards: Tensor::randn([n], opts),
                        dones: Tensor::zeros([n], opts),
                        time_outs: None,
                    };
                    env_s = t.elapsed().as_secs_f64();
                    Ok(answer)
                })
                .expect("rollout step");
            step_s += t.elapsed().as_secs_f64() - env_s;
            obs = answer.next_obs;
            critic_obs = answer.next_critic_obs;
        }
        let t = Instant::now();
        let stats = ppo.update(&critic_obs).expect("update");
        let update_s = t.elapsed().as_secs_f64();
        if round < a.warmup {
            continue;
        }
        let samples = (n as usize * steps) as f64;
        let (act_ms, step_ms) = (act_s * 1e3 / steps as f64, step_s * 1e3 / steps as f64);
        println!(
            "{{\"side\": \"moonhaul\", \"round\": {}, \"update_samples_per_s\": {:.1}, \
             \"act_ms_per_step\": {act_ms:.3}, \"step_ms_per_step\": {step_ms:.3}, \
             \"update_s\": {update_s:.4}, \"value_loss\": {}, \"learning_rate\": {}}}",
            round - a.warmup + 1,
            samples / update_s,
            stats.value_loss,
            ppo.learning_rate()
        );
        if a.human {
            eprintln!(
                "round {}: update {update_s:.2} s = {:.0} samples/s | act {act_ms:.1} ms/step, \
                 act+store {step_ms:.1} ms/step over {n} rows | kl {:.4}",
                round - a.warmup + 1,
                samples / update_s,
                stats.kl
            );
        }
    }
}
