"""Train a moonhaul task with stock rsl_rl, on one process or under ``torchrun``.

    python -m moonhaul.train --config configs/train/lift.toml --out runs/lift-rsl [--iterations N]
    torchrun --nnodes N --nproc_per_node K ... -m moonhaul.train --config ... --out ...

Every rank steps its own ``--num-envs`` worlds (the config's ``env.num_envs`` unless given),
seeded ``seed + rank`` (``--same-seed``: ``seed`` on every rank, which reproduces a
single-process run). Rank 0 writes the rsl_rl log and checkpoints (``model_<it>.pt``) under
``--out`` and, at the end, the final actor as moonhaul's policy file ``policy.safetensors``
(``moonhaul.export``), which ``moonhaul eval`` and ``moonhaul-unit`` fly; ``--resume
CHECKPOINT`` continues one. ``--save-params FILE`` writes every rank's
final actor and critic state (``FILE.rank<r>``), what the tests compare.
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from .export import export_actor
from .rsl import RSL_RL_VERSION, OnPolicyRunner, train_cfg
from .vec_env import PhaseVecEnv


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m moonhaul.train", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="a training config, configs/train/<task>.toml")
    p.add_argument("--out", default=None, help="run folder (rank 0's log and checkpoints)")
    p.add_argument("--iterations", type=int, default=None, help="the config's run.iterations unless given")
    p.add_argument("--num-envs", type=int, default=None, help="worlds per rank")
    p.add_argument("--seed", type=int, default=None, help="the config's run.seed unless given")
    p.add_argument("--same-seed", action="store_true", help="every rank uses --seed (not seed + rank)")
    p.add_argument("--threads", type=int, default=None, help="simulator threads (config's run.threads)")
    p.add_argument("--torch-threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--resume", default=None, help="an rsl_rl checkpoint (model_<it>.pt) to continue")
    p.add_argument("--save-params", default=None, help="write each rank's final parameters here")
    args = p.parse_args(argv)

    rank = int(os.getenv("RANK", "0"))
    world_size = int(os.getenv("WORLD_SIZE", "1"))
    started = time.monotonic()
    torch.set_num_threads(args.torch_threads)
    env = PhaseVecEnv(args.config, num_envs=args.num_envs, seed=0, threads=args.threads)
    seed = env.cfg["run"]["seed"] if args.seed is None else args.seed
    if not args.same_seed:
        seed += rank
    # The networks' initial weights and the action noise: seeded like the environments.
    torch.manual_seed(seed)
    env.reset(seed)
    cfg = train_cfg(env.cfg)
    log_dir = args.out if rank == 0 else None
    runner = OnPolicyRunner(env, cfg, log_dir=log_dir, device=args.device)
    if args.resume:
        runner.load(args.resume)
    iterations = env.cfg["run"]["iterations"] if args.iterations is None else args.iterations
    runner.learn(iterations - runner.current_learning_iteration if args.resume else iterations)
    if rank == 0 and args.out:
        it = runner.current_learning_iteration
        export_actor(
            runner.alg.actor,
            env,
            os.path.join(args.out, "policy.safetensors"),
            {
                "created_by": f"rsl_rl {RSL_RL_VERSION} (python -m moonhaul.train)",
                "train_run": env.cfg["run"]["name"],
                "seed": seed,
                "world_size": world_size,
                "iteration": it,
                # Every rank stepped its own rows for steps_per_env steps per iteration.
                "env_steps": (it + 1) * env.cfg["env"]["steps_per_env"] * env.num_envs * world_size,
                "wall_s": f"{time.monotonic() - started:.0f}",
            },
        )
    if args.save_params:
        state = {
            "actor": runner.alg.actor.state_dict(),
            "critic": runner.alg.critic.state_dict(),
        }
        torch.save(state, f"{args.save_params}.rank{rank}")
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main()
