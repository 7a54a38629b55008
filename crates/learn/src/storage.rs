//! The rollout buffer (rsl_rl's `RolloutStorage`): `[T, N, …]` tensors filled step by step,
//! then GAE, whole-batch advantage normalisation and shuffled minibatches.

use tch::{Device, Kind, Tensor};

/// Added to the advantage std (rsl_rl's constant).
const ADV_EPS: f64 = 1e-8;

/// One step of all envs, as the PPO update needs it later.
#[derive(Debug)]
pub struct Transition<'a> {
    /// `[N, O]` raw observations the action was taken in.
    pub obs: &'a Tensor,
    /// `[N, C]` raw critic observations of the same state (what `values` were computed on).
    pub critic_obs: &'a Tensor,
    pub actions: &'a Tensor,
    /// `[N]` rewards, time-out bootstrap already added.
    pub rewards: &'a Tensor,
    /// `[N]` 1.0 where the episode ended (terminated or truncated).
    pub dones: &'a Tensor,
    pub values: &'a Tensor,
    pub log_probs: &'a Tensor,
    pub means: &'a Tensor,
    pub stds: &'a Tensor,
}

/// One minibatch, flattened over time and envs.
#[derive(Debug)]
pub struct Batch {
    pub obs: Tensor,
    pub critic_obs: Tensor,
    pub actions: Tensor,
    pub old_values: Tensor,
    pub advantages: Tensor,
    pub returns: Tensor,
    pub old_log_probs: Tensor,
    pub old_means: Tensor,
    pub old_stds: Tensor,
    /// `[B]` Int64: each sample's row in the rollout flattened over time and envs (step t of
    /// env n is `t·N + n`), so an algorithm built on PPO's update can gather its own per-sample
    /// data (kickstarting's expert labels) for the minibatch.
    pub rows: Tensor,
}

#[derive(Debug)]
pub struct RolloutStorage {
    obs: Tensor,
    critic_obs: Tensor,
    actions: Tensor,
    rewards: Tensor,
    dones: Tensor,
    values: Tensor,
    log_probs: Tensor,
    means: Tensor,
    stds: Tensor,
    returns: Tensor,
    advantages: Tensor,
    step: i64,
}

impl RolloutStorage {
    pub fn new(
        steps: usize,
        envs: usize,
        obs_dim: usize,
        critic_obs_dim: usize,
        action_dim: usize,
    ) -> Self {
        let (t, n) = (steps as i64, envs as i64);
        let z = |shape: &[i64]| Tensor::zeros(shape, (Kind::Float, Device::Cpu));
        RolloutStorage {
            obs: z(&[t, n, obs_dim as i64]),
            critic_obs: z(&[t, n, critic_obs_dim as i64]),
            actions: z(&[t, n, action_dim as i64]),
            rewards: z(&[t, n]),
            dones: z(&[t, n]),
            values: z(&[t, n]),
            log_probs: z(&[t, n]),
            means: z(&[t, n, action_dim as i64]),
            stds: z(&[t, n, action_dim as i64]),
            returns: z(&[t, n]),
            advantages: z(&[t, n]),
            step: 0,
        }
    }

    pub fn steps(&self) -> i64 {
        self.obs.size()[0]
    }

    /// Rows per step (agent rows, see [`crate::env`]).
    pub fn envs(&self) -> i64 {
        self.obs.size()[1]
    }

    pub fn is_full(&self) -> bool {
        self.step == self.steps()
    }

    /// Appends one step. Panics past capacity: the runner owns the step count.
    pub fn add(&mut self, t: &Transition<'_>) {
        assert!(!self.is_full(), "rollout storage overflow");
        let s = self.step;
        for (dst, src) in [
            (&mut self.obs, t.obs),
            (&mut self.critic_obs, t.critic_obs),
            (&mut self.actions, t.actions),
            (&mut self.rewards, t.rewards),
            (&mut self.dones, t.dones),
            (&mut self.values, t.values),
            (&mut self.log_probs, t.log_probs),
            (&mut self.means, t.means),
            (&mut self.stds, t.stds),
        ] {
            dst.get(s).copy_(src);
        }
        self.step += 1;
    }

    /// GAE returns and whole-batch-normalised advantages; `last_values` `[N]` are the critic's
    /// values of the critic observations after the last step. Empties the buffer for the next rollout
    /// (the data stays readable by [`RolloutStorage::minibatches`]).
    pub fn compute_returns(&mut self, last_values: &Tensor, gamma: f64, lambda: f64) {
        self.returns = gae(
            &self.rewards,
            &self.dones,
            &self.values,
            last_values,
            gamma,
            lambda,
        );
        let adv = &self.returns - &self.values;
        self.advantages = (&adv - adv.mean(Kind::Float)) / (adv.std(true) + ADV_EPS);
        self.step = 0;
    }

