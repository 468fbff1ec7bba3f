"""Engine throughput benchmark: agent steps per second for a grid of world counts.

Prints one JSON row per configuration. `agent_steps_per_s` counts every slot
(W x A) stepped with dynamics, collision, road queries, reward, cost and full
observations, as the engine issue defines it; `valid_agent_steps_per_s`
counts only slots that hold an agent, `controlled_agent_steps_per_s` the
policy-driven ones, so numbers can be compared with GPUDrive's honestly.
Scenes are a pool of distinct scenes cycled over the worlds (the engine's cost
does not depend on which copy a world holds). Memory: `gpu_mem_mb` is the memory
in use by Warp's pool and torch's allocator (CUDA; the road tables are torch tensors), `engine_mb_per_world` the engine's own arrays
(`Simulator.memory_bytes`, by group in `engine_kb_per_world`); worlds that share
a scene share its roads, logs and expert actions, so per-world memory falls
as `distinct_scenes` falls below the world count.
"""

from __future__ import annotations

import dataclasses
import json
import time

import torch
import warp as wp

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.agents.builtin import constant_policy
from tg_gpudrive.enums import ControlMode


def benchmark_one(scenes, worlds: int, cfg: EngineConfig, device: str, steps: int, warmup: int = 5) -> dict:
    pool = [scenes[i % len(scenes)] for i in range(worlds)]
    t_build = time.perf_counter()
    sim = Simulator(pool, cfg, device)
    build_s = time.perf_counter() - t_build
    sim.reset()
    constant_policy(sim)
    for _ in range(warmup):  # module load and graph capture happen here
        sim.step()
    if sim.is_cuda:
        torch.cuda.synchronize(sim.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step()
    if sim.is_cuda:
        torch.cuda.synchronize(sim.device)
    dt = time.perf_counter() - t0
    slots = worlds * cfg.max_agents
    row = {
        "worlds": worlds,
        "agents": cfg.max_agents,
        "device": sim.device,  # the resolved name ("auto" -> cpu / cuda:0)
        "graph": sim._graph is not None,
        "steps": steps,
        "agent_steps_per_s": slots * steps / dt,
        "valid_agent_steps_per_s": int(sim.slot_valid.sum()) * steps / dt,
        "controlled_agent_steps_per_s": int(sim.policy_agents.sum()) * steps / dt,
        "ms_per_step": 1000 * dt / steps,
        "obs_dim": sim.obs_dim,
        "build_s": build_s,
        "distinct_scenes": len({id(sc) for sc in pool}),
    }
    return row | memory_row(sim)


def memory_row(sim: Simulator) -> dict:
    """The engine's arrays per world (total MB, KB by group) and, on CUDA, the device memory in use
    by Warp's pool and torch's allocator (which holds the road tables)."""
    W = sim.num_worlds
    mem = sim.memory_bytes()
    row = {"engine_mb_per_world": sum(mem.values()) / W / 2**20,
           "engine_kb_per_world": {k: round(v / W / 1024, 1) for k, v in mem.items()}}
    if sim.is_cuda:
        row["gpu_mem_mb"] = (wp.get_mempool_used_mem_current(sim.device) + torch.cuda.memory_allocated(sim.device)) / 2**20
    return row


def run_benchmark(scenes, worlds_list, cfg: EngineConfig, device: str, steps: int):
    for w in worlds_list:
        try:
            yield benchmark_one(scenes, w, cfg, device, steps)
        except (RuntimeError, MemoryError) as e:  # out of device memory ends the sweep, says why
            yield {"worlds": w, "agents": cfg.max_agents, "device": device, "error": str(e).splitlines()[0]}
            return


def main(args) -> int:
    device = resolve_device(args.device, flag="--device")  # the rows name the device that ran
    cfg = dataclasses.replace(args.engine_config, control=ControlMode.ALL_AGENTS,
                              use_graph=not args.no_graph)
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=args.seed)
    scenes = [src.get(i) for i in range(min(len(src), args.num_scenes))]
    worlds = args.worlds or ([1, 64, 1024, 4096, 8192, 16384] if device.startswith("cuda")
                             else [1, 64, 256])
    for row in run_benchmark(scenes, worlds, cfg, device, args.steps):
        row["scenes"] = args.scenes
        print_row(row, args.json)
    return 0


def print_row(row: dict, as_json: bool) -> None:
    """One benchmark row on stdout: a JSON object, or key=value pairs (floats to 4 digits)."""
    if as_json:
        print(json.dumps(row), flush=True)
    else:
        print("  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
