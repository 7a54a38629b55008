//! The lift, transport and place tasks as a [`VecEnv`] over [`moonhaul_sim::BatchEnv`]: the
//! episodes of [`moonhaul_sim::task`] plus the paper's rewards ([`crate::reward`]).
//!
//! **One row per unit.** The actor is shared by both units (see
//! [`moonhaul_core::observation`]), so each world contributes two rows: row `2w + i` is unit
//! `i` of world `w`, observing o⁽ⁱ⁾ and emitting its u⁽ⁱ⁾. Both rows of a world get the world's
//! reward and end together; the critic row adds privileged truth
//! ([`moonhaul_sim::task::CRITIC_OBS_DIM`]).
//!
//! **Terminations and the all-negative rewards.** Every term of r_L, r_T and r_P is ≤ 0, so a
//! plain termination would *end* the penalties and pay a policy to break its grasp. A
//! terminated episode therefore receives, on its last step, the discounted sum of that step's
//! reward held until the time limit, `r · (1 − γ^k)/(1 − γ)` for the k steps left: failing is
//! worth what staying in the failed state would have cost, no more and no less.
//!
//! **The expert.** Built [`PhaseVecEnv::with_expert`], every world carries one scripted expert
//! per unit ([`PhaseTask::expert`]), started afresh with each of its episodes (at a reset, an
//! auto-reset inside [`VecEnv::step`], a hand-over start), and [`VecEnv::expert_actions`] labels
//! each row with its unit's expert raw action ([`Episode::expert_action`]), the labels DAgger
//! clones (`moonhaul_learn::distill`).

use std::sync::Arc;
use std::time::Instant;

use moonhaul_core::observation::ACTOR_OBS_DIM;
use moonhaul_core::scripted::{MissionPlan, PhaseScript};
use moonhaul_core::state::{Phase, UNIT_ACTION_DIM};
use moonhaul_sim::handover::HandOver;
use moonhaul_sim::scene::{Env, EnvState, SceneModel, UNITS};
use moonhaul_sim::task::{Episode, PhaseTask, StepOutcome, TaskConfig, CRITIC_OBS_DIM};
use moonhaul_sim::{BatchEnv, SimError};
use rand_chacha::ChaCha8Rng;

use crate::env::{check_len, PipelineStats, VecEnv, VecStep};
use crate::reward::{force_variance, Goal, PayloadSample, RewardConfig};
use crate::EnvError;

/// Everything one world needs between steps, and its outputs of the last step.
struct World {
    episode: Episode,
    /// The hand-over this world was replayed from and its episodes start at (`None`: settled
    /// starts).
    handover: Option<Arc<HandOver>>,
    rng: ChaCha8Rng,
    /// This step's increments Δ = step ⊙ a of both units, fed to the episode's pipelines.
    deltas: [[f64; UNIT_ACTION_DIM]; UNITS],
    obs: [[f64; ACTOR_OBS_DIM]; UNITS],
    critic: [[f64; CRITIC_OBS_DIM]; UNITS],
    final_obs: [[f64; ACTOR_OBS_DIM]; UNITS],
    final_critic: [[f64; CRITIC_OBS_DIM]; UNITS],
    reward: f64,
    outcome: StepOutcome,
    /// CPU time of this step's physics, s.
    physics_cpu_s: f64,
    /// CPU time of the rest of this step (the task's half), s.
    task_cpu_s: f64,
    /// What both units' pipelines did since [`VecEnv::take_pipeline_stats`].
    pipeline: PipelineStats,
    /// Both units' scripted experts (built [`PhaseVecEnv::with_expert`]).
    expert: Option<Expert>,
}

/// One world's scripted experts, started with its episode. The scripts carry state from tick to
/// tick (the lift they asked for, their compliance), so each must see every control step of
/// its episode exactly once, in order: `next_step` says which one it labels next.
#[derive(Debug, Clone)]
struct Expert {
    plan: MissionPlan,
    scripts: [PhaseScript; UNITS],
    /// The episode step ([`Episode::steps`]) the scripts label next.
    next_step: u64,
    /// The labels of step `next_step − 1`, given again if asked again before the next step.
    labels: [[f64; UNIT_ACTION_DIM]; UNITS],
}

