//! Many independent worlds stepped in parallel.
//!
//! Each env owns its world and its random stream (seeded from the batch seed and its index),
//! so a trajectory depends only on the seed and the commands, never on the number of threads
//! or on which thread ran an env. Stepping writes into preallocated state buffers; the only
//! allocations are rapier's internal buffers, which reach their steady size in the first steps,
//! and resets, which copy each world's template back (see [`Env::reset`]).

use moonhaul_core::seed::stream_seed;
use moonhaul_core::state::UnitCommand;
use rayon::prelude::*;

use crate::scene::{Env, EnvOptions, EnvState, SceneModel, UNITS};
use crate::SimError;

/// The seed of env `index` in a batch seeded with `seed` (see [`stream_seed`]).
pub fn env_seed(seed: u64, index: usize) -> u64 {
    stream_seed(seed, index as u64)
}

/// N worlds, their latest states, and the thread pool that steps them.
pub struct BatchEnv {
    scene: SceneModel,
    envs: Vec<Env>,
    states: Vec<EnvState>,
    options: EnvOptions,
    pool: rayon::ThreadPool,
}

impl BatchEnv {
    /// `count` envs on `threads` worker threads (0: one per core).
    pub fn new(
        scene: SceneModel,
        count: usize,
        seed: u64,
        options: EnvOptions,
        threads: usize,
    ) -> Result<Self, SimError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| SimError::Config {
                field: "threads",
                reason: e.to_string(),
            })?;
        let envs = pool.install(|| {
            (0..count)
                .into_par_iter()
                .map(|i| Env::new(&scene, env_seed(seed, i), options))
                .collect::<Result<Vec<_>, _>>()
        })?;
        let states = envs.iter().map(|e| e.state(&scene)).collect();
        Ok(BatchEnv {
            scene,
            envs,
            states,
            options,
            pool,
        })
    }

    /// Rebuilds every env from `seed` (as [`BatchEnv::new`] would), keeping the thread pool.
    pub fn reseed(&mut self, seed: u64) -> Result<(), SimError> {
        let options = self.options;
        self.reseed_with(seed, |scene, _, env_seed| {
            Env::new(scene, env_seed, options)
        })
    }

    /// Rebuilds env `i` as `build(scene, i, env_seed(seed, i))`, in parallel on the pool (e.g.
    /// some envs replayed from hand-overs, [`crate::handover`]).
    pub fn reseed_with(
        &mut self,
        seed: u64,
        build: impl Fn(&SceneModel, usize, u64) -> Result<Env, SimError> + Sync,
    ) -> Result<(), SimError> {
        let scene = &self.scene;
        let (envs, states) = (&mut self.envs, &mut self.states);
        self.pool.install(|| {
            envs.par_iter_mut()
                .zip(states.par_iter_mut())
                .enumerate()
                .try_for_each(|(i, (env, state))| {
                    *env = build(scene, i, env_seed(seed, i))?;
                    env.state_into(scene, state);
                    Ok(())
                })
        })
    }

    /// Runs `f` on every env, its latest state and its entry of `slots`, in parallel on the
    /// batch's pool: how a task steps, observes and resets each world in one pass.
    pub fn for_each_with<T, E>(
        &mut self,
        slots: &mut [T],
        f: impl Fn(&SceneModel, &mut Env, &mut EnvState, &mut T) -> Result<(), E> + Sync,
    ) -> Result<(), E>
    where
        T: Send,
        E: Send,
    {
        assert_eq!(slots.len(), self.envs.len(), "one slot per env");
        let scene = &self.scene;
        let (envs, states) = (&mut self.envs, &mut self.states);
        self.pool.install(|| {
            envs.par_iter_mut()
                .zip(states.par_iter_mut())
                .zip(slots.par_iter_mut())
                .try_for_each(|((env, state), slot)| f(scene, env, state, slot))
        })
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// Worker threads stepping the batch.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    pub fn scene(&self) -> &SceneModel {
        &self.scene
    }

    pub fn envs(&self) -> &[Env] {
        &self.envs
    }

    /// The states after the last step or reset, one per env.
    pub fn states(&self) -> &[EnvState] {
        &self.states
    }

    /// Advances every env by one control step with its units' commands.
    pub fn step(&mut self, commands: &[[UnitCommand; UNITS]]) -> Result<(), SimError> {
        if commands.len() != self.envs.len() {
            return Err(SimError::Config {
                field: "commands",
                reason: format!(
                    "{} command sets for {} envs",
                    commands.len(),
                    self.envs.len()
                ),
            });
        }
        let scene = &self.scene;
        let (envs, states) = (&mut self.envs, &mut self.states);
        self.pool.install(|| {
            envs.par_iter_mut()
                .zip(states.par_iter_mut())
                .zip(commands.par_iter())
                .for_each(|((env, state), command)| {
                    env.step(scene, command);
                    env.state_into(scene, state);
                })
        });
        Ok(())
    }

    /// Starts a new episode in the envs where `mask` is true.
    pub fn reset(&mut self, mask: &[bool]) -> Result<(), SimError> {
        if mask.len() != self.envs.len() {
            return Err(SimError::Config {
                field: "mask",
                reason: format!("{} flags for {} envs", mask.len(), self.envs.len()),
            });
        }
        let scene = &self.scene;
        let (envs, states) = (&mut self.envs, &mut self.states);
        self.pool.install(|| {
            envs.par_iter_mut()
                .zip(states.par_iter_mut())
                .zip(mask.par_iter())
                .filter(|(_, reset)| **reset)
                .for_each(|((env, state), _)| {
                    env.reset();
                    env.state_into(scene, state);
                })
        });
        Ok(())
    }
}
