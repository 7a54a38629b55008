//! The on-policy loop (rsl_rl's `OnPolicyRunner`, without the file handling that lives in
//! [`crate::trainer`]): rollouts of `steps_per_env` steps on the training envs, a PPO update,
//! episode statistics, and deterministic evaluation on separate envs.

use std::collections::VecDeque;
use std::time::Instant;

use tch::{Kind, Tensor};

use crate::config::TrainConfig;
use crate::env::{VecEnv, VecStep};
use crate::ppo::{EnvAnswer, Ppo, TimeOuts, UpdateStats};
use crate::LearnError;

/// Completed episodes the mean return and length are taken over (rsl_rl's logger window).
const EPISODE_WINDOW: usize = 100;

/// Where a run stands: what a checkpoint restores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Progress {
    /// Completed iterations.
    pub iteration: usize,
    /// Environment transitions collected so far (all envs).
    pub env_steps: u64,
}

/// One iteration's figures (a `metrics.csv` row without the evaluation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IterationStats {
    pub progress: Progress,
    /// Mean undiscounted return of the last 100 completed training episodes (stochastic
    /// policy); `None` until an episode has finished.
    pub mean_return: Option<f64>,
    pub mean_episode_length: Option<f64>,
    pub update: UpdateStats,
    pub mean_std: f64,
    /// Learning rate after the update.
    pub lr: f64,
    pub steps_per_s: f64,
}

/// Running sums of the episodes in progress and a window of finished ones.
#[derive(Debug)]
struct EpisodeStats {
    returns: Vec<f64>,
    lengths: Vec<u64>,
    finished: VecDeque<(f64, u64)>,
}

impl EpisodeStats {
    fn new(envs: usize) -> Self {
        EpisodeStats {
            returns: vec![0.0; envs],
            lengths: vec![0; envs],
            finished: VecDeque::new(),
        }
    }

    fn record(&mut self, step: &VecStep) {
        for i in 0..self.returns.len() {
            self.returns[i] += step.rewards[i];
            self.lengths[i] += 1;
            if step.terminated[i] || step.truncated[i] {
                if self.finished.len() == EPISODE_WINDOW {
                    self.finished.pop_front();
                }
                self.finished.push_back((self.returns[i], self.lengths[i]));
                self.returns[i] = 0.0;
                self.lengths[i] = 0;
            }
        }
    }

    fn means(&self) -> (Option<f64>, Option<f64>) {
        if self.finished.is_empty() {
            return (None, None);
        }
        let n = self.finished.len() as f64;
        let (r, l) = self
            .finished
            .iter()
            .fold((0.0, 0.0), |(r, l), &(er, el)| (r + er, l + el as f64));
        (Some(r / n), Some(l / n))
    }
}

/// A well-mixed per-iteration seed, so a resumed run draws fresh, reproducible randomness.
pub fn iteration_seed(seed: u64, iteration: usize) -> u64 {
    moonhaul_core::seed::stream_seed(seed, iteration as u64)
}

/// Flat f64 rows as an f32 tensor `[rows, cols]`.
pub fn to_tensor(data: &[f64], rows: usize, cols: usize) -> Tensor {
    let f: Vec<f32> = data.iter().map(|&v| v as f32).collect();
    Tensor::from_slice(&f).view([rows as i64, cols as i64])
}

/// An f32 tensor as flat f64 values (row-major).
pub fn to_f64(t: &Tensor) -> Result<Vec<f64>, LearnError> {
    let f: Vec<f32> = Vec::try_from(&t.flatten(0, -1))?;
    Ok(f.into_iter().map(f64::from).collect())
}

fn check_finite(what: &str, data: &[f64]) -> Result<(), LearnError> {
    match data.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(LearnError::NonFinite {
            what: format!("{what}[{i}]"),
        }),
        None => Ok(()),
    }
}

/// Steps `env` with `actions` and converts its answer to tensors, rewards multiplied by
/// `reward_scale`; a time-out that is also a termination counts as a termination (no
/// bootstrap).
fn step_env(
    env: &mut dyn VecEnv,
    buf: &mut VecStep,
    actions: &Tensor,
    reward_scale: f64,
) -> Result<EnvAnswer, LearnError> {
    env.step(&to_f64(actions)?, buf)?;
    check_finite("environment observation", &buf.obs)?;
    check_finite("environment reward", &buf.rewards)?;
    let (n, o) = (env.num_envs(), env.obs_dim());
    let dones: Vec<f32> = (0..n)
        .map(|i| f32::from(u8::from(buf.terminated[i] || buf.truncated[i])))
        .collect();
    let ids: Vec<i64> = (0..n)
        .filter(|&i| buf.truncated[i] && !buf.terminated[i])
        .map(|i| i as i64)
        .collect();
    let time_outs = if ids.is_empty() {
        None
    } else {
        let rows: Vec<f64> = ids
            .iter()
            .flat_map(|&i| {
                buf.final_obs[i as usize * o..(i as usize + 1) * o]
                    .iter()
                    .copied()
            })
            .collect();
        check_finite("final observation", &rows)?;
        Some(TimeOuts {
            final_obs: to_tensor(&rows, ids.len(), o),
            env_ids: Tensor::from_slice(&ids),
        })
    };
    Ok(EnvAnswer {
        next_obs: to_tensor(&buf.obs, n, o),
        rewards: to_tensor(&buf.rewards, n, 1).view([-1]) * reward_scale,
        dones: Tensor::from_slice(&dones),
        time_outs,
    })
}

