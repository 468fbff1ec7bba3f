"""Throughput and per-rank phases of multi-process training runs: the scale stage of scripts/gpu_measure.sh.

    python scripts/scale_timing.py /tmp/res/scale [--glob 'scale*']

For each run directory matching `--glob` under the root (e.g. scale1, scale2: the same config trained
with 1 and 2 processes), in name order, prints the median end-to-end and rollout-only agent steps/s
over its metrics.csv rows after the first two (warm-up), then per rank the median over updates
3 on (timing.csv) of its own rollout, its wait for the slowest rank's rollout, and the update.
Numbers only; a missing file gives nan / no rank lines.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

WARMUP_ROWS = 2  # metrics.csv rows left out of the throughput medians
FIRST_TIMED_UPDATE = 3  # timing.csv: updates before it are left out of the per-rank medians
PHASES = ("rollout_s", "wait_s", "update_s")


def _rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(float(r[key]) for r in rows) if rows else float("nan")


def describe(run: Path) -> list[str]:
    """The lines of one run: its throughput, then one line per rank."""
    m = _rows(run / "metrics.csv")[WARMUP_ROWS:]
    timed = [r for r in _rows(run / "timing.csv") if int(r["update"]) >= FIRST_TIMED_UPDATE]
    lines = [f"{run.name}: {_median(m, 'agent_steps_per_s'):,.0f} agent steps/s end to end, "
             f"rollout {_median(m, 'rollout_agent_steps_per_s'):,.0f}"]
    for rank in sorted({r["rank"] for r in timed}):
        own = [r for r in timed if r["rank"] == rank]
        med = {k: _median(own, k) for k in PHASES}
        lines.append(f"  rank {rank}: rollout {med['rollout_s']:.3f} s, wait {med['wait_s']:.3f} s, "
                     f"update {med['update_s']:.3f} s")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="the directory holding the run directories")
    ap.add_argument("--glob", default="scale*", help="run directories to read (default: scale*)")
    args = ap.parse_args(argv)
    for run in sorted(args.root.glob(args.glob)):
        print("\n".join(describe(run)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
