"""The motion history of every agent slot, kept in step with a Simulator: what the world model
reads as its temporal input and what an actor with `actor_history` > 0 sees besides its observation
(the paper's pi(a | o, h)).

History features (per agent and step, `HIST_FEATURES`), in the agent's current frame:

    field    unit     meaning
    dx, dy   m        past position in the agent's current frame (x forward, y left)
    dyaw     rad      past heading minus current heading (wrapped)
    speed    m/s      past speed
    accel    m/s^2    action that brought the agent to that state
    kappa    1/m
    valid    0/1      the agent was present at that step

With `partners` K > 0 (`actor_history_partners`), each step also holds the window of the agent's K
nearest partners (the observation's partner rows, nearest first), in the agent's current frame, as
the paper's actor sees a history of all agents (`PARTNER_HIST_FEATURES`, zero where a row is empty):

    dx, dy   m        the partner's past position
    dyaw     rad      its past heading minus the agent's current heading (wrapped)
    speed    m/s      its past speed
    valid    0/1      it was present then (and is a partner now)

It reads the Simulator's torch views and the Model's logs; it never writes engine state.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM

HIST_FEATURES = ("dx", "dy", "dyaw", "speed", "accel", "kappa", "valid")
HIST_DIM = len(HIST_FEATURES)
HIST_SCALE = [20.0, 5.0, 1.0, 20.0, 6.0, 0.3, 1.0]  # per feature, so a network sees values of order 1
PARTNER_HIST_FEATURES = ("dx", "dy", "dyaw", "speed", "valid")
PARTNER_HIST_DIM = len(PARTNER_HIST_FEATURES)
PARTNER_HIST_SCALE = [20.0, 20.0, 1.0, 20.0, 1.0]


def hist_dim(partners: int = 0) -> int:
    """Features per step of a window with `partners` partner blocks."""
    return HIST_DIM + partners * PARTNER_HIST_DIM


def hist_scale(partners: int = 0) -> list[float]:
    return HIST_SCALE + PARTNER_HIST_SCALE * partners
# raw ring entries: world-frame x, y, yaw, speed, accel, kappa, valid
_RAW_DIM = 7


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Angles into [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class HistoryBuffer:
    """Rolling (W, A, H, 7) window of every slot's states, kept in step with a Simulator.

    `sync(sim)` brings it up to the simulator's current step: one step later it
    pushes the current state; at a reset (or any other jump of `world_step`, or
    the first call) it refills the world's window from the log, whose warm-up
    steps precede `init_step`. Call it once per step before reading (the
    consumers here do), at least once every step the simulator takes."""

    def __init__(self, history: int = 10):
        self.H = history
        self.raw: torch.Tensor | None = None
        self._model = None
        self._last: torch.Tensor | None = None
        # sync without reading the host (inside a CUDA graph): the log's window is read every step and taken
        # where a world jumped, instead of only when one did
        self.fixed_shapes = False

    def _bind(self, sim) -> None:
        m = sim.model
        W, A = m.num_worlds, m.max_agents
        self._model = m
        self.raw = torch.zeros((W, A, self.H, _RAW_DIM), device=sim.pos.device)
        self._last = torch.full((W,), -10, dtype=torch.int64, device=sim.pos.device)

    def _from_log(self, sim) -> torch.Tensor:
        """(W, A, H, raw) window every world would hold at its current step had it replayed its log."""
        T = self._model.num_steps
        steps = sim.world_step.long()[:, None] + torch.arange(-self.H + 1, 1, device=self.raw.device)  # (W, H)
        ok = steps >= 0
        s = steps.clamp(0, T - 1)
        pos = sim.log_at("log_pos", s)  # (W, A, H, 2)
        yaw = sim.log_at("log_yaw", s)
        speed = sim.log_at("log_vel", s).norm(dim=-1)
        valid = sim.log_at("log_valid", s).float() * ok[:, None, :].float()
        act = sim.log_at("expert_action", (s - 1).clamp(min=0))[..., :2]
        act = act * (s > 0)[:, None, :, None].float()
        return torch.cat([pos, yaw[..., None], speed[..., None], act, valid[..., None]], dim=-1)

    def sync(self, sim) -> None:
        """Bring the window up to each world's current step: push the present state where a world
        moved one step on, refill from the log where it jumped (a reset); masked selects, so an
        ordinary step needs one host sync (whether any world must refill), none with `fixed_shapes`."""
        if self._model is not sim.model:
            self._bind(sim)
        step = sim.world_step.long()
        push = step == self._last + 1
        refill = (step != self._last) & ~push
        cur = torch.cat([sim.pos, sim.yaw[..., None], sim.speed[..., None], sim.applied_action[..., :2],
                         (sim.present != 0).float()[..., None]], dim=-1)
        rolled = torch.cat([self.raw[:, :, 1:], cur[:, :, None]], dim=2)
        new = torch.where(push[:, None, None, None], rolled, self.raw)
        if self.fixed_shapes or bool(refill.any()):
            new = torch.where(refill[:, None, None, None], self._from_log(sim), new)
        self.raw.copy_(new)  # in place: a captured graph keeps reading and writing the same window
        self._last.copy_(step)

    def state_dict(self) -> dict:
        """The window and the step it was synced at (for an exact resume mid-episode)."""
        return {} if self.raw is None else {"raw": self.raw.clone(), "last": self._last.clone()}

    def load_state_dict(self, sim, state: dict) -> None:
        self._bind(sim)
        if state:
            self.raw.copy_(state["raw"])
            self._last.copy_(state["last"])

    def features(self, sim, rows: slice | None = None, partners: int = 0) -> torch.Tensor:
        """(W, A', H, hist_dim(partners)) window in each agent's current frame (`rows`: slot slice,
        default all): its own motion, then that of its `partners` nearest partners."""
        rows = rows or slice(None)
        own = self._own_features(sim, rows)
        if not partners:
            return own
        return torch.cat([own, self._partner_features(sim, rows, partners)], dim=-1)

    def _partner_features(self, sim, rows: slice, partners: int) -> torch.Tensor:
        """(W, A', H, partners * PARTNER_HIST_DIM): the windows of each agent's nearest partners (the
        observation's partner rows, whose slots the observation kernel leaves in `part_j`)."""
        W, A, H = self.raw.shape[:3]
        K = sim.model.partner_k
        if partners > K:
            raise ValueError(f"a window of {partners} partners needs partner_k >= {partners}, got {K}")
        j = wp.to_torch(sim.state.part_j).view(W, A, K)[:, rows, :partners].long()
        part = sim.obs[:, rows, EGO_DIM:EGO_DIM + partners * PARTNER_DIM]
        present = part.reshape(*part.shape[:-1], partners, PARTNER_DIM)[..., 0] > 0.5  # the rows' present flag
        world = torch.arange(W, device=j.device)[:, None, None]
        local = torch.where(present, j - world * A, 0).clamp(0, A - 1)
        raw = self.raw[world, local]  # (W, A', K, H, raw)
        p, yaw = sim.pos[:, rows][:, :, None, None], sim.yaw[:, rows][:, :, None, None]
        c, s = torch.cos(yaw), torch.sin(yaw)
        d = raw[..., :2] - p
        dx = c * d[..., 0] + s * d[..., 1]
        dy = -s * d[..., 0] + c * d[..., 1]
        valid = raw[..., 6] * present[..., None].float()
        out = torch.stack([dx, dy, wrap_angle(raw[..., 2] - yaw), raw[..., 3], valid], dim=-1) * valid[..., None]
        return out.permute(0, 1, 3, 2, 4).reshape(W, out.shape[1], H, partners * PARTNER_HIST_DIM)

    def _own_features(self, sim, rows: slice) -> torch.Tensor:
        raw = self.raw[:, rows]
        p, yaw = sim.pos[:, rows], sim.yaw[:, rows]
        c, s = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
        d = raw[..., :2] - p[:, :, None]
        dx = c * d[..., 0] + s * d[..., 1]
        dy = -s * d[..., 0] + c * d[..., 1]
        dyaw = wrap_angle(raw[..., 2] - yaw[..., None])
        valid = raw[..., 6]
        out = torch.stack([dx, dy, dyaw, raw[..., 3], raw[..., 4], raw[..., 5], valid], dim=-1)
        return out * valid[..., None]
