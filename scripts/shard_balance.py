"""Per-rank load of N shards of a scene source: strided (scene i on rank i % N, the old split) against
the fixed shuffle `ShardSource` uses now. Prints the mean agents and road points per scene per rank.

    python scripts/shard_balance.py [--scenes procedural:all] [--n 1000] [--ranks 2]
"""

from __future__ import annotations

import argparse

import numpy as np

from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.learn.distributed import ShardSource


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="procedural:all")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--ranks", type=int, default=2)
    args = ap.parse_args()
    src = resolve_scenes(args.scenes, n=args.n, seed=0)
    scenes = [src.get(i) for i in range(len(src))]
    agents = np.array([s.num_agents for s in scenes])
    points = np.array([len(s.road_points) for s in scenes])
    splits = {"strided": [np.arange(r, len(src), args.ranks) for r in range(args.ranks)],
              "shuffled": [ShardSource(src, r, args.ranks).indices for r in range(args.ranks)]}
    for name, idx in splits.items():
        print(f"{name:>8}: agents / scene per rank {[round(float(agents[i].mean()), 2) for i in idx]}, "
              f"road points / scene {[round(float(points[i].mean()), 1) for i in idx]}")


if __name__ == "__main__":
    main()
