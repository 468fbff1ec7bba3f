"""Uses of the world model: the CCE-MAPPO magnet (`WorldModelPrior`) and a driver of vehicles.

    prior = WorldModelPrior(load_shipped(sim), sim)     # trainer.prior = prior
    driver = WorldModelDriver(load_shipped(sim))        # driver(sim) before sim.step()

The prior's context is the agent's history window in its current frame
(H x 7 floats, 70 by default); the observation row the learner already stores
supplies map and neighbours, so `distribution(context, obs)` recomputes the
logits at update time instead of storing 91 of them per agent-step. The
history is synced from the simulator at each `context` call, so the trainer
must call it every step (it does).

Checkpoints (`save_world_model` / `load_world_model`) hold the weights, the
model's hyper-parameters and the action grid it was trained on; loading onto a
simulator whose grid differs is an error. `load_shipped(sim)` loads the small
model trained on procedural scenes that ships in the package (shipped.pt).
"""

from __future__ import annotations

from pathlib import Path

import torch

from tg_gpudrive.learn.prior import BehaviourPrior
from tg_gpudrive.worldmodel.model import HIST_DIM, HistoryBuffer, WorldModel, require_discrete

SHIPPED = Path(__file__).resolve().parent / "shipped.pt"


def grid_of(cfg) -> dict:
    return {"accel_bins": cfg.accel_bins, "curvature_bins": cfg.curvature_bins, "max_accel": cfg.max_accel,
            "max_curvature": cfg.max_curvature}


def save_world_model(model: WorldModel, path: str | Path, env_cfg, extra: dict | None = None) -> Path:
    """Weights + hyper-parameters + action grid; written atomically."""
    import os

    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save({"hparams": model.hparams, "grid": grid_of(env_cfg),
                "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
                **(extra or {})}, tmp)
    os.replace(tmp, path)
    return path


def load_world_model(path: str | Path, sim=None, device: str | None = None) -> WorldModel:
    """A WorldModel from `path` (a world-model checkpoint or a train-world-model run's checkpoint.pt),
    laid out for `sim`'s observation rows and on its device, in eval mode."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.pt"
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if "model" in ck and "state_dict" not in ck:  # a training checkpoint
        ck = ck["model"]
    model = WorldModel(**ck["hparams"])
    model.load_state_dict(ck["state_dict"])
    if sim is not None:
        require_discrete(sim.cfg)
        want, have = ck["grid"], grid_of(sim.cfg)
        if want != have:
            raise ValueError(f"{path}: world model trained on the action grid {want}; the simulator has {have}")
        model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        device = device or str(sim.pos.device)
    return model.to(device or "cpu").eval()


def load_shipped(sim=None, device: str | None = None) -> WorldModel:
    if not SHIPPED.exists():
        raise FileNotFoundError(f"{SHIPPED}: the shipped world model is missing from the package "
                                "(pyproject package-data must include tg_gpudrive/worldmodel/shipped.pt)")
    return load_world_model(SHIPPED, sim, device)


class WorldModelPrior(BehaviourPrior):
    """The world model's next-action distribution as the CCE-MAPPO magnet.

    context(sim, C) -> (W, C, H * 7): the history window of the first C slots.
    distribution(context, obs) -> logits (..., num_actions)."""

    def __init__(self, model: WorldModel, sim=None):
        if sim is not None:
            require_discrete(sim.cfg)
            model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        self.model = model
        self.history = HistoryBuffer(model.history)

    @property
    def context_dim(self) -> int:
        return self.model.history * HIST_DIM

    @torch.no_grad()
    def context(self, sim, num_controlled: int) -> torch.Tensor:
        self.model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        self.history.sync(sim)
        h = self.history.features(sim, slice(0, num_controlled))
        return h.reshape(*h.shape[:2], -1)

    def distribution(self, context: torch.Tensor, obs: torch.Tensor):
        hist = context.reshape(*context.shape[:-1], self.model.history, HIST_DIM)
        # the magnet is a fixed target: no gradient flows into the world model
        with torch.no_grad():
            return self.model(obs.float(), hist.float()).float()


class WorldModelDriver:
    """`driver(sim)`: writes sampled world-model actions into `sim.actions_index` for the
    background rows (`rows="background"`), every controlled row (`"controlled"`, e.g. to
    drive a whole scene closed loop) or the policy's rows (`"policy"`). Call it once per
    step, before `sim.step()`; other rows of the buffer are left as they are."""

    ROWS = ("background", "controlled", "policy")

    def __init__(self, model: WorldModel, rows: str = "background", temperature: float = 1.0,
                 greedy: bool = False, seed: int = 0):
        if rows not in self.ROWS:
            raise ValueError(f"rows: expected one of {', '.join(self.ROWS)}, got {rows!r}")
        self.model, self.rows, self.temperature, self.greedy = model, rows, temperature, greedy
        self.history = HistoryBuffer(model.history)
        self.seed = seed
        self.gen: torch.Generator | None = None

    @torch.no_grad()
    def __call__(self, sim) -> None:
        require_discrete(sim.cfg)
        if self.gen is None or self.gen.device != sim.pos.device:
            self.gen = torch.Generator(device=sim.pos.device).manual_seed(self.seed)
        self.model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        self.history.sync(sim)
        if self.rows == "background":
            sel = sim.background != 0
        elif self.rows == "controlled":
            sel = sim.controlled != 0
        else:
            sel = sim.policy_agents
        sel = sel & (sim.present != 0)
        if not bool(sel.any()):
            return
        w, a = sel.nonzero(as_tuple=True)
        hist = self.history.features(sim)[w, a]
        logits = self.model(sim.obs[w, a], hist)
        if self.greedy:
            act = logits.argmax(-1)
        else:
            p = torch.softmax(logits / self.temperature, -1)
            act = torch.multinomial(p, 1, generator=self.gen)[:, 0]
        sim.actions_index[w, a] = act.to(sim.actions_index.dtype)
