"""Which situations make a policy's collisions on a scene set, and whether they recur.

    python scripts/crash_anatomy.py --policies shipped runs/x/checkpoint.pt --scenes <store> \
        --seeds 0 1 2 [--device cpu]

Every policy drives every scene once per sampling seed (a slot for every agent, the rest replaying
their logs, ignore mode). Each policy vehicle's first collision is described by evaluation/risk.py's
`collision_partners` (the nearest agent then, the contact in the vehicle's frame, both speeds), plus
the partner's type, its scene agent index (for `--approach`) and whether its log moves at all. The events are grouped by (world, vehicle) over
policies and seeds and printed as a markdown table, the most recurrent first: a row present in every run
is a trait of the scene that more sampling will not average away; the rate bar says how many such rows
a policy may keep.

`--approach WORLD:AGENT:PARTNER` (scene agent indices, repeatable) follows one pair instead, every 0.4 s up
to the agent's first collision: both speeds, the gap between their centres and whether the partner is
among the agent's observed partner rows. It tells a vehicle that never saw what it hit from one that saw
it and drove on.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

import torch
import warp as wp

from tg_gpudrive.agents import check_specs, open_policy
from tg_gpudrive.cli import one_line_errors
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.enums import AgentType
from tg_gpudrive.evaluation.episodes import record_episodes
from tg_gpudrive.evaluation.risk import collision_partners
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM

STANDING_M = 1.0  # m: a partner whose whole log moves less than this stands still


def describe(tr, types: np.ndarray, row: dict) -> dict:
    """One collision_partners row with the vehicle as its scene's agent index (slots differ between
    policies' worlds), the partner's type and whether it stands still."""
    e, b = row["episode"], row["partner"]
    path = tr.pos[e, b][tr.valid[e, b]]
    standing = len(path) == 0 or float(np.ptp(path, axis=0).max()) < STANDING_M
    return {**row, "agent": int(tr.slot_agent[e, row["agent"]]), "partner": int(tr.slot_agent[e, b]),
            "partner_type": AgentType(int(types[e, b])).name.lower(), "partner_standing": standing}


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
                    "partner_agent": common(lambda x: x["partner"]),
                    "contact": common(lambda x: x["contact"]),
                    "speed": (min(x["speed"] for x in evs), max(x["speed"] for x in evs)),
                    "partner_speed": (min(x["partner_speed"] for x in evs), max(x["partner_speed"] for x in evs)),
                    "steps": (min(x["step"] for x in evs), max(x["step"] for x in evs))})
    out.sort(key=lambda r: (-r["runs"], r["world"], r["agent"]))
    return out


def approach(sim, policy, seed: int, cases: list[tuple[int, int, int]]) -> dict[tuple, list[dict]]:
    """One episode of every world under `policy`: per (world, agent, partner) case (scene agent indices),
    a row per step up to the agent's first collision, with both speeds, the centres' gap, where the partner's
    centre lies in the agent's frame (ahead along its heading, and to its left) and whether the partner is one of
    the agent's observed partner rows."""
    W, A, K = sim.num_worlds, sim.max_agents, sim.cfg.partner_k
    slot_agent = np.asarray(sim.model.slot_agent)
    slots = {}
    for w, a, b in cases:
        if not 0 <= w < W:
            raise SystemExit(f"--approach {w}:{a}:{b}: no world {w} (the scenes give {W})")
        have = [int(np.flatnonzero(slot_agent[w] == x)[0]) if (slot_agent[w] == x).any() else None for x in (a, b)]
        if None in have:
            raise SystemExit(f"--approach {w}:{a}:{b}: agent {(a, b)[have.index(None)]} has no slot in world {w}")
        slots[(w, a, b)] = have
    # only the followed agents' rows come to the host each step, not the worlds' whole state
    dev = sim.pos.device
    ws = torch.tensor([w for w, _, _ in slots], device=dev)
    sa_, sb_ = (torch.tensor([s[k] for s in slots.values()], device=dev) for k in (0, 1))
    part_rows = slice(EGO_DIM, EGO_DIM + K * PARTNER_DIM)
    torch.manual_seed(seed)
    sim.reset()
    out: dict[tuple, list[dict]] = {c: [] for c in cases}
    for step in range(sim.episode_length):
        rel = sim.pos[ws, sb_] - sim.pos[ws, sa_]
        gap = rel.norm(dim=-1).cpu().numpy()
        cos, sin = torch.cos(sim.yaw[ws, sa_]), torch.sin(sim.yaw[ws, sa_])
        ahead = (rel[:, 0] * cos + rel[:, 1] * sin).cpu().numpy()
        left = (rel[:, 1] * cos - rel[:, 0] * sin).cpu().numpy()
        speed_a, speed_b = sim.speed[ws, sa_].cpu().numpy(), sim.speed[ws, sb_].cpu().numpy()
        collided = (sim.collided[ws, sa_] != 0).cpu().numpy()
        part_j = wp.to_torch(sim.state.part_j).view(W, A, K)[ws, sa_].cpu().numpy()
        present = (sim.obs[ws, sa_, part_rows].reshape(len(ws), K, PARTNER_DIM)[..., 0] > 0.5).cpu().numpy()
        for n, ((w, a, b), (_, sb)) in enumerate(slots.items()):
            rows = out[(w, a, b)]
            if rows and rows[-1]["collided"]:
                continue
            seen = {int(j) - w * A for j in part_j[n][present[n]]}
            rows.append({"step": step, "speed": float(speed_a[n]), "partner_speed": float(speed_b[n]),
                         "gap": float(gap[n]), "ahead": float(ahead[n]), "left": float(left[n]), "seen": sb in seen,
                         "collided": bool(collided[n]) and step > 0})
        policy(sim)
        sim.step()
    return out