impl Expert {
    fn new(task: &PhaseTask, plan: MissionPlan) -> Self {
        Expert {
            plan,
            scripts: [task.expert(plan), task.expert(plan)],
            next_step: 0,
            labels: [[0.0; UNIT_ACTION_DIM]; UNITS],
        }
    }
}

/// What the reward sees of the payload (privileged truth).
pub fn payload_sample(state: &EnvState) -> PayloadSample {
    let p = &state.payload;
    PayloadSample {
        height_m: p.height_m,
        vertical_speed_mps: p.linvel_mps.z,
        tilt_rad: p.tilt_rad,
        planar_position_m: [p.pose.translation.x, p.pose.translation.y],
        planar_velocity_mps: [p.linvel_mps.x, p.linvel_mps.y],
    }
}

/// The phase reward of one step: the paper's r_L, r_T or r_P plus the two terms not in the paper
/// ([`RewardConfig::pipeline_terms`], off at the shipped weights of 0).
pub fn phase_reward(
    reward: &RewardConfig,
    task: &PhaseTask,
    scene: &SceneModel,
    env: &Env,
    episode: &Episode,
    state: &EnvState,
) -> f64 {
    let sample = payload_sample(state);
    let p_ref = episode.reference_position_m(task);
    let v_cmd = episode.command_velocity_mps(task);
    let goal = Goal {
        height_m: episode.goal_height_m(),
        position_m: [p_ref.x, p_ref.y],
        velocity_mps: [v_cmd.x, v_cmd.y],
    };
    let weight_n = env.payload_mass_kg(scene) * scene.config.physics.gravity_mps2.abs();
    let forces = state.units.map(|u| u.grasp.force_n);
    let paper = match episode.phase() {
        Phase::Lift | Phase::Idle => reward.lift(&sample, &goal, force_variance(&forces, weight_n)),
        Phase::Transport => reward.transport(&sample, &goal),
        Phase::Place => reward.place(&sample, &goal),
    };
    let t_max = episode
        .reports()
        .map_or([1.0; UNITS], |r| r.map(|r| r.clamp.t_max));
    paper + reward.pipeline_terms(&t_max, &forces, weight_n)
}

/// A batch of phase-task worlds.
pub struct PhaseVecEnv {
    batch: BatchEnv,
    task: PhaseTask,
    reward: RewardConfig,
    gamma: f64,
    worlds: Vec<World>,
    starts: HandOverStarts,
    /// The plan the worlds' scripted experts fly (`None`: no expert labels).
    expert_plan: Option<MissionPlan>,
    /// Physics' share of the step wall time since [`VecEnv::take_physics_s`], s.
    physics_s: f64,
}

impl PhaseVecEnv {
    /// `worlds` simulated worlds (2 rows each) of `phase` (`None`: the monolithic baseline's
    /// whole mission) on `scene` with the tasks' settings and the clamp of `sync`, on `threads`
    /// simulator threads, with domain randomization on.
    /// The action map is built around the grasp of the first of `randomization.payloads` (a
    /// payload file the caller added with [`SceneModel::add_payload_file`], say).
    pub fn new(
        phase: Option<Phase>,
        scene: SceneModel,
        (tasks, sync): (TaskConfig, moonhaul_coord::SyncConfig),
        reward: RewardConfig,
        gamma: f64,
        worlds: usize,
        threads: usize,
    ) -> Result<Self, EnvError> {
        let task = match phase {
            Some(phase) => PhaseTask::new(phase, tasks, sync, &scene)?,
            None => PhaseTask::mission(tasks, sync, &scene)?,
        };
        let options = task.env_options(true, None);
        let batch = BatchEnv::new(scene, worlds, 0, options, threads)?;
        let mut env = PhaseVecEnv {
            batch,
            task,
            reward,
            gamma,
            worlds: Vec::with_capacity(worlds),
            starts: HandOverStarts::default(),
            expert_plan: None,
            physics_s: 0.0,
        };
        env.begin_all(0)?;
        Ok(env)
    }

