"""Cost of the gymnasium vector env over the raw engine, and seconds per rendered frame.

    python scripts/bench_envs.py --device cuda --worlds 1024 --steps 100

Both loops apply the same random discrete actions written on the device; the
vector env adds its masks, info dict and action checks. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.envs.vector import TGVectorEnv
from tg_gpudrive.render import EpisodeRecorder
from tg_gpudrive.agents.builtin import expert_policy


def timed(fn, steps: int, device: str) -> float:
    fn()  # warm-up (module load, graph capture)
    fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--worlds", type=int, default=64)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--scenes", default="procedural:all")
    ap.add_argument("--num-scenes", type=int, default=36)
    ap.add_argument("--frames", type=int, default=20)
    args = ap.parse_args()

    src = resolve_scenes(args.scenes, n=args.num_scenes)
    pool = [src.get(i) for i in range(len(src))]
    scenes = [pool[i % len(pool)] for i in range(args.worlds)]
    cfg = EngineConfig(max_agents=32)
    dev = args.device
    gen = torch.Generator(device=dev).manual_seed(0)

    sim = Simulator(scenes, cfg, dev)
    sim.reset()
    n_ctrl = int(sim.policy_agents.sum())

    def raw_step():
        sim.actions_index.copy_(torch.randint(0, 91, sim.actions_index.shape, generator=gen, device=dev,
                                              dtype=torch.int32))
        sim.step()

    env = TGVectorEnv(scenes, config=cfg, device=dev)
    env.reset(seed=0)

    def env_step():
        a = torch.randint(0, 91, (env.num_envs,), generator=gen, device=dev, dtype=torch.int32)
        env.step(a)

    t_raw = timed(raw_step, args.steps, dev)
    t_env = timed(env_step, args.steps, dev)

    rsim = Simulator(pool[:1], cfg, "cpu")
    rsim.reset()
    rec = EpisodeRecorder(rsim, size=(640, 640))
    t0 = time.perf_counter()
    for _ in range(args.frames):
        expert_policy(rsim)
        rsim.step()
        rec.capture()
    per_frame = (time.perf_counter() - t0) / args.frames
    print(json.dumps({
        "device": dev, "worlds": args.worlds, "agents": cfg.max_agents, "controlled": n_ctrl,
        "raw_controlled_agent_steps_per_s": n_ctrl * args.steps / t_raw,
        "env_controlled_agent_steps_per_s": n_ctrl * args.steps / t_env,
        "wrapper_overhead": t_env / t_raw - 1.0,
        "render_s_per_frame_640": per_frame,
    }))


if __name__ == "__main__":
    main()
