//! The on-policy loop (rsl_rl's `OnPolicyRunner`, without the file handling that lives in
//! [`crate::trainer`]): rollouts of `steps_per_env` steps on the training envs, a PPO update,
//! episode statistics, and deterministic evaluation on separate envs.

use std::collections::VecDeque;
use std::time::Instant;

use tch::{Kind, Tensor};

use crate::actor_critic::ActorCritic;
use crate::config::TrainConfig;
use crate::env::{PipelineStats, VecEnv, VecStep};
use crate::kickstart::{Kickstart, KickstartStats};
use crate::ppo::{EnvAnswer, Ppo, TimeOuts, UpdateStats};
use crate::LearnError;

/// Completed episodes the mean return and length are taken over (rsl_rl's logger window).
const EPISODE_WINDOW: usize = 100;

/// Where a run stands: what a checkpoint restores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Progress {
    /// Completed iterations.
    pub iteration: usize,
    /// Environment transitions collected so far (all agent rows).
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
    pub timing: IterationTiming,
    /// What the action pipeline did in this iteration's rollout (phase tasks).
    pub pipeline: Option<PipelineStats>,
    /// The behaviour-cloning term of a kickstarted iteration (weight above 0).
    pub kickstart: Option<KickstartStats>,
}

/// Where one iteration's wall time went, s.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct IterationTiming {
    /// The rollout: acting, stepping the envs, storing transitions.
    pub rollout_s: f64,
    /// Of the rollout, stepping the envs (with the tensor conversions to and from them).
    pub env_s: f64,
    /// Of `env_s`, the physics, where the env separates it ([`VecEnv::take_physics_s`]).
    pub physics_s: Option<f64>,
    /// The PPO update (returns, advantages and the gradient steps).
    pub update_s: f64,
}

impl IterationTiming {
    /// Sampling actions and values, normalizer updates and storage: the rollout less the envs.
    pub fn act_s(&self) -> f64 {
        self.rollout_s - self.env_s
    }
}

/// Running sums of the episodes in progress and a window of finished ones.
#[derive(Debug)]
pub(crate) struct EpisodeStats {
    returns: Vec<f64>,
    lengths: Vec<u64>,
    finished: VecDeque<(f64, u64)>,
}

impl EpisodeStats {
    pub(crate) fn new(envs: usize) -> Self {
        EpisodeStats {
            returns: vec![0.0; envs],
            lengths: vec![0; envs],
            finished: VecDeque::new(),
        }
    }

