"""A safety guard over a driving policy's discrete actions, read from the agent's own observation.

An action is *unsafe* when, taken for one step and followed by the hardest braking on the same curvature
(the bicycle of kernels/dynamics.py), it brings the agent's box within `margin` of a partner's box at some
step of the next `horizon` seconds, each observed partner moving on at its observed velocity and heading.
This is the stopping-distance test of rule-based safety filters: an agent may go only where it could
still stop short of what it sees coming. The guard keeps a safe sampled action; it replaces an unsafe
one by a draw from the policy's own distribution restricted to the safe actions (the safe mode at
temperature 0); where no action is safe (a car about to run into the agent from behind, a contact
already made), it leaves the sampled action, since no choice of the agent's passes the test.

Everything is in the agent's frame (x forward, y left), as the observation gives it (kernels/observation.py):
the agent at the origin with speed `obs[:, 0]` along x, a partner at (x, y) with heading (cos, sin) relative
to the agent's and velocity relative to the agent's.
"""

from __future__ import annotations

import torch

from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM


def boxes_overlap(c1: torch.Tensor, h1: torch.Tensor, e1: torch.Tensor,
                  c2: torch.Tensor, h2: torch.Tensor, e2: torch.Tensor) -> torch.Tensor:
    """Whether oriented boxes overlap (separating-axis test), broadcasting over leading dimensions.

    c: (..., 2) centres; h: (..., 2) unit headings (cos, sin); e: (..., 2) half extents (along, across).
    Boxes that only touch count as overlapping."""
    n1 = torch.stack((-h1[..., 1], h1[..., 0]), -1)
    n2 = torch.stack((-h2[..., 1], h2[..., 0]), -1)
    d = c2 - c1
    apart = None
    for axis in (h1, n1, h2, n2):
        r1 = e1[..., 0] * (h1 * axis).sum(-1).abs() + e1[..., 1] * (n1 * axis).sum(-1).abs()
        r2 = e2[..., 0] * (h2 * axis).sum(-1).abs() + e2[..., 1] * (n2 * axis).sum(-1).abs()
        sep = (d * axis).sum(-1).abs() > r1 + r2
        apart = sep if apart is None else apart | sep
    return ~apart