def print_approach(name: str, seed: int, case: tuple, rows: list[dict], every: int = 4) -> None:
    w, a, b = case
    hit = next((r["step"] for r in rows if r["collided"]), None)
    print(f"\n{name}, seed {seed}, world {w}: agent {a} and agent {b}"
          f" ({'first collision at step ' + str(hit) if hit is not None else 'no collision'})\n")
    print("| step | speed [m/s] | partner speed [m/s] | gap [m] | partner ahead / left [m] | partner observed |")
    print("|---:|---:|---:|---:|---:|---|")
    for r in rows[::every] + ([rows[-1]] if (len(rows) - 1) % every else []):
        print(f"| {r['step']} | {r['speed']:.1f} | {r['partner_speed']:.1f} | {r['gap']:.1f} | "
              f"{r['ahead']:.1f} / {r['left']:.1f} | {'yes' if r['seen'] else 'no'} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policies", nargs="+", required=True, help="checkpoints, run directories or built-in names")
    p.add_argument("--scenes", required=True, help="a scene spec: a store, a folder of JSON files, procedural:...")
    p.add_argument("--num-scenes", type=int, default=None, help="procedural specs: how many (seed 90000)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--device", default="cpu")
    p.add_argument("--approach", action="append", default=[], metavar="WORLD:AGENT:PARTNER",
                   help="follow this pair (scene agent indices) instead of tabling the collisions")
    args = p.parse_args(argv)
    check_specs(args.policies, "--policies")  # a mistyped run fails before the scenes are built
    try:
        cases = [tuple(int(x) for x in c.split(":")) for c in args.approach]
    except ValueError:
        cases = [()]
    if any(len(c) != 3 for c in cases):
        p.error("--approach takes WORLD:AGENT:PARTNER, three integers")
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=90000) if args.num_scenes else resolve_scenes(args.scenes)
    scenes = [src.get(i) for i in range(len(src))]
    events, vehicles = [], Counter()
    runs = [(spec, seed) for spec in args.policies for seed in args.seeds]
    for spec, seed in tqdm(runs, desc="crash_anatomy", unit="run"):
        opened = open_policy(spec, scenes, args.device, collision_mode="ignore", seed=seed, option="--policies")
        if cases:
            for case, rows in approach(opened.sim, opened.policy, seed, cases).items():
                print_approach(Path(spec).name, seed, case, rows)
            continue
        tr = record_episodes(opened.sim, opened.policy, seed=seed)
        types = opened.sim.agent_type.cpu().numpy()
        vehicles[spec] = int(tr.policy.sum())
        events += [{**describe(tr, types, r), "run": (spec, seed)} for r in collision_partners(tr)]
    if cases:
        return 0
    rows = group(events)
    print(f"\n{len(events)} first collisions over {len(runs)} runs ({', '.join(f'{Path(s).name}: {n} policy vehicles' for s, n in vehicles.items())} a run)\n")
    print("| world | scene | agent | runs with it | partner (agent) | contact | speed [m/s] | partner speed [m/s] | step |")
    print("|---:|---|---:|---:|---|---|---|---|---|")
    def rng(x, f="{:.1f}"):
        lo, hi = f.format(x[0]), f.format(x[1])
        return lo if lo == hi else f"{lo}-{hi}"
    for r in rows:
        print(f"| {r['world']} | {scenes[r['world']].scene_id} | {r['agent']} | {r['runs']} of {len(runs)} | "
              f"{r['partner']} ({r['partner_agent']}) | "
              f"{r['contact']} | {rng(r['speed'])} | {rng(r['partner_speed'])} | {rng(r['steps'], '{}')} |")
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("crash_anatomy.py", main))
