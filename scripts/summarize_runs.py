"""One summary per training run of a directory: windowed rates, the last update's learning state and
the time to quality.

    python scripts/summarize_runs.py /tmp/res/quality

For each `<root>/<run>/metrics.csv` of a policy run (world-model logs are skipped), in name order:

    <run>: N updates, goal / coll / off over the episodes that ended in the last RATE_WINDOW updates
           (episode-weighted, tg_gpudrive.learn.quality.windowed_rates: per-update rates alone are
           biased, as worlds whose cars all reach the goal end early and report 1.0), then the last
           update's entropy, KL to the prior, lambda (and its cap), CVaR, cost budget and wall-clock
      time to quality: the first update whose window has goal >= 0.95 with collision <= 0.05 and
           off-road <= 0.02 (tg_gpudrive.learn.quality.time_to_quality), or "not reached"
      quality stop: where the run stopped at its own targets after the held-out check (target.json,
           `--set target_heldout=...`): its wall-clock, update and held-out rates

Then, where runs that stopped at quality differ in their number of GPUs (metrics.csv's `ranks`), one line per
run of several GPUs: its quality stop against the fastest one-GPU run of the same seed (config.json), and per GPU
count the ratio of the summed fastest times over the seeds both have (how much sooner more GPUs reach quality).

Used by scripts/gpu_measure.sh after its training stages; numbers only, it never fails on them.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from tg_gpudrive.learn.quality import RATE_KEYS, RATE_WINDOW, time_to_quality, windowed_rates


def policy_runs(root: Path) -> list[tuple[str, list[dict]]]:
    """(name, metrics.csv rows) of every run directory under `root` whose log is a policy's."""
    out = []
    for d in sorted(p for p in root.iterdir() if (p / "metrics.csv").exists()):
        with (d / "metrics.csv").open() as f:
            rows = list(csv.DictReader(f))
        if rows and "goal_rate" in rows[0]:  # else not a policy run (a world model's log)
            out.append((d.name, rows))
    return out


def describe(name: str, rows: list[dict]) -> list[str]:
    """The two lines of one run (see the module docstring)."""
    r = windowed_rates(rows) or dict.fromkeys(RATE_KEYS, float("nan"))
    n = sum(float(x["episodes"] or 0) for x in rows[-RATE_WINDOW:])
    last = rows[-1]
    rates = (f"{name}: {len(rows)} updates, goal {r['goal_rate']:.3f} coll {r['collision_rate']:.3f} "
             f"off {r['offroad_rate']:.3f} ({n:.0f} episodes), ent {float(last['entropy']):.2f} "
             f"klp {float(last['kl/prior']):.2f} lambda {float(last['lambda']):.2f} "
             f"(max {float(last.get('lambda_max') or 0):.2f}) cvar {float(last['cvar']):.2f} "
             f"budget {float(last.get('cost_budget') or 0):.2f} wall {float(last['wall_s']):.0f}s")
    q = time_to_quality(rows)
    reached = (f"{q['wall_s']:.0f} s of rollouts and updates, {q.get('elapsed_s', float('nan')):.0f} s "
               f"elapsed (update {q['update']})") if q else "not reached"
    return [rates, f"  time to quality: {reached}"]


def quality_stop(run: Path) -> dict | None:
    """target.json of a run that stopped at its quality targets (with the held-out check), else None."""
    path = run / "target.json"
    return json.loads(path.read_text()) if path.exists() else None


def stop_line(stop: dict) -> str:
    """The quality-stop line of one run: its time, update and held-out rates."""
    h = stop.get("heldout") or {}
    held = (f", held out goal {h['goal_rate']:.3f} coll {h['collision_rate']:.3f} off {h['offroad_rate']:.3f} "
            f"({h.get('episodes', 0):.0f} episodes)") if h else ""
    return f"  quality stop: {stop['wall_s']:.1f} s (update {stop['update']}){held}"


def scaling_lines(stops: list[tuple[str, int, int, float]]) -> list[str]:
    """(run, GPUs, seed, seconds to its quality stop) -> each several-GPU run against the fastest one-GPU run of
    its seed, then per GPU count the ratio of the summed fastest times over the seeds both have (the fastest, so
    that a warm repeat counts, not its cold first run)."""
    best: dict[tuple[int, int], float] = {}
    for _, gpus, seed, wall in stops:
        best[gpus, seed] = min(wall, best.get((gpus, seed), float("inf")))
    lines = [f"{name}: {gpus} GPUs {wall:.1f} s against {best[1, seed]:.1f} s on one (seed {seed}): "
             f"{wall / best[1, seed]:.2f}x" for name, gpus, seed, wall in stops if gpus > 1 and (1, seed) in best]
    for gpus in sorted({g for g, _ in best if g > 1}):
        seeds = sorted(s for g, s in best if g == gpus and (1, s) in best)
        if seeds:
            ratio = sum(best[gpus, s] for s in seeds) / sum(best[1, s] for s in seeds)
            lines.append(f"{gpus} GPUs: {ratio:.2f}x one GPU's time to quality over seeds {seeds}")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="the directory holding the run directories")
    args = ap.parse_args(argv)
    stops = []
    for name, rows in policy_runs(args.root):
        lines = describe(name, rows)
        stop = quality_stop(args.root / name)
        if stop is not None:
            lines.append(stop_line(stop))
            config = args.root / name / "config.json"
            if config.exists():  # its seed pairs it with the one-GPU run below
                seed = int(json.loads(config.read_text())["seed"])
                stops.append((name, int(float(rows[-1].get("ranks") or 1)), seed, float(stop["wall_s"])))
        print("\n".join(lines))
    if len({gpus for _, gpus, _, _ in stops}) > 1:
        print("\n".join(scaling_lines(stops)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
