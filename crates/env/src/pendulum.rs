//! Gymnasium's `Pendulum-v1` (classic control, gymnasium 1.x), reproduced exactly: the
//! benchmark that proves the trainer on a task with published reference results.
//!
//! The constants are the benchmark's definition, not tunables. Dynamics, cost, limits, the
//! initial-state distribution θ ~ U[-π, π), θ̇ ~ U[-1, 1) and the 200-step `TimeLimit` are
//! checked against gymnasium itself by `tests/pendulum_gymnasium.rs` (fixture and generating
//! script in `tests/data/`). Episodes never terminate; they are truncated at 200 steps.

use std::f64::consts::PI;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::env::{check_len, VecEnv, VecStep};
use crate::EnvError;

/// Angular speed limit, rad/s.
pub const MAX_SPEED_RADPS: f64 = 8.0;
/// Torque limit, N·m; actions beyond it are clipped.
pub const MAX_TORQUE_NM: f64 = 2.0;
/// Integration step, s.
pub const DT_S: f64 = 0.05;
/// Gravity, m/s² (gymnasium's default `g=10.0`).
pub const GRAVITY_MPS2: f64 = 10.0;
pub const MASS_KG: f64 = 1.0;
pub const LENGTH_M: f64 = 1.0;
/// `TimeLimit` of the registered `Pendulum-v1`.
pub const MAX_EPISODE_STEPS: u32 = 200;
/// Half-widths of the uniform initial state (gymnasium's `DEFAULT_X`, `DEFAULT_Y`).
pub const INIT_THETA_RAD: f64 = PI;
pub const INIT_THETA_DOT_RADPS: f64 = 1.0;

pub const OBS_DIM: usize = 3;
pub const ACTION_DIM: usize = 1;

/// One pendulum's state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pendulum {
    pub theta_rad: f64,
    pub theta_dot_radps: f64,
}

/// `((x + π) mod 2π) − π` with Python's floored modulo (numpy `%`).
pub fn angle_normalize(x: f64) -> f64 {
    (x + PI).rem_euclid(2.0 * PI) - PI
}

impl Pendulum {
    /// A state drawn as gymnasium's `reset` draws it: `low + (high − low) · U[0, 1)`, θ first.
    pub fn sample(rng: &mut impl Rng) -> Self {
        let mut uniform = |half: f64| -half + 2.0 * half * rng.random::<f64>();
        let theta_rad = uniform(INIT_THETA_RAD);
        let theta_dot_radps = uniform(INIT_THETA_DOT_RADPS);
        Pendulum {
            theta_rad,
            theta_dot_radps,
        }
    }

    /// `[cos θ, sin θ, θ̇]`.
    pub fn observation(&self) -> [f64; OBS_DIM] {
        [
            self.theta_rad.cos(),
            self.theta_rad.sin(),
            self.theta_dot_radps,
        ]
    }

    /// Applies `torque_nm` (clipped to ±2) for one step and returns the reward
    /// `−(angle_normalize(θ)² + 0.1 θ̇² + 0.001 u²)` of the state before the step. Operation
    /// order follows gymnasium's so the f64 results agree to the last bits libm allows.
    pub fn step(&mut self, torque_nm: f64) -> f64 {
        let (th, thdot) = (self.theta_rad, self.theta_dot_radps);
        let u = torque_nm.clamp(-MAX_TORQUE_NM, MAX_TORQUE_NM);
        let costs = angle_normalize(th).powi(2) + 0.1 * thdot.powi(2) + 0.001 * u.powi(2);
        let new_thdot = thdot
            + (3.0 * GRAVITY_MPS2 / (2.0 * LENGTH_M) * th.sin()
                + 3.0 / (MASS_KG * LENGTH_M.powi(2)) * u)
                * DT_S;
        let new_thdot = new_thdot.clamp(-MAX_SPEED_RADPS, MAX_SPEED_RADPS);
        self.theta_rad = th + new_thdot * DT_S;
        self.theta_dot_radps = new_thdot;
        -costs
    }
}

/// A batch of `Pendulum-v1` envs, each wrapped in the 200-step time limit.
#[derive(Debug, Clone)]
pub struct PendulumVecEnv {
    envs: Vec<Pendulum>,
    steps: Vec<u32>,
    rng: ChaCha8Rng,
}

impl PendulumVecEnv {
    /// `num_envs` pendulums; call [`VecEnv::reset`] before stepping.
    pub fn new(num_envs: usize) -> Self {
        PendulumVecEnv {
            envs: vec![
                Pendulum {
                    theta_rad: 0.0,
                    theta_dot_radps: 0.0
                };
                num_envs
            ],
            steps: vec![0; num_envs],
            rng: ChaCha8Rng::seed_from_u64(0),
        }
    }
}

impl VecEnv for PendulumVecEnv {
    fn num_envs(&self) -> usize {
        self.envs.len()
    }

    fn obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn action_dim(&self) -> usize {
        ACTION_DIM
    }

    fn max_episode_steps(&self) -> Option<u64> {
        Some(u64::from(MAX_EPISODE_STEPS))
    }

    /// The pendulum has no privileged state: the critic sees the observation.
    fn critic_obs_dim(&self) -> usize {
        OBS_DIM
    }

    fn reset(
        &mut self,
        seed: u64,
        obs: &mut [f64],
        critic_obs: &mut [f64],
    ) -> Result<(), EnvError> {
        let n = self.envs.len();
        check_len("observation batch", obs, n * OBS_DIM)?;
        check_len("critic observation batch", critic_obs, n * OBS_DIM)?;
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        let rows = obs
            .chunks_exact_mut(OBS_DIM)
            .zip(critic_obs.chunks_exact_mut(OBS_DIM));
        for (i, (row, critic_row)) in rows.enumerate() {
            self.reset_env(i, row, critic_row)?;
        }
        Ok(())
    }