    pub(crate) fn record(&mut self, step: &VecStep) {
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

    pub(crate) fn means(&self) -> (Option<f64>, Option<f64>) {
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

pub(crate) fn check_finite(what: &str, data: &[f64]) -> Result<(), LearnError> {
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
pub(crate) fn step_env(
    env: &mut dyn VecEnv,
    buf: &mut VecStep,
    actions: &Tensor,
    reward_scale: f64,
) -> Result<EnvAnswer, LearnError> {
    env.step(&to_f64(actions)?, buf)?;
    check_finite("environment observation", &buf.obs)?;
    check_finite("environment critic observation", &buf.critic_obs)?;
    check_finite("environment reward", &buf.rewards)?;
    let (n, o, c) = (env.num_envs(), env.obs_dim(), env.critic_obs_dim());
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
                buf.final_critic_obs[i as usize * c..(i as usize + 1) * c]
                    .iter()
                    .copied()
            })
            .collect();
        check_finite("final critic observation", &rows)?;
        Some(TimeOuts {
            final_critic_obs: to_tensor(&rows, ids.len(), c),
            env_ids: Tensor::from_slice(&ids),
        })
    };
    Ok(EnvAnswer {
        next_obs: to_tensor(&buf.obs, n, o),
        next_critic_obs: to_tensor(&buf.critic_obs, n, c),
        rewards: to_tensor(&buf.rewards, n, 1).view([-1]) * reward_scale,
        dones: Tensor::from_slice(&dones),
        time_outs,
    })
}

/// Fails with `what` unless the widths `found` and `expected` agree.
fn check_width(what: &'static str, expected: usize, found: usize) -> Result<(), LearnError> {
    if found == expected {
        Ok(())
    } else {
        Err(LearnError::Shape {
            what,
            expected,
            found,
        })
    }
}

/// The evaluation env must speak the training env's language, and the learner must be sized
/// for the training env's rows and widths (a task may give several rows per simulated world,
/// so `config.env.num_envs` is not the row count).
fn check_dims(
    env: &dyn VecEnv,
    eval_env: &dyn VecEnv,
    ppo: &Ppo,
    steps_per_env: usize,
) -> Result<(), LearnError> {
    let (o, c, a) = (env.obs_dim(), env.critic_obs_dim(), env.action_dim());
    check_width("evaluation env observation width", o, eval_env.obs_dim())?;
    check_width(
        "evaluation env critic observation width",
        c,
        eval_env.critic_obs_dim(),
    )?;
    check_width("evaluation env action width", a, eval_env.action_dim())?;
    let policy = ppo.policy();
    check_width("policy observation width", o, policy.obs_dim())?;
    check_width(
        "policy critic observation width",
        c,
        policy.critic_obs_dim(),
    )?;
    check_width("policy action width", a, policy.action_dim())?;
    let storage = ppo.storage();
    check_width(
        "rollout storage rows",
        env.num_envs(),
        storage.envs() as usize,
    )?;
    check_width(
        "rollout storage steps",
        steps_per_env,
        storage.steps() as usize,
    )
}

pub struct Runner {
    env: Box<dyn VecEnv>,
    eval_env: Box<dyn VecEnv>,
    ppo: Ppo,
    steps_per_env: usize,
    reward_scale: f64,
    obs: Tensor,
    critic_obs: Tensor,
    buf: VecStep,
    episodes: EpisodeStats,
    progress: Progress,
    eval_seed: u64,
    kickstart: Option<Kickstart>,
}

impl Runner {
    /// Starts (or, with a non-zero `progress`, continues) a run: reseeds libtorch and the
    /// training envs from the config seed and the iteration, and resets the envs. `ppo` must
    /// be sized for `env`'s rows and widths, and `eval_env` have `env`'s widths.
    pub fn new(
        config: &TrainConfig,
        mut env: Box<dyn VecEnv>,
        eval_env: Box<dyn VecEnv>,
        ppo: Ppo,
        progress: Progress,
    ) -> Result<Self, LearnError> {
        check_dims(
            env.as_ref(),
            eval_env.as_ref(),
            &ppo,
            config.env.steps_per_env,
        )?;
        let (n, o, c) = (env.num_envs(), env.obs_dim(), env.critic_obs_dim());
        let seed = iteration_seed(config.run.seed, progress.iteration);
        tch::manual_seed(seed as i64);
        let (mut obs, mut critic_obs) = (vec![0.0; n * o], vec![0.0; n * c]);
        env.reset(seed, &mut obs, &mut critic_obs)?;
        check_finite("environment observation", &obs)?;
        check_finite("environment critic observation", &critic_obs)?;
        Ok(Runner {
            obs: to_tensor(&obs, n, o),
            critic_obs: to_tensor(&critic_obs, n, c),
            buf: VecStep::new(n, o, c),
            episodes: EpisodeStats::new(n),
            steps_per_env: config.env.steps_per_env,
            reward_scale: config.ppo.reward_scale,
            env,
            eval_env,
            ppo,
            progress,
            eval_seed: eval_seed(config.run.seed),
            kickstart: None,
        })
    }

    /// Kickstarts the PPO iterations ([`crate::kickstart`]): the expert labels every rollout
    /// state, and the update adds the behaviour-cloning term while its weight is above 0.
    pub fn with_kickstart(mut self, config: crate::config::KickstartConfig) -> Self {
        let (steps, envs, actions) = (
            self.steps_per_env,
            self.env.num_envs(),
            self.env.action_dim(),
        );
        self.kickstart = Some(Kickstart::new(config, steps, envs, actions));
        self
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
        let mut env_s = 0.0;
        self.env.take_physics_s();
        self.env.take_pipeline_stats();
        let iteration = self.progress.iteration;
        let mut kickstart = self.kickstart.as_mut().filter(|k| k.coef(iteration) > 0.0);
        for step in 0..self.steps_per_env {
            let (env, buf, episodes) = (&mut self.env, &mut self.buf, &mut self.episodes);
            let reward_scale = self.reward_scale;
            let kickstart = kickstart.as_deref_mut();
            let answer = self
                .ppo
                .act_and_store(&self.obs, &self.critic_obs, |actions| {
                    let env_start = Instant::now();
                    if let Some(k) = kickstart {
                        // The state the action was sampled in, before the step changes it.
                        k.label(env.as_mut(), step)?;
                    }
                    let answer = step_env(env.as_mut(), buf, actions, reward_scale)?;
                    episodes.record(buf);
                    env_s += env_start.elapsed().as_secs_f64();
                    Ok(answer)
                })?;
            self.obs = answer.next_obs;
            self.critic_obs = answer.next_critic_obs;
        }
        let rollout_s = start.elapsed().as_secs_f64();
        let physics_s = self.env.take_physics_s();
        let pipeline = self.env.take_pipeline_stats();
        let update_start = Instant::now();
        let (update, kickstart) = match kickstart {
            Some(k) => {
                let mut term = k.term(k.coef(iteration));
                let update = self
                    .ppo
                    .update_with(&self.critic_obs, Some(&mut |b, m| term.loss(b, m)))?;
                (update, Some(term.stats()))
            }
            None => (self.ppo.update(&self.critic_obs)?, None),
        };
        let timing = IterationTiming {
            rollout_s,
            env_s,
            physics_s,
            update_s: update_start.elapsed().as_secs_f64(),
        };
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
            timing,
            pipeline,
            kickstart,
        })
    }

    /// [`evaluate`] of the learner's policy on the evaluation envs, from the run's evaluation
    /// seed.
    pub fn evaluate(&mut self) -> Result<f64, LearnError> {
        evaluate(self.eval_env.as_mut(), self.ppo.policy(), self.eval_seed)
    }
}

