"""The batched phase environment as an rsl_rl (>= 5) ``VecEnv``.

Observations are a ``TensorDict`` with two groups, rsl_rl's and IsaacLab's convention:
``"policy"``, what the actor (and the exported, onboard policy) sees, and ``"critic"``, what the
training-only critic sees (privileged simulator state). Configure rsl_rl with
``obs_groups = {"actor": ["policy"], "critic": ["critic"]}`` (``moonhaul.rsl.train_cfg`` does).

Buffers: the native environment writes observations, rewards and flags in place into torch
tensors (through their ``.numpy()`` views, no copy in Python). There are two sets, used in turn:
rsl_rl keeps the observation of step t (``alg.act`` records it) while it calls ``step`` for
t + 1, so one set overwritten in place would silently record o(t+1) as o(t). A tensor returned by
``step`` therefore stays as it was through the next ``step`` and is overwritten by the one after;
clone it to keep it longer.
"""

from __future__ import annotations

import json
import os

import torch
from tensordict import TensorDict

from ._native import Env


class _Buffers:
    """One set of step outputs: tensors, and the numpy views the native side writes through."""

    def __init__(self, env: Env) -> None:
        n = env.num_envs
        self.obs = torch.zeros(n, env.obs_dim, dtype=torch.float32)
        self.critic = torch.zeros(n, env.critic_obs_dim, dtype=torch.float32)
        self.rewards = torch.zeros(n, dtype=torch.float32)
        self.dones = torch.zeros(n, dtype=torch.uint8)
        self.time_outs = torch.zeros(n, dtype=torch.uint8)
        self.views = tuple(
            t.numpy() for t in (self.obs, self.critic, self.rewards, self.dones, self.time_outs)
        )
        self.td = TensorDict({"policy": self.obs, "critic": self.critic}, batch_size=[n])


class PhaseVecEnv:
    """The environments of a training config, as an rsl_rl ``VecEnv``.

    Args:
        config: a training config, ``configs/train/<task>.toml``.
        num_envs: simulated worlds (the config's ``env.num_envs`` unless given). A phase task
            drives two units per world with one shared policy, so ``self.num_envs``, rsl_rl's
            row count, is twice this: the same batch ``moonhaul-train`` trains on.
        seed: seeds the environments' randomness (the config's ``run.seed`` unless given).
        threads: simulator threads (the config's ``run.threads`` unless given).
        payload: a payload URDF every world carries instead of the sim config's payloads.
        reward_scale: multiplies every reward (the config's ``ppo.reward_scale`` unless given,
            as ``moonhaul-train`` scales them).
    """

    def __init__(
        self,
        config: str | os.PathLike,
        num_envs: int | None = None,
        seed: int | None = None,
        threads: int | None = None,
        payload: str | os.PathLike | None = None,
        reward_scale: float | None = None,
    ) -> None:
        self._native = Env(
            os.fspath(config),
            num_envs,
            threads,
            None if payload is None else os.fspath(payload),
            reward_scale,
        )
        #: The training config as a dict (rsl_rl's logger records it).
        self.cfg: dict = json.loads(self._native.config_json)
        self.num_envs: int = self._native.num_envs
        self.num_actions: int = self._native.action_dim
        self.max_episode_length: int = self._native.max_episode_length
        self.device = torch.device("cpu")
        #: Steps into each row's episode. rsl_rl's ``init_at_random_ep_len`` writes it; the
        #: episodes' time limits are the simulator's own, so writing it changes nothing there.
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long)
        self._sets = (_Buffers(self._native), _Buffers(self._native))
        self._current = 0
        self.seed = self.cfg["run"]["seed"] if seed is None else int(seed)
        self.reset(self.seed)

    def reset(self, seed: int | None = None) -> TensorDict:
        """Reseeds every environment (``self.seed`` unless given) and starts new episodes."""
        if seed is not None:
            self.seed = int(seed)
        b = self._sets[self._current]
        self._native.reset(self.seed, b.views[0], b.views[1])
        self.episode_length_buf.zero_()
        return b.td

    @property
    def native(self) -> Env:
        """The native environment (``moonhaul._native.Env``): its action map, policy metadata
        and ``export_policy``."""
        return self._native

    def get_observations(self) -> TensorDict:
        return self._sets[self._current].td

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        self._current ^= 1
        b = self._sets[self._current]
        a = actions.detach().to(device="cpu", dtype=torch.float32).contiguous()
        obs, critic, rewards, dones, time_outs = b.views
        self._native.step(a.numpy(), obs, critic, rewards, dones, time_outs)
        self.episode_length_buf += 1
        self.episode_length_buf[b.dones.bool()] = 0
        extras = {"time_outs": b.time_outs, "log": self._log()}
        return b.td, b.rewards, b.dones, extras

    def _log(self) -> dict[str, float]:
        """The action pipeline's figures over this step (rsl_rl averages them per iteration)."""
        stats = self._native.take_pipeline_stats()
        if stats is None or stats["ticks"] == 0:
            return {}
        ticks = stats["ticks"]
        return {
            "/pipeline/clamp_t_max_mean": stats["t_max_sum"] / ticks,
            "/pipeline/clamp_clamped_rate": stats["clamped"] / ticks,
            "/pipeline/clamp_hold_rate": stats["holds"] / ticks,
            "/pipeline/grasp_force_mean_n": stats["grasp_force_sum_n"] / ticks,
        }

    # Export helpers: what the onboard policy file records of the environment.

    def action_scale(self) -> list[float]:
        return self._native.action_scale()

    def action_offset(self) -> list[float]:
        return self._native.action_offset()

    def policy_metadata(self) -> list[tuple[str, str]]:
        return self._native.policy_metadata()

    def close(self) -> None:
        """Nothing to release (rsl_rl and gymnasium-style callers may call it)."""


try:  # An rsl_rl VecEnv by registration, without importing rsl_rl where it is not installed.
    from rsl_rl.env import VecEnv as _RslVecEnv

    _RslVecEnv.register(PhaseVecEnv)
except ImportError:  # pragma: no cover - rsl_rl is optional for the environment itself
    pass
