#!/usr/bin/env python3
"""Gymnasium's Pendulum-v1 trained by stock rsl_rl 5.5.1: the reference side of the pendulum
side-by-side with `moonhaul-train --config configs/train/pendulum.toml`.

What it mirrors (every hyperparameter is read from the TOML config, default
configs/train/pendulum.toml):

- Environment: `gymnasium.vector.SyncVectorEnv` of `[env] num_envs` registered `Pendulum-v1`
  (200-step `TimeLimit`) with same-step auto-reset, behind a small rsl_rl `VecEnv`
  (`GymPendulumVecEnv`): truncations are reported as `extras["time_outs"]`, which is how rsl_rl
  expects time limits; rewards are multiplied by `[ppo] reward_scale` before the algorithm
  sees them (moonhaul-train scales them in the same place, `runner::step_env`).
- Learner: rsl_rl's own `MLPModel` actor and critic (ELU, `[policy] actor_hidden` /
  `critic_hidden`, empirical observation normalizers if `obs_normalization`, the scalar- or
  log-std `GaussianDistribution` starting at `init_std`), its `RolloutStorage` and its `PPO`
  with the config's epochs, minibatches, clip, gamma, lambda, value-loss coefficient, clipped
  value loss, entropy coefficient, max grad norm, learning rate, schedule and desired KL (the
  adaptive schedule's factor 1.5 and range [1e-5, 1e-2] are hard-coded in rsl_rl; the script
  refuses a config that asks for others). The actor's output layer is scaled by
  `actor_output_gain` as `ActorCritic::new` does (1.0 = PyTorch's default init).
- Loop: `OnPolicyRunner.learn`'s loop, written out (act / env.step / process_env_step for
  `[env] steps_per_env` steps under `torch.inference_mode()`, compute_returns, update), so an
  evaluation can run between iterations; rsl_rl's logger is not used.
- Evaluation, as moonhaul-train's `Runner::evaluate`: after every `[run] eval_interval`-th
  iteration (and the last), one deterministic episode (the Gaussian mean, normalizer applied,
  not updated) on each of `[run] eval_episodes` separate envs, always from the same initial
  states (a fixed reset seed derived from --seed); the mean undiscounted, unscaled return.

Unavoidable differences from moonhaul-train, apart from what is under test: the random streams
(torch's generator, gymnasium's per-env numpy generators) differ, so the initial weights,
initial states and evaluation states are not the same draws; f32 observations (gymnasium's)
versus our f64 env converted to f32 at the tensor boundary.

Differences between the two algorithms that the side-by-side is meant to expose (moonhaul's
side documents them in crates/learn/src): rsl_rl 5.5.1 updates the observation normalizers
once per update, after the gradient steps, from the rollout's observations; it bootstraps a
time-out with the value of the state the action was taken in, γ·V(s_t); it clips the actor's
and the critic's gradient norms separately.

Ablations (not stock; off by default): `--like-moonhaul X` (repeatable, or `all`) switches
one of those three rsl_rl behaviours to moonhaul-train's, to test whether it matters:
`normalizer` (update both normalizers every rollout step from the new observations, before
the transition is stored, and not in `update()`; the update then sees the whole rollout
through the end-of-rollout statistics, as `Ppo::update` does), `joint_clip` (one gradient-norm
clip over actor, std and critic together), `final_bootstrap` (a time-out's reward gains
γ·V(s_final), the critic's value of the true final observation).

Output: one CSV row per iteration (iteration, env_steps, mean_return, eval_return, mean_std,
lr, value_loss, surrogate_loss, entropy) to <out>/metrics.csv and to stdout; mean_return is
the mean stochastic training return of the last 100 finished episodes (unscaled).

Usage: bench/pendulum_rsl_rl.py [--config configs/train/pendulum.toml] [--seed N]
       [--threads 1] [--out runs/pendulum-rsl_rl-s1] [--set ppo.entropy_coef=0.01 ...]
"""

from __future__ import annotations

import argparse
import collections
import csv
import importlib.metadata
import os
import sys
import time
import tomllib


def parse_set(cfg: dict, assignments: list[str]) -> None:
    """Applies `section.key=value` overrides (value parsed as TOML) to the loaded config."""
    for a in assignments:
        key, _, value = a.partition("=")
        section, _, name = key.partition(".")
        if section not in cfg or name not in cfg[section]:
            sys.exit(f"--set {a}: no such config key {key}")
        cfg[section][name] = tomllib.loads(f"v = {value}")["v"]