pub struct Runner {
    env: Box<dyn VecEnv>,
    eval_env: Box<dyn VecEnv>,
    ppo: Ppo,
    steps_per_env: usize,
    reward_scale: f64,
    obs: Tensor,
    buf: VecStep,
    episodes: EpisodeStats,
    progress: Progress,
    eval_seed: u64,
}

impl Runner {
    /// Starts (or, with a non-zero `progress`, continues) a run: reseeds libtorch and the
    /// training envs from the config seed and the iteration, and resets the envs.
    pub fn new(
        config: &TrainConfig,
        mut env: Box<dyn VecEnv>,
        eval_env: Box<dyn VecEnv>,
        ppo: Ppo,
        progress: Progress,
    ) -> Result<Self, LearnError> {
        let (n, o) = (env.num_envs(), env.obs_dim());
        if n != config.env.num_envs
            || eval_env.obs_dim() != o
            || eval_env.action_dim() != env.action_dim()
        {
            return Err(LearnError::Shape {
                what: "environment batch",
                expected: config.env.num_envs,
                found: n,
            });
        }
        let seed = iteration_seed(config.run.seed, progress.iteration);
        tch::manual_seed(seed as i64);
        let mut first = vec![0.0; n * o];
        env.reset(seed, &mut first)?;
        check_finite("environment observation", &first)?;
        Ok(Runner {
            obs: to_tensor(&first, n, o),
            buf: VecStep::new(n, o),
            episodes: EpisodeStats::new(n),
            steps_per_env: config.env.steps_per_env,
            reward_scale: config.ppo.reward_scale,
            env,
            eval_env,
            ppo,
            progress,
            eval_seed: iteration_seed(config.run.seed, usize::MAX),
        })
    }

    pub fn ppo(&self) -> &Ppo {
        &self.ppo
    }

    pub fn progress(&self) -> Progress {
        self.progress
    }

    /// The training envs' action map (for export).
    pub fn env(&self) -> &dyn VecEnv {
        self.env.as_ref()
    }

    /// One rollout and one PPO update.
    pub fn iterate(&mut self) -> Result<IterationStats, LearnError> {
        let start = Instant::now();
        for _ in 0..self.steps_per_env {
            let (env, buf, episodes) = (&mut self.env, &mut self.buf, &mut self.episodes);
            let reward_scale = self.reward_scale;
            let answer = self.ppo.act_and_store(&self.obs, |actions| {
                let answer = step_env(env.as_mut(), buf, actions, reward_scale)?;
                episodes.record(buf);
                Ok(answer)
            })?;
            self.obs = answer.next_obs;
        }
        let update = self.ppo.update(&self.obs)?;
        let samples = (self.env.num_envs() * self.steps_per_env) as u64;
        self.progress.iteration += 1;
        self.progress.env_steps += samples;
        let (mean_return, mean_episode_length) = self.episodes.means();
        Ok(IterationStats {
            progress: self.progress,
            mean_return,
            mean_episode_length,
            update,
            mean_std: self.ppo.policy().std().mean(Kind::Float).double_value(&[]),
            lr: self.ppo.learning_rate(),
            steps_per_s: samples as f64 / start.elapsed().as_secs_f64(),
        })
    }

    /// Mean undiscounted return of the deterministic policy (the Gaussian mean) over one
    /// episode per evaluation env, always from the same initial states. Relies on every
    /// episode ending (tasks have a time limit).
    pub fn evaluate(&mut self) -> Result<f64, LearnError> {
        let env = self.eval_env.as_mut();
        let (n, o) = (env.num_envs(), env.obs_dim());
        let mut obs = vec![0.0; n * o];
        env.reset(self.eval_seed, &mut obs)?;
        let mut buf = VecStep::new(n, o);
        let mut returns = vec![0.0; n];
        let mut running = vec![true; n];
        while running.iter().any(|&r| r) {
            check_finite("environment observation", &obs)?;
            let actions = self.ppo.policy().act_deterministic(&to_tensor(&obs, n, o));
            env.step(&to_f64(&actions)?, &mut buf)?;
            for i in 0..n {
                if running[i] {
                    returns[i] += buf.rewards[i];
                    running[i] = !(buf.terminated[i] || buf.truncated[i]);
                }
            }
            std::mem::swap(&mut obs, &mut buf.obs);
        }
        check_finite("evaluation return", &returns)?;
        Ok(returns.iter().sum::<f64>() / n as f64)
    }
}
