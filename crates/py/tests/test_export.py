"""Export of an rsl_rl actor to moonhaul's policy file: the file, read and run by the onboard
runtime's own code (``moonhaul_core::policy`` through ``OnboardPolicy``), computes what the
torch actor and the environment's action map compute; bad input is refused by name; and the
``moonhaul`` CLI accepts the file (when the tests run under ``cargo xtask test``, which points
``MOONHAUL_BIN`` at the binary it built)."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

import moonhaul
from moonhaul.export import export_actor
from moonhaul.rsl import OnPolicyRunner, train_cfg


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A lift actor after two rsl_rl iterations on two worlds: its normalizer has moved off
    identity and its weights off their initialisation, so the comparison sees every part."""
    root = os.path.join(os.path.dirname(__file__), "..", "..", "..")
    config = os.path.join(root, "configs", "train", "lift.toml")
    torch.manual_seed(3)
    env = moonhaul.PhaseVecEnv(config, num_envs=2, seed=3, threads=1)
    cfg = train_cfg(env.cfg)
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(env, cfg, log_dir=None, device="cpu")
    runner.learn(2)
    path = tmp_path_factory.mktemp("export") / "lift.safetensors"
    export_actor(runner.alg.actor, env, path, {"created_by": "test", "seed": 3})
    return env, runner, path


def test_the_file_flies_what_the_actor_computes(trained):
    env, runner, path = trained
    policy = moonhaul.OnboardPolicy(str(path))
    scale = torch.tensor(env.action_scale(), dtype=torch.float64)
    offset = torch.tensor(env.action_offset(), dtype=torch.float64)
    obs = env.get_observations()
    # Real observations, and the same pushed far from the normalizer's mean.
    rows = torch.cat([obs["policy"], 3.0 * obs["policy"] + 1.0])
    with torch.inference_mode():
        mean = runner.alg.actor({"policy": rows}).to(torch.float64)
    expected = offset + scale * mean
    got = torch.tensor([policy.act(r.tolist()) for r in rows], dtype=torch.float64)
    tol = 1e-5 * (1.0 + expected.abs())
    assert (got - expected).abs().le(tol).all(), (got - expected).abs().max()
    # The normalizer was exported, not identity: without it the outputs would differ.
    assert not torch.allclose(runner.alg.actor.obs_normalizer.std, torch.ones_like(runner.alg.actor.obs_normalizer.std))


def test_the_file_says_what_it_is(trained):
    env, _, path = trained
    meta = moonhaul.OnboardPolicy(str(path)).metadata
    assert meta["phase"] == "lift" and meta["task"] == "lift"
    assert int(meta["obs_dim"]) == env.native.obs_dim
    assert int(meta["action_dim"]) == env.num_actions
    for key, value in env.policy_metadata():
        assert meta[key] == value, key
    assert len(meta["config_sha256"]) == 64 and meta["commit"]
    assert meta["created_by"] == "test" and meta["seed"] == "3"


def test_extra_cannot_forge_the_identity(trained, tmp_path):
    env, runner, _ = trained
    path = tmp_path / "p.safetensors"
    export_actor(runner.alg.actor, env, path, {"task": "place", "config_sha256": "0" * 64})
    meta = moonhaul.OnboardPolicy(str(path)).metadata
    assert meta["task"] == "lift" and meta["config_sha256"] != "0" * 64


def test_bad_layers_are_refused_by_name_and_nothing_is_written(trained, tmp_path):
    env, runner, _ = trained
    path = tmp_path / "bad.safetensors"
    w = [m.weight.detach().numpy() for m in runner.alg.actor.mlp if isinstance(m, torch.nn.Linear)]
    b = [m.bias.detach().numpy() for m in runner.alg.actor.mlp if isinstance(m, torch.nn.Linear)]
    with pytest.raises(ValueError, match=r"actor\.1\."):
        env.native.export_policy(str(path), w, [b[0], b[1][:-1]] + b[2:])
    with pytest.raises(ValueError, match=r"weights\[0\]"):
        env.native.export_policy(str(path), [w[0].astype(np.float64)] + w[1:], b)
    nan = w[-1].copy()
    nan[0, 0] = np.nan
    with pytest.raises(ValueError):
        env.native.export_policy(str(path), w[:-1] + [nan], b)
    with pytest.raises(ValueError, match="obs_mean and obs_std"):
        env.native.export_policy(str(path), w, b, obs_mean=np.zeros(env.native.obs_dim, np.float32))
    assert not path.exists()


def test_a_broken_file_is_named(tmp_path):
    path = tmp_path / "broken.safetensors"
    path.write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    with pytest.raises(ValueError, match="broken.safetensors"):
        moonhaul.OnboardPolicy(str(path))


def moonhaul_bin():
    path = os.environ.get("MOONHAUL_BIN")
    if not path:
        if os.environ.get("MOONHAUL_XTASK_TEST"):
            pytest.fail("MOONHAUL_BIN is not set under cargo xtask test")
        pytest.skip("MOONHAUL_BIN (the moonhaul CLI) not given; cargo xtask test gives it")
    return path


def test_train_exports_and_the_cli_reads_it(tmp_path):
    """``python -m moonhaul.train`` writes policy.safetensors, ``python -m moonhaul.export``
    re-exports a checkpoint to the same network, and ``moonhaul policy inspect`` reads both."""
    out = tmp_path / "run"
    common = ["--config", "configs/train/lift.toml", "--threads", "1"]
    subprocess.run(
        [sys.executable, "-m", "moonhaul.train", *common, "--out", str(out), "--iterations", "1", "--num-envs", "2"],
        check=True, timeout=600, capture_output=True,
    )
    trained = out / "policy.safetensors"
    checkpoint = sorted(out.glob("model_*.pt"))[-1]
    again = tmp_path / "again.safetensors"
    subprocess.run(
        [sys.executable, "-m", "moonhaul.export", "--config", "configs/train/lift.toml",
         "--checkpoint", str(checkpoint), "--out", str(again)],
        check=True, timeout=600, capture_output=True,
    )
    a, b = moonhaul.OnboardPolicy(str(trained)), moonhaul.OnboardPolicy(str(again))
    obs = [0.1 * i for i in range(int(a.metadata["obs_dim"]))]
    assert a.act(obs) == b.act(obs)
    assert a.metadata["created_by"].startswith("rsl_rl 5.5.1 (python -m moonhaul.train)")
    assert a.metadata["world_size"] == "1" and a.metadata["iteration"] == "0"

    broken = subprocess.run(
        [sys.executable, "-m", "moonhaul.export", "--config", "configs/train/lift.toml",
         "--checkpoint", str(tmp_path / "missing.pt"), "--out", str(tmp_path / "x.safetensors")],
        timeout=600, capture_output=True, text=True,
    )
    assert broken.returncode != 0 and "missing.pt" in broken.stderr
    assert not (tmp_path / "x.safetensors").exists()

    cli = moonhaul_bin()
    for path in (trained, again):
        inspect = subprocess.run([cli, "policy", "inspect", str(path)], capture_output=True, text=True, timeout=60)
        assert inspect.returncode == 0, inspect.stderr
        assert "lift" in inspect.stdout
