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

Used by scripts/gpu_measure.sh after its training stages; numbers only, it never fails on them.
"""

from __future__ import annotations

import argparse
import csv
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="the directory holding the run directories")
    args = ap.parse_args(argv)
    for name, rows in policy_runs(args.root):
        print("\n".join(describe(name, rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
