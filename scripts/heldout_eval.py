"""Held-out rates of trained policies per collision mode: goal, collision and off-road together.

    python scripts/heldout_eval.py --runs runs/cce runs/ppo --scenes procedural:all --seed 90000 \
        --num-scenes 1024 --modes ignore stop remove --device cuda [--out heldout.jsonl]

The scenes are generated (or read) once and every run is evaluated on the same worlds, one
episode per world, with its sampled policy driving the agents it was trained to drive (its
`control`: all vehicles, or e.g. the 5 nearest each conflict point, the others replaying logs;
`--control` overrides it); a built-in policy name (expert, constant, random) works in place of a run. Rates are episode-weighted over the policy's agents, as a user counts
them: a goal reached after leaving the road is not a goal (the engine does not count it). The
seed of procedural training runs is 0 with at most a few thousand scenes, so seed 90000 names
scenes no run has seen. Prints one JSON line per (run, mode) and a table; never fails on the
numbers. Runs whose training configs differ only in their seed (a grid cell's training seeds) are
also pooled into one row per cell and mode, episode-weighted.

`--own-scenes` evaluates each run on the first `--num-scenes` of the scenes it trained on (its
`scenes`, `num_scenes` and `seed`) instead, to set a run's training-scene rates beside its held-out
ones (a built-in policy plays the first run's); `--seed` then seeds only the sampling.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import time
from pathlib import Path

from tqdm import tqdm

from tg_gpudrive.agents import BUILTIN, check_specs, open_policy
from tg_gpudrive.checkpoint import checkpoint_path, load_checkpoint
from tg_gpudrive.cli import CONTROL_CHOICES, one_line_errors
from tg_gpudrive.config import TrainConfig, from_dict
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.rollout import run_rollout


def train_config(run: str, fallback: TrainConfig | None) -> TrainConfig:
    """The run's training config (its engine settings); a built-in policy takes the first run's."""
    if run in BUILTIN:
        if fallback is None:
            raise SystemExit("heldout_eval: give at least one trained run first (it sets the engine config)")
        return fallback
    ck = load_checkpoint(checkpoint_path(run, "--runs"), "--runs")
    return from_dict(TrainConfig, ck["config"], run)


NOT_RECIPE = ("seed", "out_dir", "device")  # what a grid's training seeds of one cell may differ in


def recipe_key(cfg: TrainConfig) -> str:
    """What a run was trained with, less its seed and where it ran: runs that share it are one cell's training
    seeds."""
    return json.dumps({k: v for k, v in dataclasses.asdict(cfg).items() if k not in NOT_RECIPE}, sort_keys=True,
                      default=str)


def pooled_rows(rows: list[dict], recipes: dict[str, str]) -> list[dict]:
    """One row per (recipe, mode) that more than one run shares: goal, collision and off-road weighted by
    each run's agent-episodes, named after the first run less its `_s<seed>` suffix (and its folder, where
    runs of another recipe share that name)."""
    def name(run: str) -> str:
        return re.sub(r"_s\d+$", "", Path(run).name)

    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((recipes[r["run"]], r["mode"]), []).append(r)
    pooled = []
    for (recipe, mode), rs in groups.items():
        if len(rs) < 2:
            continue
        n = sum(r["episodes"] for r in rs)
        cell = name(rs[0]["run"])
        if any(name(run) == cell and key != recipe for run, key in recipes.items()):
            cell = f"{Path(rs[0]['run']).parent.name}/{cell}"
        pooled.append({"cell": cell, "mode": mode, "runs": len(rs), "episodes": n,
                       **{k: sum(r[k] * r["episodes"] for r in rs) / max(n, 1)
                          for k in ("goal_rate", "collision_rate", "offroad_rate")}})
    return pooled


def load_scenes(spec: str, n: int, seed: int, first: int | None = None) -> list:
    """The first `first` (default all `n`) scenes of `spec` with procedural seeds from `seed`."""
    src = resolve_scenes(spec, n=n, seed=seed)
    count = len(src) if first is None else min(first, len(src))
    getter = getattr(src, "get_many", None)
    return getter(range(count)) if getter else [src.get(i) for i in range(count)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", required=True, help="run directories / checkpoints, or expert|constant|random")
    p.add_argument("--scenes", default="procedural:all")
    p.add_argument("--seed", type=int, default=90000, help="scene seed (procedural) and sampling seed")
    p.add_argument("--num-scenes", type=int, default=1024, help="worlds, one distinct scene each")
    p.add_argument("--modes", nargs="+", default=["ignore", "stop", "remove"])
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", default=None, help="also append the JSON lines here")
    p.add_argument("--control", default=None, choices=CONTROL_CHOICES,
                   help="the agents the policies drive (default: each run's own training control; the rest "
                        "replay their logs); vehicles compares runs trained on different controls")
    p.add_argument("--temperature", type=float, default=None,
                   help="the trained runs' acting temperature (default: each checkpoint's act_temperature)")
    p.add_argument("--guard", type=float, default=None, metavar="S",
                   help="the trained runs' safety guard horizon, s; 0: none (default: each checkpoint's act_guard_s)")
    p.add_argument("--own-scenes", action="store_true",
                   help="each run on the first --num-scenes of its own training scenes (not held out) in place of "
                        "--scenes")
    args = p.parse_args(argv)
    check_specs(args.runs, "--runs")  # a mistyped run fails before the scenes are built

    t0 = time.perf_counter()
    scenes = None if args.own_scenes else load_scenes(args.scenes, args.num_scenes, args.seed)
    if scenes is not None:
        print(f"{len(scenes)} scenes in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    base = None
    rows, recipes = [], {}
    for run in tqdm(args.runs, desc="heldout_eval", unit="run"):
        trained = train_config(run, base)
        base = base or trained
        recipes[run] = run if run in BUILTIN else recipe_key(trained)
        if args.own_scenes:
            spec = f"own: {trained.scenes} from seed {trained.seed}"
            scenes = load_scenes(trained.scenes, trained.num_scenes, trained.seed, args.num_scenes)
        else:
            spec = args.scenes
        for mode in args.modes:
            # a slot for every agent of the scenes; the agents the run was trained to drive (e.g. the 5
            # nearest each conflict point) or --control's, the rest replayed; a built-in policy drives
            # those of the first run, in its engine
            opened = open_policy(run, scenes, args.device, engine=base.env, collision_mode=mode,
                                 control=args.control or (base.control if run in BUILTIN else None),
                                 control_k=base.control_k if run in BUILTIN else None, seed=args.seed,
                                 temperature=args.temperature, guard_s=args.guard, option="--runs")
            sim = opened.sim
            # the same sampling draws for every run and mode
            out = run_rollout(sim, opened.policy, sim.episode_length, episodes_per_world=1, seed=args.seed)
            row = {"run": run, "mode": mode, "scenes": spec, "seed": args.seed, "worlds": len(scenes),
                   "temperature": opened.temperature, "guard_s": opened.guard_s,
                   "dropped_agents": sim.model.report.total_truncated,
                   **{k: out[k] for k in ("episodes", "goal_rate", "collision_rate", "offroad_rate", "mean_speed",
                                          "device")},
                   "per_type": {t: {k: round(v[k], 4) for k in ("episodes", "goal_rate", "collision_rate",
                                                                "offroad_rate")}
                                for t, v in out.get("per_type", {}).items()}}
            guard = getattr(opened.policy, "guard", None)
            if guard is not None:  # the share of the run's actions its safety guard replaced
                row["guard_replaced"] = round(guard.replaced_share, 5)
            if "kerb_stops" in out:  # agents whose goal lies at the kerb (procedural kerb_stops)
                row["kerb_stops"] = {k: round(out["kerb_stops"][k], 4) for k in ("episodes", "goal_rate",
                                                                               "collision_rate", "offroad_rate")}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(json.dumps(row) + "\n")
    print("\n| run | mode | agent-episodes | goal | collision | off-road |\n|---|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {Path(r['run']).name} | {r['mode']} | {r['episodes']} | {r['goal_rate']:.3f} | "
              f"{r['collision_rate']:.3f} | {r['offroad_rate']:.3f} |")
    pooled = pooled_rows(rows, recipes)
    if pooled:
        print("\nPooled over training seeds (runs trained alike but for the seed):\n"
              "| cell | mode | runs | agent-episodes | goal | collision | off-road |\n|---|---|---:|---:|---:|---:|---:|")
        for r in pooled:
            print(f"| {r['cell']} | {r['mode']} | {r['runs']} | {r['episodes']} | {r['goal_rate']:.3f} | "
                  f"{r['collision_rate']:.3f} | {r['offroad_rate']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("heldout_eval.py", main))
