"""Draw a training run's curves (metrics.csv -> PNG) with tg_gpudrive.learn.plots.plot_curves.

    python scripts/plot_curves.py runs/cce/metrics.csv curves.png

The trainer draws its run's curves.png when training ends by itself; a run stopped from outside (a
`timeout`, as in scripts/gpu_measure.sh's ttq stage) leaves only metrics.csv, which this draws.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tg_gpudrive.learn.plots import plot_curves


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("metrics", type=Path, help="a run's metrics.csv")
    ap.add_argument("out", type=Path, help="the PNG to write")
    args = ap.parse_args(argv)
    plot_curves(args.metrics, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
