#!/usr/bin/env python3
"""Where a simulator control step's time goes: samples `moonhaul sim bench` with `perf` (call
graphs by DWARF unwinding) and sorts every sample of the batched step into the categories below
by the functions on its stack (first match wins); samples of env construction are set aside.

Usage (from the project root, after `cargo build --release -p moonhaul`; needs `perf`):
    bench/step_profile.py [--envs 8] [--steps 500] [--binary target/release/moonhaul] [--plan FILE]
"""

from __future__ import annotations

import argparse
import collections
import os
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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, default=8)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--binary", default="target/release/moonhaul")
    p.add_argument("--plan", default="bench/mujoco/plan.json")
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "perf.data")
        subprocess.run(["perf", "record", "-q", "-F", "1999", "--call-graph", "dwarf,32768", "-o", data,
                        a.binary, "sim", "bench", "--json", "--envs", str(a.envs), "--threads", "1",
                        "--steps", str(a.steps), "--plan", a.plan],
                       check=True, stdout=subprocess.DEVNULL)
        script = subprocess.run(["perf", "script", "-i", data], check=True, capture_output=True, text=True).stdout
    counts: collections.Counter[str] = collections.Counter()
    setup = 0
    for sample in script.split("\n\n"):
        stack = " | ".join(line.strip() for line in sample.strip().split("\n")[1:])
        if not stack:
            continue
        if any(k in stack for k in SETUP):
            setup += 1
            continue
        name = next((n for n, keys in CATEGORIES if any(k in stack for k in keys)), "other")
        counts[name] += 1
    total = sum(counts.values())
    if total == 0:
        sys.exit("step_profile: no samples of the step")
    print(f"{total} samples of the batched step ({setup} more of env construction set aside), "
          f"{a.envs} envs x {a.steps} control steps on one thread:")
    for name, _ in CATEGORIES + [("other", [])]:
        print(f"  {100 * counts[name] / total:5.1f} %  {name}")


if __name__ == "__main__":
    main()