class ActionGuard:
    """The guard of a discrete action `grid` ((A, 2) of (accel, curvature), agents.policy.action_grid)
    for agents that see `partner_k` partners, stepping `dt` seconds, braking at `max_accel`."""

    def __init__(self, grid: torch.Tensor, partner_k: int, dt: float, max_accel: float,
                 horizon: float, margin: float = 0.0):
        if not horizon > 0:
            raise ValueError(f"guard horizon: expected seconds > 0, got {horizon}")
        if not margin >= 0:
            raise ValueError(f"guard margin: expected metres >= 0, got {margin}")
        self.grid, self.partner_k, self.dt, self.max_accel = grid, partner_k, float(dt), float(max_accel)
        self.steps = max(1, round(horizon / dt))
        self.horizon, self.margin = float(horizon), float(margin)
        self._counts = None  # acting agents' actions (checked, replaced) so far, summed on the device

    @property
    def checked(self) -> int:
        """The acting agents' actions checked so far."""
        return 0 if self._counts is None else int(self._counts[0])

    @property
    def replaced(self) -> int:
        """... and those of them the guard replaced."""
        return 0 if self._counts is None else int(self._counts[1])

    @property
    def replaced_share(self) -> float:
        """The share of the acting agents' actions checked so far that the guard replaced."""
        return self.replaced / max(self.checked, 1)

    def ego_paths(self, speed: torch.Tensor, actions: torch.Tensor):
        """Centres and headings (..., T, 2) of the agent taking `actions` ((..., 2): accel, curvature) for one
        step, then braking at full rate on the same curvature, for T = `steps` steps (speed: (...))."""
        accel, kappa = actions[..., 0], actions[..., 1]
        pos = torch.zeros(*accel.shape, 2, dtype=speed.dtype, device=speed.device)
        yaw = torch.zeros_like(accel)
        v = speed.expand_as(accel)
        dt, centres, heads = self.dt, [], []
        for t in range(self.steps):
            a = accel if t == 0 else torch.full_like(accel, -self.max_accel)
            c, s = torch.cos(yaw), torch.sin(yaw)
            dirn = torch.stack((c, s), -1)
            pos = pos + dirn * (v * dt + 0.5 * a * dt * dt).unsqueeze(-1)
            yaw = yaw + kappa * (v * dt + 0.5 * a * dt * dt)
            v = (v + a * dt).clamp(min=0.0)
            centres.append(pos)
            heads.append(torch.stack((torch.cos(yaw), torch.sin(yaw)), -1))
        return torch.stack(centres, -2), torch.stack(heads, -2)

    def observed(self, obs: torch.Tensor):
        """The partner rows (rows, K, PARTNER_DIM) and each partner's velocity in the agent's frame (rows, K, 2)
        (the observation holds it relative to the agent's own, (speed, 0))."""
        p = obs[:, EGO_DIM: EGO_DIM + self.partner_k * PARTNER_DIM].reshape(-1, self.partner_k, PARTNER_DIM)
        speed = obs[:, 0]
        return p, p[..., 5:7] + torch.stack((speed, torch.zeros_like(speed)), -1).unsqueeze(1)

    def partners(self, obs: torch.Tensor):
        """Per observed partner (rows, K, ...): mask, centres over the horizon (rows, K, T, 2), heading, half
        extents."""
        p, vel = self.observed(obs)
        t = torch.arange(1, self.steps + 1, dtype=obs.dtype, device=obs.device) * self.dt
        centres = p[..., 1:3].unsqueeze(-2) + vel.unsqueeze(-2) * t[:, None]
        return p[..., 0] > 0.5, centres, p[..., 3:5], 0.5 * p[..., 7:9] + 0.5 * self.margin

    def within_reach(self, obs: torch.Tensor) -> torch.Tensor:
        """(rows,) bool: rows with an observed partner that either box could reach within the horizon under any
        action (a bound on both paths' lengths); the rest have no unsafe action."""
        h = self.steps * self.dt
        p, vel = self.observed(obs)
        own = (obs[:, 0] + self.max_accel * self.dt) * h + 0.5 * obs[:, 1:3].norm(dim=-1) + self.margin
        theirs = vel.norm(dim=-1) * h + 0.5 * p[..., 7:9].norm(dim=-1)
        return ((p[..., 0] > 0.5) & (p[..., 1:3].norm(dim=-1) <= own[:, None] + theirs)).any(-1)

    def unsafe(self, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(rows, C) bool: whether each of C candidate actions ((rows, C, 2)) of each row of `obs` is unsafe."""
        out = torch.zeros(actions.shape[:2], dtype=torch.bool, device=obs.device)
        rows = self.within_reach(obs).nonzero().squeeze(-1)
        if rows.numel() == 0:
            return out
        obs, actions = obs[rows], actions[rows]
        mask, pc, ph, pe = self.partners(obs)
        ec, eh = self.ego_paths(obs[:, 0, None], actions)  # (rows, C, T, 2)
        ee = 0.5 * obs[:, 1:3] + 0.5 * self.margin  # (rows, 2)
        hit = boxes_overlap(ec[:, :, None], eh[:, :, None], ee[:, None, None, None],
                            pc[:, None], ph[:, None, :, None], pe[:, None, :, None])  # (rows, C, K, T)
        out[rows] = (hit.any(-1) & mask[:, None]).any(-1)
        return out

    def __call__(self, obs: torch.Tensor, logits: torch.Tensor, sampled: torch.Tensor,
                 deterministic: bool = False, acting: torch.Tensor | None = None,
                 generator: torch.Generator | None = None) -> torch.Tensor:
        """The guarded action indices: `sampled` where safe or where nothing is; else a draw from `logits`
        (already tempered) over the safe actions, or their mode when `deterministic`. Leading dimensions
        (worlds, slots) are kept: obs (..., obs_dim), logits (..., A), sampled (...). `acting` (bool, like
        `sampled`; None: all) says which rows are agents that act, for the counts alone; `generator` draws the
        redraws (None: torch's global one), so that a driver with its own stream stays reproducible."""
        shape = sampled.shape
        acting = torch.ones_like(sampled, dtype=torch.bool) if acting is None else acting.bool()
        flat = self._guard(obs.reshape(-1, obs.shape[-1]), logits.reshape(-1, logits.shape[-1]).float(),
                           sampled.reshape(-1), deterministic, acting.reshape(-1), generator)
        return flat.reshape(shape)

    def _guard(self, obs, logits, sampled, deterministic, acting, generator):
        grid = self.grid.to(obs.device, obs.dtype)
        bad = self.unsafe(obs, grid[sampled.long()][:, None])[:, 0]
        if self._counts is None:
            self._counts = torch.zeros(2, dtype=torch.long, device=obs.device)
        self._counts[0] += acting.sum()  # no host read: the counts are read when asked for
        rows = bad.nonzero().squeeze(-1)
        if rows.numel() == 0:
            return sampled
        sub = obs[rows]
        unsafe = self.unsafe(sub, grid.expand(len(rows), *grid.shape))
        some_safe = ~unsafe.all(-1)
        masked = logits[rows].masked_fill(unsafe, float("-inf"))
        if deterministic:
            pick = masked.argmax(-1)
        elif generator is None:
            pick = torch.distributions.Categorical(logits=masked.masked_fill(~some_safe[:, None], 0.0),
                                                   validate_args=False).sample()
        else:
            probs = torch.softmax(masked.masked_fill(~some_safe[:, None], 0.0), -1)
            pick = torch.multinomial(probs, 1, generator=generator)[:, 0]
        out = sampled.clone()
        out[rows[some_safe]] = pick[some_safe].to(out.dtype)
        self._counts[1] += (some_safe & acting[rows]).sum()
        return out
