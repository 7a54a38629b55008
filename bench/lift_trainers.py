#!/usr/bin/env python3
"""Lift trained by moonhaul-train and by stock rsl_rl (through the `moonhaul` extension), side by
side: training curves per seed and the final policies' `moonhaul eval` figures, as Markdown.

    python bench/lift_trainers.py RUNS [--eval EVALS] [--png FILE]

RUNS holds `mt-s<seed>/` (a `moonhaul-train` run folder: `metrics.csv`) and `rsl-s<seed>/` (a
`python -m moonhaul.train` folder: rsl_rl's TensorBoard events) for each seed. Both trainers
step the same environment (`moonhaul_env::task::make_env` of the same config) and count the
same rows; rsl_rl's `Train/mean_reward` is the mean over its last 100 completed episodes of the
*scaled* reward (the extension multiplies by `ppo.reward_scale` as moonhaul-train does), so it
is divided by the scale here to compare with `metrics.csv`'s `mean_return`, the unscaled mean
over moonhaul-train's last 100 completed episodes. rsl_rl logs iteration `it` (0-based) after
`it + 1` updates; rows here are by updates completed.

EVALS, if given, holds `<run>.json`: `moonhaul eval --json` of each run's final policy (lift
from the run, transport and place bundled), whose learned open-loop lift rows and deployed
missions are tabulated. `--png` draws the training-return curves (Pillow).
"""

from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import statistics
import tomllib

CHECKPOINTS = (25, 50, 100, 150, 200)


def moonhaul_curve(run: str) -> dict[int, dict[str, float]]:
    rows = {}
    with open(os.path.join(run, "metrics.csv")) as f:
        for r in csv.DictReader(f):
            it = int(r["iteration"])
            if it == 0 or not r["mean_return"]:
                continue
            rows[it] = {
                "return": float(r["mean_return"]),
                "t_max": float(r["mean_t_max"]) if r["mean_t_max"] else float("nan"),
                "hold": float(r["hold_fraction"]) if r["hold_fraction"] else float("nan"),
                "grasp_n": float(r["mean_grasp_force_n"]) if r["mean_grasp_force_n"] else float("nan"),
                "env_steps": int(r["env_steps"]),
            }
    return rows