def main() -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=os.path.join(here, "..", "configs", "train", "pendulum.toml"))
    p.add_argument("--seed", type=int, default=None, help="overrides run.seed")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--out", default=None, help="run folder for metrics.csv [runs/pendulum-rsl_rl-s<seed>]")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a config value (hypothesis tests), e.g. ppo.entropy_coef=0.01")
    p.add_argument("--like-moonhaul", action="append", default=[],
                   choices=["normalizer", "joint_clip", "final_bootstrap", "all"],
                   help="ablation: adopt one of moonhaul-train's documented differences (see above)")
    args = p.parse_args()
    like = set(args.like_moonhaul)
    if "all" in like:
        like = {"normalizer", "joint_clip", "final_bootstrap"}

    import gymnasium as gym
    import numpy as np
    import torch
    from tensordict import TensorDict

    from rsl_rl.algorithms import PPO
    from rsl_rl.env import VecEnv
    from rsl_rl.models import MLPModel
    from rsl_rl.storage import RolloutStorage

    with open(args.config, "rb") as f:
        cfg = tomllib.load(f)
    parse_set(cfg, args.set)
    run, env_cfg, pol, ppo = cfg["run"], cfg["env"], cfg["policy"], cfg["ppo"]
    if run["task"] != "pendulum":
        sys.exit(f"this script trains Pendulum-v1; the config's task is {run['task']!r}")
    if ppo["schedule"] == "adaptive" and (
        ppo["lr_factor"] != 1.5 or ppo["min_lr"] != 1e-5 or ppo["max_lr"] != 1e-2
    ):
        sys.exit("rsl_rl's adaptive schedule hard-codes factor 1.5 within [1e-5, 1e-2]: the config differs")
    seed = run["seed"] if args.seed is None else args.seed
    out = args.out or os.path.join("runs", f"pendulum-rsl_rl-s{seed}")
    os.makedirs(out, exist_ok=True)

    torch.set_num_threads(args.threads)
    torch.manual_seed(seed)
    np.random.seed(seed)

    def make_vec(n: int) -> gym.vector.SyncVectorEnv:
        return gym.vector.SyncVectorEnv(
            [lambda: gym.make("Pendulum-v1") for _ in range(n)],
            autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
        )

    class GymPendulumVecEnv(VecEnv):
        """rsl_rl VecEnv over a same-step auto-resetting SyncVectorEnv of Pendulum-v1."""

        def __init__(self, n: int, seed: int, reward_scale: float) -> None:
            self.envs = make_vec(n)
            self.num_envs = n
            self.num_actions = 1
            self.max_episode_length = 200
            self.episode_length_buf = torch.zeros(n, dtype=torch.long)
            self.device = "cpu"
            self.cfg = {}
            self.reward_scale = reward_scale
            obs, _ = self.envs.reset(seed=seed)
            self.obs = self._td(obs)
            self.ep_return = np.zeros(n)
            self.finished: collections.deque[float] = collections.deque(maxlen=100)

        def _td(self, obs: np.ndarray) -> TensorDict:
            return TensorDict({"policy": torch.as_tensor(obs, dtype=torch.float32)}, batch_size=[self.num_envs])

        def get_observations(self) -> TensorDict:
            return self.obs

        def step(self, actions: torch.Tensor):
            obs, rew, term, trunc, info = self.envs.step(actions.detach().cpu().numpy())
            done = np.logical_or(term, trunc)
            self.ep_return += rew
            for i in np.flatnonzero(done):
                self.finished.append(float(self.ep_return[i]))
                self.ep_return[i] = 0.0
            self.episode_length_buf += 1
            self.episode_length_buf[torch.as_tensor(done)] = 0
            self.obs = self._td(obs)
            rewards = torch.as_tensor(rew, dtype=torch.float32) * self.reward_scale
            dones = torch.as_tensor(done, dtype=torch.float32)
            to = np.logical_and(trunc, np.logical_not(term))
            time_outs = torch.as_tensor(to, dtype=torch.float32)
            extras = {"time_outs": time_outs}
            if to.any():
                ids = np.flatnonzero(to)
                extras["time_out_ids"] = torch.as_tensor(ids)
                extras["final_obs"] = TensorDict(
                    {"policy": torch.as_tensor(np.stack([info["final_obs"][i] for i in ids]), dtype=torch.float32)},
                    batch_size=[len(ids)],
                )
            return self.obs, rewards, dones, extras

    n, t = env_cfg["num_envs"], env_cfg["steps_per_env"]
    env = GymPendulumVecEnv(n, seed, ppo["reward_scale"])
    obs = env.get_observations()
    groups = {"actor": ["policy"], "critic": ["policy"]}
    actor = MLPModel(
        obs, groups, "actor", env.num_actions,
        hidden_dims=pol["actor_hidden"], activation="elu", obs_normalization=pol["obs_normalization"],
        distribution_cfg={
            "class_name": "rsl_rl.modules.distribution:GaussianDistribution",
            "init_std": pol["init_std"],
            "std_type": pol["std_type"],
        },
    )
    critic = MLPModel(
        obs, groups, "critic", 1,
        hidden_dims=pol["critic_hidden"], activation="elu", obs_normalization=pol["obs_normalization"],
    )
    with torch.no_grad():
        last = [m for m in actor.mlp if isinstance(m, torch.nn.Linear)][-1]
        last.weight.mul_(pol["actor_output_gain"])
        last.bias.mul_(pol["actor_output_gain"])
    storage = RolloutStorage("rl", n, t, obs, [env.num_actions], "cpu")
    alg = PPO(
        actor, critic, storage,
        num_learning_epochs=ppo["epochs"],
        num_mini_batches=ppo["minibatches"],
        clip_param=ppo["clip"],
        gamma=ppo["gamma"],
        lam=ppo["lambda"],
        value_loss_coef=ppo["value_loss_coef"],
        entropy_coef=ppo["entropy_coef"],
        learning_rate=ppo["learning_rate"],
        max_grad_norm=ppo["max_grad_norm"],
        use_clipped_value_loss=ppo["clipped_value_loss"],
        schedule=ppo["schedule"],
        desired_kl=ppo["desired_kl"],
        device="cpu",
    )
    alg.train_mode()

    # Ablations (see the docstring); each replaces one stock behaviour with moonhaul-train's.
    if "normalizer" in like:
        per_step_norm = (alg.actor.update_normalization, alg.critic.update_normalization)
        alg.actor.update_normalization = lambda obs: None  # update() no longer refreshes them
        alg.critic.update_normalization = lambda obs: None
    if "joint_clip" in like:
        alg.max_grad_norm = float("inf")  # rsl_rl's two per-network clips become no-ops
        params = list(alg.actor.parameters()) + list(alg.critic.parameters())
        stock_step = alg.optimizer.step

        def joint_clipped_step(*a, **k):
            torch.nn.utils.clip_grad_norm_(params, ppo["max_grad_norm"])
            return stock_step(*a, **k)

        alg.optimizer.step = joint_clipped_step

    eval_env = make_vec(run["eval_episodes"])
    eval_seed = 1_000_003 * seed + 12345

    def evaluate() -> float:
        o, _ = eval_env.reset(seed=eval_seed)
        m = run["eval_episodes"]
        returns = np.zeros(m)
        running = np.ones(m, dtype=bool)
        with torch.inference_mode():
            while running.any():
                a = alg.actor(TensorDict({"policy": torch.as_tensor(o, dtype=torch.float32)}, batch_size=[m]))
                o, r, term, trunc, _ = eval_env.step(a.numpy())
                returns += np.where(running, r, 0.0)
                running &= ~np.logical_or(term, trunc)
        return float(returns.mean())

    def mean_std() -> float:
        d = alg.actor.distribution
        if d.std_type == "scalar":
            s = d.std_param.clamp(*d.std_range)
        else:
            s = d.log_std_param.clamp(*d.log_std_range).exp()
        return float(s.detach().mean())

    print(
        f"# rsl_rl {importlib.metadata.version('rsl-rl-lib')} torch {torch.__version__} gymnasium {gym.__version__}: "
        f"Pendulum-v1 seed {seed}, {n} envs x {t} steps, {run['iterations']} iterations, {torch.get_num_threads()} threads"
        + (f", overrides {args.set}" if args.set else "")
        + (f", like moonhaul: {sorted(like)}" if like else ""),
        file=sys.stderr,
    )
    columns = ["iteration", "env_steps", "mean_return", "eval_return", "mean_std", "lr",
               "value_loss", "surrogate_loss", "entropy"]
    start = time.time()
    with open(os.path.join(out, "metrics.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        print(",".join(columns), flush=True)
        for it in range(1, run["iterations"] + 1):
            with torch.inference_mode():
                for _ in range(t):
                    actions = alg.act(obs)
                    obs, rewards, dones, extras = env.step(actions)
                    if "final_bootstrap" in like:
                        extras = dict(extras)
                        del extras["time_outs"]
                        if "time_out_ids" in extras:
                            v = alg.critic(extras["final_obs"]).squeeze(-1)
                            rewards = rewards.index_add(0, extras["time_out_ids"], ppo["gamma"] * v)
                    if "normalizer" in like:
                        per_step_norm[0](obs)
                        per_step_norm[1](obs)
                    alg.process_env_step(obs, rewards, dones, extras)
                alg.compute_returns(obs)
            losses = alg.update()
            ev = evaluate() if it % run["eval_interval"] == 0 or it == run["iterations"] else None
            mr = float(np.mean(env.finished)) if env.finished else None
            row = [it, it * n * t,
                   "" if mr is None else f"{mr:.2f}",
                   "" if ev is None else f"{ev:.2f}",
                   f"{mean_std():.4f}", f"{alg.learning_rate:.3e}",
                   f"{losses['value']:.5f}", f"{losses['surrogate']:.5f}", f"{losses['entropy']:.4f}"]
            w.writerow(row)
            f.flush()
            print(",".join(map(str, row)), flush=True)
    print(f"# wall {time.time() - start:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
