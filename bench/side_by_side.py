#!/usr/bin/env python3
"""moonhaul beside its yardsticks, alternating in one run: the simulator against MuJoCo on the
same scene and command plan, the PPO update and act against rsl_rl 5.5.1 at the same sizes.

Run through `cargo xtask bench` (which builds both sides and prepares the Python venv); it calls

    side_by_side.py --python VENV_PYTHON [--rounds 5] [--envs 64] [--threads 2] [--steps 500]
                    [--only sim|ppo]

Each round runs A (moonhaul) then B (the yardstick) as fresh processes; every program times its
own work after its set-up and prints JSON, so the ratio of each round compares two runs made
seconds apart under the same machine load. The medians of the per-round ratios are printed last.

Simulator: `moonhaul sim bench --plan bench/mujoco/plan.json` (control steps/s of N randomized
envs on T threads, one sync per control step) against `bench/mujoco/mj_bench.py` on the same
plan, envs and threads: MuJoCo's `batch_rollout` (its fastest batched mode, one call for the
whole rollout) and `batch_percontrol` (one call per control step, as our batch syncs). Read the
ratios with bench/mujoco/README.md, "What differs between the two simulators".
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# glibc's tunables for what `retain_freed_memory` in crates/learn/src/ppo.rs sets with mallopt.
GLIBC_RETAIN = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}


def json_lines(cmd: list[str], env: dict | None = None) -> list[dict]:
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, **(env or {})})
    if done.returncode != 0:
        sys.exit(f"side_by_side: {' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    rows = []
    for line in done.stdout.splitlines():
        line = line.strip()
        if line.startswith("{"):
            rows.append(json.loads(line))
    if not rows:
        sys.exit(f"side_by_side: {' '.join(cmd)} printed no JSON line:\n{done.stdout[-2000:]}")
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--python", required=True, help="python of the venv with mujoco and rsl_rl")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--envs", type=int, default=64)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--only", choices=["sim", "ppo"])
    a = p.parse_args()
    if a.rounds < 1:
        sys.exit("side_by_side: --rounds must be at least 1")

    cargo = os.environ.get("CARGO", "cargo")
    sizes = ["--envs", str(a.envs), "--threads", str(a.threads), "--steps", str(a.steps)]
    sim_a = [cargo, "run", "-q", "--release", "-p", "moonhaul", "--", "sim", "bench", "--json",
             "--plan", "bench/mujoco/plan.json", *sizes]
    sim_b = [a.python, "bench/mujoco/mj_bench.py", "--json", "--skip", "single_rollout,single_pyloop", *sizes]
    ppo_a = [cargo, "bench", "-q", "-p", "moonhaul-learn", "--bench", "ppo", "--", "--rounds", "1",
             "--threads", str(a.threads)]
    ppo_b = [a.python, "bench/rsl_rl_ppo.py", "--rounds", "1", "--threads", str(a.threads)]

    ratios: dict[str, list[float]] = {}

    def keep(name: str, value: float) -> str:
        ratios.setdefault(name, []).append(value)
        return f"{name} {value:.2f}x"

    print(f"side by side, {a.rounds} rounds alternating A (moonhaul) and B (yardstick), {os.cpu_count()} CPUs")
    for k in range(1, a.rounds + 1):
        if a.only in (None, "sim"):
            ours = json_lines(sim_a)[-1]
            mj = json_lines(sim_b)[-1]
            rate = ours["control_steps_per_s"]
            print(f"round {k} sim: moonhaul {rate:.0f} control steps/s ({ours['envs']} envs, {ours['threads']} threads) | "
                  f"MuJoCo {mujoco_version(mj)} batch_rollout {mj['batch_rollout_control_per_s']:.0f}, "
                  f"batch_percontrol {mj['batch_percontrol_control_per_s']:.0f} | "
                  + keep("sim/MuJoCo batch_rollout", rate / mj["batch_rollout_control_per_s"]) + ", "
                  + keep("sim/MuJoCo batch_percontrol", rate / mj["batch_percontrol_control_per_s"]) + " | "
                  f"reset {ours['reset_s'] * 1e3:.3f} ms = "
                  + keep("reset/control step", ours["reset_s"] / ours["control_step_s"]).replace("x", "")
                  + " control steps", flush=True)
        if a.only in (None, "ppo"):
            ours = json_lines(ppo_a)[-1]
            ref = json_lines(ppo_b)[-1]
            # moonhaul keeps freed heap in the process (mallopt in Ppo::new); rsl_rl given the
            # same glibc settings through the environment is the like-for-like yardstick.
            tuned = json_lines(ppo_b, env=GLIBC_RETAIN)[-1]
            print(f"round {k} ppo: moonhaul update {ours['update_samples_per_s']:.0f} samples/s, "
                  f"act {ours['act_ms_per_step']:.2f} ms/step | rsl_rl update {ref['update_samples_per_s']:.0f}, "
                  f"act {ref['act_ms_per_step']:.2f} | rsl_rl with moonhaul's malloc settings "
                  f"update {tuned['update_samples_per_s']:.0f}, act {tuned['act_ms_per_step']:.2f} | "
                  + keep("update/rsl_rl", ours["update_samples_per_s"] / ref["update_samples_per_s"]) + ", "
                  + keep("act speed/rsl_rl", ref["act_ms_per_step"] / ours["act_ms_per_step"]) + ", "
                  + keep("update/rsl_rl same malloc", ours["update_samples_per_s"] / tuned["update_samples_per_s"])
                  + ", "
                  + keep("act speed/rsl_rl same malloc", tuned["act_ms_per_step"] / ours["act_ms_per_step"]),
                  flush=True)
    print("medians over the rounds:")
    for name, values in ratios.items():
        unit = "" if name.startswith("reset") else "x"
        print(f"  {name}: {statistics.median(values):.2f}{unit} (min {min(values):.2f}, max {max(values):.2f})")


def mujoco_version(row: dict) -> str:
    return str(row.get("mujoco", "?"))


if __name__ == "__main__":
    main()