    /// The same batch with `starts.fraction` of its worlds replayed from `starts.handovers`
    /// (rebuilt now, and at every reset).
    pub fn with_handover_starts(mut self, starts: HandOverStarts) -> Result<Self, EnvError> {
        if starts.worlds(self.batch.len()) == 0 {
            return Ok(self);
        }
        self.starts = starts;
        self.rebuild(0)?;
        self.begin_all(0)?;
        Ok(self)
    }

    /// The same batch with its episodes cut at `episode_s` instead of the phase's `duration_s`,
    /// which the actor's phase clock goes on measuring ([`PhaseTask::with_time_limit_s`]).
    pub fn with_episode_s(mut self, episode_s: f64) -> Self {
        self.task = self.task.with_time_limit_s(episode_s);
        self
    }

    /// The same batch with a scripted expert flying `plan` in every world, for
    /// [`VecEnv::expert_actions`]. Attach it before the first step: a script that missed the
    /// start of its episode is refused until the world's next episode.
    pub fn with_expert(mut self, plan: MissionPlan) -> Self {
        self.expert_plan = Some(plan);
        for world in &mut self.worlds {
            world.expert = Some(Expert::new(&self.task, plan));
        }
        self
    }

    pub fn task(&self) -> &PhaseTask {
        &self.task
    }

    /// Rebuilds every world from `seed`: the hand-over worlds replayed from their captures,
    /// the others drawn as [`BatchEnv::reseed`] draws them.
    fn rebuild(&mut self, seed: u64) -> Result<(), EnvError> {
        let worlds = self.batch.len();
        let starts = &self.starts;
        let options = self.task.env_options(true, None);
        self.batch.reseed_with(seed, |scene, w, env_seed| {
            match starts.of_world(seed, w, worlds) {
                Some(h) => Env::replay(scene, &h),
                None => Env::new(scene, env_seed, options),
            }
        })?;
        Ok(())
    }

    /// Starts an episode in every world from its current (freshly built) state.
    fn begin_all(&mut self, seed: u64) -> Result<(), EnvError> {
        let scene = self.batch.scene();
        let mut worlds = Vec::with_capacity(self.batch.len());
        for (i, (env, state)) in self
            .batch
            .envs()
            .iter()
            .zip(self.batch.states())
            .enumerate()
        {
            let mut rng = PhaseTask::rng(moonhaul_sim::batch::env_seed(seed, i));
            let handover = self.starts.of_world(seed, i, self.batch.len());
            let episode = begin(&self.task, scene, env, state, handover.as_deref(), &mut rng)?;
            let mut world = World {
                episode,
                handover,
                rng,
                deltas: [[0.0; UNIT_ACTION_DIM]; UNITS],
                obs: [[0.0; ACTOR_OBS_DIM]; UNITS],
                critic: [[0.0; CRITIC_OBS_DIM]; UNITS],
                final_obs: [[0.0; ACTOR_OBS_DIM]; UNITS],
                final_critic: [[0.0; CRITIC_OBS_DIM]; UNITS],
                reward: 0.0,
                outcome: StepOutcome {
                    terminated: None,
                    truncated: false,
                },
                physics_cpu_s: 0.0,
                task_cpu_s: 0.0,
                pipeline: PipelineStats::default(),
                expert: self.expert_plan.map(|plan| Expert::new(&self.task, plan)),
            };
            observe(&self.task, scene, env, state, &mut world)?;
            worlds.push(world);
        }
        self.worlds = worlds;
        Ok(())
    }

    fn write_rows(&self, obs: &mut [f64], critic: &mut [f64]) {
        for (w, world) in self.worlds.iter().enumerate() {
            for i in 0..UNITS {
                let row = w * UNITS + i;
                obs[row * ACTOR_OBS_DIM..(row + 1) * ACTOR_OBS_DIM].copy_from_slice(&world.obs[i]);
                critic[row * CRITIC_OBS_DIM..(row + 1) * CRITIC_OBS_DIM]
                    .copy_from_slice(&world.critic[i]);
            }
        }
    }
}

/// The hand-over starts of a batch: the captured hand-overs and the share of worlds replayed
/// from them ([`moonhaul_sim::handover`]).
#[derive(Debug, Clone, Default)]
pub struct HandOverStarts {
    pub handovers: Vec<Arc<HandOver>>,
    /// Share of the worlds, 0 to 1.
    pub fraction: f64,
}

