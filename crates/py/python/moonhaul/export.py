"""Export an rsl_rl actor to moonhaul's onboard policy file, which ``moonhaul-unit`` and
``moonhaul eval`` fly without Python.

    python -m moonhaul.export --config configs/train/lift.toml \\
        --checkpoint runs/lift-rsl/model_300.pt --out runs/lift-rsl/policy.safetensors

What goes in: the actor MLP's linear layers (the Gaussian's mean: rsl_rl's
``GaussianDistribution`` takes the MLP output as the mean, and the std is training-only), and
its ``EmpiricalNormalization`` with the normalizer's ε added to the std, as the file stores it.
The native side (``Env.export_policy``) adds what the environment knows -- the phase, the
observation layout, the action map -- plus the config's digest and the source commit, checks
the shapes and values, and writes the file atomically. ``moonhaul.train`` calls
:func:`export_actor` at the end of a run; this module's command exports any checkpoint.
"""

from __future__ import annotations

import argparse
import os

import torch

from .vec_env import PhaseVecEnv


def actor_layers(actor: torch.nn.Module) -> tuple[list, list]:
    """The weights and biases of an rsl_rl ``MLPModel``'s MLP, float32 arrays in order.

    Refuses anything the onboard network does not compute: an activation other than ELU
    between the layers, or one after the last.
    """
    modules = list(actor.mlp)
    linear = [m for m in modules if isinstance(m, torch.nn.Linear)]
    for i, m in enumerate(modules):
        if isinstance(m, torch.nn.Linear):
            continue
        if not isinstance(m, torch.nn.ELU) or i == len(modules) - 1:
            raise ValueError(f"actor.mlp[{i}] is {m!r}: the onboard network is ELU between linear layers")
    if not linear:
        raise ValueError("actor.mlp has no linear layer")
    weights = [m.weight.detach().cpu().to(torch.float32).contiguous().numpy() for m in linear]
    biases = [m.bias.detach().cpu().to(torch.float32).contiguous().numpy() for m in linear]
    return weights, biases


def actor_normalizer(actor: torch.nn.Module):
    """(mean, std + ε) of the actor's observation normalizer, or (None, None) without one."""
    if not getattr(actor, "obs_normalization", False):
        return None, None
    norm = actor.obs_normalizer
    mean = norm.mean.detach().cpu().to(torch.float32).contiguous()
    std = (norm.std.detach().cpu() + norm.eps).to(torch.float32).contiguous()
    return mean.numpy(), std.numpy()


def export_actor(actor: torch.nn.Module, env: PhaseVecEnv, path: str | os.PathLike, extra: dict | None = None) -> None:
    """Writes ``actor`` (rsl_rl's ``MLPModel`` trained on ``env``'s task) as a policy file at
    ``path``; ``extra`` (str -> str) is the trainer's provenance."""
    weights, biases = actor_layers(actor)
    mean, std = actor_normalizer(actor)
    extra = {str(k): str(v) for k, v in (extra or {}).items()}
    env.native.export_policy(os.fspath(path), weights, biases, mean, std, extra)


def main(argv: list[str] | None = None) -> None:
    from .rsl import RSL_RL_VERSION, OnPolicyRunner, train_cfg

    p = argparse.ArgumentParser(prog="python -m moonhaul.export", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, help="the training config the checkpoint was trained with")
    p.add_argument("--checkpoint", required=True, help="an rsl_rl checkpoint, model_<it>.pt")
    p.add_argument("--out", required=True, help="the policy file to write (.safetensors)")
    p.add_argument("--payload", default=None, help="the payload URDF the run trained with, if any")
    args = p.parse_args(argv)

    # One world is enough to build the runner's networks; nothing is stepped.
    env = PhaseVecEnv(args.config, num_envs=1, threads=1, payload=args.payload)
    runner = OnPolicyRunner(env, train_cfg(env.cfg), log_dir=None, device="cpu")
    try:
        runner.load(args.checkpoint, load_cfg={"actor": True, "iteration": True}, strict=True)
    except (OSError, RuntimeError, KeyError) as e:
        raise SystemExit(f"{args.checkpoint}: not an rsl_rl checkpoint of {args.config}'s actor: {e}") from e
    export_actor(
        runner.alg.actor,
        env,
        args.out,
        {
            "created_by": f"rsl_rl {RSL_RL_VERSION} (python -m moonhaul.export)",
            "checkpoint": os.path.basename(args.checkpoint),
            "iteration": runner.current_learning_iteration,
            "train_run": env.cfg["run"]["name"],
        },
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
