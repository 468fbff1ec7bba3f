"""What the learned world model costs: training, driving, and its magnet inside CCE-MAPPO.

    python scripts/bench_world_model.py --device cuda --worlds 1024 --steps 50
    python scripts/bench_world_model.py --device cpu --threads 1 --worlds 8 --steps 5 --train-scenes 2 \\
        --train-steps 5 --batch 64 --updates 1 --set num_worlds=2 --set rollout_steps=8   # CPU smoke, < 1 min

Prints one JSON object (timings exclude warm-up calls; CUDA is synchronised around each):

    train      teacher-forced MLE minibatch steps (worldmodel.train.fit) on a dataset collected
               from --train-scenes scenes: samples/s at the config's batch size (or --batch)
    inference  WorldModelDriver driving every vehicle of --worlds worlds for --steps steps:
               agent-steps/s of driver + engine step, of the engine alone under expert replay,
               and the driver's seconds per step
    forward    the model's forward alone on --forward-rows random observation rows (partners and road
               points 60-70 % present, a full history), float32 and under bf16 autocast (CUDA only),
               as the magnet calls it: milliseconds per call
    prior      tg_gpudrive.learn.train.Trainer (configs/train/small_cpu.yaml + --set overrides),
               --updates timed updates (rollout + learn) after --warmup, with prior=expert and
               with prior=world_model, same config otherwise: seconds per update and the difference

The world model is the shipped one unless --model is given (or the world-model config asks for
the continuous action space, in which case an untrained model of that config is timed: weights
do not change the cost). Reports numbers, never fails on them.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from tg_gpudrive.config import TrainConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.history import HIST_DIM
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.learn.train import Trainer
from tg_gpudrive.worldmodel import WorldModelDriver, load_world_model
from tg_gpudrive.worldmodel.data import collect
from tg_gpudrive.worldmodel.prior import SHIPPED
from tg_gpudrive.worldmodel.train import WorldModelConfig, build_model, fit

CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # this checkout's (an installed package has none)


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def _model(cfg, path, device):
    if path:
        return load_world_model(path, device=device)
    if cfg.env.discrete:
        return load_world_model(SHIPPED, device=device)
    return build_model(cfg).to(device).eval()


def bench_train(cfg, args, device: str) -> dict:
    src = resolve_scenes(cfg.scenes, n=args.train_scenes, seed=cfg.seed)
    scenes = [src.get(i) for i in range(min(args.train_scenes, len(src)))]
    t0 = time.perf_counter()
    data = collect(scenes, cfg.env, history=cfg.history, max_partners=cfg.max_partners, max_roads=cfg.max_roads,
                   num_worlds=cfg.num_worlds, device=device)
    collect_s = time.perf_counter() - t0
    data = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in data.items()}
    model = build_model(cfg).to(device)
    batch = args.batch or cfg.batch_size
    gen = torch.Generator().manual_seed(0)
    opt = fit(model, data, steps=2, batch_size=batch, lr=cfg.lr, gen=gen)  # warm-up
    _sync(device)
    t0 = time.perf_counter()
    fit(model, data, steps=args.train_steps, batch_size=batch, lr=cfg.lr, gen=gen, opt=opt)
    _sync(device)
    dt = time.perf_counter() - t0
    used = min(batch, int(data["target"].shape[0]))
    return {"dataset_samples": int(data["target"].shape[0]), "collect_s": collect_s, "batch": used,
            "steps": args.train_steps, "samples_per_s": used * args.train_steps / dt,
            "s_per_step": dt / args.train_steps, "parameters": sum(p.numel() for p in model.parameters())}


@torch.no_grad()
def bench_inference(cfg, args, device: str) -> dict:
    src = resolve_scenes(args.scenes, n=args.pool, seed=0)
    pool = [src.get(i) for i in range(len(src))]
    scenes = [pool[i % len(pool)] for i in range(args.worlds)]
    sim = Simulator(scenes, cfg.env, device)
    sim.reset()
    model = _model(cfg, args.model, device)
    driver = WorldModelDriver(model, rows="controlled", seed=0)
    rows = sim.integrated != 0
    driven = torch.zeros((), dtype=torch.int64, device=sim.pos.device)

    def wm_step():
        nonlocal driven
        driven += (rows & (sim.present != 0)).sum()
        driver(sim)
        sim.step()

    def expert_step():
        sim.use_expert_actions()
        sim.step()

    out = {"worlds": args.worlds, "steps": args.steps, "agents_driven_per_step": int(rows.sum())}
    for name, fn in (("engine_expert", expert_step), ("world_model", wm_step)):
        fn(), fn()  # warm-up: kernel load, CUDA graph capture, history fill
        _sync(device)
        driven.zero_()
        t0 = time.perf_counter()
        for _ in range(args.steps):
            fn()
        _sync(device)
        dt = time.perf_counter() - t0
        n = int(driven) if name == "world_model" else int(rows.sum()) * args.steps
        out[name] = {"agent_steps_per_s": n / dt, "s_per_step": dt / args.steps}
    out["driver_s_per_step"] = out["world_model"]["s_per_step"] - out["engine_expert"]["s_per_step"]
    return out


@torch.no_grad()
def bench_forward(cfg, args, device: str) -> dict:
    model = _model(cfg, args.model, device)
    model.set_layout(cfg.env.partner_k, cfg.env.road_k)
    k, kr = cfg.env.partner_k, cfg.env.road_k
    gen = torch.Generator(device=device).manual_seed(0)
    out = {}
    for n in args.forward_rows:
        obs = torch.randn(n, EGO_DIM + k * PARTNER_DIM + kr * ROAD_DIM, device=device, generator=gen)
        flags = torch.rand(n, k + kr, device=device, generator=gen) < 0.65
        obs[:, EGO_DIM:EGO_DIM + k * PARTNER_DIM].view(n, k, PARTNER_DIM)[..., 0] = flags[:, :k].float()
        obs[:, EGO_DIM + k * PARTNER_DIM:].view(n, kr, ROAD_DIM)[..., 0] = flags[:, k:].float()
        hist = torch.randn(n, model.history, HIST_DIM, device=device, generator=gen)
        hist[..., -1] = 1.0
        for name, amp in (("float32", False), ("bf16", True)):
            if amp and not device.startswith("cuda"):
                continue
            with torch.autocast("cuda", dtype=torch.bfloat16, enabled=amp):
                for _ in range(3):
                    model(obs, hist)
                _sync(device)
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    model(obs, hist)
                _sync(device)
            out[f"{n}_{name}_ms"] = (time.perf_counter() - t0) / args.steps * 1e3
    return out


def bench_prior(args, device: str) -> dict:
    overrides = [f"device={device}", *args.set]
    out = {}
    for prior in ("expert", "world_model"):
        extra = [f"prior={prior}"] + ([f"prior_model={args.model}"] if prior == "world_model" and args.model else [])
        cfg = load_config(TrainConfig, args.train_config or CONFIGS / "train" / "small_cpu.yaml",
                          overrides + extra)
        with tempfile.TemporaryDirectory() as tmp:
            tr = Trainer(cfg, out_dir=tmp, progress=False)
            roll, learn = [], []
            for i in range(args.warmup + args.updates):
                _sync(device)
                t0 = time.perf_counter()
                buf, _ = tr.collect()
                _sync(device)
                t1 = time.perf_counter()
                tr.learn(buf)
                _sync(device)
                t2 = time.perf_counter()
                if i >= args.warmup:
                    roll.append(t1 - t0)
                    learn.append(t2 - t1)
        n = len(roll)
        out[prior] = {"s_per_update": (sum(roll) + sum(learn)) / n, "rollout_s": sum(roll) / n,
                      "learn_s": sum(learn) / n, "num_worlds": cfg.num_worlds, "rollout_steps": cfg.rollout_steps,
                      "action_space": cfg.env.action_space}
    e, w = out["expert"], out["world_model"]
    out["world_model_extra_s_per_update"] = w["s_per_update"] - e["s_per_update"]
    out["world_model_extra_rollout_s"] = w["rollout_s"] - e["rollout_s"]
    out["world_model_extra_learn_s"] = w["learn_s"] - e["learn_s"]
    out["updates_timed"] = args.updates
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--wm-config", default=None, help="world-model config (default configs/worldmodel/small_cpu.yaml)")
    ap.add_argument("--wm-set", action="append", default=[], metavar="KEY=VALUE", help="world-model config override")
    ap.add_argument("--model", default=None, help="world-model checkpoint (default: the shipped model)")
    ap.add_argument("--train-scenes", type=int, default=16, help="scenes collected for the training benchmark")
    ap.add_argument("--train-steps", type=int, default=20, help="timed minibatch steps")
    ap.add_argument("--batch", type=int, default=0, help="training batch (default: the config's batch_size)")
    ap.add_argument("--worlds", type=int, default=1024, help="worlds driven by the world model")
    ap.add_argument("--steps", type=int, default=50, help="timed steps of the inference benchmark")
    ap.add_argument("--scenes", default="procedural:all", help="scene spec of the inference benchmark")
    ap.add_argument("--pool", type=int, default=36, help="distinct scenes cycled over the worlds")
    ap.add_argument("--forward-rows", type=int, nargs="+", default=[4096],
                    help="rows of the forward benchmark (one timing per count)")
    ap.add_argument("--train-config", default=None, help="CCE-MAPPO config (default configs/train/small_cpu.yaml)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="CCE-MAPPO config override, e.g. --set num_worlds=1024 --set rollout_steps=32")
    ap.add_argument("--updates", type=int, default=3, help="timed CCE-MAPPO updates per prior")
    ap.add_argument("--warmup", type=int, default=1, help="untimed CCE-MAPPO updates first")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: train,inference,forward,prior")
    ap.add_argument("--threads", type=int, default=0,
                    help="torch CPU threads (0: torch's default; 1 avoids thread contention on a busy CPU)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    device = resolve_device(args.device)
    wm_cfg = load_config(WorldModelConfig, args.wm_config or CONFIGS / "worldmodel" / "small_cpu.yaml",
                         [f"device={args.device}", *args.wm_set])
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    res: dict = {"device": device, "gpu": torch.cuda.get_device_name(device) if device.startswith("cuda") else None,
                 "torch_threads": torch.get_num_threads(), "action_space": wm_cfg.env.action_space}
    t0 = time.perf_counter()
    if "train" not in skip:
        res["train"] = bench_train(wm_cfg, args, device)
    if "inference" not in skip:
        res["inference"] = bench_inference(wm_cfg, args, device)
    if "forward" not in skip:
        res["forward"] = bench_forward(wm_cfg, args, device)
    if "prior" not in skip:
        res["prior"] = bench_prior(args, device)
    res["wall_s"] = time.perf_counter() - t0
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
