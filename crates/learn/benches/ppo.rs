//! PPO throughput at the paper's scale: a 4096-env × 24-step rollout with the [256, 128, 64]
//! actor and critic, 80-dim observations and 18-dim actions, updated for 5 epochs × 4
//! minibatches (configs/train/lift.toml), on 2 libtorch threads. Prints figures; asserts none.
//! The critic reads the actor's observations (a symmetric critic, as the reference measured).
//!
//! Reference (this machine, 2 threads): rsl_rl 5.5.1 on torch 2.13 updates ~18,500 samples/s
//! and needs ~17 ms per batched inference step over 4096 envs.

use std::time::Instant;

use moonhaul_learn::actor_critic::ActorCritic;
use moonhaul_learn::config::TrainConfig;
use moonhaul_learn::ppo::{EnvAnswer, Ppo};
use tch::{Device, Kind, Tensor};

const ENVS: i64 = 4096;
const STEPS: usize = 24;
const OBS: i64 = 80;
const ACTIONS: i64 = 18;
const ROUNDS: usize = 3;

fn main() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml");
    let mut config = TrainConfig::load(path).expect("configs/train/lift.toml");
    config.policy.actor_hidden = vec![256, 128, 64];
    config.policy.critic_hidden = vec![256, 128, 64];
    tch::set_num_threads(2);
    tch::manual_seed(0);
    let policy = ActorCritic::new(OBS as usize, OBS as usize, ACTIONS as usize, &config.policy);
    let mut ppo = Ppo::new(policy, config.ppo.clone(), STEPS, ENVS as usize);
    let opts = (Kind::Float, Device::Cpu);
    let samples = ENVS as f64 * STEPS as f64;
    println!(
        "PPO update: {ENVS} envs x {STEPS} steps, obs {OBS}, actions {ACTIONS}, nets [256,128,64], \
         {} epochs x {} minibatches, 2 threads",
        config.ppo.epochs, config.ppo.minibatches
    );
    let mut obs = Tensor::randn([ENVS, OBS], opts);
    for round in 1..=ROUNDS {
        let mut infer_s = 0.0;
        for _ in 0..STEPS {
            // Inference alone: actor + critic + sampling + log-prob over 4096 envs.
            let t = Instant::now();
            let sample = ppo.policy().act(&obs, &obs);
            infer_s += t.elapsed().as_secs_f64();
            drop(sample);
            // Then the rollout step proper, filling the storage for the update.
            let answer = ppo
                .act_and_store(&obs, &obs, |_| {
                    let next_obs = Tensor::randn([ENVS, OBS], opts);
                    Ok(EnvAnswer {
                        next_critic_obs: next_obs.shallow_clone(),
                        next_obs,
                        rewards: Tensor::randn([ENVS], opts),
                        dones: Tensor::zeros([ENVS], opts),
                        time_outs: None,
                    })
                })
                .expect("rollout step");
            obs = answer.next_obs;
        }
        let t = Instant::now();
        let stats = ppo.update(&obs).expect("update");
        let update_s = t.elapsed().as_secs_f64();
        println!(
            "round {round}: update {update_s:.2} s = {:.0} samples/s | inference {:.1} ms/step over {ENVS} envs | kl {:.4}",
            samples / update_s,
            infer_s * 1e3 / STEPS as f64,
            stats.kl
        );
    }
}
