"""Uses of the world model: the CCE-MAPPO magnet (`WorldModelPrior`) and a driver of vehicles.

    prior = WorldModelPrior(load_shipped(sim), sim)     # trainer.prior = prior
    driver = WorldModelDriver(load_shipped(sim))        # driver(sim) before sim.step()

The prior's context is the agent's history window in its current frame
(H x 7 floats, 70 by default); the observation row the learner already stores
supplies map and neighbours, so `distribution(context, obs)` recomputes the
distribution at update time instead of storing 91 logits per agent-step. The
history is synced from the simulator at each `context` call, so the trainer
must call it every step (it does).

Discrete: `distribution` returns logits and the trainer's categorical KL is
exact. Continuous: it returns a `LaplaceMixture` (mixture.py). The trainer's
`PolicyHead.kl` calls its `kl_from((mean, log_std))`, a closed-form variational
upper bound on KL(Gaussian policy || mixture), exact for one component; read
as a plain (mean, log_std) tuple it is the moment-matched Gaussian, so a
Gaussian-only KL still gets a defined (unimodal) magnet.

Checkpoints (`save_world_model` / `load_world_model`) hold the weights, the
model's hyper-parameters and the action grid (discrete) or box (continuous) it
was trained on; loading onto a simulator whose action space, grid or box
differs is an error. `load_shipped(sim)` loads the model that ships in the package
for the simulator's action space (shipped.pt, discrete; shipped_continuous.pt):
trained on procedural scenes on one GPU, teacher forcing then closed-loop
fine-tuning (configs/worldmodel/gpu.yaml).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from tg_gpudrive.checkpoint import WORLD_MODEL, check_kind, save_atomic
from tg_gpudrive.engine.control import DRIVER_ROWS, driver_rows
from tg_gpudrive.history import HIST_DIM, HistoryBuffer
from tg_gpudrive.agents.policy import BehaviourPrior, guard_for
from tg_gpudrive.worldmodel.mixture import LaplaceMixture
from tg_gpudrive.worldmodel.model import WorldModel, check_action_space

SHIPPED = Path(__file__).resolve().parent / "shipped.pt"
# world models that ship in the package, by the name a config or `--background-model` may give:
# shipped    configs/worldmodel/gpu.yaml on one GPU (teacher forcing + closed-loop fine-tuning); the default
# small_cpu  configs/worldmodel/small_cpu.yaml on a laptop CPU (teacher forcing only): the
#            magnet of configs/train/small_cpu.yaml, whose 30-update, 8-world run with a small
#            observation learns from this softer model and not from the sharper GPU one (BENCHMARKS.md)
# shipped_continuous  the same recipe with env.action_space continuous, then 9 closed-loop rounds at the
#            driver's temperature 0.1 (BENCHMARKS.md): the default of a continuous simulator
PACKAGED = {"shipped": SHIPPED, "small_cpu": SHIPPED.with_name("small_cpu.pt"),
            "shipped_continuous": SHIPPED.with_name("shipped_continuous.pt")}


def grid_of(cfg) -> dict:
    """What a checkpoint must agree on with the simulator: the grid (discrete; the dict older
    checkpoints hold) or the action box (continuous)."""
    if not cfg.discrete:
        return {"action_space": "continuous", "max_accel": cfg.max_accel, "max_curvature": cfg.max_curvature}
    return {"accel_bins": cfg.accel_bins, "curvature_bins": cfg.curvature_bins, "max_accel": cfg.max_accel,
            "max_curvature": cfg.max_curvature}


def save_world_model(model: WorldModel, path: str | Path, env_cfg, extra: dict | None = None) -> Path:
    """Weights + hyper-parameters + action grid; written atomically."""
    return save_atomic({"kind": WORLD_MODEL, "hparams": model.hparams, "grid": grid_of(env_cfg),
                        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
                        **(extra or {})}, path)


def world_model_file(path: str | Path) -> Path:
    """The checkpoint file `path` names: a world-model checkpoint, a train-world-model run's
    checkpoint.pt or run directory (its model.pt), or a PACKAGED name. A missing one is a
    FileNotFoundError that lists the accepted forms."""
    path = PACKAGED.get(str(path), Path(path))
    if path.is_dir():
        path = path / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(f"no world-model checkpoint at {path} (a file, a run directory or a packaged "
                                f"name: {', '.join(PACKAGED)})")
    return path


def load_world_model(path: str | Path, sim=None, device: str | None = None) -> WorldModel:
    """A WorldModel from `path` (see `world_model_file`), laid out for `sim`'s observation rows and on
    its device, in eval mode."""
    path = world_model_file(path)
    ck = check_kind(torch.load(path, map_location="cpu", weights_only=False), WORLD_MODEL, path, "world model")
    if "model" in ck and "state_dict" not in ck:  # a training checkpoint
        ck = ck["model"]
    model = WorldModel(**ck["hparams"])
    model.load_state_dict(ck["state_dict"])
    if sim is not None:
        check_action_space(model, sim.cfg)
        want, have = ck["grid"], grid_of(sim.cfg)
        if want != have:
            raise ValueError(f"{path}: world model trained on the action grid {want}; the simulator has {have}")
        model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        device = device or str(sim.pos.device)
    return model.to(device or "cpu").eval()


def load_shipped(sim=None, device: str | None = None) -> WorldModel:
    """The packaged world model for `sim`'s action space: `shipped` (discrete, also without a sim) or
    `shipped_continuous`."""
    name = "shipped_continuous" if sim is not None and not sim.cfg.discrete else "shipped"
    path = PACKAGED[name]
    if not path.exists():
        raise FileNotFoundError(f"{path}: the packaged world model {name} is missing from the package "
                                f"(pyproject package-data must include tg_gpudrive/worldmodel/{path.name})")
    return load_world_model(path, sim, device)


class WorldModelPrior(BehaviourPrior):
    """The world model's next-action distribution as the CCE-MAPPO magnet.

    context(sim, C) -> (W, C, H * 7): the history window of the first C slots.
    distribution(context, obs) -> logits (..., num_actions), or a LaplaceMixture (continuous)
    whose KL from the Gaussian policy is the closed-form bound (`kl_samples` None) or a
    Monte Carlo estimate with that many fixed draws. `top_component` (default, as TrafficGamer
    does): the continuous magnet is the mixture's most probable component alone. `min_std`
    (accel m/s^2, curvature 1/m), continuous only: each component is widened to at least this
    standard deviation (Laplace scale std / sqrt 2). A model trained on the GPU predicts the
    logged action to 0.02 m/s^2, and the KL of any Gaussian policy to so sharp a target is about
    10 nats, which swamped the advantage (BENCHMARKS.md); the discrete magnet can be no
    sharper than a grid bin, and this gives the continuous one a like floor."""

    def __init__(self, model: WorldModel, sim=None, kl_samples: int | None = None, top_component: bool = True,
                 min_std: tuple[float, float] | None = None):
        if sim is not None:
            check_action_space(model, sim.cfg)
            model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        self.model = model
        self.kl_samples = kl_samples
        self.top_component = top_component  # continuous: the most probable component is the magnet
        if min_std is not None and min(min_std) <= 0:
            raise ValueError(f"min_std must be > 0 (m/s^2, 1/m), got {min_std}")
        # log of the least Laplace scale b = std / sqrt(2), per action dimension
        self.min_log_scale = None if min_std is None else [math.log(x / math.sqrt(2.0)) for x in min_std]
        self.history = HistoryBuffer(model.history)

    @property
    def context_dim(self) -> int:
        return self.model.history * HIST_DIM

    def state_dict(self) -> dict:
        return self.history.state_dict()

    def load_state_dict(self, sim, state: dict) -> None:
        self.history.load_state_dict(sim, state)

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
            out = self.model(obs.float(), hist.float())
        if self.model.discrete:
            return out.float()
        log_scale = out.log_scale.float()
        if self.min_log_scale is not None:
            log_scale = torch.maximum(log_scale, log_scale.new_tensor(self.min_log_scale))
        mix = LaplaceMixture(out.logits.float(), out.loc.float(), log_scale, self.kl_samples)
        return mix.top_component() if self.top_component else mix


class WorldModelDriver:
    """`driver(sim)`: writes sampled world-model actions for the background rows
    (`rows="background"`), every controlled row (`"controlled"`, e.g. to drive a whole scene
    closed loop) or the policy's rows (`"policy"`): grid indices into `sim.actions_index`
    (discrete) or (accel, curvature), clipped to the action box, into `sim.actions[..., :2]`
    (continuous). Call it once per step, before `sim.step()`; other rows are left as they are.
    `greedy`: the arg-max bin, or the location of the most probable mixture component.
    `temperature` divides the logits (and, continuous, multiplies the Laplace scales:
    `LaplaceMixture.sample`); 0 is greedy. None (the default) is 1 for the discrete head and
    `CONTINUOUS_TEMPERATURE` for the continuous one. `guard_s` > 0 (discrete only) puts the safety guard
    of agents/guard.py, looking that many seconds ahead, behind the sampled actions.

    Why the continuous default is not 1: per-step draws are independent, so at T = 1 the
    curvature noise (and the occasional pick of a minor component) random-walks the heading over
    an episode. Tempering both the logits and the scales is needed; T = 0.1 drives about as well
    as greedy while keeping a little diversity (the sweep: BENCHMARKS.md, "World model")."""

    ROWS = DRIVER_ROWS
    CONTINUOUS_TEMPERATURE = 0.1

    def __init__(self, model: WorldModel, rows: str = "background", temperature: float | None = None,
                 greedy: bool = False, seed: int = 0, guard_s: float = 0.0):
        if rows not in self.ROWS:
            raise ValueError(f"rows: expected one of {', '.join(self.ROWS)}, got {rows!r}")
        if temperature is None:
            temperature = 1.0 if model.discrete else self.CONTINUOUS_TEMPERATURE
        if temperature < 0:
            raise ValueError(f"temperature must be >= 0, got {temperature}")
        greedy = greedy or temperature == 0
        self.model, self.rows, self.temperature, self.greedy = model, rows, float(temperature), greedy
        self.history = HistoryBuffer(model.history)
        self.seed = seed
        self.gen: torch.Generator | None = None
        if guard_s and not model.discrete:
            raise ValueError("guard_s: the action guard needs the discrete world model")
        self.guard_s, self.guard = guard_s, None  # the guard, built for the layout of the simulator driven
        # discrete: the rows the last call drove and the logits it sampled them from (kept as they are;
        # `last_out` spreads them over the world's slots only when a best response asks)
        self._last: tuple | None = None

    @property
    def last_out(self) -> torch.Tensor | None:
        """Discrete: the logits the last call sampled from, (W, A, num_actions), zero on the rows it left
        alone: the distribution a best response to this driver starts from
        (evaluation.exploitability.SimGame). None before the first call."""
        if self._last is None:
            return None
        w, a, logits, shape = self._last
        out = torch.zeros((*shape, self.model.num_actions), device=self.model.ego_scale.device)
        if logits is not None:
            out[w, a] = logits
        return out

    @torch.no_grad()
    def __call__(self, sim) -> None:
        check_action_space(self.model, sim.cfg)
        if self.gen is None or self.gen.device != sim.pos.device:
            self.gen = torch.Generator(device=sim.pos.device).manual_seed(self.seed)
        self.model.set_layout(sim.cfg.partner_k, sim.cfg.road_k)
        self.history.sync(sim)
        sel = driver_rows(sim, self.rows)
        if not bool(sel.any()):
            self._last = (None, None, None, sel.shape)  # no row driven: zero logits everywhere
            return
        w, a = sel.nonzero(as_tuple=True)
        hist = self.history.features(sim)[w, a]
        out = self.model(sim.obs[w, a], hist)
        if not self.model.discrete:
            act = out.mode_loc() if self.greedy else out.sample(self.gen, self.temperature)
            box = torch.tensor([sim.cfg.max_accel, sim.cfg.max_curvature], device=act.device, dtype=act.dtype)
            sim.actions[w, a, :2] = torch.maximum(torch.minimum(act, box), -box).to(sim.actions.dtype)
            return
        logits = out.float() if self.greedy else out.float() / self.temperature
        self._last = (w, a, logits, sel.shape)
        if self.greedy:
            act = out.argmax(-1)
        else:
            act = torch.multinomial(torch.softmax(logits, -1), 1, generator=self.gen)[:, 0]
        if self.guard_s:
            g, layout = self.guard, (sim.cfg.partner_k, float(sim.model.dt), sim.obs.device)
            if g is None or (g.partner_k, g.dt, g.grid.device) != layout:
                self.guard = guard_for(sim, self.guard_s)
            act = self.guard(sim.obs[w, a], logits, act, self.greedy, generator=self.gen)
        sim.actions_index[w, a] = act.to(sim.actions_index.dtype)