impl HandOverStarts {
    /// How many of `worlds` start from a hand-over (rounded to nearest).
    fn worlds(&self, worlds: usize) -> usize {
        if self.handovers.is_empty() {
            0
        } else {
            ((self.fraction * worlds as f64).round() as usize).min(worlds)
        }
    }

    /// The hand-over of world `w` of `worlds` after a rebuild from `seed`: the first
    /// [`HandOverStarts::worlds`] worlds replay hand-overs, each rebuild moving on through
    /// the list so that every capture is used.
    fn of_world(&self, seed: u64, w: usize, worlds: usize) -> Option<Arc<HandOver>> {
        let n = self.worlds(worlds);
        (w < n).then(|| {
            let k = (seed as usize).wrapping_mul(n).wrapping_add(w) % self.handovers.len();
            self.handovers[k].clone()
        })
    }
}

impl World {
    /// Starts this world's next episode in its freshly reset `env`.
    fn begin(
        &mut self,
        task: &PhaseTask,
        scene: &SceneModel,
        env: &Env,
        state: &EnvState,
    ) -> Result<(), SimError> {
        self.episode = begin(
            task,
            scene,
            env,
            state,
            self.handover.as_deref(),
            &mut self.rng,
        )?;
        if let Some(expert) = &mut self.expert {
            *expert = Expert::new(task, expert.plan);
        }
        Ok(())
    }

    /// Labels both units at the episode's current step, unless already labelled (the caller
    /// checked the scripts have seen every earlier step).
    fn label(&mut self, task: &PhaseTask, scene: &SceneModel) -> Result<(), SimError> {
        let Some(expert) = &mut self.expert else {
            return Ok(());
        };
        if self.episode.steps() == expert.next_step {
            for (i, script) in expert.scripts.iter_mut().enumerate() {
                expert.labels[i] = self.episode.expert_action(task, scene, i, script)?;
            }
            expert.next_step += 1;
        }
        Ok(())
    }
}

/// A new episode in a freshly reset world: at its hand-over, or settled.
fn begin(
    task: &PhaseTask,
    scene: &SceneModel,
    env: &Env,
    state: &EnvState,
    handover: Option<&HandOver>,
    rng: &mut ChaCha8Rng,
) -> Result<Episode, SimError> {
    match handover {
        Some(h) => task.begin_handover(scene, state, h, rng),
        None => task.begin(scene, env, state, rng),
    }
}

/// Both units' actor and critic observations of a world.
fn observe(
    task: &PhaseTask,
    scene: &SceneModel,
    env: &Env,
    state: &EnvState,
    world: &mut World,
) -> Result<(), SimError> {
    for i in 0..UNITS {
        world.episode.observe(task, scene, i, &mut world.obs[i])?;
        world
            .episode
            .observe_critic(task, scene, env, state, i, &mut world.critic[i])?;
    }
    Ok(())
}

impl VecEnv for PhaseVecEnv {
    fn num_envs(&self) -> usize {
        self.worlds.len() * UNITS
    }

    fn obs_dim(&self) -> usize {
        ACTOR_OBS_DIM
    }

    fn critic_obs_dim(&self) -> usize {
        CRITIC_OBS_DIM
    }

    fn action_dim(&self) -> usize {
        UNIT_ACTION_DIM
    }

    /// The increment map: raw actions are scaled to Δ = step ⊙ a (no offset), the pipeline
    /// bounds them; the exported policy therefore outputs the increment itself.
    fn action_scale(&self) -> Vec<f64> {
        self.task.action_map().step.to_vec()
    }

    fn max_episode_steps(&self) -> Option<u64> {
        Some(self.task.max_steps())
    }

