"""Stock rsl_rl (pinned: ``rsl-rl-lib==5.5.1``) on moonhaul's phase environments.

``OnPolicyRunner`` is rsl_rl's own, with one method replaced: rsl_rl initialises
``torch.distributed`` with NCCL and binds a CUDA device, which a CPU host has neither of; here a
CPU device gets gloo and no device binding, a CUDA device rsl_rl's own path. Everything else --
PPO, the parameter broadcast at the start, the gradient and KL all-reduce, the learning rate
broadcast -- is rsl_rl's. The observation normalizers need nothing added: rsl_rl 5.5.1's
``EmpiricalNormalization.update`` already all-reduces the batch count, mean and variance
whenever ``torch.distributed`` is initialised, so every rank keeps the same statistics.

``train_cfg`` turns a moonhaul training config (``configs/train/<task>.toml``, as
``PhaseVecEnv.cfg``) into rsl_rl's ``train_cfg`` dict: same networks, same PPO settings.
"""

from __future__ import annotations

import os

import torch
from rsl_rl.runners import OnPolicyRunner as _RslOnPolicyRunner

#: The rsl_rl release this module is written against (its runner's ``_configure_multi_gpu``).
RSL_RL_VERSION = "5.5.1"


def train_cfg(cfg: dict) -> dict:
    """rsl_rl's ``train_cfg`` for a moonhaul training config (``PhaseVecEnv.cfg``).

    rsl_rl's adaptive schedule hard-codes the factor 1.5 within [1e-5, 1e-2], the values the
    shipped configs use; a config asking for others is refused rather than silently changed.
    """
    pol, ppo, run = cfg["policy"], cfg["ppo"], cfg["run"]
    if ppo["schedule"] == "adaptive" and (
        ppo["lr_factor"] != 1.5 or ppo["min_lr"] != 1e-5 or ppo["max_lr"] != 1e-2
    ):
        raise ValueError(
            "rsl_rl's adaptive schedule hard-codes factor 1.5 within [1e-5, 1e-2]; "
            f"the config asks for {ppo['lr_factor']} within [{ppo['min_lr']}, {ppo['max_lr']}]"
        )

    def model(hidden: list[int], distribution: dict | None) -> dict:
        m = {
            "class_name": "rsl_rl.models:MLPModel",
            "hidden_dims": list(hidden),
            "activation": "elu",
            "obs_normalization": bool(pol["obs_normalization"]),
        }
        if distribution is not None:
            m["distribution_cfg"] = distribution
        return m

    return {
        "num_steps_per_env": cfg["env"]["steps_per_env"],
        "save_interval": run["checkpoint_interval"],
        "obs_groups": {"actor": ["policy"], "critic": ["critic"]},
        "actor": model(
            pol["actor_hidden"],
            {
                "class_name": "rsl_rl.modules.distribution:GaussianDistribution",
                "init_std": pol["init_std"],
                "std_type": pol["std_type"],
            },
        ),
        "critic": model(pol["critic_hidden"], None),
        "algorithm": {
            "class_name": "rsl_rl.algorithms:PPO",
            "num_learning_epochs": ppo["epochs"],
            "num_mini_batches": ppo["minibatches"],
            "clip_param": ppo["clip"],
            "gamma": ppo["gamma"],
            "lam": ppo["lambda"],
            "value_loss_coef": ppo["value_loss_coef"],
            "entropy_coef": ppo["entropy_coef"],
            "learning_rate": ppo["learning_rate"],
            "max_grad_norm": ppo["max_grad_norm"],
            "use_clipped_value_loss": ppo["clipped_value_loss"],
            "schedule": ppo["schedule"],
            "desired_kl": ppo["desired_kl"],
        },
        # moonhaul's actor_output_gain (not an rsl_rl option): OnPolicyRunner applies it.
        "actor_output_gain": pol.get("actor_output_gain", 1.0),
        "check_for_nan": True,
        "logger": "tensorboard",
    }


class OnPolicyRunner(_RslOnPolicyRunner):
    """rsl_rl's ``OnPolicyRunner``; gloo on CPU hosts (see the module docs).

    It also scales the actor's output layer by ``train_cfg["actor_output_gain"]`` (moonhaul's
    ``policy.actor_output_gain``, as ``moonhaul-train`` initialises its actor), before rsl_rl
    broadcasts rank 0's parameters to the others.
    """

    def __init__(self, env, train_cfg: dict, log_dir: str | None = None, device: str = "cpu") -> None:
        gain = train_cfg.pop("actor_output_gain", 1.0)
        super().__init__(env, train_cfg, log_dir=log_dir, device=device)
        if gain != 1.0:
            with torch.no_grad():
                last = [m for m in self.alg.actor.mlp if isinstance(m, torch.nn.Linear)][-1]
                last.weight.mul_(gain)
                last.bias.mul_(gain)

    def _configure_multi_gpu(self) -> None:
        if torch.device(self.device).type == "cuda":
            return super()._configure_multi_gpu()
        self.gpu_world_size = int(os.getenv("WORLD_SIZE", "1"))
        self.is_distributed = self.gpu_world_size > 1
        if not self.is_distributed:
            self.gpu_local_rank = self.gpu_global_rank = 0
            self.cfg["multi_gpu"] = None
            return
        self.gpu_local_rank = int(os.getenv("LOCAL_RANK", "0"))
        self.gpu_global_rank = int(os.getenv("RANK", "0"))
        self.cfg["multi_gpu"] = {
            "global_rank": self.gpu_global_rank,
            "local_rank": self.gpu_local_rank,
            "world_size": self.gpu_world_size,
        }
        if not torch.distributed.is_initialized():
            torch.distributed.init_process_group(
                backend="gloo", rank=self.gpu_global_rank, world_size=self.gpu_world_size
            )
