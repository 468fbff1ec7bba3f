"""Run the paper's beta x alpha grid (configs/train/grid.yaml) and tabulate the knobs' effect.

    python scripts/run_grid.py --base configs/train/small_cpu.yaml --out runs/grid \
        [--set scenes=procedural:dense_intersection --set control=nearest_conflict --set control_k=5]

One training run per cell (sequential, each on the base config's device); the
table averages the last `--tail` updates of each run: Lagrange multiplier,
mean minimum gap to the nearest agent, mean speed, cost per agent-step,
collision and goal rates. Writes <out>/grid.json and <out>/grid.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import yaml

from tg_gpudrive.config import REPO_CONFIGS, TrainConfig, apply_overrides, from_dict, load_yaml
from tg_gpudrive.learn.train import Trainer

COLUMNS = ("lambda", "mean_min_distance", "mean_speed", "cost", "collision_rate", "goal_rate")


def tail_mean(rows: list[dict], key: str, tail: int) -> float:
    vals = [float(r[key]) for r in rows[-tail:] if r.get(key) not in (None, "", "nan")]
    return sum(vals) / len(vals) if vals else math.nan


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default=str(REPO_CONFIGS / "train" / "small_cpu.yaml"))
    ap.add_argument("--grid", default=str(REPO_CONFIGS / "train" / "grid.yaml"))
    ap.add_argument("--out", default="runs/grid")
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--tail", type=int, default=5)
    args = ap.parse_args()
    grid = yaml.safe_load(Path(args.grid).read_text())
    out = Path(args.out)
    results = []
    for beta in grid["beta"]:
        for alpha in grid["alpha"]:
            over = args.set + [f"env.beta={beta}", f"alpha={alpha}"]
            cfg = from_dict(TrainConfig, apply_overrides(load_yaml(args.base), over), args.base)
            run = out / f"beta{beta}_alpha{alpha}"
            Trainer(cfg, run, progress=False).train()
            rows = list(csv.DictReader((run / "metrics.csv").open()))
            res = {"beta": beta, "alpha": alpha} | {k: tail_mean(rows, k, args.tail) for k in COLUMNS}
            results.append(res)
            print(json.dumps(res), flush=True)
    (out / "grid.json").write_text(json.dumps(results, indent=1))
    lines = ["| beta | alpha | " + " | ".join(COLUMNS) + " |", "|" + "---|" * (len(COLUMNS) + 2)]
    for r in results:
        lines.append(f"| {r['beta']} | {r['alpha']} | " + " | ".join(f"{r[k]:.3f}" for k in COLUMNS) + " |")
    (out / "grid.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