    fn policy_metadata(&self) -> Vec<(String, String)> {
        moonhaul_core::action::ActionMap::metadata()
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v))
            .collect()
    }

    fn reset(
        &mut self,
        seed: u64,
        obs: &mut [f64],
        critic_obs: &mut [f64],
    ) -> Result<(), EnvError> {
        check_len("reset observations", obs, self.num_envs() * ACTOR_OBS_DIM)?;
        check_len(
            "reset critic observations",
            critic_obs,
            self.num_envs() * CRITIC_OBS_DIM,
        )?;
        self.rebuild(seed)?;
        self.begin_all(seed)?;
        self.write_rows(obs, critic_obs);
        Ok(())
    }

    fn reset_env(
        &mut self,
        index: usize,
        obs: &mut [f64],
        critic_obs: &mut [f64],
    ) -> Result<(), EnvError> {
        check_len("reset observation", obs, ACTOR_OBS_DIM)?;
        check_len("reset critic observation", critic_obs, CRITIC_OBS_DIM)?;
        let w = index / UNITS;
        if w >= self.worlds.len() {
            return Err(EnvError::Shape {
                what: "env index",
                expected: self.num_envs(),
                found: index,
            });
        }
        // A world holds both units: resetting one row restarts its world, and the other row
        // sees the new episode at the next step.
        let task = &self.task;
        let mut mask = vec![false; self.worlds.len()];
        mask[w] = true;
        self.batch.reset(&mask)?;
        let scene = self.batch.scene();
        let (env, state) = (&self.batch.envs()[w], &self.batch.states()[w]);
        let world = &mut self.worlds[w];
        world.begin(task, scene, env, state)?;
        observe(task, scene, env, state, world)?;
        let i = index % UNITS;
        obs.copy_from_slice(&world.obs[i]);
        critic_obs.copy_from_slice(&world.critic[i]);
        Ok(())
    }

    fn expert_actions(&mut self, actions: &mut [f64]) -> Result<(), EnvError> {
        check_len("expert actions", actions, self.num_envs() * UNIT_ACTION_DIM)?;
        if self.expert_plan.is_none() {
            return Err(EnvError::NoExpert {
                reason: "this phase env was built without a mission plan for its scripted \
                         expert (a training config's [warm_start] mission)"
                    .into(),
            });
        }
        // Checked for every world before any script runs, so a refusal changes no script.
        for (w, world) in self.worlds.iter().enumerate() {
            let step = world.episode.steps();
            let next = world.expert.as_ref().map_or(0, |e| e.next_step);
            if step != next && step + 1 != next {
                return Err(EnvError::NoExpert {
                    reason: format!(
                        "world {w} is at step {step} of its episode, its experts have seen \
                         {next} steps of it: they must be asked at every step from the \
                         episode's first"
                    ),
                });
            }
        }
        let task = &self.task;
        self.batch
            .for_each_with(&mut self.worlds, |scene, _, _, world| {
                world.label(task, scene)
            })?;
        for (w, world) in self.worlds.iter().enumerate() {
            if let Some(expert) = &world.expert {
                for (i, labels) in expert.labels.iter().enumerate() {
                    let row = w * UNITS + i;
                    actions[row * UNIT_ACTION_DIM..(row + 1) * UNIT_ACTION_DIM]
                        .copy_from_slice(labels);
                }
            }
        }
        Ok(())
    }

    fn take_physics_s(&mut self) -> Option<f64> {
        Some(std::mem::take(&mut self.physics_s))
    }

    fn take_pipeline_stats(&mut self) -> Option<PipelineStats> {
        let mut total = PipelineStats::default();
        for world in &mut self.worlds {
            total.merge(&std::mem::take(&mut world.pipeline));
        }
        Some(total)
    }

    fn step(&mut self, actions: &[f64], out: &mut VecStep) -> Result<(), EnvError> {
        let rows = self.num_envs();
        check_len("actions", actions, rows * UNIT_ACTION_DIM)?;
        for (w, world) in self.worlds.iter_mut().enumerate() {
            for i in 0..UNITS {
                let row = w * UNITS + i;
                world.deltas[i] = self
                    .task
                    .increment(&actions[row * UNIT_ACTION_DIM..(row + 1) * UNIT_ACTION_DIM]);
            }
        }
        let (task, reward, gamma) = (&self.task, &self.reward, self.gamma);
        let parallel_start = Instant::now();
        self.batch
            .for_each_with(&mut self.worlds, |scene, env, state, world| {
                let start = Instant::now();
                let commands = world.episode.commands(task, &world.deltas)?;
                env.step(scene, &commands);
                env.state_into(scene, state);
                let physics_end = Instant::now();
                if let Some(reports) = world.episode.reports() {
                    for (report, unit) in reports.iter().zip(&state.units) {
                        world.pipeline.record(&report.clamp, unit.grasp.force_n);
                    }
                }
                world.physics_cpu_s = (physics_end - start).as_secs_f64();
                let result = task_step(task, reward, gamma, scene, env, state, world);
                world.task_cpu_s = physics_end.elapsed().as_secs_f64();
                result
            })?;
        // The workers' CPU split applied to the parallel section's wall time: what the
        // physics cost this step with the task's work beside it on the same threads.
        let parallel_s = parallel_start.elapsed().as_secs_f64();
        let physics: f64 = self.worlds.iter().map(|w| w.physics_cpu_s).sum();
        let rest: f64 = self.worlds.iter().map(|w| w.task_cpu_s).sum();
        if physics + rest > 0.0 {
            self.physics_s += parallel_s * physics / (physics + rest);
        }
        self.write_rows(&mut out.obs, &mut out.critic_obs);
        for (w, world) in self.worlds.iter().enumerate() {
            let ended = world.outcome.terminated.is_some() || world.outcome.truncated;
            for i in 0..UNITS {
                let row = w * UNITS + i;
                out.rewards[row] = world.reward;
                out.terminated[row] = world.outcome.terminated.is_some();
                out.truncated[row] = world.outcome.truncated;
                if ended {
                    out.final_obs[row * ACTOR_OBS_DIM..(row + 1) * ACTOR_OBS_DIM]
                        .copy_from_slice(&world.final_obs[i]);
                    out.final_critic_obs[row * CRITIC_OBS_DIM..(row + 1) * CRITIC_OBS_DIM]
                        .copy_from_slice(&world.final_critic[i]);
                }
            }
        }
        Ok(())
    }
}

