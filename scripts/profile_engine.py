"""Per-kernel profile of the engine step on a GPU: which kernels cost what per step.

    python scripts/profile_engine.py --scenes procedural:all --worlds 4096
    python scripts/profile_engine.py --scenes procedural:dense --worlds 1024 --set max_agents=128

Steps are launched without the CUDA graph (so Warp's CUDA activity timer sees every kernel and
memset) after a warm-up, with `wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)`.
Prints one row per kernel: milliseconds per step, share of the step, launches per step; then the
sum of the kernels against the wall-clock step time with and without the graph (the difference is
launch overhead and gaps). `--json` prints one JSON object instead. Numbers only: nothing here
fails on them. Needs CUDA (Warp times only CUDA activity).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections import defaultdict

import torch
import warp as wp

from tg_gpudrive.config import ConfigError, EngineConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.agents.builtin import constant_policy


def wall_ms_per_step(sim: Simulator, steps: int) -> float:
    torch.cuda.synchronize(sim.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step()
    torch.cuda.synchronize(sim.device)
    return 1000 * (time.perf_counter() - t0) / steps


def profile(scenes, cfg: EngineConfig, device: str, worlds: int, steps: int, warmup: int = 5) -> dict:
    pool = [scenes[i % len(scenes)] for i in range(worlds)]
    out = {"worlds": worlds, "agents": cfg.max_agents, "steps": steps, "device": device,
           "gpu": torch.cuda.get_device_name(torch.device(device))}
    for graph in (True, False):
        sim = Simulator(pool, dataclasses.replace(cfg, use_graph=graph), device)
        sim.reset()
        constant_policy(sim)
        for _ in range(warmup):
            sim.step()
        out["ms_per_step_graph" if graph else "ms_per_step_plain"] = wall_ms_per_step(sim, steps)
    # `sim` is the plain one: every launch is visible to the activity timer
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)
    for _ in range(steps):
        sim.step()
    results = wp.timing_end()
    ms, calls = defaultdict(float), defaultdict(int)
    for r in results:
        name = r.name.replace("forward kernel ", "")
        ms[name] += r.elapsed
        calls[name] += 1
    total = sum(ms.values())
    out["kernels"] = [{"name": k, "ms_per_step": ms[k] / steps, "share": ms[k] / total if total else 0.0,
                       "launches_per_step": calls[k] / steps}
                      for k in sorted(ms, key=ms.get, reverse=True)]
    out["kernel_ms_per_step"] = total / steps
    out["slot_steps_per_s_graph"] = worlds * cfg.max_agents / (out["ms_per_step_graph"] / 1000)
    out["valid_agents"] = int(sim.slot_valid.sum())
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="procedural:all", help="scene spec (default: %(default)s)")
    p.add_argument("--num-scenes", type=int, default=64, help="distinct scenes, cycled (default: %(default)s)")
    p.add_argument("--worlds", type=int, nargs="+", default=[4096], help="world counts (default: %(default)s)")
    p.add_argument("--steps", type=int, default=20, help="steps timed (default: %(default)s)")
    p.add_argument("--config", default=None, help="engine YAML (default: configs/env/default.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="engine config override, e.g. --set max_agents=128 (default: none)")
    p.add_argument("--device", default="cuda", help="cuda or cuda:N (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--json", action="store_true", help="one JSON object per world count")
    args = p.parse_args(argv)
    try:
        device = resolve_device(args.device, flag="--device")
        if not device.startswith("cuda"):
            raise ValueError("--device: the per-kernel profile needs CUDA (Warp times only CUDA activity)")
        cfg = load_config(EngineConfig, args.config, args.set)
    except (ValueError, ConfigError) as e:
        print(f"profile_engine: {e}", file=sys.stderr)
        return 2
    cfg = dataclasses.replace(cfg, control="all_agents")  # as `tg-gpudrive benchmark`: every agent acts
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=args.seed)
    scenes = [src.get(i) for i in range(len(src))]
    for w in args.worlds:
        row = profile(scenes, cfg, device, w, args.steps)
        row["scenes"] = args.scenes
        if args.json:
            print(json.dumps(row), flush=True)
            continue
        print(f"{args.scenes}: {w} worlds x {cfg.max_agents} slots ({row['valid_agents']} agents), {row['gpu']}")
        print(f"  step {row['ms_per_step_graph']:.2f} ms with the CUDA graph, {row['ms_per_step_plain']:.2f} ms "
              f"plain; kernels {row['kernel_ms_per_step']:.2f} ms")
        for k in row["kernels"]:
            print(f"  {k['ms_per_step']:8.3f} ms  {100 * k['share']:5.1f} %  x{k['launches_per_step']:.0f}  {k['name']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
