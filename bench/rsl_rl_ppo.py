#!/usr/bin/env python3
"""rsl_rl 5.5.1's PPO at the lift task's sizes: the reference side of the PPO side-by-side
benchmark (our side: `cargo xtask cargo bench -p moonhaul-learn --bench ppo`).

It builds rsl_rl's own `MLPModel` actor and critic (ELU, empirical observation normalizers, the
scalar-std `GaussianDistribution`), its `RolloutStorage` and its `PPO`, with the hyperparameters of
configs/train/lift.toml, and runs rounds of `steps` rollout steps on random observations and
rewards followed by one `PPO.update()`. It prints one JSON line per round:

- `update_samples_per_s`: rows x steps / the wall time of `alg.update()` (epochs x minibatches
  gradient steps and rsl_rl's once-per-update normalizer refresh). `alg.compute_returns()`
  (last value + GAE) is timed separately as `returns_ms`.
- `act_ms_per_step`: mean wall time of `alg.act(obs)` per rollout step under
  `torch.inference_mode()` as `OnPolicyRunner` runs it: actor forward (normalizer, MLP), Gaussian
  sample, critic forward, log-prob, distribution params.
- `step_ms_per_step`: `alg.act(obs)` plus `alg.process_env_step(...)` (reward clone, storage
  add): all the learner does per rollout step apart from the environment.

Usage: bench/rsl_rl_ppo.py [--config configs/train/lift.toml] [--rows 4096] [--steps 24]
       [--obs 61] [--critic-obs 81] [--actions 9] [--rounds 3] [--threads 2] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tomllib


def main() -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=os.path.join(here, "..", "configs", "train", "lift.toml"))
    p.add_argument("--rows", type=int, default=4096, help="agent rows per step (2048 worlds x 2 units)")
    p.add_argument("--steps", type=int, default=24, help="rollout steps per iteration")
    p.add_argument("--obs", type=int, default=61, help="actor observation width (layout 3)")
    p.add_argument("--critic-obs", type=int, default=81, help="critic observation width")
    p.add_argument("--actions", type=int, default=9, help="action width")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1, help="untimed rounds first")
    p.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    import torch
    from tensordict import TensorDict

    import rsl_rl
    from rsl_rl.algorithms import PPO
    from rsl_rl.models import MLPModel
    from rsl_rl.storage import RolloutStorage

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    with open(args.config, "rb") as f:
        cfg = tomllib.load(f)
    pol, ppo = cfg["policy"], cfg["ppo"]
    if ppo["schedule"] != "adaptive" or ppo["lr_factor"] != 1.5 or ppo["min_lr"] != 1e-5 or ppo["max_lr"] != 1e-2:
        sys.exit("rsl_rl's adaptive schedule hard-codes factor 1.5 within [1e-5, 1e-2]: the config differs")

    n, t = args.rows, args.steps
    opts = dict(dtype=torch.float32)

    def observations() -> TensorDict:
        return TensorDict(
            {"policy": torch.randn(n, args.obs, **opts), "critic": torch.randn(n, args.critic_obs, **opts)},
            batch_size=[n],
        )

    obs = observations()
    groups = {"actor": ["policy"], "critic": ["critic"]}
    actor = MLPModel(
        obs, groups, "actor", args.actions,
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
    # The lift config's actor_output_gain (not an rsl_rl option): scale the actor's output
    # layer as our ActorCritic::new does, so both sides start from the same kind of policy.
    with torch.no_grad():
        last = [m for m in actor.mlp if isinstance(m, torch.nn.Linear)][-1]
        last.weight.mul_(pol["actor_output_gain"])
        last.bias.mul_(pol["actor_output_gain"])
    storage = RolloutStorage("rl", n, t, obs, [args.actions], "cpu")
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
    print(
        f"# rsl_rl {getattr(rsl_rl, '__version__', '?')} torch {torch.__version__}: rows {n} x steps {t}, obs {args.obs}, "
        f"critic obs {args.critic_obs}, actions {args.actions}, actor {pol['actor_hidden']} critic {pol['critic_hidden']}, "
        f"{ppo['epochs']} epochs x {ppo['minibatches']} minibatches, {torch.get_num_threads()} threads",
        file=sys.stderr,
    )

    for r in range(args.warmup + args.rounds):
        act_s = step_s = 0.0
        with torch.inference_mode():
            for _ in range(t):
                t0 = time.perf_counter()
                alg.act(obs)
                t1 = time.perf_counter()
                # The environment's answer (not timed).
                next_obs = observations()
                rewards = torch.randn(n, **opts)
                dones = torch.zeros(n, **opts)
                t2 = time.perf_counter()
                alg.process_env_step(next_obs, rewards, dones, {})
                t3 = time.perf_counter()
                act_s += t1 - t0
                step_s += (t1 - t0) + (t3 - t2)
                obs = next_obs
            t0 = time.perf_counter()
            alg.compute_returns(obs)
            returns_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        losses = alg.update()
        update_s = time.perf_counter() - t0
        if r < args.warmup:
            continue
        print(
            json.dumps(
                {
                    "side": "rsl_rl",
                    "round": r - args.warmup + 1,
                    "update_samples_per_s": round(n * t / update_s, 1),
                    "act_ms_per_step": round(act_s * 1e3 / t, 3),
                    "step_ms_per_step": round(step_s * 1e3 / t, 3),
                    "returns_ms": round(returns_s * 1e3, 2),
                    "update_s": round(update_s, 4),
                    "value_loss": losses["value"],
                    "learning_rate": alg.learning_rate,
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