/// The task's half of one world's step, after the physics: outcome, reward (with a
/// termination charged the discounted cost of staying failed), auto-reset, observation.
fn task_step(
    task: &PhaseTask,
    reward: &RewardConfig,
    gamma: f64,
    scene: &SceneModel,
    env: &mut Env,
    state: &mut EnvState,
    world: &mut World,
) -> Result<(), SimError> {
    world.outcome = world
        .episode
        .advance(task, scene, env, state, &mut world.rng);
    let r = if world.outcome.terminated == Some(moonhaul_sim::task::Termination::NonFinite) {
        // A diverged world has no meaningful reward; the last finite one stands.
        world.reward
    } else {
        phase_reward(reward, task, scene, env, &world.episode, state)
    };
    world.reward = if world.outcome.terminated.is_some() {
        let left = task.max_steps().saturating_sub(world.episode.steps()) as i32;
        r * (1.0 - gamma.powi(left.max(1))) / (1.0 - gamma)
    } else {
        r
    };
    if world.outcome.terminated.is_some() || world.outcome.truncated {
        if world.outcome.terminated != Some(moonhaul_sim::task::Termination::NonFinite) {
            observe(task, scene, env, state, world)?;
        }
        world.final_obs = world.obs;
        world.final_critic = world.critic;
        env.reset();
        env.state_into(scene, state);
        world.begin(task, scene, env, state)?;
    }
    observe(task, scene, env, state, world)
}

#[cfg(test)]
mod tests {
    use super::*;
    use moonhaul_sim::SimConfig;

    use crate::pendulum::PendulumVecEnv;

    /// Steps of the test's lift episodes: 1 s of settling and 1 s of lifting by the shipped plan,
    /// so the labels move, and short enough for several episodes.
    const EPISODE_S: f64 = 2.0;

    fn lift_env(worlds: usize) -> PhaseVecEnv {
        let scene = SceneModel::new(SimConfig::shipped().unwrap()).unwrap();
        let mut tasks = TaskConfig::shipped().unwrap();
        tasks.lift.duration_s = EPISODE_S;
        let sync = moonhaul_coord::SyncConfig::shipped().unwrap();
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/train/lift.toml");
        let config = crate::config::TrainConfig::load(path).unwrap();
        let reward = config.reward.unwrap();
        PhaseVecEnv::new(
            Some(Phase::Lift),
            scene,
            (tasks, sync),
            reward,
            0.98,
            worlds,
            1,
        )
        .unwrap()
    }

