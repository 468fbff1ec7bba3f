"""World models as traffic: every vehicle of held-out scenes driven closed loop by a world model.

    python scripts/wm_traffic.py --models shipped runs/wm_gpu/model.pt runs/wm_cont/model.pt:0.1 \\
        --scenes procedural:all --seed 90000 --num-scenes 256 --device cuda --seeds 0 1 [--json]

Each `--models` entry is a world-model checkpoint (or a packaged name: `shipped`, `small_cpu`), or `idm` (reactive
log replay, agents/idm.py, on the discrete grid of --set's engine), optionally `:T` for the driver's
sampling temperature (`:0` greedy; default: WorldModelDriver's, 1 discrete / 0.1 continuous). The
scenes are generated for the model's action space and `env` (max_agents, partner_k, road_k from
the checkpoint's training config when it has one, else --set). Prints one row per model and seed
(collision and off-road rates of the vehicles it drives: `metrics.background_rates`) and the
expert replay's row; the target is a model within 0.02 of the replay on both.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch
from tqdm import tqdm

from tg_gpudrive.agents.idm import IDMDriver
from tg_gpudrive.config import EngineConfig, apply_overrides, from_dict
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import resolve_device
from tg_gpudrive.worldmodel import WorldModelDriver, load_world_model
from tg_gpudrive.worldmodel.metrics import background_rates
from tg_gpudrive.worldmodel.prior import world_model_file


def _env_of(path: str, overrides: list[str]) -> EngineConfig:
    ck = torch.load(path, map_location="cpu", weights_only=False)
    data = dict(((ck.get("config") or {}).get("env") or {}))
    return from_dict(EngineConfig, apply_overrides(data, overrides), path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["shipped"])
    p.add_argument("--scenes", default="procedural:all")
    p.add_argument("--seed", type=int, default=90000, help="scene seed (default 90000: never trained on)")
    p.add_argument("--num-scenes", type=int, default=256)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="driver sampling seeds")
    p.add_argument("--batch", type=int, default=256, help="scenes simulated at once")
    p.add_argument("--device", default="auto")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="engine config overrides")
    p.add_argument("--guard", type=float, default=0.0, metavar="S",
                   help="discrete world models: act behind the safety guard looking S seconds ahead (agents/guard.py)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    device = resolve_device(args.device, flag="--device")
    replayed = set()  # (action space, env) pairs whose expert replay is printed
    for spec in args.models:
        path, _, temp = spec.partition(":")
        if path == "idm":
            model, env = None, from_dict(EngineConfig, apply_overrides({}, args.set), "--set")
        else:
            path = str(world_model_file(path))  # _env_of reads the checkpoint's training config
            env = _env_of(path, args.set)
            model = load_world_model(path, device=device)
            # the checkpoint decides the action space; scenes and replay are per action space and env
            env = dataclasses.replace(env, action_space=model.action_space)
        src = resolve_scenes(args.scenes, n=args.num_scenes, seed=args.seed)
        scenes = [src.get(i) for i in range(min(args.num_scenes, len(src)))]
        batches = [scenes[b:b + args.batch] for b in range(0, len(scenes), args.batch)]

        def run(make_driver, label, seed):
            t0 = time.perf_counter()
            tot = {"vehicles": 0, "coll": 0.0, "off": 0.0}
            for chunk in tqdm(batches, desc=label, leave=False):
                r = background_rates(make_driver(), chunk, env, device=device)
                tot["vehicles"] += r["vehicles"]
                tot["coll"] += r["collision_rate"] * r["vehicles"]
                tot["off"] += r["offroad_rate"] * r["vehicles"]
            n = max(tot["vehicles"], 1)
            r = {"model": label, "seed": seed, "action_space": env.action_space, "vehicles": tot["vehicles"],
                 "collision_rate": tot["coll"] / n, "offroad_rate": tot["off"] / n,
                 "seconds": time.perf_counter() - t0}
            print(json.dumps(r) if args.json else
                  f"{label:<48} seed {seed!s:<5} vehicles {r['vehicles']:>6}  collision "
                  f"{r['collision_rate']:.3f}  off-road {r['offroad_rate']:.3f}  ({r['seconds']:.0f} s)", flush=True)

        key = (env.action_space, env.max_agents, env.partner_k, env.road_k)
        if key not in replayed:
            replayed.add(key)
            run(lambda: None, f"expert replay ({env.action_space})", None)
        if model is None:  # deterministic: one run
            run(lambda: IDMDriver(rows="background"), spec, None)
            continue
        kw = {} if temp == "" else {"temperature": float(temp)}
        for seed in args.seeds:
            run(lambda: WorldModelDriver(model, rows="background", seed=seed, guard_s=args.guard, **kw),
                spec + (f" guard {args.guard:g} s" if args.guard else ""), seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
