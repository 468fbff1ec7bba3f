"""Fitting the world model: `train_world_model` behind `tg-gpudrive train-world-model --config ...`.

Maximum likelihood on the logged expert actions, teacher-forced: the samples
of data.collect (the first `num_scenes` scenes of the source train, the next
`val_scenes` are held out), then minibatches of cross-entropy (discrete) or
mixture-of-Laplace NLL (continuous, `mixtures` components), with a tqdm bar,
metrics.csv, an atomic checkpoint.pt (weights, optimiser, RNG, step) and
`--resume`. The run's `model.pt` is what `load_world_model` reads.

Closed-loop fine-tuning (`closed_loop_steps > 0`, DAgger): after teacher
forcing, `closed_loop_rounds` times, the current model drives every vehicle of
the training scenes for `closed_loop_horizon` steps, each visited state is
labelled with the corrective action back to the log (closed_loop.py), the
samples join the aggregated set (teacher-forced + all rounds) and the round's
share of `closed_loop_steps` minibatch steps is fitted at `closed_loop_lr`.
Rounds are logged to closed_loop.csv (roll-out drift, collision and off-road of
the model driving, and the held-out background rates before and after);
the checkpoint is written once the phase ends (a resume during it repeats it).
It is tuned for the discrete head only: keep closed_loop_steps 0 for the
continuous head, whose drift it made worse on the CPU (BENCHMARKS.md, "World model").

Shipped model: the two commands at the top of configs/worldmodel/gpu.yaml (teacher forcing, then
closed-loop fine-tuning, on one GPU), then `cp runs/wm_gpu_dagger/model.pt tg_gpudrive/worldmodel/shipped.pt`.

On a WOMD store, set `scenes: <store dir>` (made with `tg-gpudrive convert`), `num_scenes` to what
fits in memory (a sample is about 1.5 kB with the default `max_partners` / `max_roads`) and train on
the GPU (`device: cuda`). Every agent of a scene gets a slot (`env.max_agents` is raised where a scene
needs more), so no agent is left out of the samples.

The metrics it logs come from metrics.py; the command line is cli.py. This
module must not parse arguments or print: it returns its results.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import random
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from tg_gpudrive.checkpoint import WORLD_MODEL, load_checkpoint, save_atomic
from tg_gpudrive.config import ConfigError, EngineConfig, require_nonempty, to_dict
from tg_gpudrive.engine.simulator import resolve_device
from tg_gpudrive.worldmodel.closed_loop import closed_loop_samples, rounds_schedule
from tg_gpudrive.worldmodel.data import collect, load_scene_split
from tg_gpudrive.worldmodel.metrics import background_rates, baseline_nlls, dataset_nll
from tg_gpudrive.worldmodel.model import WorldModel, require_bicycle
from tg_gpudrive.worldmodel.prior import WorldModelDriver, grid_of, load_world_model, save_world_model


@dataclasses.dataclass(frozen=True)
class WorldModelConfig:
    """A world-model training run. YAML files live in configs/worldmodel/."""

    env: EngineConfig = EngineConfig()
    scenes: str = "procedural:all"  # scene spec (tg_gpudrive.data.sources)
    num_scenes: int = 96  # training scenes: source indices [0, num_scenes)
    val_scenes: int = 12  # held out: the next val_scenes indices
    num_worlds: int = 16  # worlds simulated at once while collecting
    device: str = "auto"  # auto (cuda when Warp and torch see one, else cpu) | cpu | cuda | cuda:N
    seed: int = 0
    # model
    hidden: int = 64
    heads: int = 4
    history: int = 10  # steps of the temporal window (1 s at 10 Hz)
    max_partners: int = 8  # nearest partner rows read
    max_roads: int = 32  # nearest road rows read
    mixtures: int = 4  # continuous action space: Laplace components of the head
    init_model: str = ""  # start from this world-model checkpoint's weights (then steps may be 0)
    # optimisation
    steps: int = 2000  # teacher-forced minibatch steps
    batch_size: int = 512
    lr: float = 2e-3
    weight_decay: float = 1e-4
    label_smoothing: float = 0.0  # discrete only
    # closed-loop (DAgger) fine-tuning after teacher forcing; 0 steps = off
    closed_loop_steps: int = 0  # minibatch steps over all rounds
    closed_loop_rounds: int = 3  # roll out, label, aggregate, fit
    closed_loop_horizon: int = 80  # steps per roll-out from init_step (capped at the episode)
    closed_loop_lr: float = 5e-4
    closed_loop_temperature: float = 1.0  # sampling temperature of the roll-outs
    # labels of the visited states: log (the corrective action back to the log) | log_brake (the same, braking
    # as IDM for the nearest agent across the logged path ahead where that is harder)
    closed_loop_labels: str = "log_brake"
    # bookkeeping
    log_every: int = 100
    checkpoint_every: int = 500
    out_dir: str = "runs/worldmodel"

    def __post_init__(self):
        require_nonempty(self, ("scenes", "device", "out_dir"))
        try:
            require_bicycle(self.env)
        except NotImplementedError as e:
            raise ConfigError(str(e)) from None
        if min(self.num_scenes, self.num_worlds, self.batch_size, self.history, self.mixtures) < 1:
            raise ConfigError("num_scenes, num_worlds, batch_size, history and mixtures must be >= 1")
        if self.steps < (0 if self.init_model else 1):
            raise ConfigError("steps must be >= 1 (>= 0 with init_model)")
        if self.val_scenes < 0:
            raise ConfigError("val_scenes must be >= 0")
        if self.closed_loop_steps < 0:
            raise ConfigError("closed_loop_steps must be >= 0 (0: no closed-loop fine-tuning)")
        if self.closed_loop_steps and min(self.closed_loop_rounds, self.closed_loop_horizon) < 1:
            raise ConfigError("closed_loop_rounds and closed_loop_horizon must be >= 1")
        if self.closed_loop_steps and self.closed_loop_temperature <= 0:
            raise ConfigError("closed_loop_temperature must be > 0")
        if self.closed_loop_labels not in ("log", "log_brake"):
            raise ConfigError(f"closed_loop_labels: expected log or log_brake, got {self.closed_loop_labels!r}")


# ---------------------------------------------------------------- training
def build_model(cfg: WorldModelConfig) -> WorldModel:
    e = cfg.env
    return WorldModel(num_actions=e.num_actions, hidden=cfg.hidden, heads=cfg.heads, history=cfg.history,
                      max_partners=cfg.max_partners, max_roads=cfg.max_roads,
                      partner_k=min(e.partner_k, cfg.max_partners), road_k=min(e.road_k, cfg.max_roads),
                      action_space=e.action_space, mixtures=cfg.mixtures, max_accel=e.max_accel,
                      max_curvature=e.max_curvature)


def fit(model: WorldModel, data: dict, *, steps: int, batch_size: int, lr: float, weight_decay: float = 0.0,
        label_smoothing: float = 0.0, gen: torch.Generator | None = None, opt=None, start: int = 0,
        on_step=None, max_grad_norm: float = 1.0) -> torch.optim.Optimizer:
    """Minibatch NLL steps [start, steps) on `data`; `on_step(step, loss)` after each.

    Gradients are clipped to `max_grad_norm` times `model.grad_scale` (1 for the discrete head; for
    the Laplace head the inverse of its smallest scale, since its NLL gradients grow as 1 / b)."""
    dev = next(model.parameters()).device
    model.set_layout(*data["layout"])
    opt = opt or torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    n = data["target"].shape[0]
    for step in range(start, steps):
        for g in opt.param_groups:  # cosine decay to lr / 20
            g["lr"] = lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * step / steps)))
        model.train()
        idx = torch.randint(0, n, (min(batch_size, n),), generator=gen)
        out = model(data["obs"][idx].to(dev), data["hist"][idx].to(dev))
        loss = model.nll(out, data["target"][idx].to(dev), label_smoothing=label_smoothing).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), max_grad_norm * model.grad_scale)
        opt.step()
        if on_step is not None:
            on_step(step + 1, float(loss.detach()))
    return opt


def train_world_model(cfg: WorldModelConfig, out_dir: str | Path | None = None, resume: str | Path | None = None,
                      progress: bool = True) -> dict:
    """Collect, fit, log, checkpoint; returns the last metrics with `out_dir` and `model` paths."""
    out = Path(out_dir or resume or cfg.out_dir)
    device = resolve_device(cfg.device, flag="device")  # before anything is written or built
    out.mkdir(parents=True, exist_ok=True)
    random.seed(cfg.seed), np.random.seed(cfg.seed), torch.manual_seed(cfg.seed)
    ck = None if resume is None else load_checkpoint(resume, kind=WORLD_MODEL)
    t0 = time.perf_counter()
    train_scenes, val_scenes = load_scene_split(cfg)
    kw = dict(history=cfg.history, max_partners=cfg.max_partners, max_roads=cfg.max_roads,
              num_worlds=cfg.num_worlds, device=device)
    data = collect(train_scenes, cfg.env, **kw)
    val = collect(val_scenes, cfg.env, **kw) if val_scenes else None
    collect_s = time.perf_counter() - t0
    model = build_model(cfg).to(device)
    if cfg.init_model and ck is None:
        _load_init_model(model, cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(cfg.seed)
    step0, wall = 0, 0.0
    if ck is not None:
        model.load_state_dict(ck["model"]["state_dict"])
        opt.load_state_dict(ck["opt"])
        gen.set_state(ck["gen"])
        torch.set_rng_state(ck["torch_rng"])
        step0, wall = ck["step"], ck["wall"]
        _drop_rows_after(out / "metrics.csv", step0)
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=1))

    run = _TeacherForcedRun(cfg, out, model, opt, gen, data, val, wall, step0, progress)
    if step0 < cfg.steps:
        fit(model, data, steps=cfg.steps, batch_size=cfg.batch_size, lr=cfg.lr, weight_decay=cfg.weight_decay,
            label_smoothing=cfg.label_smoothing, gen=gen, opt=opt, start=step0, on_step=run.on_step)
    elif not (out / "model.pt").exists():
        run.save_checkpoint(step0)
    if run.bar is not None:
        run.bar.close()
    result = dict(run.last)
    if cfg.closed_loop_steps > 0:
        if ck is not None and ck.get("closed_loop_done"):
            result["closed_loop"] = "done before the resume"
        else:
            result["closed_loop"] = closed_loop_finetune(model, cfg, data, train_scenes, val_scenes, out,
                                                         device, progress)
            run.save_checkpoint(cfg.steps, closed_loop_done=True)
    result.update({"train_samples": int(data["target"].shape[0]), "collect_s": collect_s,
                   "parameters": sum(p.numel() for p in model.parameters()),
                   "out_dir": str(out), "model": str(out / "model.pt")})
    if val is not None:
        result["val_baselines"] = baseline_nlls(val, cfg.env, data)
    return result


def _load_init_model(model: WorldModel, cfg: WorldModelConfig) -> None:
    """Starts `model` from the weights of `cfg.init_model`, which must have the same hyper-parameters."""
    init = load_world_model(cfg.init_model)
    if init.hparams != model.hparams:
        raise ConfigError(f"init_model {cfg.init_model}: hyper-parameters {init.hparams} differ from the "
                          f"config's {model.hparams}")
    model.load_state_dict(init.state_dict())


def _drop_rows_after(csv_path: Path, step0: int) -> None:
    """Drops the rows of a resumed run's metrics.csv logged after its checkpoint's step `step0`."""
    if not csv_path.exists():
        return
    rows = [r for r in csv.DictReader(csv_path.open()) if int(r["step"]) <= step0]
    with csv_path.open("w", newline="") as f:
        if rows:
            w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
            w.writeheader()
            w.writerows(rows)


class _TeacherForcedRun:
    """The bookkeeping of the teacher-forced steps: the running loss, a metrics.csv row (with the held-out
    NLL) every `log_every` steps, checkpoint.pt and model.pt every `checkpoint_every`, the tqdm bar."""

    def __init__(self, cfg: WorldModelConfig, out: Path, model: WorldModel, opt, gen: torch.Generator,
                 data: dict, val: dict | None, wall: float, step0: int, progress: bool):
        self.cfg, self.out, self.model, self.opt, self.gen, self.data, self.val = cfg, out, model, opt, gen, data, val
        self.csv_path = out / "metrics.csv"
        self.bar = tqdm(total=cfg.steps, initial=step0, desc="world model", unit="step") if progress else None
        self.loss, self.n, self.t, self.wall, self.last = 0.0, 0, time.perf_counter(), wall, {}

    def save_checkpoint(self, step: int, closed_loop_done: bool = False) -> None:
        cfg, model = self.cfg, self.model
        ckpt = {"kind": WORLD_MODEL, "model": {"hparams": model.hparams, "grid": grid_of(cfg.env),
                          "state_dict": model.state_dict()},
                "opt": self.opt.state_dict(), "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(),
                "step": step, "wall": self.wall, "config": to_dict(cfg), "closed_loop_done": closed_loop_done}
        save_atomic(ckpt, self.out / "checkpoint.pt")
        save_world_model(model, self.out / "model.pt", cfg.env, {"config": to_dict(cfg), "step": step})

    def on_step(self, step: int, loss: float) -> None:
        cfg = self.cfg
        self.loss += loss
        self.n += 1
        if self.bar is not None:
            self.bar.update(1)
        if step % cfg.log_every == 0 or step == cfg.steps:
            self._log(step)
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            self.save_checkpoint(step)

    def _log(self, step: int) -> None:
        now = time.perf_counter()
        self.wall += now - self.t
        bs = self.cfg.batch_size
        row = {"step": step, "train_nll": self.loss / self.n, "samples": step * bs,
               "samples_per_s": self.n * bs / max(now - self.t, 1e-9), "wall_s": self.wall}
        if self.val is not None:
            v = dataset_nll(self.model, self.val)
            row.update({f"val_{k}": x for k, x in v.items()})
            self.model.set_layout(*self.data["layout"])
        _append_csv(self.csv_path, row)
        self.last = row
        if self.bar is not None:
            self.bar.set_postfix(nll=f"{row['train_nll']:.3f}", val=f"{row.get('val_nll', float('nan')):.3f}")
        self.loss, self.n, self.t = 0.0, 0, time.perf_counter()


def closed_loop_finetune(model: WorldModel, cfg: WorldModelConfig, data: dict, train_scenes: list,
                         val_scenes: list, out: Path, device: str, progress: bool = False) -> dict:
    """DAgger rounds (closed_loop.py) on `train_scenes`, aggregated with the teacher-forced `data`.

    One row per round in out/closed_loop.csv: `rollout_*` describe the model that drove the round
    (before its fit), `train_nll` the round's minibatches, `visited_nll_before` / `visited_nll` the
    NLL of the corrective labels of the round's visited states before / after its fit. Returns
    (and writes to out/closed_loop.json) the last row plus the held-out background rates
    (`background_rates`, one episode) before and after, when there are `val_scenes`."""
    csv_path = out / "closed_loop.csv"
    csv_path.unlink(missing_ok=True)  # a resumed run repeats the whole phase
    (out / "closed_loop.json").unlink(missing_ok=True)
    t0 = time.perf_counter()
    bg_driver = lambda: WorldModelDriver(model, rows="background", seed=cfg.seed)  # noqa: E731
    before = background_rates(bg_driver(), val_scenes, cfg.env, device=device) if val_scenes else None
    agg = {k: [data[k]] for k in ("obs", "hist", "target")}
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.closed_loop_lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    bar = None
    if progress:
        bar = tqdm(total=cfg.closed_loop_steps, desc="closed loop", unit="step")
    done, row = 0, {}
    for r, steps in enumerate(rounds_schedule(cfg.closed_loop_steps, cfg.closed_loop_rounds)):
        new, roll = closed_loop_samples(
            model, train_scenes, cfg.env, horizon=cfg.closed_loop_horizon, history=cfg.history,
            max_partners=cfg.max_partners, max_roads=cfg.max_roads, num_worlds=cfg.num_worlds, device=device,
            seed=cfg.seed + 1000 * (r + 1), temperature=cfg.closed_loop_temperature, labels=cfg.closed_loop_labels)
        visited_before = dataset_nll(model, new)["nll"]
        for k in agg:
            agg[k].append(new[k])
        merged = {k: torch.cat(v) for k, v in agg.items()}
        merged["layout"] = data["layout"]
        losses = []
        fit(model, merged, steps=steps, batch_size=cfg.batch_size, lr=cfg.closed_loop_lr,
            weight_decay=cfg.weight_decay, label_smoothing=cfg.label_smoothing, gen=gen, opt=opt,
            on_step=lambda _s, loss: (losses.append(loss), bar.update(1) if bar is not None else None))
        done += steps
        visited = dataset_nll(model, new)
        row = {"round": r + 1, "step": cfg.steps + done, "train_nll": sum(losses) / max(len(losses), 1),
               "visited_nll_before": visited_before, "visited_nll": visited["nll"],
               "dataset_samples": int(merged["target"].shape[0]), **roll, "wall_s": time.perf_counter() - t0}
        _append_csv(csv_path, row)
        # each round's model, so that a run stopped by a time limit keeps the rounds it finished
        save_world_model(model, out / "model.pt", cfg.env,
                         {"config": to_dict(cfg), "step": cfg.steps + done, "closed_loop_round": r + 1})
    if bar is not None:
        bar.close()
    model.set_layout(*data["layout"])
    result = dict(row)
    if before is not None:
        after = background_rates(bg_driver(), val_scenes, cfg.env, device=device)
        result.update({"val_background_before": before, "val_background_after": after})
    (out / "closed_loop.json").write_text(json.dumps(result, indent=1))
    return result


def _append_csv(path: Path, row: dict) -> None:
    new = not path.exists()
    with path.open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row.keys()))
        if new:
            w.writeheader()
        w.writerow(row)
