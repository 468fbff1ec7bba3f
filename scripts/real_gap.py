"""The gap between two scene sets, feature by feature (tg_gpudrive/evaluation/scene_stats.py): by default
the real WOMD development scenes against the procedural generator's held-out scenes.

    python scripts/real_gap.py --ref ~/.cache/tg_gpudrive/womd_dev --other procedural:all --num-other 300

Prints a markdown table: each feature's median in both sets, the sample counts and the distance
(Wasserstein-1 over the reference's standard deviation), largest first.
"""

from __future__ import annotations

import argparse

from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.evaluation.scene_stats import UNITS, gap_table, set_features


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ref", required=True, help="the reference scenes (a scene spec: real scenes)")
    p.add_argument("--other", default="procedural:all", help="the scenes compared with them (default procedural:all)")
    p.add_argument("--num-other", type=int, default=300, help="scenes of --other (default 300)")
    p.add_argument("--seed", type=int, default=90000, help="procedural seed of --other (default 90000: held out)")
    args = p.parse_args(argv)
    ref_src = resolve_scenes(args.ref)
    other_src = resolve_scenes(args.other, n=args.num_other, seed=args.seed)
    ref = set_features([ref_src.get(i) for i in range(len(ref_src))])
    other = set_features([other_src.get(i) for i in range(len(other_src))])
    print(f"| feature | unit | {args.ref} median | {args.other} median | samples (ref / other) | distance |")
    print("|---|---|---:|---:|---:|---:|")
    for g in gap_table(ref, other):
        print(f"| {g.feature} | {UNITS.get(g.feature, '-')} | {g.ref_median:.3g} | {g.other_median:.3g} | "
              f"{g.ref_n} / {g.other_n} | {g.distance:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