    fn reset_env(
        &mut self,
        index: usize,
        obs: &mut [f64],
        critic_obs: &mut [f64],
    ) -> Result<(), EnvError> {
        check_len("observation", obs, OBS_DIM)?;
        check_len("critic observation", critic_obs, OBS_DIM)?;
        let n = self.envs.len();
        let env = self.envs.get_mut(index).ok_or(EnvError::Shape {
            what: "env index",
            expected: n,
            found: index,
        })?;
        *env = Pendulum::sample(&mut self.rng);
        self.steps[index] = 0;
        obs.copy_from_slice(&env.observation());
        critic_obs.copy_from_slice(obs);
        Ok(())
    }

    fn step(&mut self, actions: &[f64], out: &mut VecStep) -> Result<(), EnvError> {
        let n = self.envs.len();
        check_len("action batch", actions, n * ACTION_DIM)?;
        check_len("observation buffer", &out.obs, n * OBS_DIM)?;
        check_len("critic observation buffer", &out.critic_obs, n * OBS_DIM)?;
        check_len("final observation buffer", &out.final_obs, n * OBS_DIM)?;
        let final_critic = &out.final_critic_obs;
        check_len("final critic observation buffer", final_critic, n * OBS_DIM)?;
        if actions.iter().any(|a| !a.is_finite()) {
            return Err(EnvError::NonFinite {
                what: "pendulum action".into(),
            });
        }
        for (i, &torque) in actions.iter().enumerate() {
            out.rewards[i] = self.envs[i].step(torque);
            self.steps[i] += 1;
            out.terminated[i] = false;
            out.truncated[i] = self.steps[i] >= MAX_EPISODE_STEPS;
            let row = i * OBS_DIM..(i + 1) * OBS_DIM;
            out.obs[row.clone()].copy_from_slice(&self.envs[i].observation());
            if out.truncated[i] {
                out.final_obs[row.clone()].copy_from_slice(&out.obs[row.clone()]);
                out.final_critic_obs[row.clone()].copy_from_slice(&out.obs[row.clone()]);
                self.reset_env(i, &mut out.obs[row.clone()], &mut out.critic_obs[row])?;
            } else {
                out.critic_obs[row.clone()].copy_from_slice(&out.obs[row]);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angle_normalize_is_floored_modulo() {
        assert_eq!(angle_normalize(0.0), 0.0);
        assert!((angle_normalize(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert!((angle_normalize(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-12);
        assert!((angle_normalize(-7.0) - (-7.0 + 2.0 * PI)).abs() < 1e-12);
    }

    #[test]
    fn initial_states_are_uniform_in_gymnasium_bounds() {
        let mut env = PendulumVecEnv::new(4000);
        let mut obs = vec![0.0; 4000 * OBS_DIM];
        let mut critic_obs = obs.clone();
        env.reset(7, &mut obs, &mut critic_obs).unwrap();
        let (th, thd): (Vec<f64>, Vec<f64>) = env
            .envs
            .iter()
            .map(|p| (p.theta_rad, p.theta_dot_radps))
            .unzip();
        assert!(th.iter().all(|t| (-PI..PI).contains(t)));
        assert!(thd.iter().all(|t| (-1.0..1.0).contains(t)));
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(mean(&th).abs() < 0.1 && mean(&thd).abs() < 0.05);
        let spread = th.iter().filter(|t| t.abs() > 0.9 * PI).count();
        assert!(spread > 250, "tails of U[-pi, pi) too thin: {spread}");
    }

    #[test]
    fn truncates_at_200_steps_and_auto_resets() {
        let mut env = PendulumVecEnv::new(2);
        let mut obs = vec![0.0; 2 * OBS_DIM];
        let mut critic_obs = vec![1.0; 2 * OBS_DIM];
        env.reset(1, &mut obs, &mut critic_obs).unwrap();
        assert_eq!(critic_obs, obs, "no privileged state: the critic sees obs");
        let mut out = VecStep::new(2, OBS_DIM, OBS_DIM);
        for step in 1..=MAX_EPISODE_STEPS {
            env.step(&[0.5, -0.5], &mut out).unwrap();
            assert_eq!(out.truncated, vec![step == MAX_EPISODE_STEPS; 2]);
            assert_eq!(out.terminated, vec![false; 2]);
            assert_eq!(out.critic_obs, out.obs);
        }
        assert_eq!(env.steps, vec![0, 0]);
        // The final observation is the old episode's, obs the new episode's first.
        assert_ne!(out.final_obs, out.obs);
        assert_eq!(out.final_critic_obs, out.final_obs);
        assert_eq!(&out.obs[..OBS_DIM], &env.envs[0].observation());
    }

    #[test]
    fn rejects_wrong_batch_and_non_finite_actions() {
        let mut env = PendulumVecEnv::new(2);
        let mut out = VecStep::new(2, OBS_DIM, OBS_DIM);
        assert!(matches!(
            env.step(&[0.0], &mut out),
            Err(EnvError::Shape { .. })
        ));
        let mut narrow = VecStep::new(2, OBS_DIM, OBS_DIM - 1);
        assert!(matches!(
            env.step(&[0.0, 0.0], &mut narrow),
            Err(EnvError::Shape {
                what: "critic observation buffer",
                ..
            })
        ));
        assert!(matches!(
            env.step(&[0.0, f64::NAN], &mut out),
            Err(EnvError::NonFinite { .. })
        ));
    }
}
