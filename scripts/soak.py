"""Soak: many resets and steps with random actions and collision modes switching; memory must stay flat.

    python scripts/soak.py --device cuda --worlds 256 --steps 1000000 --resets 10000
    python scripts/soak.py --device cpu --worlds 8 --steps 20000 --resets 2000     # a CPU-sized run

Every `--switch-every` steps the Simulator is rebuilt on the same scenes with the next collision
mode (ignore -> stop -> remove -> ...), which also exercises building and freeing the engine's
arrays; `sim.reset()` is called often enough to reach `--resets` explicit resets, on top of the
worlds' own auto-resets. Actions are random grid indices, with a share of unusable ones (out of
range) that the engine must count and survive. Host RSS and device memory (used = total - free, all
allocators) are read after one warm-up cycle of the three modes and at the end; the script prints
them and the growth in percent (the target is within 2 %). Numbers only; it never fails on them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time

import torch
from tqdm import tqdm

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator

MODES = ("ignore", "stop", "remove")
ACTION_BLOCK = 1000  # steps of random actions drawn at once: the loop stays one copy and one step per step


def random_actions(sim: Simulator, gen: torch.Generator, bad_share: float) -> torch.Tensor:
    """(ACTION_BLOCK, W, A) random grid indices on the engine's device, `bad_share` of them out of range."""
    dev = sim.actions_index.device
    shape = (ACTION_BLOCK, *sim.actions_index.shape)
    a = torch.randint(0, sim.num_actions, shape, generator=gen, dtype=torch.int32, device=dev)
    a[torch.rand(shape, generator=gen, device=dev) < bad_share] = sim.num_actions + 7
    return a


def host_rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # peak, where /proc is missing


def device_used_mb(device: str) -> float | None:
    if not device.startswith("cuda"):
        return None
    torch.cuda.synchronize(device)
    free, total = torch.cuda.mem_get_info(torch.device(device))
    return (total - free) / 2**20


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    p.add_argument("--scenes", default="procedural:all", help="scene spec (default: %(default)s)")
    p.add_argument("--worlds", type=int, default=64, help="worlds (default: %(default)s)")
    p.add_argument("--steps", type=int, default=1_000_000, help="sim.step() calls in all (default: %(default)s)")
    p.add_argument("--resets", type=int, default=10_000, help="explicit sim.reset() calls (default: %(default)s)")
    p.add_argument("--switch-every", type=int, default=5_000,
                   help="steps between collision-mode switches (rebuilds) (default: %(default)s)")
    p.add_argument("--bad-share", type=float, default=0.01, help="share of unusable actions (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="(default: %(default)s)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="stop early after this wall-clock time and report the steps done (default: no limit)")
    args = p.parse_args(argv)

    src = resolve_scenes(args.scenes, n=args.worlds, seed=args.seed)
    scenes = [src.get(i) for i in range(len(src))]
    base = EngineConfig(max_agents=32, partner_k=8, road_k=32)
    reset_every = max(1, args.steps // max(args.resets, 1))
    gen = None  # made on the engine's device once it exists: drawing actions there keeps the host out of the loop
    sim = block = None
    mode_i = -1
    start = None
    resets = bad_total = 0
    t0 = time.perf_counter()
    bar = tqdm(total=args.steps, desc="soak", unit="step", mininterval=2.0)
    steps_done = 0
    for step in range(args.steps):
        if args.max_seconds is not None and time.perf_counter() - t0 > args.max_seconds:
            break
        if step % args.switch_every == 0:
            if sim is not None:
                bad_total += sim.report()["bad_actions"]
            mode_i += 1
            if mode_i == len(MODES):  # one warm-up cycle of every mode: allocators and caches are full
                start = {"host_rss_mb": host_rss_mb(), "device_used_mb": device_used_mb(sim.device), "step": step}
            sim = None  # the old engine's arrays go before the new ones are made
            sim = Simulator(scenes, dataclasses.replace(base, collision_mode=MODES[mode_i % 3]), args.device)
            sim.reset()
            if gen is None:
                gen = torch.Generator(device=sim.actions_index.device).manual_seed(args.seed)
        if step % reset_every == 0:
            sim.reset()
            resets += 1
        if step % ACTION_BLOCK == 0 or block is None or block.shape[1:] != sim.actions_index.shape:
            block = random_actions(sim, gen, args.bad_share)
        sim.actions_index.copy_(block[step % ACTION_BLOCK])
        sim.step()
        steps_done += 1
        bar.update(1)
    bar.close()
    bad_total += sim.report()["bad_actions"]
    end = {"host_rss_mb": host_rss_mb(), "device_used_mb": device_used_mb(sim.device)}
    start = start or {"host_rss_mb": float("nan"), "device_used_mb": None, "step": None}
    growth = {k: (100 * (end[k] - start[k]) / start[k] if start[k] else None)
              for k in ("host_rss_mb", "device_used_mb") if end[k] is not None}
    print(json.dumps({"device": sim.device, "worlds": args.worlds, "steps": steps_done, "explicit_resets": resets,
                      "episodes_per_world": sim.episode_count.float().mean().item(),
                      "mode_switches": mode_i, "unusable_actions_counted": bad_total,
                      "seconds": time.perf_counter() - t0, "start": start, "end": end, "growth_pct": growth}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
