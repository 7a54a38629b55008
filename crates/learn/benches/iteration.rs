//! Seconds per training iteration of a phase task at the paper's scale, with where they go.
//!
//! `cargo xtask cargo bench -p moonhaul-learn --bench iteration -- [--config FILE]
//! [--worlds N] [--iterations K] [--json]`: builds the config's task (default
//! `configs/train/lift.toml`) with N worlds (default 2048, Table I's lift env count; two unit
//! rows each) and the config's steps per env (24) and threads, runs one warm-up iteration, then
//! K (default 3) timed ones, and prints each with its breakdown and the medians:
//!
//! - physics: stepping the simulator and reading its state (the env's parallel section split
//!   by its workers' CPU time, see `PhaseVecEnv`);
//! - obs & reward: the rest of the env step — outcomes, rewards, resets, observations — and
//!   the tensor conversions to and from the env;
//! - act: actor and critic forward passes, sampling, normalizer updates, storage;
//! - update: returns, advantages and the PPO gradient steps.
//!
//! Prints figures; asserts none.

use std::process::ExitCode;

use moonhaul_learn::actor_critic::ActorCritic;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::ppo::Ppo;
use moonhaul_learn::runner::{IterationTiming, Progress, Runner};
use moonhaul_learn::task::make_env;

struct Args {
    config: String,
    worlds: usize,
    iterations: usize,
    json: bool,
}

fn parse() -> Result<Args, String> {
    let mut args = Args {
        config: concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml")
            .replace("crates/learn/../../", ""),
        worlds: 2048,
        iterations: 3,
        json: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match arg.as_str() {
            "--config" => args.config = value("--config")?,
            "--worlds" => {
                args.worlds = value("--worlds")?
                    .parse()
                    .map_err(|e| format!("--worlds: {e}"))?
            }
            "--iterations" => {
                args.iterations = value("--iterations")?
                    .parse()
                    .map_err(|e| format!("--iterations: {e}"))?
            }
            "--json" => args.json = true,
            // cargo bench passes `--bench` to every harness-less bench.
            "--bench" => {}
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if args.worlds == 0 || args.iterations == 0 {
        return Err("--worlds and --iterations must be at least 1".into());
    }
    Ok(args)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn run(args: &Args) -> Result<(), String> {
    let mut config = TrainConfig::load(&args.config).map_err(|e| e.to_string())?;
    config.env.num_envs = args.worlds;
    tch::set_num_threads(config.run.threads as i32);
    let env = make_env(&config, args.worlds, None).map_err(|e| e.to_string())?;
    let eval_env = make_env(&config, 1, None).map_err(|e| e.to_string())?;
    let rows = env.num_envs();
    let policy = ActorCritic::new(
        env.obs_dim(),
        env.critic_obs_dim(),
        env.action_dim(),
        &config.policy,
    );
    let ppo = Ppo::new(policy, config.ppo.clone(), config.env.steps_per_env, rows);
    let mut runner =
        Runner::new(&config, env, eval_env, ppo, Progress::default()).map_err(|e| e.to_string())?;
    if !args.json {
        println!(
            "{}: {} worlds ({rows} rows) x {} steps, {} threads; one warm-up iteration, then {}",
            args.config, args.worlds, config.env.steps_per_env, config.run.threads, args.iterations
        );
    }
    let mut timings: Vec<IterationTiming> = Vec::new();
    for k in 0..=args.iterations {
        let stats = runner.iterate().map_err(|e| e.to_string())?;
        let t = stats.timing;
        if k == 0 {
            continue;
        }
        if !args.json {
            let physics = t.physics_s.unwrap_or(f64::NAN);
            println!(
                "iteration {k}: {:.2} s = physics {physics:.2} + obs & reward {:.2} + act {:.2} + update {:.2} | {:.0} rows/s",
                t.rollout_s + t.update_s,
                t.env_s - physics,
                t.act_s(),
                t.update_s,
                stats.steps_per_s
            );
        }
        timings.push(t);
    }
    let med = |f: fn(&IterationTiming) -> f64| median(timings.iter().map(f).collect());
    let total = med(|t| t.rollout_s + t.update_s);
    let physics = med(|t| t.physics_s.unwrap_or(f64::NAN));
    let obs_reward = med(|t| t.env_s - t.physics_s.unwrap_or(f64::NAN));
    let act = med(IterationTiming::act_s);
    let update = med(|t| t.update_s);
    if args.json {
        println!(
            "{{\"worlds\":{},\"rows\":{rows},\"steps\":{},\"iteration_s\":{total},\"physics_s\":{physics},\"obs_reward_s\":{obs_reward},\"act_s\":{act},\"update_s\":{update}}}",
            args.worlds, config.env.steps_per_env
        );
    } else {
        println!(
            "median: {total:.2} s per iteration = physics {physics:.2} + obs & reward {obs_reward:.2} + act {act:.2} + update {update:.2}"
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    match parse().and_then(|args| run(&args)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("iteration bench: {e}");
            ExitCode::FAILURE
        }
    }
}