    #[test]
    fn expert_labels_are_each_units_scripted_action_from_each_episodes_start() {
        let plan = MissionPlan::shipped().unwrap();
        let mut env = lift_env(2).with_expert(plan);
        let (n, o, c, a) = (
            env.num_envs(),
            ACTOR_OBS_DIM,
            CRITIC_OBS_DIM,
            UNIT_ACTION_DIM,
        );
        env.reset(3, &mut vec![0.0; n * o], &mut vec![0.0; n * c])
            .unwrap();
        let steps = (2.5 * EPISODE_S * env.batch.scene().config.control_hz).round() as usize;
        // The reference: each world's own episode asked with scripts of the test's, started
        // afresh whenever an episode is at its first step, as crates/sim/tests/expert.rs does.
        let task = env.task.clone();
        let fresh = || [task.expert(plan), task.expert(plan)];
        let mut scripts = [fresh(), fresh()];
        let (mut labels, mut again) = (vec![0.0; n * a], vec![0.0; n * a]);
        let mut buf = VecStep::new(n, o, c);
        let (mut starts, mut largest) = (0, 0.0f64);
        for step in 0..steps {
            if step == steps / 2 {
                // A restart of world 1 alone, between steps (the trainer's reset_env).
                env.reset_env(3, &mut vec![0.0; o], &mut vec![0.0; c])
                    .unwrap();
            }
            let mut expected = vec![0.0; n * a];
            for (w, world) in env.worlds.iter().enumerate() {
                if world.episode.steps() == 0 {
                    scripts[w] = fresh();
                    starts += 1;
                }
                for (i, script) in scripts[w].iter_mut().enumerate() {
                    let row = w * UNITS + i;
                    let action = world
                        .episode
                        .expert_action(&task, env.batch.scene(), i, script)
                        .unwrap();
                    expected[row * a..(row + 1) * a].copy_from_slice(&action);
                }
            }
            env.expert_actions(&mut labels).unwrap();
            assert_eq!(labels, expected, "step {step}");
            // Asked again before the step: the same labels, no script advanced twice.
            env.expert_actions(&mut again).unwrap();
            assert_eq!(again, expected, "step {step}, asked again");
            largest = labels.iter().fold(largest, |m, v| m.max(v.abs()));
            env.step(&labels, &mut buf).unwrap();
        }
        // Two worlds' first episodes, two auto-resets each, and the restart of world 1.
        let (first, auto_resets, restart) = (2, 2 * 2, 1);
        assert!(
            starts >= first + auto_resets + restart,
            "{starts} episode starts"
        );
        assert!(largest > 0.1, "the expert never moved: {largest}");

        // A step without labels leaves the scripts a step behind: refused, naming the world.
        env.step(&labels, &mut buf).unwrap();
        let err = env.expert_actions(&mut labels).unwrap_err().to_string();
        assert!(
            err.contains("world 0") && err.contains("every step"),
            "{err}"
        );
        // Until the world's next episode, which starts its experts afresh.
        env.reset_env(0, &mut vec![0.0; o], &mut vec![0.0; c])
            .unwrap();
        let err = env.expert_actions(&mut labels).unwrap_err().to_string();
        assert!(err.contains("world 1"), "{err}");
        env.reset(4, &mut vec![0.0; n * o], &mut vec![0.0; n * c])
            .unwrap();
        env.expert_actions(&mut labels).unwrap();
    }

    #[test]
    fn envs_without_an_expert_say_so() {
        let mut env = lift_env(1);
        let err = env.expert_actions(&mut [0.0; 2 * UNIT_ACTION_DIM]);
        assert!(
            matches!(&err, Err(EnvError::NoExpert { reason }) if reason.contains("mission plan")),
            "{err:?}"
        );
        let mut pendulum = PendulumVecEnv::new(2);
        let err = pendulum
            .expert_actions(&mut [0.0; 2])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("PendulumVecEnv has no scripted expert"),
            "{err}"
        );
    }
}
