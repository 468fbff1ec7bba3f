"""`TGVectorEnv`: the batched engine as a torch-native gymnasium vector env.

An env is one agent slot (one row of every returned tensor), as gymnasium's
``num_envs`` is the batch size of obs, reward and terminated:
``num_envs = num_worlds * max_agents`` and row ``w * max_agents + a`` is slot
``a`` of world ``w``. Ask for rows (``num_envs=``, a multiple of
``max_agents``) or for worlds (``num_worlds=``); ``gymnasium.make_vec(...,
num_envs=1024)`` with the default ``max_agents=64`` builds 16 worlds and
reports ``num_envs == 1024``. Rows whose slot is not
the policy's (empty, replayed from the log, or a background vehicle) are
always masked out (``info["active"]`` False, reward 0, never terminated or
truncated). A build that takes longer than a second (many worlds on the CPU)
shows a tqdm bar on stderr (``progress=False``: none).

Background (``background=``): "log" (default) replays the vehicles the policy
does not drive; "world_model" has the learned world model drive them
(tg_gpudrive.agents.builtin.make_background_driver, `background_model` a checkpoint
or None for the shipped model): every step() writes the user's actions, then
the model's actions of the background rows, then steps the engine, so the
user's values in those rows are ignored. Background rows keep an obs row (the
model reads it) but are masked like any other row that is not the policy's;
their reward, cost and reward terms then come from small buffers allocated
once instead of engine views. The engine ends a world's episode when every
integrated agent, background vehicles included, is done (or at the time limit).

Everything returned is a torch tensor on the engine's device and, apart from
a few bool buffers allocated once (terminations, truncations, masks), a view
of an engine array: nothing is copied to the host and step() allocates no
tensor of its own (numpy actions are copied to the device). The tensors are
overwritten by the next step(); clone what you keep.

    step() returns        shape              dtype    meaning
    obs                   (N, obs_dim)       float32  already the next episode's first obs on reset worlds
    reward                (N,)               float32  weighted sum of the named terms
    terminated            (N,)               bool     the agent's episode ended this step (goal/collision/off-road)
    truncated             (N,)               bool     ... by the time limit
    info["reward_terms"]  {name: (N,)}       float32  names: sim.reward_term_names
    info["cost"]          (N,)               float32  distance cost (1 when a partner is closer than beta)
    info["active"]        (N,)               bool     the row acts on the next step (the action mask)
    info["alive"]         (N,)               bool     the row acted on this step
    info["world_ended"]   (N,)               bool     controlled row of a world whose episode ended this step
    info["world_reset"]   (N,)               bool     ... and that was reset in it (auto_reset)
    info["final_goal"], ["final_collided"], ["final_offroad"]   (N,) int32 0/1
    info["final_return"], ["final_cost"]                        (N,) float32
    info["final_steps"]   (N,)               int32    outcomes of the finished episode, valid where world_ended

Auto-reset is the engine's (``EngineConfig.auto_reset``, default on),
declared as gymnasium's SAME_STEP mode: a world resets inside the step in
which its episode ended, so the obs returned with terminated/truncated is
already the new episode's first obs. Unlike gymnasium's SAME_STEP vector envs
there is no ``info["final_obs"]`` (the engine keeps no second obs buffer); the
terminal *outcomes* are in the ``final_*`` entries. With ``auto_reset=False``
the env declares the DISABLED mode: a world whose episode ended stays frozen
(its rows inactive, the returned obs its terminal one) until
``reset(options={"reset_mask": rows})`` resets the worlds holding any of
those rows (or ``{"worlds": (W,) bool}``).

Actions: discrete, an integer tensor/array (N,) of grid indices in
[0, num_actions); continuous, a float (N, 2) bicycle (accel m/s^2, curvature
1/m) or (N, 3) delta-local action (values outside the box are clipped by the
engine). Actions of rows that are not active are ignored; with
``strict=True`` they must equal `noop_action` or step() raises
``ValueError("action for finished agent row ...")``.

This module must not copy observations to the host nor allocate per step (the world model, when it
drives the background, allocates its own inference temporaries).
The helpers here (`make_config`, `scene_source`, `load_scenes`, the space builders) serve the other envs too.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import gymnasium
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from tqdm import tqdm

from tg_gpudrive.config import EngineConfig, apply_overrides, from_dict, load_config, to_dict
from tg_gpudrive.data.sources import SceneListSource, SceneSource, resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.agents.builtin import background_masks, check_background, make_background_driver
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import ActionSpace

ConfigLike = EngineConfig | Mapping[str, Any] | str | Path | None
OverridesLike = Sequence[str] | Mapping[str, Any] | None


# ----------------------------------------------------------- shared helpers
def make_config(config: ConfigLike = None, overrides: OverridesLike = None,
                continuous: bool | None = None) -> EngineConfig:
    """An `EngineConfig` from a config, a mapping of its fields, or a YAML path, plus overrides.

    `overrides`: ``["collision_mode=remove", "reward.goal_reached=2"]`` or
    ``{"collision_mode": "remove", "reward.goal_reached": 2}``; unknown keys are
    errors naming the key. `continuous` (when not None) sets ``action_space``.
    """
    if isinstance(config, (str, Path)):
        data = to_dict(load_config(EngineConfig, config))
    elif isinstance(config, EngineConfig):
        data = to_dict(config)
    elif config is None:
        data = to_dict(EngineConfig())
    elif isinstance(config, Mapping):
        data = to_dict(from_dict(EngineConfig, dict(config), "config"))
    else:
        raise TypeError(f"config: expected EngineConfig, a mapping or a YAML path, got {type(config).__name__}")
    if isinstance(overrides, Mapping):
        for key, value in overrides.items():
            node = data
            *path, last = str(key).split(".")
            for p in path:
                node[p] = dict(node.get(p) or {})
                node = node[p]
            node[last] = value
    elif overrides:
        if isinstance(overrides, str):
            overrides = [overrides]
        data = apply_overrides(data, list(overrides))
    if continuous is not None:
        data["action_space"] = str(ActionSpace.CONTINUOUS if continuous else ActionSpace.DISCRETE)
    return from_dict(EngineConfig, data, "config")


def scene_source(scenes, seed: int = 0):
    """A `SceneSource` over a Scene, a list of Scenes, a SceneSource or a scene spec string.

    Specs (tg_gpudrive.data.sources): ``"procedural:<type>"``, ``"procedural:all"``,
    a GPUDrive .json file, a WOMD TFRecord, a packed store or a directory;
    procedural seeds are offset by `seed`. An unknown spec is a ValueError
    listing the accepted forms.
    """
    if isinstance(scenes, (str, Path)):
        return resolve_scenes(str(scenes), seed=seed)
    if isinstance(scenes, SceneSource):
        return scenes
    if isinstance(scenes, Scene):
        return SceneListSource([scenes])
    if isinstance(scenes, Sequence) and scenes and all(isinstance(s, Scene) for s in scenes):
        return SceneListSource(scenes)
    raise TypeError("scenes: expected a Scene, a non-empty list of Scenes, a SceneSource or a scene spec "
                    f"string such as 'procedural:merge', got {type(scenes).__name__}")


def load_scenes(scenes, num_worlds: int | None = None, seed: int = 0, bar=None) -> list[Scene]:
    """Scenes 0..W-1 of `scene_source(scenes, seed)`, cycled when the source is shorter.

    W defaults to the number of scenes given as a Scene list, else to 1. `bar`: a tqdm bar
    advanced once per scene (its total set to W).
    """
    if num_worlds is not None and int(num_worlds) <= 0:
        raise ValueError(f"num_worlds must be positive, got {num_worlds}")
    src = scene_source(scenes, seed)
    n = int(num_worlds) if num_worlds is not None else (len(src) if isinstance(src, SceneListSource) else 1)
    if bar is None:
        return [src.get(i % len(src)) for i in range(n)]
    bar.total = n
    out = []
    for i in range(n):
        out.append(src.get(i % len(src)))
        bar.update(1)
    return out


def worlds_for(num_envs: int | None, num_worlds: int | None, max_agents: int) -> int | None:
    """The number of worlds that gives `num_envs` rows (an env is an agent slot: num_envs = worlds x
    max_agents), checked against `num_worlds` when both are given; None: neither given."""
    if num_envs is None:
        return num_worlds
    n, A = int(num_envs), int(max_agents)
    if n <= 0 or n % A:
        near = A * max(1, round(n / A))
        raise ValueError(f"num_envs={num_envs}: an env is one agent slot (a row), so num_envs must be a positive "
                         f"multiple of max_agents={A} (num_envs = worlds x max_agents), e.g. num_envs={near} "
                         f"({near // A} worlds); or give num_worlds=")
    if num_worlds is not None and int(num_worlds) * A != n:
        raise ValueError(f"num_envs={num_envs} and num_worlds={num_worlds} disagree: num_envs = worlds x "
                         f"max_agents = {int(num_worlds) * A} (max_agents={A}); give one of them")
    return n // A


def single_action_space(cfg: EngineConfig) -> gymnasium.spaces.Space:
    """Discrete(num_actions), Box(2) for the continuous bicycle, Box(3) for delta-local."""
    if cfg.discrete:
        return gymnasium.spaces.Discrete(cfg.num_actions)
    hi = np.array(cfg.act_high, np.float32)
    return gymnasium.spaces.Box(-hi, hi, dtype=np.float32)


def single_observation_space(obs_dim: int) -> gymnasium.spaces.Box:
    # positions and distances in the agent's frame are unbounded; masks and flags are 0/1 within that
    return gymnasium.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)


def render_world(sim: Simulator, world: int = 0, **kwargs) -> np.ndarray:
    """`tg_gpudrive.render.render_frame`, imported on first use."""
    try:  # matplotlib is an optional extra: import it only when a frame is asked for
        from tg_gpudrive.render import render_frame
    except ImportError as e:
        raise RuntimeError(f"rendering needs tg_gpudrive.render and its extras (pip install -e '.[render]'): {e}"
                           ) from e
    return render_frame(sim, world=world, **kwargs)


# ---------------------------------------------------------------- the env
class TGVectorEnv(gymnasium.vector.VectorEnv):
    """Every agent slot of W worlds as one row (one env) of a torch-native vector env (see module docstring).

    Args:
        scenes: Scene, list of Scenes, SceneSource or spec string ("procedural:all", a .json, a store).
        num_worlds: worlds W (default: len(scenes), or 1 for a spec).
        num_envs: rows instead of worlds: a multiple of the config's max_agents (W = num_envs / max_agents);
            the env's ``num_envs`` is then this number.
        config: EngineConfig, a mapping of its fields, or a YAML path; `overrides` on top of it.
        continuous: set the config's action_space (None: keep it).
        device: "auto" (default: cuda:0 when CUDA is usable, else cpu), "cpu", "cuda" or "cuda:N".
        seed: offset of procedural scene seeds (the engine itself is deterministic).
        controlled: optional per-scene bool masks over the scene's agents (Simulator's `controlled`).
        background: who drives the other eligible vehicles: "log" (replay) or "world_model".
        background_model: world-model checkpoint for "world_model" (None: the shipped model).
        strict: actions of inactive rows must be `noop_action`.
        render_mode: None or "rgb_array" (frames of `render_worlds`).
        progress: a tqdm bar on stderr over scene loading and the engine build, shown when they take
            longer than a second.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}
    progress_delay_s = 1.0  # the build's progress bar appears once the build has taken this long

    def __init__(self, scenes="procedural:all", num_worlds: int | None = None, config: ConfigLike = None,
                 overrides: OverridesLike = None, continuous: bool | None = None, device: str = "auto",
                 seed: int = 0, controlled: Sequence[np.ndarray] | None = None, strict: bool = False,
                 render_mode: str | None = None, render_worlds: Sequence[int] = (0,), background: str = "log",
                 background_model: str | Path | None = None, num_envs: int | None = None, progress: bool = True):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        device = resolve_device(device)  # a CUDA request without CUDA fails here, before scenes load
        self.background = check_background(background)
        self.cfg = make_config(config, overrides, continuous)
        self.metadata = dict(self.metadata, autoreset_mode=AutoresetMode.SAME_STEP if self.cfg.auto_reset
                             else AutoresetMode.DISABLED)
        num_worlds = worlds_for(num_envs, num_worlds, self.cfg.max_agents)
        self.progress = bool(progress)
        with self._bar() as bar:
            loaded = load_scenes(scenes, num_worlds, seed, bar)
            self._building(bar)
            self.sim = Simulator(loaded, self.cfg, device, controlled,
                                 background_masks(loaded, self.cfg, background, controlled))
            self._driver = make_background_driver(self.sim, background, background_model, seed)
        self.device = torch.device(self.sim.device)
        self.strict = bool(strict)
        self.render_mode = render_mode
        self.render_worlds = tuple(int(w) for w in render_worlds)
        self._seed = seed
        self._setup()

    def _bar(self):
        """A tqdm bar over the scenes, then a note while the engine builds; shown after progress_delay_s."""
        return tqdm(desc="TGVectorEnv: scenes", unit="world", delay=self.progress_delay_s, leave=False,
                    disable=not self.progress)

    @staticmethod
    def _building(bar) -> None:
        bar.set_description("TGVectorEnv: building the engine", refresh=False)
        if not bar.disable and bar.last_print_t >= bar.start_t + bar.delay:  # shown already: say what comes
            bar.refresh()

    def _setup(self) -> None:
        sim, cfg = self.sim, self.cfg
        W, A = sim.num_worlds, sim.max_agents
        self.num_worlds, self.max_agents = W, A
        self.num_envs = N = W * A
        self.single_observation_space = single_observation_space(sim.obs_dim)
        self.single_action_space = single_action_space(cfg)
        self.observation_space = batch_space(self.single_observation_space, N)
        self.action_space = batch_space(self.single_action_space, N)
        self.discrete = cfg.discrete
        self.action_dim = 0 if self.discrete else self.single_action_space.shape[0]
        # views of the engine arrays, made once
        self._obs = sim.obs.view(N, sim.obs_dim)
        self._reward = sim.reward.view(N)
        self._cost = sim.cost.view(N)
        K = len(sim.reward_term_names)
        terms = sim.reward_terms.view(N, K)
        self._terms = {name: terms[:, k] for k, name in enumerate(sim.reward_term_names)}
        self._final = {name: getattr(sim, name).view(N) for name in
                       ("final_goal", "final_collided", "final_offroad", "final_return", "final_cost",
                        "final_steps")}
        # the few bool buffers gymnasium's types need, filled in place
        dev = self.device
        self._term = torch.zeros(N, dtype=torch.bool, device=dev)
        self._trunc = torch.zeros(N, dtype=torch.bool, device=dev)
        self._active = torch.zeros(N, dtype=torch.bool, device=dev)
        self._alive = torch.zeros(N, dtype=torch.bool, device=dev)
        self._reset_rows = torch.zeros(N, dtype=torch.bool, device=dev)
        self._ended_rows = torch.zeros(N, dtype=torch.bool, device=dev)
        self._flag_w = torch.zeros(W, dtype=torch.bool, device=dev)
        self._ctrl = sim.policy_agents.clone()  # background-driven agents are not the user's rows
        self._has_background = bool((sim.background != 0).any())
        if self._has_background:
            # the engine scores background rows like the policy's: serve masked copies instead of views
            self._keep = self._ctrl.view(N).to(self._reward.dtype)
            self._reward = torch.zeros_like(self._reward)
            self._cost = torch.zeros_like(self._cost)
            self._terms_buf = torch.zeros((N, K), dtype=terms.dtype, device=dev)
            self._terms = {name: self._terms_buf[:, k] for k, name in enumerate(sim.reward_term_names)}
        if self.discrete:
            self.noop_action = cfg.noop_index
            self._action_view = sim.actions_index.view(N)
        else:
            self.noop_action = 0.0
            self._action_view = sim.actions[..., : self.action_dim].reshape(N, self.action_dim)
        self._needs_reset = True

    # -------------------------------------------------------------- properties
    @property
    def actions(self) -> torch.Tensor:
        """The engine's action buffer as rows ((N,) int32 or (N, k) float32; writable in place)."""
        return self._action_view

    @property
    def reward_term_names(self) -> tuple[str, ...]:
        return self.sim.reward_term_names

    @property
    def controlled(self) -> torch.Tensor:
        """(N,) bool: rows driven by the policy (all other rows are always masked)."""
        return self._ctrl.view(self.num_envs)

    # ---------------------------------------------------------------- the API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Worlds back to their start: all of them, or (options) those holding a row of
        ``reset_mask`` (N,) bool or flagged in ``worlds`` (W,) bool; ``scenes`` (with an
        optional ``controlled``) loads new scenes for the same number of worlds."""
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(seed)
        options = dict(options or {})
        worlds = None
        if "reset_mask" in options:
            m = _as_tensor(options.pop("reset_mask"), self.device)
            if tuple(m.shape) != (self.num_envs,) or m.dtype != torch.bool:
                raise ValueError(f"reset options: reset_mask must be a bool array of shape ({self.num_envs},), "
                                 f"got {m.dtype} {tuple(m.shape)}")
            worlds = m.view(self.num_worlds, self.max_agents).any(1)
        if "worlds" in options:
            w = _as_tensor(options.pop("worlds"), self.device)
            if tuple(w.shape) != (self.num_worlds,) or w.dtype != torch.bool:
                raise ValueError(f"reset options: worlds must be a bool array of shape ({self.num_worlds},), "
                                 f"got {w.dtype} {tuple(w.shape)}")
            worlds = w if worlds is None else worlds | w
        if "scenes" in options:
            with self._bar() as bar:
                new = load_scenes(options.pop("scenes"), self.num_worlds, self._seed if seed is None else seed, bar)
                ctrl = options.pop("controlled", None)
                self._building(bar)
                self.sim.set_scenes(new, ctrl, background_masks(new, self.cfg, self.background, ctrl))
            self._setup()
            worlds = None
        if options:
            raise ValueError(f"reset options: unknown keys {sorted(options)} "
                             "(known: reset_mask, worlds, scenes, controlled)")
        if worlds is not None and self._needs_reset:
            raise RuntimeError("TGVectorEnv: the first reset() resets every world (no reset_mask / worlds)")
        self.sim.reset(worlds)
        self._needs_reset = False
        self._fill_flags()
        self._ended_rows.zero_()
        if worlds is None:
            self._reset_rows.zero_()
        else:
            torch.logical_and(worlds[:, None], self._ctrl, out=self._reset_rows.view(self.num_worlds, -1))
        return self._obs, self._info()

    def step(self, actions):
        if self._needs_reset:
            raise RuntimeError("TGVectorEnv: call reset() before step()")
        a = self._check_actions(actions)
        if self.strict:
            self._check_inactive(a)
        W, A = self.num_worlds, self.max_agents
        a = a.view(W, A) if self.discrete else a.view(W, A, self.action_dim)
        if self._driver is None:
            self.sim.step(a)
        else:
            self.sim._write_actions(a)  # the user's rows first: the driver overwrites the background rows
            self._driver(self.sim)
            self.sim.step()
        self._fill_flags()
        for flags, rows in ((self.sim.world_reset, self._reset_rows), (self.sim.world_ended, self._ended_rows)):
            torch.ne(flags, 0, out=self._flag_w)
            torch.logical_and(self._flag_w[:, None], self._ctrl, out=rows.view(W, A))
        torch.ne(self.sim.terminated.view(-1), 0, out=self._term)
        torch.ne(self.sim.truncated.view(-1), 0, out=self._trunc)
        if self._has_background:
            ctrl = self._ctrl.view(-1)
            self._term.logical_and_(ctrl)
            self._trunc.logical_and_(ctrl)
        return self._obs, self._reward, self._term, self._trunc, self._info()

    def _fill_flags(self) -> None:
        torch.ne(self.sim.active.view(-1), 0, out=self._active)
        torch.ne(self.sim.alive.view(-1), 0, out=self._alive)
        if not self.cfg.auto_reset:
            # the engine's `active` still says 1 for agents truncated in a frozen (world_done) world
            torch.eq(self.sim.world_done, 0, out=self._flag_w)
            self._active.view(self.num_worlds, self.max_agents).logical_and_(self._flag_w[:, None])
        if self._has_background:
            N = self.num_envs
            ctrl = self._ctrl.view(N)
            self._active.logical_and_(ctrl)
            self._alive.logical_and_(ctrl)
            torch.mul(self.sim.reward.view(N), self._keep, out=self._reward)
            torch.mul(self.sim.cost.view(N), self._keep, out=self._cost)
            torch.mul(self.sim.reward_terms.view(N, -1), self._keep[:, None], out=self._terms_buf)

    def _info(self) -> dict:
        info = {"reward_terms": self._terms, "cost": self._cost, "active": self._active, "alive": self._alive,
                "world_ended": self._ended_rows, "world_reset": self._reset_rows}
        info.update(self._final)
        return info

    def _check_actions(self, actions) -> torch.Tensor:
        N = self.num_envs
        a = actions if isinstance(actions, torch.Tensor) else torch.as_tensor(np.asarray(actions))
        if self.discrete:
            if tuple(a.shape) != (N,):
                raise ValueError(f"actions: expected shape ({N},) (num_envs = {self.num_worlds} worlds x "
                                 f"{self.max_agents} slots) of discrete indices, got shape {tuple(a.shape)}")
            if a.dtype.is_floating_point or a.dtype.is_complex or a.dtype == torch.bool:
                raise ValueError(f"actions: discrete actions must be an integer dtype, got {a.dtype}")
        else:
            k = self.action_dim
            if tuple(a.shape) != (N, k):
                raise ValueError(f"actions: expected shape ({N}, {k}) (num_envs = {self.num_worlds} worlds x "
                                 f"{self.max_agents} slots, {k} action values), got shape {tuple(a.shape)}")
            if not a.dtype.is_floating_point:
                raise ValueError(f"actions: continuous actions must be a float dtype, got {a.dtype}")
        if a.device != self.device:
            a = a.to(self.device)
        return a.contiguous()

    def _check_inactive(self, a: torch.Tensor) -> None:
        idle = ~self._active
        diff = (a != self.noop_action) if self.discrete else (a != 0).any(-1)
        bad = torch.nonzero(idle & diff)
        if len(bad):
            rows = bad[:5, 0].tolist()
            raise ValueError(f"action for finished agent row(s) {rows}{' ...' if len(bad) > 5 else ''}: "
                             f"these rows are not active (uncontrolled slot or agent done); with strict=True "
                             f"they must hold the no-op action {self.noop_action}")

    def render(self):
        if self.render_mode is None:
            return None
        return tuple(render_world(self.sim, w) for w in self.render_worlds)

    def close_extras(self, **kwargs) -> None:
        self.sim = None


def _as_tensor(x, device) -> torch.Tensor:
    return x.to(device) if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x), device=device)


def make_vector_env(num_envs: int = 1, num_worlds: int | None = None, **kwargs) -> TGVectorEnv:
    """`gymnasium.make_vec` entry point: an env is an agent slot, so ``num_envs`` rows are
    ``num_envs / max_agents`` worlds (a multiple of the config's max_agents, default 64) and the
    env's ``num_envs`` equals the argument. Or give ``num_worlds=`` (then ``num_envs`` is
    ``num_worlds * max_agents``). make_vec's default ``num_envs=1`` means "not given": one world
    per scene of a Scene list, else one world.
    """
    if kwargs.pop("max_episode_steps", None) is not None:
        raise ValueError("max_episode_steps is not supported: episodes end with the scene's log "
                         "(its length after EngineConfig.init_steps)")
    return TGVectorEnv(num_worlds=num_worlds, num_envs=None if num_envs == 1 else num_envs, **kwargs)
