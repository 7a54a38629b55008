"""moonhaul.PhaseVecEnv as rsl_rl sees it: interface, buffers, errors."""

import pytest
import torch
from rsl_rl.env import VecEnv

import moonhaul


def lift(config, worlds=2, seed=3):
    return moonhaul.PhaseVecEnv(config("lift"), num_envs=worlds, seed=seed, threads=1)


def test_the_rsl_rl_interface(config):
    env = lift(config)
    assert isinstance(env, VecEnv)
    # Two units per world, one row each; the increment of 2 wheels and 7 arm joints.
    assert (env.num_envs, env.num_actions) == (4, 9)
    assert env.max_episode_length > 0
    assert env.episode_length_buf.shape == (4,)
    assert env.cfg["run"]["task"] == "lift"
    obs = env.get_observations()
    assert set(obs.keys()) == {"policy", "critic"}
    assert obs["policy"].dtype == torch.float32 and obs["policy"].shape[0] == 4
    assert obs["critic"].shape[1] > obs["policy"].shape[1]  # privileged state
    o, r, d, extras = env.step(torch.zeros(4, 9))
    assert r.shape == (4,) and r.dtype == torch.float32 and (r <= 0).all()  # Table II: all ≤ 0
    assert d.shape == (4,) and extras["time_outs"].shape == (4,)
    assert 0.0 <= extras["log"]["/pipeline/clamp_t_max_mean"] <= 1.0
    assert (env.episode_length_buf == 1).all()
    # Both units of a world share its reward.
    assert r[0] == r[1] and r[2] == r[3]


def test_stock_rsl_rl_runner_takes_the_env_unchanged(config):
    """rsl_rl's own OnPolicyRunner, not moonhaul's subclass, on one process: the env is all it
    needs (the subclass only adds gloo for torchrun on CPU hosts)."""
    from rsl_rl.runners import OnPolicyRunner

    from moonhaul.rsl import train_cfg

    torch.manual_seed(0)
    env = lift(config)
    cfg = train_cfg(env.cfg)
    cfg.pop("actor_output_gain")  # moonhaul's subclass applies it; stock rsl_rl has no such key
    cfg["num_steps_per_env"] = 4
    runner = OnPolicyRunner(env, cfg, log_dir=None, device="cpu")
    runner.learn(1)
    assert runner.current_learning_iteration == 0
    with torch.inference_mode():
        actions = runner.get_inference_policy()(env.get_observations())
    assert actions.shape == (env.num_envs, env.num_actions) and torch.isfinite(actions).all()


def test_an_observation_held_from_step_t_is_unchanged_after_step(config):
    """(c): rsl_rl keeps o(t) while it calls step(t+1); it must still read o(t)."""
    env = lift(config)
    held = env.get_observations()
    before = {k: v.clone() for k, v in held.items()}
    for _ in range(3):
        nxt, _, _, _ = env.step(0.5 * torch.ones(env.num_envs, env.num_actions))
        for k in before:
            assert torch.equal(held[k], before[k]), k
            assert not torch.equal(nxt[k], before[k]), k
        held, before = nxt, {k: v.clone() for k, v in nxt.items()}


def test_same_seed_same_episodes_other_seed_other_episodes(config):
    a, b, c = lift(config, seed=5), lift(config, seed=5), lift(config, seed=6)
    actions = 0.3 * torch.ones(a.num_envs, a.num_actions)
    for _ in range(3):
        oa, ra, _, _ = a.step(actions)
        ob, rb, _, _ = b.step(actions)
        oc, _, _, _ = c.step(actions)
        assert torch.equal(oa["critic"], ob["critic"]) and torch.equal(ra, rb)
    assert not torch.equal(oa["critic"], oc["critic"])


def test_episodes_end_with_time_outs_and_restart(config):
    env = moonhaul.PhaseVecEnv(config("pendulum"), num_envs=3, seed=1)
    assert env.max_episode_length == 200
    for t in range(1, 201):
        _, _, dones, extras = env.step(torch.zeros(3, 1))
        if t < 200:
            assert not dones.any(), t
    # Pendulum-v1 never terminates: its episodes are cut by the clock, and bootstrapped.
    assert dones.all() and extras["time_outs"].all()
    assert (env.episode_length_buf == 0).all()
    assert extras["log"] == {}  # no action pipeline


def test_bad_input_is_refused_by_name(config, tmp_path):
    env = lift(config)
    with pytest.raises(ValueError, match="actions has 9 values, expected 36"):
        env.step(torch.zeros(1, 9))
    with pytest.raises(ValueError, match="not finite"):
        env.step(torch.full((4, 9), float("nan")))
    with pytest.raises(ValueError, match="nope.toml"):
        moonhaul.PhaseVecEnv(tmp_path / "nope.toml")
    with pytest.raises(ValueError, match="num_envs"):
        moonhaul.PhaseVecEnv(config("lift"), num_envs=0)
