"""Which situations make a policy's collisions on a scene set, and whether they recur.

    python scripts/crash_anatomy.py --policies shipped runs/x/checkpoint.pt --scenes <store> \
        --seeds 0 1 2 [--device cpu]

Every policy drives every scene once per sampling seed (a slot for every agent, the rest replaying
their logs, ignore mode). Each policy vehicle's first collision is described by evaluation/risk.py's
`collision_partners` (the nearest agent then, the contact in the vehicle's frame, both speeds), plus
the partner's type and whether its log moves at all. The events are grouped by (world, vehicle) over
policies and seeds and printed as a markdown table, the most recurrent first: a row present in every run
is a trait of the scene that more sampling will not average away; the rate bar says how many such rows
a policy may keep.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tg_gpudrive.agents import open_policy
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.enums import AgentType
from tg_gpudrive.evaluation.episodes import record_episodes
from tg_gpudrive.evaluation.risk import collision_partners

STANDING_M = 1.0  # m: a partner whose whole log moves less than this stands still


def describe(tr, types: np.ndarray, row: dict) -> dict:
    """One collision_partners row with the vehicle as its scene's agent index (slots differ between
    policies' worlds), the partner's type and whether it stands still."""
    e, b = row["episode"], row["partner"]
    path = tr.pos[e, b][tr.valid[e, b]]
    standing = len(path) == 0 or float(np.ptp(path, axis=0).max()) < STANDING_M
    return {**row, "agent": int(tr.slot_agent[e, row["agent"]]), "partner_type": AgentType(int(types[e, b])).name.lower(),
            "partner_standing": standing}


def group(events: list[dict]) -> list[dict]:
    """Events (describe's rows plus `run`) grouped by (episode, agent): how many runs each recurs in, and
    its commonest partner and contact, the speed ranges and the first-contact steps; most recurrent first."""
    by = defaultdict(list)
    for ev in events:
        by[(ev["episode"], ev["agent"])].append(ev)
    out = []
    for (e, a), evs in by.items():
        def common(f):
            return Counter(f(x) for x in evs).most_common(1)[0][0]
        who = common(lambda x: ("policy" if x["partner_policy"] else "replayed")
                      + (" standing" if x["partner_standing"] else "") + " " + x["partner_type"])
        out.append({"world": e, "agent": a, "runs": len({x["run"] for x in evs}), "partner": who,
                    "contact": common(lambda x: x["contact"]),
                    "speed": (min(x["speed"] for x in evs), max(x["speed"] for x in evs)),
                    "partner_speed": (min(x["partner_speed"] for x in evs), max(x["partner_speed"] for x in evs)),
                    "steps": (min(x["step"] for x in evs), max(x["step"] for x in evs))})
    out.sort(key=lambda r: (-r["runs"], r["world"], r["agent"]))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policies", nargs="+", required=True, help="checkpoints, run directories or built-in names")
    p.add_argument("--scenes", required=True, help="a scene spec: a store, a folder of JSON files, procedural:...")
    p.add_argument("--num-scenes", type=int, default=None, help="procedural specs: how many (seed 90000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=90000) if args.num_scenes else resolve_scenes(args.scenes)
    scenes = [src.get(i) for i in range(len(src))]
    events, vehicles = [], Counter()
    runs = [(spec, seed) for spec in args.policies for seed in args.seeds]
    for spec, seed in tqdm(runs, desc="crash_anatomy", unit="run"):
        opened = open_policy(spec, scenes, args.device, collision_mode="ignore", seed=seed, option="--policies")
        tr = record_episodes(opened.sim, opened.policy, seed=seed)
        types = opened.sim.agent_type.cpu().numpy()
        vehicles[spec] = int(tr.policy.sum())
        events += [{**describe(tr, types, r), "run": (spec, seed)} for r in collision_partners(tr)]
    rows = group(events)
    print(f"\n{len(events)} first collisions over {len(runs)} runs ({', '.join(f'{Path(s).name}: {n} policy vehicles' for s, n in vehicles.items())} a run)\n")
    print("| world | scene | agent | runs with it | partner | contact | speed [m/s] | partner speed [m/s] | step |")
    print("|---:|---|---:|---:|---|---|---|---|---|")
    def rng(x, f="{:.1f}"):
        lo, hi = f.format(x[0]), f.format(x[1])
        return lo if lo == hi else f"{lo}-{hi}"
    for r in rows:
        print(f"| {r['world']} | {scenes[r['world']].scene_id} | {r['agent']} | {r['runs']} of {len(runs)} | {r['partner']} | "
              f"{r['contact']} | {rng(r['speed'])} | {rng(r['partner_speed'])} | {rng(r['steps'], '{}')} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