/// The seed every evaluation of a run resets its evaluation envs with: the same initial states
/// each time, so evaluations compare.
pub fn eval_seed(seed: u64) -> u64 {
    iteration_seed(seed, usize::MAX)
}

/// Mean undiscounted return of the deterministic `policy` (the Gaussian mean) over one episode
/// per env of `env`, reset from `seed`. Relies on every episode ending (tasks have a time
/// limit). Acts on the actor's observations alone, as the exported policy does; the critic
/// observations are written but not read.
pub fn evaluate(env: &mut dyn VecEnv, policy: &ActorCritic, seed: u64) -> Result<f64, LearnError> {
    let (n, o, c) = (env.num_envs(), env.obs_dim(), env.critic_obs_dim());
    let mut obs = vec![0.0; n * o];
    env.reset(seed, &mut obs, &mut vec![0.0; n * c])?;
    let mut buf = VecStep::new(n, o, c);
    let mut returns = vec![0.0; n];
    let mut running = vec![true; n];
    while running.iter().any(|&r| r) {
        check_finite("environment observation", &obs)?;
        let actions = policy.act_deterministic(&to_tensor(&obs, n, o));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::env::check_len;
    use crate::EnvError;

    /// Steps after which every episode of [`Privileged`] is truncated.
    const EPISODE: usize = 3;
    const OBS: usize = 2;

    /// Rows observing `[x, row]`; the critic also sees `privileged` copies of the step count
    /// within the episode, state the actor has no access to.
    struct Privileged {
        x: Vec<f64>,
        t: Vec<usize>,
        privileged: usize,
    }

    impl Privileged {
        fn boxed(rows: usize, privileged: usize) -> Box<dyn VecEnv> {
            Box::new(Privileged {
                x: vec![0.0; rows],
                t: vec![0; rows],
                privileged,
            })
        }

        fn observe(&self, i: usize, obs: &mut [f64], critic_obs: &mut [f64]) {
            obs.copy_from_slice(&[self.x[i], i as f64]);
            critic_obs[..OBS].copy_from_slice(obs);
            critic_obs[OBS..].fill(self.t[i] as f64);
        }
    }

    impl VecEnv for Privileged {
        fn num_envs(&self) -> usize {
            self.x.len()
        }

        fn obs_dim(&self) -> usize {
            OBS
        }

        fn action_dim(&self) -> usize {
            1
        }

        fn critic_obs_dim(&self) -> usize {
            OBS + self.privileged
        }

        fn reset(&mut self, _: u64, obs: &mut [f64], critic: &mut [f64]) -> Result<(), EnvError> {
            let (n, c) = (self.num_envs(), self.critic_obs_dim());
            check_len("observation batch", obs, n * OBS)?;
            check_len("critic observation batch", critic, n * c)?;
            let rows = obs.chunks_exact_mut(OBS).zip(critic.chunks_exact_mut(c));
            for (i, (o, c)) in rows.enumerate() {
                self.reset_env(i, o, c)?;
            }
            Ok(())
        }

        fn reset_env(
            &mut self,
            i: usize,
            obs: &mut [f64],
            critic: &mut [f64],
        ) -> Result<(), EnvError> {
            self.x[i] = 0.1 * i as f64;
            self.t[i] = 0;
            self.observe(i, obs, critic);
            Ok(())
        }

        fn step(&mut self, actions: &[f64], out: &mut VecStep) -> Result<(), EnvError> {
            let c = self.critic_obs_dim();
            for (i, a) in actions.iter().enumerate() {
                out.rewards[i] = -self.x[i].powi(2);
                self.x[i] += 0.1 * a.clamp(-1.0, 1.0);
                self.t[i] += 1;
                out.terminated[i] = false;
                out.truncated[i] = self.t[i] == EPISODE;
                let (o_row, c_row) = (i * OBS..(i + 1) * OBS, i * c..(i + 1) * c);
                self.observe(
                    i,
                    &mut out.obs[o_row.clone()],
                    &mut out.critic_obs[c_row.clone()],
                );
                if out.truncated[i] {
                    out.final_obs[o_row.clone()].copy_from_slice(&out.obs[o_row.clone()]);
                    out.final_critic_obs[c_row.clone()]
                        .copy_from_slice(&out.critic_obs[c_row.clone()]);
                    self.reset_env(i, &mut out.obs[o_row], &mut out.critic_obs[c_row])?;
                }
            }
            Ok(())
        }

        /// An expert that drives every row's x to 0.5: its raw action depends on the state,
        /// so labels taken from another state than the action's would not fit.
        fn expert_actions(&mut self, actions: &mut [f64]) -> Result<(), EnvError> {
            check_len("expert actions", actions, self.num_envs())?;
            for (a, x) in actions.iter_mut().zip(&self.x) {
                *a = 5.0 * (0.5 - x);
            }
            Ok(())
        }
    }

    /// Three worlds of two agent rows each, four steps per rollout.
    fn config() -> TrainConfig {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../configs/train/pendulum.toml"
        );
        let mut config = TrainConfig::load(path).unwrap();
        config.env.num_envs = 3;
        config.env.steps_per_env = 4;
        config.ppo.epochs = 1;
        config.ppo.minibatches = 2;
        config
    }

    fn ppo(config: &TrainConfig, rows: usize, critic_obs_dim: usize) -> Ppo {
        let policy = ActorCritic::new(OBS, critic_obs_dim, 1, &config.policy);
        Ppo::new(policy, config.ppo.clone(), config.env.steps_per_env, rows)
    }

    fn values(t: &Tensor) -> Vec<f64> {
        to_f64(t).unwrap()
    }

    /// A runner on six rows of [`Privileged`] with one privileged column, seeded 0.
    fn privileged_runner() -> Runner {
        tch::manual_seed(0);
        let config = config();
        let (env, eval_env) = (Privileged::boxed(6, 1), Privileged::boxed(2, 1));
        let ppo = ppo(&config, 6, 3);
        Runner::new(&config, env, eval_env, ppo, Progress::default()).unwrap()
    }

    #[test]
    fn the_critic_learns_from_the_privileged_observations() {
        let mut runner = privileged_runner();
        assert_eq!(runner.obs.size(), [6, 2]);
        assert_eq!(runner.critic_obs.size(), [6, 3]);

        let stats = runner.iterate().unwrap();
        assert_eq!(
            stats.progress.env_steps, 24,
            "rows, not worlds, are counted"
        );
        assert!(stats.update.value_loss.is_finite());
        // After four steps of three-step episodes every row is one step into its second.
        assert_eq!(values(&runner.critic_obs.select(1, 2)), vec![1.0; 6]);

        // The rollout stored the critic observations beside the actor's: steps 0..4 had
        // step counts 0, 1, 2, 0 in every row.
        let batch = runner.ppo.storage().minibatches(1, 1).next().unwrap();
        assert_eq!(batch.obs.size(), [24, 2]);
        assert_eq!(batch.critic_obs.size(), [24, 3]);
        assert_eq!(
            values(&batch.critic_obs.narrow(1, 0, 2)),
            values(&batch.obs)
        );
        let counts = values(&batch.critic_obs.select(1, 2));
        let of = |k: f64| counts.iter().filter(|&&c| c == k).count();
        assert_eq!((of(0.0), of(1.0), of(2.0)), (12, 6, 6));

        let policy = runner.ppo.policy();
        let critic_norm = policy.critic_obs_normalizer().unwrap();
        assert_eq!(
            (critic_norm.mean().size(), critic_norm.count()),
            (vec![3], 24)
        );
        assert_eq!(policy.obs_normalizer().unwrap().mean().size(), [2]);
        assert!(runner.evaluate().unwrap().is_finite());
    }

    /// Mean squared error of the actor's mean to the expert's action over the states `[x, row]`
    /// for x in [0, 0.6] and every row.
    fn expert_error(runner: &Runner) -> f64 {
        let (mut obs, mut labels) = (Vec::new(), Vec::new());
        for row in 0..6 {
            for k in 0..=6 {
                let x = 0.1 * k as f64;
                obs.extend([x, row as f64]);
                labels.push(5.0 * (0.5 - x));
            }
        }
        let mean = values(
            &runner
                .ppo
                .policy()
                .act_deterministic(&to_tensor(&obs, 42, 2)),
        );
        mean.iter()
            .zip(&labels)
            .map(|(m, l)| (m - l).powi(2))
            .sum::<f64>()
            / 42.0
    }

    #[test]
    fn kickstarting_pulls_the_actor_to_the_expert_until_its_weight_is_zero() {
        let run = |kickstart: Option<f64>| {
            let mut runner = privileged_runner();
            if let Some(bc_coef) = kickstart {
                runner = runner.with_kickstart(crate::config::KickstartConfig {
                    bc_coef,
                    anneal_iterations: 40,
                });
            }
            let before = expert_error(&runner);
            let stats: Vec<IterationStats> = (0..42).map(|_| runner.iterate().unwrap()).collect();
            (before, expert_error(&runner), stats)
        };
        // The two starts are not bit-equal: libtorch's generator is global, and tests running
        // beside this one draw from it too.
        let (_, plain, stats) = run(None);
        assert!(stats.iter().all(|s| s.kickstart.is_none()));
        let (before, kicked, stats) = run(Some(50.0));
        // PPO alone does not learn the expert's state-dependent action; the term does.
        assert!(
            kicked < 0.25 * plain && kicked < 0.25 * before,
            "{before} {plain} {kicked}"
        );
        let k: Vec<_> = stats.iter().map(|s| s.kickstart).collect();
        let first = k[0].unwrap();
        assert_eq!(first.coef, 50.0);
        assert!(first.bc_loss > 0.0 && (0.0..=1.0).contains(&first.expert_agreement));
        assert!((k[39].unwrap().coef - 50.0 / 40.0).abs() < 1e-9);
        assert!(
            k[40].is_none() && k[41].is_none(),
            "weight 0: no term, no labels"
        );
        assert!(k[39].unwrap().bc_loss < first.bc_loss);
    }

    #[test]
    fn time_outs_carry_the_final_critic_observations() {
        let mut env = Privileged::boxed(4, 2);
        let (o, c) = (env.obs_dim(), env.critic_obs_dim());
        env.reset(0, &mut vec![0.0; 4 * o], &mut vec![0.0; 4 * c])
            .unwrap();
        let mut buf = VecStep::new(4, o, c);
        let actions = Tensor::zeros([4, 1], (Kind::Float, tch::Device::Cpu));
        for _ in 1..EPISODE {
            let answer = step_env(env.as_mut(), &mut buf, &actions, 1.0).unwrap();
            assert!(answer.time_outs.is_none());
        }
        let answer = step_env(env.as_mut(), &mut buf, &actions, 1.0).unwrap();
        let time_outs = answer.time_outs.expect("all rows timed out");
        assert_eq!(
            Vec::<i64>::try_from(&time_outs.env_ids).unwrap(),
            [0, 1, 2, 3]
        );
        assert_eq!(time_outs.final_critic_obs.size(), [4, 4]);
        let last = EPISODE as f64;
        assert_eq!(
            values(&time_outs.final_critic_obs.narrow(1, 2, 2)),
            vec![last; 8]
        );
        assert_eq!(answer.next_critic_obs.size(), [4, 4]);
        assert_eq!(
            values(&answer.next_critic_obs.narrow(1, 2, 2)),
            vec![0.0; 8]
        );
    }

    #[test]
    fn mismatched_widths_and_rows_are_named() {
        let config = config();
        let refused = |env, eval_env, ppo| match Runner::new(
            &config,
            env,
            eval_env,
            ppo,
            Progress::default(),
        ) {
            Err(LearnError::Shape { what, .. }) => what,
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("accepted"),
        };
        let what = refused(
            Privileged::boxed(6, 1),
            Privileged::boxed(2, 0),
            ppo(&config, 6, 3),
        );
        assert_eq!(what, "evaluation env critic observation width");
        let what = refused(
            Privileged::boxed(6, 1),
            Privileged::boxed(2, 1),
            ppo(&config, 6, 2),
        );
        assert_eq!(what, "policy critic observation width");
        // Sized by the config's worlds instead of the env's rows.
        let what = refused(
            Privileged::boxed(6, 1),
            Privileged::boxed(2, 1),
            ppo(&config, 3, 3),
        );
        assert_eq!(what, "rollout storage rows");
    }
}
