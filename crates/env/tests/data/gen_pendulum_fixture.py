"""Regenerates pendulum_v1.json: Pendulum-v1 trajectories from gymnasium itself, the reference
that tests/pendulum_gymnasium.rs replays through the Rust implementation.

    python3 -m venv /tmp/gymvenv && /tmp/gymvenv/bin/pip install gymnasium numpy
    /tmp/gymvenv/bin/python gen_pendulum_fixture.py > pendulum_v1.json

Each trajectory starts from the state gymnasium's reset(seed) draws and runs until the
TimeLimit truncates it (200 steps), with random torques in [-3, 3] (beyond the ±2 limit, so
clipping is exercised). Actions are passed as float64 (pure f64 dynamics, compared tightly)
and as float32 (the action space's dtype: NumPy 2 then computes the torque terms in float32).
"""
import json

import gymnasium as gym
import numpy as np


def trajectory(seed, dtype):
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=seed)
    theta, theta_dot = (float(v) for v in env.unwrapped.state)
    rng = np.random.default_rng(1000 + seed)
    steps = []
    while True:
        action = rng.uniform(-3.0, 3.0, size=(1,)).astype(dtype)
        obs, reward, terminated, truncated, _ = env.step(action)
        state = env.unwrapped.state
        steps.append({
            "action": float(action[0]),
            "reward": float(reward),
            "obs": [float(v) for v in obs],
            "state": [float(state[0]), float(state[1])],
            "terminated": bool(terminated),
            "truncated": bool(truncated),
        })
        if terminated or truncated:
            break
    return {"seed": seed, "action_dtype": np.dtype(dtype).name,
            "initial_state": [theta, theta_dot],
            "steps": steps}


def main():
    trajectories = [trajectory(seed, dtype) for seed in range(3) for dtype in (np.float64, np.float32)]
    print(json.dumps({"gymnasium": gym.__version__, "numpy": np.__version__,
                      "trajectories": trajectories}))


if __name__ == "__main__":
    main()
