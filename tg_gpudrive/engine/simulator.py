"""`Simulator`: the batched engine's Python API.

    sim = Simulator(scenes, EngineConfig(), device="cuda:0")
    sim.reset()
    while ...:
        sim.actions_index[:] = policy(sim.obs)   # write actions in place (or pass them to step)
        sim.step()
        sim.reward, sim.cost, sim.terminated, sim.truncated, sim.obs   # torch views, no copies

Every tensor attribute is a zero-copy torch view of an engine array on the
engine's device, shaped (W, A, ...) or (W,): the State's fields under their
own names (declared once in `engine.model.StepState`, which `Simulator`
inherits, so `sim.collided` is a typed attribute), and the Model's per-slot
arrays. Agents: `policy_agents` (bool, the policy's), `background` (driven by
a background model) and `integrated` (both: moved from the action buffers);
the others replay their logs (tg_gpudrive.engine.control decides who is which). On CUDA the whole step is
captured once as a CUDA graph; step() allocates nothing after the first call.
Worlds whose episode ended (`world_ended`) are reset to their scene's
`init_step` inside the step (`world_reset` says which; with
`auto_reset: false` they stay frozen, `world_done`, until `reset(worlds)`); the
outcomes of the finished episode are kept in the `final_*` tensors.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from typing import Sequence

import numpy as np
import torch
import warp as wp

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.engine.model import Control, Model, State, StepState, view_shape
from tg_gpudrive.kernels.collision import launch_collision, launch_ttc
from tg_gpudrive.kernels.dynamics import launch_corrective_expert, launch_expert_to_control, launch_step_agents
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM, launch_observations
from tg_gpudrive.kernels.reset import launch_force_reset, launch_respond_and_finish
from tg_gpudrive.kernels.reward import REWARD_TERMS, launch_reward
from tg_gpudrive.kernels.road import launch_road_query
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import ActionSpace, RoadType

log = logging.getLogger("tg_gpudrive")


def cuda_unavailable() -> str | None:
    """Why the engine cannot run on CUDA here (None: it can). It needs a device Warp sees (the
    kernels) and a CUDA build of torch (every tensor is a zero-copy torch view of a Warp array)."""
    try:
        wp.init()
        if not wp.is_cuda_available():
            return "no CUDA device is visible (Warp sees none)"
    except Exception as e:  # pragma: no cover - driver probing failed: as good as no device
        return f"no CUDA device is usable (Warp: {e})"
    if not torch.cuda.is_available():
        return "torch sees no CUDA device (a CPU-only torch build?)"
    return None


def cuda_available() -> bool:
    """Whether device "auto" means CUDA here."""
    return cuda_unavailable() is None


def resolve_device(device: str | torch.device | None = "auto", flag: str | None = None) -> str:
    """'auto' (or None), 'cpu', 'cuda' or 'cuda:N' -> the Warp/torch device name, 'cpu' or 'cuda:N'.

    'auto' is cuda:0 where CUDA is usable (`cuda_unavailable`), else cpu, so the same call works on a
    laptop and on a GPU node. Asking for CUDA where it is not usable is a one-line ValueError, raised
    before anything is built; `flag` names the option in its message (the CLI passes "--device")."""
    d = "auto" if device is None else str(device).strip().lower()
    name, instead = ((f"{flag} {device}", f"use {flag} cpu or auto") if flag
                     else (f"device={str(device)!r}", "use device='cpu' or 'auto'"))
    if d == "auto":
        return "cpu" if cuda_unavailable() else "cuda:0"
    if d == "cpu":
        return d
    d = "cuda:0" if d == "cuda" else d
    if not re.fullmatch(r"cuda:\d+", d):
        raise ValueError(f"{name}: expected auto, cpu, cuda or cuda:N")
    why = cuda_unavailable()
    if why:
        raise ValueError(f"{name}: {why}; {instead}")
    n = wp.get_cuda_device_count()
    if int(d[5:]) >= n:
        raise ValueError(f"{name}: only {n} CUDA device(s) visible (cuda:0 to cuda:{n - 1})")
    return d


DEBUG = os.environ.get("TG_GPUDRIVE_DEBUG", "") == "1"  # raise at the first unusable action (syncs each step)


LOG_FIELDS = {  # Model fields read through Simulator.log_at / slot_log, with their trailing shape
    "log_pos": (2,), "log_yaw": (), "log_vel": (2,), "log_valid": (),
    "expert_action": (3,), "expert_index": (), "expert_track": (2,),
}


SCRATCH_DIMS = ("CELLS", "PARTNERS", "ROADS")  # State shape kinds that are work arrays, not state


class Simulator(StepState[torch.Tensor]):
    """The engine behind a torch API: a Model, its State and Control, and torch views of them."""

    def __init__(self, scenes: Sequence[Scene], config: EngineConfig | None = None, device: str = "auto",
                 controlled: Sequence[np.ndarray] | None = None, background: Sequence[np.ndarray] | None = None):
        """`device`: "auto" (cuda:0 when CUDA is usable, else cpu), "cpu", "cuda" or "cuda:N"
        (`resolve_device`; `self.device` is the resolved name). `controlled` / `background`: per
        scene, (N,) bool masks over its agents. Controlled agents
        are the policy's; background agents are integrated from the same action buffers but driven
        by a background model (reactive traffic); all others replay their logs."""
        self.cfg = config or EngineConfig()
        self.device = resolve_device(device)
        self.is_cuda = self.device.startswith("cuda")
        self._build(list(scenes), controlled, background)

    # ------------------------------------------------------------------ setup
    def _build(self, scenes: list[Scene], controlled, background=None) -> None:
        with wp.ScopedDevice(self.device):
            self.model = Model(scenes, self.cfg, self.device, controlled, background)
            self.state = State.allocate(self.model)
            self.control = Control(self.model)
        self._graph = None
        self._corr = None  # corrective_expert's output buffers, allocated on first use
        self._steps_run = 0
        self._make_views()
        # off-road is "the box crosses a road edge": without edges it can never fire
        no_edges = [s.scene_id for s in scenes if not (np.asarray(s.road_type) == int(RoadType.ROAD_EDGE)).any()]
        self.worlds_without_road_edges = len(no_edges)
        if no_edges:
            log.warning("%d of %d worlds have no road edges, so off-road cannot fire there (scenes: %s%s)",
                        len(no_edges), len(scenes), ", ".join(sorted(set(no_edges))[:5]),
                        " ..." if len(set(no_edges)) > 5 else "")
        rep = self.model.report
        if rep.total_truncated:
            hit = sorted({s.scene_id for s, n in zip(scenes, rep.truncated_agents) if n})
            log.warning("%d agents beyond max_agents=%d dropped (least relevant first) over %d worlds; "
                        "scenes: %s%s; counts per world in sim.model.report.truncated_agents",
                        rep.total_truncated, self.max_agents, sum(1 for n in rep.truncated_agents if n),
                        ", ".join(hit[:5]), " ..." if len(hit) > 5 else "")

    def _make_views(self) -> None:
        m, s, c = self.model, self.state, self.control
        W, A, T = m.num_worlds, m.max_agents, m.num_steps
        t = wp.to_torch
        for f in dataclasses.fields(StepState):  # every State field a learner reads, as (W, A, ...) / (W,)
            setattr(self, f.name, t(getattr(s, f.name)).view(view_shape(f, m)))
        self.integrated = t(m.integrated).view(W, A)  # moved from the action buffers (policy + background)
        self.background = t(m.background).view(W, A)
        # the policy's agents: what rates, returns and learners count
        self.policy_agents = (self.integrated != 0) & (self.background == 0)
        self.slot_valid = t(m.slot_valid).view(W, A)
        self.goal = t(m.goal).view(W, A, 2)
        self.length = t(m.length).view(W, A)
        self.width = t(m.width).view(W, A)
        self.agent_type = t(m.agent_type).view(W, A)
        # the logs and expert actions, one row per slot of a distinct slot plan: read through log_at / slot_log
        P = m.num_plans
        self._logs = {name: t(getattr(m, name)).view(P, A, T, *shape) for name, shape in LOG_FIELDS.items()}
        self._world_plan = torch.as_tensor(m.world_plan, device=self.obs.device)
        self._slots = torch.arange(A, device=self.obs.device)
        self.actions = t(c.action).view(W, A, 3)
        self.actions_index = t(c.action_index).view(W, A)
        # named slices of the observation row (views too)
        k, kr = self.cfg.partner_k, self.cfg.road_k
        self.obs_ego = self.obs[..., :EGO_DIM]
        self.obs_partners = self.obs[..., EGO_DIM:EGO_DIM + k * PARTNER_DIM].view(W, A, k, PARTNER_DIM)
        self.obs_road = self.obs[..., EGO_DIM + k * PARTNER_DIM:].view(W, A, kr, ROAD_DIM)
        if self.is_cuda:
            self._torch_stream = wp.stream_from_torch(torch.cuda.current_stream(torch.device(self.device)))
            self._warp_stream = wp.get_stream(self.device)
            self._ev_in = wp.Event(self.device)
            self._ev_out = wp.Event(self.device)

    def set_scenes(self, scenes: Sequence[Scene], controlled: Sequence[np.ndarray] | None = None,
                   background: Sequence[np.ndarray] | None = None, config: EngineConfig | None = None) -> None:
        """Load a new batch of scenes (resampling); the step graph is captured again. `config` replaces
        the engine config (e.g. more slots for denser scenes, `engine.model.sized_for`)."""
        if config is not None:
            self.cfg = config
        self._build(list(scenes), controlled, background)
        self.reset()

    # -------------------------------------------------------------- properties
    @property
    def num_worlds(self) -> int:
        return self.model.num_worlds

    @property
    def max_agents(self) -> int:
        return self.model.max_agents

    @property
    def max_controlled(self) -> int:
        """C: controlled agents occupy slots [0, C) of every world (fewer in some worlds)."""
        return self.model.max_controlled

    @property
    def obs_dim(self) -> int:
        return self.model.obs_dim

    @property
    def num_actions(self) -> int:
        return self.cfg.num_actions

    @property
    def reward_term_names(self) -> tuple[str, ...]:
        return REWARD_TERMS

    @property
    def episode_length(self) -> int:
        return self.model.num_steps - 1 - self.model.init_step

    # ---------------------------------------------------------------- stepping
    def reset(self, worlds: torch.Tensor | None = None) -> None:
        """Worlds back to their scene's state at init_step (all, or where the (W,) mask `worlds`
        is true); observations refreshed. Needed after an episode ends when auto_reset is off."""
        m, s, c = self.model, self.state, self.control
        with wp.ScopedDevice(self.device):
            self._sync_in()
            if worlds is None:
                launch_force_reset(m, s, c)
                launch_road_query(m, s, c)
            else:
                mask = torch.as_tensor(worlds, device=self.device).reshape(self.num_worlds).to(torch.int32)
                launch_force_reset(m, s, c, wp.from_torch(mask.contiguous()))
                launch_road_query(m, s, c, only_reset_worlds=True)
            launch_observations(m, s, c)
            s.world_reset.zero_()
            s.world_ended.zero_()
            self._sync_out()

    def _launch_step(self) -> None:
        m, s, c = self.model, self.state, self.control
        launch_step_agents(m, s, c)
        launch_collision(m, s, c)
        launch_road_query(m, s, c)
        launch_ttc(m, s, c)
        launch_reward(m, s, c)
        launch_respond_and_finish(m, s, c)
        launch_road_query(m, s, c, only_reset_worlds=True)
        launch_observations(m, s, c)

    def step(self, actions: torch.Tensor | np.ndarray | None = None) -> None:
        """Advance every world by one step.

        `actions`: (W, A) grid indices for a discrete config, (W, A, 2) bicycle
        or (W, A, 3) delta-local actions for a continuous one; omitted, the
        action buffers (`actions_index` / `actions`) are used as they are."""
        if actions is not None:
            self._write_actions(actions)
        before = int(self.bad_actions) if DEBUG else 0  # a host sync per step, in debug mode only
        with wp.ScopedDevice(self.device):
            self._sync_in()
            if self._graph is not None:
                wp.capture_launch(self._graph)
            elif self.is_cuda and self.cfg.use_graph and self._steps_run > 0:
                # modules are loaded by the first (plain) step: capture once, replay ever after
                with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                    self._launch_step()
                self._graph = cap.graph
                wp.capture_launch(self._graph)
            else:
                self._launch_step()
            self._sync_out()
        self._steps_run += 1
        if DEBUG and int(self.bad_actions) > before:
            raise ValueError(f"step {self._steps_run}: {int(self.bad_actions) - before} acting agent(s) got an "
                             "unusable action (grid index out of range or non-finite; TG_GPUDRIVE_DEBUG=1)")

    def report(self) -> dict:
        """What the engine dropped, truncated or could not use: agents beyond max_agents (from the
        build), worlds whose scene has no road edge (off-road never fires there), unusable actions
        written into the buffers (summed over the steps so far), and the vehicles the control rule
        replays instead of giving them to the policy (marked by their file, or log-infeasible)."""
        rep = self.model.report
        return {"agents_dropped": int(rep.total_truncated), "bad_actions": int(self.bad_actions),
                "worlds_without_road_edges": self.worlds_without_road_edges,
                # vehicles the control rule keeps from the policy: they replay their logs, out of the rates
                "agents_marked_expert": int(sum(rep.marked_expert)),
                "agents_log_infeasible": int(sum(rep.log_infeasible))}

    def use_expert_actions(self) -> None:
        """Fill the action buffers with the logged (inverse-dynamics) expert actions of the current step."""
        with wp.ScopedDevice(self.device):
            self._sync_in()
            launch_expert_to_control(self.model, self.state, self.control)
            self._sync_out()

    def corrective_expert(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The expert's action from every agent's current state, (W, A, 3), and its nearest grid
        index (W, A), -1 where the log has no next state. Unlike `expert_action` (the logged
        actions, computed once along the log) this steers an agent that has drifted back to its
        log: the same tracking controller, evaluated where the agent is now (kernels/dynamics.py).
        The tensors are reused by the next call."""
        if self._corr is None:
            n, dev = self.model.num_slots, self.model.device
            self._corr = (wp.zeros(n, dtype=wp.vec3, device=dev), wp.zeros(n, dtype=wp.int32, device=dev))
        W, A = self.num_worlds, self.max_agents
        with wp.ScopedDevice(self.device):
            self._sync_in()
            launch_corrective_expert(self.model, self.state, self.control, *self._corr)
            self._sync_out()
        return wp.to_torch(self._corr[0]).view(W, A, 3), wp.to_torch(self._corr[1]).view(W, A)

    def _write_actions(self, actions) -> None:
        W, A = self.num_worlds, self.max_agents
        a = torch.as_tensor(actions, device=self.device)
        if self.cfg.action_space == ActionSpace.DISCRETE:
            if tuple(a.shape) != (W, A) or a.dtype.is_floating_point or a.dtype == torch.bool:
                raise ValueError(f"discrete actions: expected integer tensor of shape ({W}, {A}), "
                                 f"got {a.dtype} {tuple(a.shape)}")
            if a.numel() and (int(a.min()) < 0 or int(a.max()) >= self.num_actions):
                raise ValueError(f"discrete actions must lie in [0, {self.num_actions}), "
                                 f"got [{int(a.min())}, {int(a.max())}]")
            self.actions_index.copy_(a)
        else:
            k = self.cfg.act_dim
            if tuple(a.shape) != (W, A, k) or not a.dtype.is_floating_point:
                raise ValueError(f"continuous actions: expected float tensor of shape ({W}, {A}, {k}), "
                                 f"got {a.dtype} {tuple(a.shape)}")
            if not torch.isfinite(a).all():
                raise ValueError("continuous actions contain NaN or inf")
            self.actions[..., :k].copy_(a)

    # torch and warp may run on different CUDA streams: order them with events
    def _sync_in(self) -> None:
        if self.is_cuda:
            self._warp_stream.wait_stream(self._torch_stream, event=self._ev_in)

    def _sync_out(self) -> None:
        if self.is_cuda:
            self._torch_stream.wait_stream(self._warp_stream, event=self._ev_out)

    # --------------------------------------------------------------- read-outs
    def log_at(self, name: str, steps: torch.Tensor, agents: int | None = None) -> torch.Tensor:
        """Log or expert field `name` (LOG_FIELDS) of every world's first `agents` slots (all by
        default) at log steps `steps`: (W,) gives (W, agents, ...), (W, k) gives (W, agents, k, ...).
        Worlds sharing a scene share these rows in the Model; this reads them without a per-world copy."""
        x = self._logs[name]
        a = self._slots[:agents]
        st = steps.long()
        if st.dim() == 1:
            return x[self._world_plan[:, None], a[None, :], st[:, None]]
        return x[self._world_plan[:, None, None], a[None, :, None], st[:, None, :]]

    def slot_log(self, name: str) -> torch.Tensor:
        """The whole field `name` (LOG_FIELDS) per slot, (W, A, T, ...): a view when every world has
        its own slot plan, else a copy gathered from the shared rows (prefer `log_at` in loops)."""
        x = self._logs[name]
        if self.model.num_plans == self.num_worlds:
            return x  # the plans are the worlds, in world order
        return x[self._world_plan]

    def finished_episodes(self) -> dict[str, torch.Tensor]:
        """Outcomes of the controlled agents whose episode ended at the last step (1-D tensors)."""
        rows = (self.world_ended[:, None] != 0) & self.policy_agents
        return {
            "goal": self.final_goal[rows], "collided": self.final_collided[rows],
            "offroad": self.final_offroad[rows], "return": self.final_return[rows],
            "cost": self.final_cost[rows], "min_dist": self.final_min_dist[rows],
            "steps": self.final_steps[rows],
        }

    def memory_bytes(self) -> dict[str, int]:
        """Bytes of the engine's arrays (Model, State, Control) by group: obs, logs (log_*), expert
        (expert_*), roads (segments and grid tables, once per distinct scene), scratch (the broad-phase
        and observation work arrays), other (per-slot and per-world arrays). Arrays shared by
        several fields count once; torch and allocator overhead are not included."""
        groups = {"obs": 0, "logs": 0, "expert": 0, "roads": 0, "scratch": 0, "other": 0}
        seen: set[int] = set()
        scratch = {f.name for f in dataclasses.fields(self.state) if f.metadata["dims"].name in SCRATCH_DIMS}
        for obj in (self.model, self.state, self.control):
            for name, arr in vars(obj).items():
                if not isinstance(arr, wp.array) or arr.ptr in seen or arr.ptr is None:
                    continue
                seen.add(arr.ptr)
                group = ("obs" if name == "obs" else "logs" if name.startswith("log_") and name != "log_row"
                         else "expert" if name.startswith("expert_")
                         else "roads" if name.startswith(("seg_", "grid_", "cell_")) else
                         "scratch" if name in scratch else "other")
                groups[group] += arr.capacity
        return groups

    # State fields that are functions of the others: the observations (and the action mask the same kernel
    # writes) and the broad phases' scratch. Snapshots leave them out (the observations alone are most of
    # a State: with real scenes' slot counts, hundreds of MB) and `restore` recomputes them.
    DERIVED = frozenset({"obs", "active", "agent_cell", "grid_count", "grid_start", "grid_fill", "grid_items",
                         "part_d", "part_j", "heap_d", "heap_j", "road_n"})

    def snapshot(self) -> dict[str, np.ndarray]:
        """A host copy of the State but its DERIVED fields, keyed by field name (checkpoints, determinism
        checks)."""
        return {f.name: getattr(self.state, f.name).numpy().copy() for f in dataclasses.fields(self.state)
                if f.name not in self.DERIVED}

    def restore(self, snapshot: dict[str, np.ndarray]) -> None:
        """Load a State saved by `snapshot()` (same scenes and config), then recompute its DERIVED fields:
        exact resume mid-episode."""
        if "world_step" not in snapshot and "step" in snapshot:  # saved before the field was renamed
            snapshot = {**snapshot, "world_step": snapshot["step"]}
        for f in dataclasses.fields(self.state):
            if f.name in self.DERIVED:
                continue
            arr = getattr(self.state, f.name)
            if f.name not in snapshot or tuple(snapshot[f.name].shape) != tuple(arr.numpy().shape):
                raise ValueError(f"snapshot does not match this simulator's State at field '{f.name}'")
            arr.assign(snapshot[f.name])
        with wp.ScopedDevice(self.device):
            self._sync_in()
            launch_observations(self.model, self.state, self.control)
            self._sync_out()