    /// How much of the returns' variance the stored values explain,
    /// `1 − Var[returns − values] / Var[returns]` (after [`RolloutStorage::compute_returns`]):
    /// 1 for a critic that predicts its targets, ≤ 0 for one no better than their mean. `None`
    /// when the returns do not vary.
    pub fn explained_variance(&self) -> Option<f64> {
        let var = |t: &Tensor| t.var(false).double_value(&[]);
        let returns = var(&self.returns);
        let ev = 1.0 - var(&(&self.returns - &self.values)) / returns;
        (returns > 0.0 && ev.is_finite()).then_some(ev)
    }

    /// `epochs × minibatches` minibatches of `⌊T·N / minibatches⌋` samples. Like rsl_rl, one
    /// random permutation (from libtorch's seeded generator) serves every epoch.
    pub fn minibatches(
        &self,
        minibatches: usize,
        epochs: usize,
    ) -> impl Iterator<Item = Batch> + '_ {
        self.minibatches_with(minibatches, epochs, |obs, critic_obs| {
            (obs.shallow_clone(), critic_obs.shallow_clone())
        })
    }

    /// [`RolloutStorage::minibatches`] with the flattened `[T·N, O]` and `[T·N, C]`
    /// observations first mapped by `map_obs` (the PPO update normalizes them here, once per
    /// update, since the normalizers do not change during it).
    ///
    /// Every per-sample field is packed side by side into one `[T·N, F]` tensor and gathered in
    /// the permutation's order once per update; minibatch `i` is then the contiguous row block
    /// `i`, and each field a column view of it. That is the samples of rsl_rl's per-minibatch
    /// `field[perm[i·size..(i+1)·size]]`, with one gather per update instead of nine per
    /// minibatch (the permutation is the same for every epoch, so their blocks are too).
    pub fn minibatches_with(
        &self,
        minibatches: usize,
        epochs: usize,
        map_obs: impl FnOnce(&Tensor, &Tensor) -> (Tensor, Tensor),
    ) -> impl Iterator<Item = Batch> + '_ {
        let batch = self.rewards.numel() as i64;
        let size = batch / minibatches as i64;
        let perm = Tensor::randperm(size * minibatches as i64, (Kind::Int64, Device::Cpu));
        let flat = |t: &Tensor| t.flatten(0, 1);
        let column = |t: &Tensor| t.flatten(0, 1).unsqueeze(1);
        let (obs, critic_obs) = map_obs(&flat(&self.obs), &flat(&self.critic_obs));
        let fields = [
            obs,
            critic_obs,
            flat(&self.actions),
            column(&self.values),
            column(&self.advantages),
            column(&self.returns),
            column(&self.log_probs),
            flat(&self.means),
            flat(&self.stds),
        ];
        let widths: Vec<i64> = fields.iter().map(|f| f.size()[1]).collect();
        let shuffled = Tensor::cat(&fields, 1).index_select(0, &perm);
        (0..epochs)
            .flat_map(move |_| 0..minibatches as i64)
            .map(move |i| {
                let rows = shuffled.narrow(0, i * size, size);
                let mut offset = 0;
                let mut next = |k: usize| {
                    let t = rows.narrow(1, offset, widths[k]);
                    offset += widths[k];
                    t
                };
                let (obs, critic_obs, actions) = (next(0), next(1), next(2));
                let (old_values, advantages, returns) = (next(3), next(4), next(5));
                let (old_log_probs, old_means, old_stds) = (next(6), next(7), next(8));
                let sq = |t: Tensor| t.squeeze_dim(1);
                Batch {
                    rows: perm.narrow(0, i * size, size),
                    obs,
                    critic_obs,
                    actions,
                    old_values: sq(old_values),
                    advantages: sq(advantages),
                    returns: sq(returns),
                    old_log_probs: sq(old_log_probs),
                    old_means,
                    old_stds,
                }
            })
    }
}

/// Generalised advantage estimation over `[T, N]` tensors, returning the returns
/// `A_t + V(s_t)`. `dones[t]` cuts the recursion after step `t`; time-outs are both done and
/// bootstrapped through their reward (see [`bootstrap_time_outs`]), so a time-out keeps
/// `γ V(s_final)` while a termination keeps nothing.
pub fn gae(
    rewards: &Tensor,
    dones: &Tensor,
    values: &Tensor,
    last_values: &Tensor,
    gamma: f64,
    lambda: f64,
) -> Tensor {
    let steps = rewards.size()[0];
    let returns = rewards.zeros_like();
    let mut advantage = last_values.zeros_like();
    for t in (0..steps).rev() {
        let next_values = if t == steps - 1 {
            last_values.shallow_clone()
        } else {
            values.get(t + 1)
        };
        let not_done = 1.0 - dones.get(t);
        let delta = rewards.get(t) + &not_done * gamma * next_values - values.get(t);
        advantage = delta + not_done * (gamma * lambda) * &advantage;
        returns.get(t).copy_(&(&advantage + values.get(t)));
    }
    returns
}

