#!/usr/bin/env python3
"""Where a simulator control step's time goes: samples `moonhaul sim bench` with `perf` (call
graphs by DWARF unwinding) and sorts every sample of the batched step into the categories below
by the functions on its stack (first match wins); samples of env construction are set aside.

Usage (from the project root, after `cargo build --release -p moonhaul`; needs `perf`):
    bench/step_profile.py [--envs 8] [--steps 500] [--binary target/release/moonhaul] [--plan FILE]

The training workload instead (a whole PPO iteration of a phase task: the env's physics and
its obs & reward, act, update), from the iteration bench's binary
(`cargo xtask cargo bench -p moonhaul-learn --bench iteration --no-run` names it):
    bench/step_profile.py --iteration --command "BENCH_BINARY --worlds 512 --iterations 2"
Its samples are sorted as the iteration bench splits the time, with the physics part split into
the solver categories; env and policy construction are set aside.
"""

from __future__ import annotations

import argparse
import collections
import os
import shlex
import subprocess
import sys
import tempfile

SETUP = ["reset_cost", "SceneModel::new", "BatchEnv::new", "terrain::", "ik::solve",
         "world::<impl moonhaul_sim::scene::Env>::new"]
CATEGORIES = [
    ("collision detection (narrow phase, wheels and casters on the heightfield)", ["detect_collisions"]),
    ("multibody mass matrix and its LU factorizations (every substep)", ["update_mass_matrix"]),
    ("grasp joints (impulse fixed joints between end effectors and payload)", ["JointGenericExternal"]),
    ("joint motors and limits (M^-1 J per DoF, every substep)", ["JointGenericInternal"]),
    ("contact constraints (M^-1 J per contact row, warm start, solve)",
     ["GenericContactConstraint", "ContactWithTwist", "ContactWithCoulomb", "contact_constraint"]),
    ("rest of the solver (solve passes, integration, forward kinematics)",
     ["staged_island_solver", "integrate", "forward_kinematics", "update_acceleration", "update_velocities"]),
    ("state readout (moonhaul's state_into)", ["state_into", "readout"]),
    ("rayon hand-off and scheduling", ["rayon", "futex", "schedule", "finish_task_switch", "_raw_spin"]),
]

# The training iteration: the update and the policy's act first (their stacks never hold the
# simulator), then the simulator's categories, then what else the env step does.
# Only construction is set aside: resets during the rollout are the iteration's own work.
ITERATION_SETUP = ["SceneModel::new", "BatchEnv::new", "world::<impl moonhaul_sim::scene::Env>::new",
                   "make_env", "ActorCritic::new", "Runner::new"]
ITERATION_CATEGORIES = [
    ("PPO update (returns, advantages, gradient steps)", ["Ppo::update"]),
    ("act (actor and critic forward, sampling, normalizers, storage)",
     ["Ppo::act", "ActorCritic::act", "Storage::", "EmpiricalNormalizer"]),
] + CATEGORIES[:-1] + [
    ("obs & reward (outcomes, rewards, resets, observations, tensor conversions)",
     ["phase_env", "moonhaul_sim::task", "moonhaul_learn::env", "reward::"]),
    CATEGORIES[-1],
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, default=8)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--binary", default="target/release/moonhaul")
    p.add_argument("--plan", default="bench/mujoco/plan.json")
    p.add_argument("--iteration", action="store_true",
                   help="sort the samples as a training iteration (with --command)")
    p.add_argument("--command", help="profile this command line instead of `sim bench`")
    p.add_argument("--frequency", type=int, default=1999,
                   help="samples per second per thread (lower it for long commands: DWARF stacks are 32 KiB each)")
    a = p.parse_args()
    if a.iteration and not a.command:
        p.error("--iteration profiles the iteration bench: give its binary with --command")
    command = shlex.split(a.command) if a.command else [
        a.binary, "sim", "bench", "--json", "--envs", str(a.envs), "--threads", "1",
        "--steps", str(a.steps), "--plan", a.plan]
    setup_keys, categories = (ITERATION_SETUP, ITERATION_CATEGORIES) if a.iteration else (SETUP, CATEGORIES)
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "perf.data")
        subprocess.run(["perf", "record", "-q", "-F", str(a.frequency), "--call-graph", "dwarf,32768",
                        "-o", data] + command,
                       check=True, stdout=subprocess.DEVNULL)
        script = subprocess.run(["perf", "script", "-i", data], check=True, capture_output=True, text=True).stdout
    counts: collections.Counter[str] = collections.Counter()
    setup = 0
    for sample in script.split("\n\n"):
        stack = " | ".join(line.strip() for line in sample.strip().split("\n")[1:])
        if not stack:
            continue
        if any(k in stack for k in setup_keys):
            setup += 1
            continue
        name = next((n for n, keys in categories if any(k in stack for k in keys)), "other")
        counts[name] += 1
    total = sum(counts.values())
    if total == 0:
        sys.exit("step_profile: no samples of the step")
    what = " ".join(command) if a.command else f"{a.envs} envs x {a.steps} control steps on one thread"
    print(f"{total} samples ({setup} more of construction set aside), {what}:")
    for name, _ in categories + [("other", [])]:
        print(f"  {100 * counts[name] / total:5.1f} %  {name}")


if __name__ == "__main__":
    main()
