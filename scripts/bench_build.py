"""Benchmark world building: seconds per phase to fill W worlds from a scene spec and build the engine.

Phases (one row per world count):

    load_s     resolve the spec and fetch one scene per world, cycling the first --num-scenes
               (what TGVectorEnv's `load_scenes` does); generated scenes are made here
    host_s     Model, host side: slot selection and masks (once per distinct scene and masks) and
               the per-world tables
    roads_s    Model: road segments and grids of the distinct scenes, one batched pass on the
               device (tg_gpudrive/engine/roads.py), their road points copied there included
    upload_s   Model: the distinct plans' logs and the per-world tables copied to the device
    expert_s   Model: expert actions of the distinct scenes (launch_expert_actions); worlds reach
               their scene's logs and expert actions through Model.log_row, nothing is copied per world
    build_s    the whole Simulator construction (Model, State, Control, torch views): what
               `tg-gpudrive benchmark` reports as build_s

`--pack DIR` first writes the spec's first --num-scenes scenes to a packed store at DIR (reused
when DIR already holds one; not timed), then builds from the store, as training from a store does.

    python3 scripts/bench_build.py --scenes procedural:dense --num-scenes 64 --set max_agents=128 \\
        --pack /tmp/dense64 --worlds 4096 16384 --device cuda --json
    python3 scripts/bench_build.py --scenes procedural:dense --num-scenes 4096 --set max_agents=128 \
        --pack /tmp/dense4096 --worlds 4096 --device cuda --json     # every world a distinct scene
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import warp as wp

from tg_gpudrive.benchmark import memory_row, print_row
from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.data.store import is_store, write_store
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.enums import ControlMode


def pack(spec: str, num_scenes: int, out: Path) -> float:
    """Write the first `num_scenes` scenes of `spec` to a store at `out` unless one is there; seconds taken."""
    if is_store(out):
        return 0.0
    t0 = time.perf_counter()
    src = resolve_scenes(spec, n=num_scenes)
    n = min(num_scenes, len(src))
    # generated sources make many scenes in worker processes at once (get_many); others read one by one
    scenes = src.get_many(range(n)) if hasattr(src, "get_many") else (src.get(i) for i in range(n))
    write_store(scenes, out, overwrite=True)
    return time.perf_counter() - t0


def build_once(spec: str, num_scenes: int, worlds: int, cfg: EngineConfig, device: str) -> dict:
    t0 = time.perf_counter()
    src = resolve_scenes(spec, n=num_scenes)
    n = min(num_scenes, len(src))
    scenes = [src.get(i % n) for i in range(worlds)]
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim = Simulator(scenes, cfg, device)
    wp.synchronize_device(sim.device)
    build_s = time.perf_counter() - t0
    m = sim.model
    row = {"worlds": worlds, "scenes": spec, "distinct_scenes": n, "device": sim.device,
           "max_agents": m.max_agents, "steps": m.num_steps, "segments": sum(m.report.segments), "segments_stored": m.seg_a.shape[0],
           "load_s": load_s, **{f"{k}_s": v for k, v in m.build_seconds.items()}, "build_s": build_s}
    return row | memory_row(sim)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="procedural:dense", help="scene spec (tg_gpudrive.data.sources)")
    p.add_argument("--num-scenes", type=int, default=64, help="distinct scenes, cycled over the worlds")
    p.add_argument("--worlds", type=int, nargs="+", default=[512, 2048])
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument("--pack", type=Path, default=None, help="build from a store of the scenes at this directory")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="engine config override")
    p.add_argument("--repeat", type=int, default=1, help="builds per world count (the fastest is kept)")
    p.add_argument("--json", action="store_true", help="one JSON object per row")
    args = p.parse_args()
    wp.config.quiet = True
    device = resolve_device(args.device, flag="--device")
    default = REPO_CONFIGS / "env" / "default.yaml"
    cfg = load_config(EngineConfig, default if default.exists() else None, args.set)
    cfg = dataclasses.replace(cfg, control=ControlMode.ALL_AGENTS)  # as `tg-gpudrive benchmark` builds
    spec = args.scenes
    if args.pack is not None:
        pack_s = pack(spec, args.num_scenes, args.pack)
        print(f"# store {args.pack} from {spec} ({pack_s:.1f} s to write)", file=sys.stderr)
        spec = str(args.pack)
    build_once(spec, args.num_scenes, 1, cfg, device)  # kernel modules load here, not in the rows
    for w in args.worlds:
        row = min((build_once(spec, args.num_scenes, w, cfg, device) for _ in range(args.repeat)),
                  key=lambda r: r["build_s"])
        print_row(row, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