/// rsl_rl's time-out bootstrap, with the value of the true final observation: the reward of
/// each env in `env_ids` (`[K]` Int64) gains `γ · final_values` (`[K]`).
pub fn bootstrap_time_outs(
    rewards: &Tensor,
    env_ids: &Tensor,
    final_values: &Tensor,
    gamma: f64,
) -> Tensor {
    rewards.index_add(0, env_ids, &(final_values * gamma))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t2(rows: &[&[f32]]) -> Tensor {
        let flat: Vec<f32> = rows.iter().flat_map(|r| r.iter().copied()).collect();
        Tensor::from_slice(&flat).view([rows.len() as i64, rows[0].len() as i64])
    }

    fn close(a: &Tensor, b: &Tensor) -> bool {
        f64::try_from((a - b).abs().max()).unwrap() < 1e-5
    }

    #[test]
    fn gae_matches_hand_computation() {
        // One env, three steps, no episode end; gamma 0.9, lambda 0.5.
        // deltas: d2 = 1 + .9*4 - 3 = 1.6, d1 = 2 + .9*3 - 2 = 2.7, d0 = 0 + .9*2 - 1 = 0.8
        // A2 = 1.6, A1 = 2.7 + .45*1.6 = 3.42, A0 = 0.8 + .45*3.42 = 2.339
        let r = t2(&[&[0.0], &[2.0], &[1.0]]);
        let v = t2(&[&[1.0], &[2.0], &[3.0]]);
        let d = t2(&[&[0.0], &[0.0], &[0.0]]);
        let ret = gae(&r, &d, &v, &Tensor::from_slice(&[4.0f32]), 0.9, 0.5);
        assert!(close(&ret, &t2(&[&[3.339], &[5.42], &[4.6]])), "{ret}");
    }

    #[test]
    fn termination_cuts_and_time_out_bootstraps() {
        // Two envs, two steps; both episodes end at step 0 with reward 1, V(s0) = 0.5,
        // V(s1) = 2 (next episode), last value 3. Env 0 terminates, env 1 times out with
        // V(s_final) = 10. gamma 0.9, lambda 1.
        let v = t2(&[&[0.5, 0.5], &[2.0, 2.0]]);
        let d = t2(&[&[1.0, 1.0], &[0.0, 0.0]]);
        let r0 = Tensor::from_slice(&[1.0f32, 1.0]);
        let r0 = bootstrap_time_outs(
            &r0,
            &Tensor::from_slice(&[1i64]),
            &Tensor::from_slice(&[10.0f32]),
            0.9,
        );
        assert!(close(&r0, &Tensor::from_slice(&[1.0f32, 10.0])));
        let r = Tensor::stack(&[r0, Tensor::from_slice(&[0.0f32, 0.0])], 0);
        let ret = gae(&r, &d, &v, &Tensor::from_slice(&[3.0f32, 3.0]), 0.9, 1.0);
        // Step 0 returns: terminated 1 (nothing beyond), timed out 1 + 0.9 * 10 = 10.
        // Step 1 returns: 0 + 0.9 * 3 = 2.7 for both (the new episodes).
        assert!(close(&ret, &t2(&[&[1.0, 10.0], &[2.7, 2.7]])), "{ret}");
    }

    #[test]
    fn advantages_are_normalised_over_the_whole_batch() {
        let mut s = RolloutStorage::new(2, 2, 1, 3, 1);
        for k in 0..2 {
            let r = Tensor::from_slice(&[k as f32, 3.0 * k as f32]);
            let z = Tensor::zeros([2], (Kind::Float, Device::Cpu));
            let z2 = Tensor::zeros([2, 1], (Kind::Float, Device::Cpu));
            // Sample ids 2k, 2k + 1 as obs, ten times them as critic obs.
            let id = Tensor::from_slice(&[2.0 * k as f32, 2.0 * k as f32 + 1.0]).view([2, 1]);
            let c = id.repeat([1, 3]) * 10.0;
            s.add(&Transition {
                obs: &id,
                critic_obs: &c,
                actions: &z2,
                rewards: &r,
                dones: &z,
                values: &z,
                log_probs: &z,
                means: &z2,
                stds: &z2,
            });
        }
        assert!(s.is_full());
        s.compute_returns(&Tensor::zeros([2], (Kind::Float, Device::Cpu)), 0.9, 0.95);
        assert!(s.advantages.mean(Kind::Float).double_value(&[]).abs() < 1e-6);
        assert!((s.advantages.std(true).double_value(&[]) - 1.0).abs() < 1e-4);
        let batches: Vec<Batch> = s.minibatches(2, 3).collect();
        assert_eq!(batches.len(), 6);
        assert!(batches.iter().all(|b| b.obs.size() == [2, 1]));
        assert!(batches.iter().all(|b| b.critic_obs.size() == [2, 3]));
        // Critic observations travel with their samples.
        for b in &batches {
            let expected = b.obs.repeat([1, 3]) * 10.0;
            assert!(close(&b.critic_obs, &expected), "{}", b.critic_obs);
        }
    }
}
