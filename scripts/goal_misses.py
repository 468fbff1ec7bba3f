"""Why a policy's vehicles miss their goals: how far short the clean misses end.

    python scripts/goal_misses.py --policies shipped runs/x/checkpoint.pt expert --scenes <store> \
        [--seeds 0 1] [--device cpu]

Every policy drives every scene once per sampling seed (a slot for every agent, the rest replaying their
logs, ignore mode). Each policy vehicle's episode ends in a goal, or without one; a miss is "clean" when the
vehicle neither collided nor left the road: it simply had not arrived when the episode ended. A goal is the
log's last position, which the logged driver reaches at the last step, so a vehicle at the log's pace with
any detour ends just short of it. Per policy the table gives the goal, collision and off-road rates, the
share of clean misses, how far from the goal they ended (median and 90th percentile, and the share within
5 m), their speed then, and the time the median miss lacked at that speed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tg_gpudrive.agents import check_specs, open_policy
from tg_gpudrive.cli import one_line_errors
from tg_gpudrive.data.sources import resolve_scenes

NEAR_M = 5.0  # m: a clean miss ending this close to its goal is a near miss


def outcomes(sim, policy, seed: int) -> list[dict]:
    """One episode of every world: per policy vehicle, its goal, collision and off-road flags, and where it
    ended: the distance left to its goal and its speed."""
    torch.manual_seed(seed)
    sim.reset()
    ended = torch.zeros(sim.num_worlds, dtype=torch.bool, device=sim.pos.device)
    rows = []
    for _ in range(sim.episode_length + 1):
        policy(sim)
        sim.step()
        newly = (sim.world_ended != 0) & ~ended
        if bool(newly.any()):
            w, a = (newly[:, None] & (sim.policy_agents != 0)).nonzero(as_tuple=True)
            left = (sim.goal[w, a] - sim.pos[w, a]).norm(dim=-1)
            for i in range(len(w)):
                rows.append({"goal": bool(sim.final_goal[w[i], a[i]]), "collided": bool(sim.final_collided[w[i], a[i]]),
                             "offroad": bool(sim.final_offroad[w[i], a[i]]), "left": float(left[i]),
                             "speed": float(sim.speed[w[i], a[i]])})
        ended |= sim.world_ended != 0
        if bool(ended.all()):
            break
    return rows


def summary(rows: list[dict]) -> dict:
    n = max(len(rows), 1)
    miss = [r for r in rows if not (r["goal"] or r["collided"] or r["offroad"])]
    left = np.array([r["left"] for r in miss])
    speed = np.array([r["speed"] for r in miss])
    out = {"episodes": len(rows), "goal": sum(r["goal"] for r in rows) / n,
           "collision": sum(r["collided"] for r in rows) / n, "offroad": sum(r["offroad"] for r in rows) / n,
           "clean_miss": len(miss) / n, "near_share": float((left < NEAR_M).mean()) if len(miss) else float("nan")}
    if len(miss):
        out.update(left_median=float(np.median(left)), left_p90=float(np.percentile(left, 90)),
                   speed_median=float(np.median(speed)),
                   short_s=float(np.median(left / np.maximum(speed, 0.1))))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policies", nargs="+", required=True, help="checkpoints, run directories or built-in names")
    p.add_argument("--scenes", required=True, help="a scene spec: a store, a folder of JSON files, procedural:...")
    p.add_argument("--num-scenes", type=int, default=None, help="procedural specs: how many (seed 90000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    check_specs(args.policies, "--policies")  # a mistyped run fails before the scenes are built
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=90000) if args.num_scenes else resolve_scenes(args.scenes)
    scenes = [src.get(i) for i in range(len(src))]
    per: dict[str, list[dict]] = {}
    runs = [(spec, seed) for spec in args.policies for seed in args.seeds]
    for spec, seed in tqdm(runs, desc="goal_misses", unit="run"):
        opened = open_policy(spec, scenes, args.device, collision_mode="ignore", seed=seed, auto_reset=False,
                             option="--policies")
        per.setdefault(spec, []).extend(outcomes(opened.sim, opened.policy, seed))
    print(f"\n{len(scenes)} scenes, seeds {' '.join(map(str, args.seeds))}; clean miss: no goal, no collision, "
          "no off-road\n")
    print("| policy | agent-episodes | goal / collision / off-road | clean misses | distance left, median / p90 [m] "
          f"| within {NEAR_M:g} m | speed then [m/s] | time short [s] |")
    print("|---|---:|---|---:|---|---:|---:|---:|")
    for spec, rows in per.items():
        s = summary(rows)
        tail = (f"{s['left_median']:.1f} / {s['left_p90']:.1f} | {s['near_share']:.2f} | {s['speed_median']:.1f} | "
                f"{s['short_s']:.2f}") if s["clean_miss"] else "- | - | - | -"
        print(f"| {Path(spec).name} | {s['episodes']} | {s['goal']:.3f} / {s['collision']:.3f} / {s['offroad']:.3f} | "
              f"{s['clean_miss']:.3f} | {tail} |")
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("goal_misses.py", main))
