"""Training and evaluation of the world model: `tg-gpudrive train-world-model --config ...`.

Maximum likelihood on the logged expert actions, teacher-forced: every scene
is driven by its closed-loop inverse-dynamics expert (`sim.use_expert_actions`)
and, at each step, every active controlled vehicle with an expert action
(`sim.expert_index >= 0`) gives one sample (observation row, history window,
expert grid index). The first `num_scenes` scenes of the source train, the
next `val_scenes` are held out. The samples are collected once (the engine is
deterministic, so a resumed run collects the same ones) and minibatches of
cross-entropy follow, with a tqdm bar, metrics.csv, an atomic checkpoint.pt
(weights, optimiser, RNG, step) and `--resume`. The run's `model.pt` is what
`load_world_model` reads.

Shipped model: `python -m tg_gpudrive.worldmodel.train --config configs/worldmodel/small_cpu.yaml
--out runs/wm_small && cp runs/wm_small/model.pt tg_gpudrive/worldmodel/shipped.pt`.

On a WOMD store, set `scenes: <store dir>` (made with `tg-gpudrive convert`), raise
`env.max_agents` to 128, `num_scenes` to what fits in memory (a sample is about
1.5 kB with the default `max_partners` / `max_roads`) and train on the GPU (`device: cuda`).

Left out: closed-loop fine-tuning (rolling out the model's own actions needs
expert targets from the simulated, not the logged, state: a per-step inverse
towards the log that the engine does not expose yet), and the continuous
(mixture of Laplace) head.

Evaluation helpers used by the tests and for the figures of the report:
`dataset_nll`, `baseline_nlls`, `sampled_displacement` (minADE / minFDE over
sampled rollouts) and `background_rates` (closed-loop collision / off-road).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import random
import sys
import time
from pathlib import Path

import numpy as np
import torch

from tg_gpudrive.config import ConfigError, EngineConfig, apply_overrides, from_dict, load_yaml, to_dict
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.worldmodel.model import HistoryBuffer, WorldModel, require_discrete
from tg_gpudrive.worldmodel.prior import WorldModelDriver, save_world_model


@dataclasses.dataclass(frozen=True)
class WorldModelConfig:
    """A world-model training run. YAML files live in configs/worldmodel/."""

    env: EngineConfig = EngineConfig()
    scenes: str = "procedural:all"  # scene spec (tg_gpudrive.data.sources)
    num_scenes: int = 96  # training scenes: source indices [0, num_scenes)
    val_scenes: int = 12  # held out: the next val_scenes indices
    num_worlds: int = 16  # worlds simulated at once while collecting
    device: str = "cpu"
    seed: int = 0
    # model
    hidden: int = 64
    heads: int = 4
    history: int = 10  # steps of the temporal window (1 s at 10 Hz)
    max_partners: int = 8  # nearest partner rows read
    max_roads: int = 32  # nearest road rows read
    # optimisation
    steps: int = 2000  # minibatch steps
    batch_size: int = 512
    lr: float = 2e-3
    weight_decay: float = 1e-4
    label_smoothing: float = 0.0
    # bookkeeping
    log_every: int = 100
    checkpoint_every: int = 500
    out_dir: str = "runs/worldmodel"

    def __post_init__(self):
        require_discrete(self.env)
        if min(self.num_scenes, self.num_worlds, self.steps, self.batch_size, self.history) < 1:
            raise ConfigError("num_scenes, num_worlds, steps, batch_size and history must be >= 1")
        if self.val_scenes < 0:
            raise ConfigError("val_scenes must be >= 0")


# -------------------------------------------------------------- collection
def _truncate_obs(obs: torch.Tensor, k: int, kr: int, kp: int, krr: int) -> torch.Tensor:
    """Observation rows with only the nearest kp partner / krr road rows (layout (kp, krr))."""
    ego = obs[..., :EGO_DIM]
    part = obs[..., EGO_DIM:EGO_DIM + k * PARTNER_DIM][..., :kp * PARTNER_DIM]
    road = obs[..., EGO_DIM + k * PARTNER_DIM:][..., :krr * ROAD_DIM]
    return torch.cat([ego, part, road], dim=-1)


@torch.no_grad()
def collect(scenes, env: EngineConfig, *, history: int, max_partners: int, max_roads: int,
            num_worlds: int = 16, device: str = "cpu") -> dict:
    """Teacher-forced samples of `scenes`, on the host: obs (N, D), hist (N, H, 7), target (N,),
    expert (N, 4) (ExpertPrior context, for the oracle bound), layout (partner_k, road_k) of obs."""
    from tg_gpudrive.learn.prior import ExpertPrior
    from tg_gpudrive.simulator import Simulator

    require_discrete(env)
    kp, krr = min(env.partner_k, max_partners), min(env.road_k, max_roads)
    out = {"obs": [], "hist": [], "target": [], "expert": []}
    for b in range(0, len(scenes), num_worlds):
        sim = Simulator(scenes[b:b + num_worlds], env, device)
        sim.reset()
        hb = HistoryBuffer(history)
        prior = ExpertPrior(sim)
        A = sim.max_agents
        for _ in range(sim.episode_length):
            hb.sync(sim)
            t = sim.world_step.long().view(-1, 1, 1).expand(-1, A, 1)
            target = torch.gather(sim.expert_index, 2, t)[..., 0]
            rows = (sim.active != 0) & (sim.background == 0) & (target >= 0)
            w, a = rows.nonzero(as_tuple=True)
            out["obs"].append(_truncate_obs(sim.obs[w, a], env.partner_k, env.road_k, kp, krr).cpu())
            out["hist"].append(hb.features(sim)[w, a].cpu())
            out["target"].append(target[w, a].long().cpu())
            out["expert"].append(prior.context(sim, A)[w, a].cpu())
            sim.use_expert_actions()
            sim.step()
    data = {k: torch.cat(v) for k, v in out.items()}
    data["layout"] = (kp, krr)
    return data


def load_scene_split(cfg: WorldModelConfig) -> tuple[list, list]:
    from tg_gpudrive.data.sources import resolve_scenes

    src = resolve_scenes(cfg.scenes, n=cfg.num_scenes + cfg.val_scenes, seed=cfg.seed)
    n = len(src)
    if n <= cfg.val_scenes:
        raise ConfigError(f"scenes {cfg.scenes!r}: {n} scenes, need more than val_scenes={cfg.val_scenes}")
    n_train = min(cfg.num_scenes, n - cfg.val_scenes)
    get = getattr(src, "get_many", None)
    scenes = get(list(range(n_train + cfg.val_scenes))) if get else [src.get(i) for i in range(n)]
    return scenes[:n_train], scenes[n_train:n_train + cfg.val_scenes]


# -------------------------------------------------------------- evaluation
@torch.no_grad()
def dataset_nll(model: WorldModel, data: dict, batch: int = 4096) -> dict:
    """Mean negative log-likelihood (nats) and top-1 accuracy of the expert actions."""
    model.eval()
    model.set_layout(*data["layout"])
    dev = next(model.parameters()).device
    nll, hit, n = 0.0, 0, data["target"].shape[0]
    for s in range(0, n, batch):
        logits = model(data["obs"][s:s + batch].to(dev), data["hist"][s:s + batch].to(dev))
        y = data["target"][s:s + batch].to(dev)
        nll += float(torch.nn.functional.cross_entropy(logits, y, reduction="sum"))
        hit += int((logits.argmax(-1) == y).sum())
    return {"nll": nll / max(n, 1), "accuracy": hit / max(n, 1)}


def _grid(env: EngineConfig) -> torch.Tensor:
    a = torch.linspace(-env.max_accel, env.max_accel, env.accel_bins)
    k = torch.linspace(-env.max_curvature, env.max_curvature, env.curvature_bins)
    return torch.stack(torch.meshgrid(a, k, indexing="ij"), -1).reshape(-1, 2)


def baseline_nlls(data: dict, env: EngineConfig, train: dict | None = None) -> dict:
    """NLL of the baselines on `data`:

    uniform            log(num_actions)
    constant_velocity  a discretised Gaussian centred on the no-op (a = 0, kappa = 0); its widths
                       are the best of a small sweep on `data` itself (a generous baseline)
    marginal           the action frequencies of `train` (add-one smoothed), when given
    expert_oracle      ExpertPrior (centred on the true logged action: an oracle bound, not a rival)"""
    from tg_gpudrive.learn.prior import ExpertPrior

    y = data["target"]
    grid = _grid(env)
    out = {"uniform": math.log(env.num_actions)}
    best = float("inf")
    for sa in (0.5, 1.0, 2.0, 4.0):
        for sk in (0.01, 0.03, 0.1):
            logits = -0.5 * (((grid) / torch.tensor([sa, sk])) ** 2).sum(-1)
            lp = torch.log_softmax(logits, -1)
            best = min(best, float(-lp[y].mean()))
    out["constant_velocity"] = best
    if train is not None:
        counts = torch.bincount(train["target"], minlength=env.num_actions).float() + 1.0
        out["marginal"] = float(-torch.log(counts / counts.sum())[y].mean())
    prior = ExpertPrior.__new__(ExpertPrior)  # its distribution only needs the grid and the widths
    prior.discrete, prior.bicycle, prior.grid = True, True, grid
    prior.sigma = torch.tensor([0.7, 0.01, 0.1])
    lp = torch.log_softmax(prior.distribution(data["expert"]), -1)
    out["expert_oracle"] = float(-lp.gather(-1, y[:, None]).mean())
    return out


def _eval_env(env: EngineConfig) -> EngineConfig:
    # agents keep driving after their goal and through contacts, so every track has the full horizon
    return dataclasses.replace(env, goal_behaviour="continue", collision_mode="ignore")


@torch.no_grad()
def sampled_displacement(policy_factory, scenes, env: EngineConfig, *, samples: int = 6, horizon: int = 60,
                         device: str = "cpu") -> dict:
    """minADE / minFDE (m) over `samples` rollouts of `horizon` steps from init_step, every controlled
    vehicle driven by `policy_factory()` (a fresh `policy(sim)`), against the logged positions.
    ADE averages the steps where the log is valid; FDE counts agents valid at the horizon."""
    import warp as wp

    from tg_gpudrive.simulator import Simulator

    env = _eval_env(env)
    S, n = samples, len(scenes)
    sim = Simulator([sc for sc in scenes for _ in range(S)], env, device)  # world = scene * S + sample
    sim.reset()
    W, A, T = sim.num_worlds, sim.max_agents, sim.model.num_steps
    log_pos = wp.to_torch(sim.model.log_pos).view(W, A, T, 2)
    log_valid = wp.to_torch(sim.model.log_valid).view(W, A, T) != 0
    ctrl = sim.policy_agents.clone()
    err_sum = torch.zeros(W, A, device=sim.pos.device)
    err_n = torch.zeros(W, A, device=sim.pos.device)
    policy = policy_factory()
    start = sim.world_step.long().clone()
    horizon = min(horizon, int(T - 1 - start.max()))
    for _ in range(horizon):
        policy(sim)
        sim.step()
        t = sim.world_step.long().view(W, 1, 1).expand(W, A, 1)
        lp = torch.gather(log_pos, 2, t[..., None].expand(W, A, 1, 2))[:, :, 0]
        v = torch.gather(log_valid, 2, t)[..., 0] & ctrl
        e = (sim.pos - lp).norm(dim=-1)
        err_sum += e * v
        err_n += v
    fde_ok = v
    ade = (err_sum / err_n.clamp(min=1)).view(n, S, A)
    fde = e.view(n, S, A)
    ok = (err_n > 0).view(n, S, A)[:, 0]
    fok = fde_ok.view(n, S, A)[:, 0]
    return {"minADE": float(ade.min(1).values[ok].mean()), "minFDE": float(fde.min(1).values[fok].mean()),
            "agents": int(ok.sum()), "horizon_steps": horizon, "samples": S}


@torch.no_grad()
def background_rates(driver, scenes, env: EngineConfig, *, steps: int | None = None, device: str = "cpu") -> dict:
    """Every eligible vehicle is a background vehicle driven by `driver(sim)` (or by the expert
    replay when driver is None) for one episode; rates of those that ever collide / go off-road."""
    from tg_gpudrive.control import control_masks
    from tg_gpudrive.simulator import Simulator

    env = _eval_env(env)
    bg = control_masks(scenes, env, "vehicles")
    sim = Simulator(scenes, env, device, controlled=[np.zeros_like(m) for m in bg], background=bg)
    sim.reset()
    rows = sim.background != 0
    coll = torch.zeros_like(rows)
    off = torch.zeros_like(rows)
    for _ in range(steps or sim.episode_length - 1):
        if driver is None:
            sim.use_expert_actions()
        else:
            driver(sim)
        sim.step()
        coll |= sim.collided != 0
        off |= sim.offroad != 0
    n = int(rows.sum())
    return {"vehicles": n, "collision_rate": float((coll & rows).sum()) / max(n, 1),
            "offroad_rate": float((off & rows).sum()) / max(n, 1)}


def model_policy_factory(model: WorldModel, seed: int = 0):
    counter = iter(range(10**9))
    return lambda: WorldModelDriver(model, rows="policy", seed=seed + next(counter))


# ---------------------------------------------------------------- training
def build_model(cfg: WorldModelConfig) -> WorldModel:
    return WorldModel(num_actions=cfg.env.num_actions, hidden=cfg.hidden, heads=cfg.heads, history=cfg.history,
                      max_partners=cfg.max_partners, max_roads=cfg.max_roads,
                      partner_k=min(cfg.env.partner_k, cfg.max_partners), road_k=min(cfg.env.road_k, cfg.max_roads))


def fit(model: WorldModel, data: dict, *, steps: int, batch_size: int, lr: float, weight_decay: float = 0.0,
        label_smoothing: float = 0.0, gen: torch.Generator | None = None, opt=None, start: int = 0,
        on_step=None) -> torch.optim.Optimizer:
    """Minibatch cross-entropy steps [start, steps) on `data`; `on_step(step, loss)` after each."""
    dev = next(model.parameters()).device
    model.set_layout(*data["layout"])
    opt = opt or torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    n = data["target"].shape[0]
    for step in range(start, steps):
        for g in opt.param_groups:  # cosine decay to lr / 20
            g["lr"] = lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * step / steps)))
        model.train()
        idx = torch.randint(0, n, (min(batch_size, n),), generator=gen)
        logits = model(data["obs"][idx].to(dev), data["hist"][idx].to(dev))
        loss = torch.nn.functional.cross_entropy(logits, data["target"][idx].to(dev), label_smoothing=label_smoothing)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if on_step is not None:
            on_step(step + 1, float(loss.detach()))
    return opt


def train_world_model(cfg: WorldModelConfig, out_dir: str | Path | None = None, resume: str | Path | None = None,
                      progress: bool = True) -> dict:
    """Collect, fit, log, checkpoint; returns the last metrics with `out_dir` and `model` paths."""
    out = Path(out_dir or resume or cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = "cuda:0" if cfg.device == "cuda" else cfg.device
    random.seed(cfg.seed), np.random.seed(cfg.seed), torch.manual_seed(cfg.seed)
    ck = None
    if resume is not None:
        path = Path(resume)
        path = path / "checkpoint.pt" if path.is_dir() else path
        if not path.exists():
            raise FileNotFoundError(f"--resume: no checkpoint at {path}")
        ck = torch.load(path, map_location="cpu", weights_only=False)
    t0 = time.perf_counter()
    train_scenes, val_scenes = load_scene_split(cfg)
    kw = dict(history=cfg.history, max_partners=cfg.max_partners, max_roads=cfg.max_roads,
              num_worlds=cfg.num_worlds, device=device)
    data = collect(train_scenes, cfg.env, **kw)
    val = collect(val_scenes, cfg.env, **kw) if val_scenes else None
    collect_s = time.perf_counter() - t0
    model = build_model(cfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(cfg.seed)
    step0, wall = 0, 0.0
    if ck is not None:
        model.load_state_dict(ck["model"]["state_dict"])
        opt.load_state_dict(ck["opt"])
        gen.set_state(ck["gen"])
        torch.set_rng_state(ck["torch_rng"])
        step0, wall = ck["step"], ck["wall"]
    csv_path = out / "metrics.csv"
    if ck is not None and csv_path.exists():  # drop rows logged after the checkpoint
        rows = [r for r in csv.DictReader(csv_path.open()) if int(r["step"]) <= step0]
        with csv_path.open("w", newline="") as f:
            if rows:
                w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
                w.writeheader()
                w.writerows(rows)
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=1))

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=step0, desc="world model", unit="step")
    state = {"loss": 0.0, "n": 0, "t": time.perf_counter(), "wall": wall, "last": {}}

    def save_checkpoint(step: int) -> None:
        ckpt = {"model": {"hparams": model.hparams, "grid": _grid_dict(cfg.env),
                          "state_dict": model.state_dict()},
                "opt": opt.state_dict(), "gen": gen.get_state(), "torch_rng": torch.get_rng_state(),
                "step": step, "wall": state["wall"], "config": to_dict(cfg)}
        tmp = out / "checkpoint.pt.tmp"
        torch.save(ckpt, tmp)
        os.replace(tmp, out / "checkpoint.pt")
        save_world_model(model, out / "model.pt", cfg.env, {"config": to_dict(cfg), "step": step})

    def on_step(step: int, loss: float) -> None:
        state["loss"] += loss
        state["n"] += 1
        if bar is not None:
            bar.update(1)
        if step % cfg.log_every == 0 or step == cfg.steps:
            now = time.perf_counter()
            state["wall"] += now - state["t"]
            row = {"step": step, "train_nll": state["loss"] / state["n"], "samples": step * cfg.batch_size,
                   "samples_per_s": state["n"] * cfg.batch_size / max(now - state["t"], 1e-9),
                   "wall_s": state["wall"]}
            if val is not None:
                v = dataset_nll(model, val)
                row.update({"val_nll": v["nll"], "val_accuracy": v["accuracy"]})
                model.set_layout(*data["layout"])
            _append_csv(csv_path, row)
            state["last"] = row
            if bar is not None:
                bar.set_postfix(nll=f"{row['train_nll']:.3f}", val=f"{row.get('val_nll', float('nan')):.3f}")
            state["loss"], state["n"], state["t"] = 0.0, 0, time.perf_counter()
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            save_checkpoint(step)

    if step0 < cfg.steps:
        fit(model, data, steps=cfg.steps, batch_size=cfg.batch_size, lr=cfg.lr, weight_decay=cfg.weight_decay,
            label_smoothing=cfg.label_smoothing, gen=gen, opt=opt, start=step0, on_step=on_step)
    elif not (out / "model.pt").exists():
        save_checkpoint(step0)
    if bar is not None:
        bar.close()
    result = dict(state["last"])
    result.update({"train_samples": int(data["target"].shape[0]), "collect_s": collect_s,
                   "parameters": sum(p.numel() for p in model.parameters()),
                   "out_dir": str(out), "model": str(out / "model.pt")})
    if val is not None:
        result["val_baselines"] = baseline_nlls(val, cfg.env, data)
    return result


def _grid_dict(env: EngineConfig) -> dict:
    from tg_gpudrive.worldmodel.prior import grid_of

    return grid_of(env)


def _append_csv(path: Path, row: dict) -> None:
    new = not path.exists()
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row.keys()))
        if new:
            w.writeheader()
        w.writerow(row)


# --------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="configs/worldmodel/<name>.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set steps=500 --set env.road_k=64")
    p.add_argument("--resume", default=None, metavar="DIR", help="continue the run saved in DIR")
    p.add_argument("--out", default=None, help="run directory (default: out_dir of the config)")
    p.add_argument("--json", action="store_true", help="print the final metrics as JSON")


def run(args) -> int:
    """`tg-gpudrive train-world-model` with parsed `args` (see add_arguments)."""
    if args.resume and (Path(args.resume) / "config.json").exists():
        data = json.loads((Path(args.resume) / "config.json").read_text())
    else:
        data = load_yaml(args.config)
    cfg = from_dict(WorldModelConfig, apply_overrides(data, args.set), args.config)
    res = train_world_model(cfg, out_dir=args.out or args.resume, resume=args.resume, progress=not args.json)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"world model: {res['model']}  val nll {res.get('val_nll', float('nan')):.3f}  "
              f"baselines {json.dumps(res.get('val_baselines', {}))}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tg-gpudrive train-world-model", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"tg-gpudrive train-world-model: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