def rsl_curve(run: str, reward_scale: float) -> dict[int, dict[str, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = glob.glob(os.path.join(run, "events.out.tfevents.*"))
    acc = EventAccumulator(events, size_guidance={"scalars": 0})
    acc.Reload()

    def series(tag: str) -> dict[int, float]:
        return {e.step + 1: e.value for e in acc.Scalars(tag)} if tag in acc.Tags()["scalars"] else {}

    ret = series("Train/mean_reward")
    t_max = series("/pipeline/clamp_t_max_mean")
    hold = series("/pipeline/clamp_hold_rate")
    grasp = series("/pipeline/grasp_force_mean_n")
    return {
        it: {
            "return": v / reward_scale,
            "t_max": t_max.get(it, float("nan")),
            "hold": hold.get(it, float("nan")),
            "grasp_n": grasp.get(it, float("nan")),
        }
        for it, v in ret.items()
    }


def window(curve: dict[int, dict[str, float]], it: int, key: str, width: int = 10) -> float:
    """Mean of `key` over the `width` iterations ending at `it` (the curves are noisy)."""
    vals = [curve[i][key] for i in range(it - width + 1, it + 1) if i in curve]
    return statistics.fmean(vals) if vals else float("nan")


def fmt(v: float, digits: int = 0) -> str:
    if v != v:
        return "–"
    s = f"{v:,.{digits}f}"
    return s.replace("-", "−")


def eval_row(path: str) -> list[str]:
    with open(path) as f:
        line = [l for l in f.read().splitlines() if l.strip()][-1]
    box = json.loads(line)["box"]
    # `moonhaul eval --json`: the learned policies' open-loop rows sit at the payload's level,
    # their deployed missions under `learned`.
    d = box["learned"]
    cells = []
    for h in ("0.3", "0.5", "0.75"):
        lift = box["lift"][h]
        cells.append(f"{fmt(lift['final_height_error_mm']['mean'], 1)} / {fmt(100 * lift['success_rate']['mean'])} %")
    dep = d.get("deployed")
    if dep:
        c = dep["clamp"]
        cells += [
            f"{dep['outcomes'].get('completed', 0)}/{dep['episodes']}",
            fmt(c["mean_t_max"], 3),
            f"{fmt(100 * c['hold_tick_fraction'], 1)} %",
            fmt(dep["mean_grasp_force_n"], 1),
        ]
    return cells


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs")
    p.add_argument("--eval", default=None)
    p.add_argument("--png", default=None)
    args = p.parse_args()

    seeds = sorted(int(d.rsplit("s", 1)[1]) for d in glob.glob(os.path.join(args.runs, "mt-s*")) if os.path.isdir(d))
    curves = {}
    for s in seeds:
        mt = os.path.join(args.runs, f"mt-s{s}")
        with open(os.path.join(mt, "config.toml"), "rb") as f:
            scale = tomllib.load(f)["ppo"]["reward_scale"]
        curves[("moonhaul-train", s)] = moonhaul_curve(mt)
        curves[("stock rsl_rl 5.5.1", s)] = rsl_curve(os.path.join(args.runs, f"rsl-s{s}"), scale)

    last = max(max(c) for c in curves.values() if c)
    marks = [m for m in CHECKPOINTS if m <= last]
    print("Training return (mean of the last 100 completed episodes, unscaled; each cell the mean "
          "over the 10 iterations ending there):\n")
    print("| trainer | seed | " + " | ".join(f"it {m}" for m in marks) + " | t_max | holds | grasp N |")
    print("|---|---|" + "---|" * (len(marks) + 3))
    for (trainer, s), c in sorted(curves.items()):
        end = max(c) if c else 0
        cells = [fmt(window(c, m, "return")) for m in marks]
        tail = [fmt(window(c, end, "t_max"), 3), f"{fmt(100 * window(c, end, 'hold'), 1)} %", fmt(window(c, end, "grasp_n"), 1)]
        print(f"| {trainer} | {s} | " + " | ".join(cells + tail) + " |")
    print()
    for trainer in ("moonhaul-train", "stock rsl_rl 5.5.1"):
        finals = [window(c, max(c), "return") for (t, _), c in curves.items() if t == trainer and c]
        if finals:
            print(f"- {trainer}: final return over seeds {fmt(statistics.fmean(finals))} "
                  f"(min {fmt(min(finals))}, max {fmt(max(finals))})")

    if args.eval:
        print("\nFinal policies, `moonhaul eval` on the box, 100 episodes per case (learned lift; "
              "bundled transport and place in the deployed missions):\n")
        print("| trainer | seed | lift 0.3 m err / success | 0.5 m | 0.75 m | deployed completed | t_max | holds | grasp N |")
        print("|---|---|---|---|---|---|---|---|---|")
        for s in seeds:
            for name, trainer in ((f"mt-s{s}", "moonhaul-train"), (f"rsl-s{s}", "stock rsl_rl 5.5.1")):
                path = os.path.join(args.eval, f"{name}.json")
                if os.path.exists(path) and os.path.getsize(path) > 0:
                    print(f"| {trainer} | {s} | " + " | ".join(eval_row(path)) + " |")

    if args.png:
        draw(curves, args.png)


def draw(curves, path: str) -> None:
    from PIL import Image, ImageDraw

    w, h, m = 900, 520, 60
    img = Image.new("RGB", (w, h), "white")
    g = ImageDraw.Draw(img)
    pts = [(i, v["return"]) for c in curves.values() for i, v in c.items()]
    x1 = max(i for i, _ in pts)
    y0, y1 = min(v for _, v in pts), max(v for _, v in pts)
    sx = lambda i: m + (w - 2 * m) * i / x1
    sy = lambda v: h - m - (h - 2 * m) * (v - y0) / (y1 - y0 or 1)
    g.rectangle([m, m, w - m, h - m], outline="black")
    for k in range(5):
        v = y0 + (y1 - y0) * k / 4
        g.text((4, sy(v) - 6), f"{v:,.0f}", fill="black")
    for k in range(5):
        i = x1 * k / 4
        g.text((sx(i) - 10, h - m + 6), f"{i:.0f}", fill="black")
    g.text((w / 2 - 80, h - 22), "PPO iterations (updates)", fill="black")
    g.text((m, 20), "Lift, training return (unscaled): blue moonhaul-train, red stock rsl_rl; one line per seed", fill="black")
    for (trainer, s), c in curves.items():
        xs = sorted(c)
        colour = ["#1f4fbf", "#4f7fef", "#8fafff"][(s - 1) % 3] if trainer == "moonhaul-train" else ["#bf1f1f", "#ef4f4f", "#ff8f8f"][(s - 1) % 3]
        g.line([(sx(i), sy(c[i]["return"])) for i in xs], fill=colour, width=2)
    img.save(path)


if __name__ == "__main__":
    main()
