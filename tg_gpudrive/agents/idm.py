"""Reactive log replay: each vehicle follows its own logged path and timing, and brakes for whoever is in
its way (the Intelligent Driver Model, IDM, on the agents ahead along that path). Waymax's `IDMRoutePolicy`
is the same idea; here the log's timing stays the target, so a vehicle with a free path drives as its log
does and only the car-following departs from it.

    driver = IDMDriver(rows="background")       # driver(sim) before every sim.step()

Per driven vehicle and step (all in torch, batched over the driven rows):

1. **Where it is on its path**: the log's positions are its path, parameterised by arc length; the vehicle
   sits at its current position's projection, searched among the log steps around its world's step (so a
   path that comes back on itself is not short-cut), from the state alone.
2. **Tracking the log** (`a_track`): the speed that closes the gap to where the log is one step later,
   along the path, like the engine's expert tracking controller (kernels/dynamics.py `tracking_target`).
3. **Following** (`a_idm`): every present agent whose box lies across the next `reach` metres of the path
   (its half extent across the path plus the vehicle's half width) is a leader; the nearest sets the IDM
   acceleration `a_max (1 - (s* / s)^2)` with `s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))`, `s` the
   bumper gap along the path and `dv` the closing speed. Without a leader there is no bound.
4. The acceleration is the smaller of the two; the curvature is pure pursuit of the path point `lookahead`
   ahead (at least `min_lookahead` metres). Both go through the engine's action box, then the nearest grid
   bin (`closed_loop.nearest_index`, the engine's rounding).

Why its own tracker and not the world model's corrective labeller (worldmodel/closed_loop.py), which also
projects onto the log and pulls back to it: that one is gentle on purpose (labels for a model to imitate),
and as this driver's tracker it left the vehicles around the policy further off their timing, with about
twice the policy's collisions (BENCHMARKS.md, "Reactive log replay").

A vehicle delayed by a leader catches up with its log afterwards, at most `catch_up` m/s above the log's
own top speed. It does not reason about crossing traffic beyond what lies on its path, nor yield at
junctions the log did not: its log's timing is what keeps it out of conflicts, as in plain replay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from tg_gpudrive.engine.control import DRIVER_ROWS, driver_rows
from tg_gpudrive.kernels.dynamics import TRACK_GAIN_LONG
from tg_gpudrive.kernels.kinds import DYNAMICS_BICYCLE
from tg_gpudrive.worldmodel.closed_loop import nearest_index

Tensor = torch.Tensor


@dataclass(frozen=True)
class IDMParams:
    """The car-following model (SI units) and how far ahead it looks."""

    a_max: float = 2.0          # m/s^2, IDM's acceleration scale
    b: float = 3.0              # m/s^2, comfortable deceleration
    s0: float = 2.0             # m, the gap kept at a standstill
    headway: float = 1.0        # s, the time gap kept at speed (IDM's T)
    reach: float = 50.0         # m of path ahead searched for leaders
    spacing: float = 1.0        # m between the path samples leaders are matched to
    margin: float = 0.3         # m added to the half widths when asking whether a box lies across the path
    lookahead: float = 0.6      # s of speed to the pure-pursuit point ...
    min_lookahead: float = 4.0  # ... but at least this many metres
    catch_up: float = 2.0       # m/s above the log's top speed a delayed vehicle may drive

    def __post_init__(self):
        for name in ("a_max", "b", "reach", "spacing", "min_lookahead"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IDMParams.{name} must be > 0, got {getattr(self, name)}")
        for name in ("s0", "headway", "margin", "lookahead", "catch_up"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"IDMParams.{name} must be >= 0, got {getattr(self, name)}")


def idm_accel(v: Tensor, gap: Tensor, dv: Tensor, p: IDMParams) -> Tensor:
    """IDM's interaction term only (no free-road term: the log's timing sets the free speed): the
    acceleration for speed `v`, bumper gap `gap` (> 0) and closing speed `dv` = v - v_leader."""
    s_star = p.s0 + (v * p.headway + v * dv / (2.0 * math.sqrt(p.a_max * p.b))).clamp(min=0.0)
    return p.a_max * (1.0 - (s_star / gap.clamp(min=1e-3)) ** 2)


class IDMDriver:
    """`driver(sim)`: writes IDM-on-the-log actions for the background rows (`rows="background"`), every
    integrated row (`"controlled"`) or the policy's rows (`"policy"`); call it once per step, before
    `sim.step()`. Other rows are left as they are. Bicycle dynamics only (discrete or continuous)."""

    ROWS = DRIVER_ROWS
    CHUNK = 2048  # rows per leader search: its (rows, agents, path samples) tensors bound its memory
    BEHIND, AHEAD = 60, 15  # log steps searched for a vehicle's place on its path, around its world's step

    def __init__(self, rows: str = "background", params: IDMParams | None = None):
        if rows not in self.ROWS:
            raise ValueError(f"rows: expected one of {', '.join(self.ROWS)}, got {rows!r}")
        self.rows, self.p = rows, params or IDMParams()
        self._model = None  # the simulator's Model (its scene build) the cached paths belong to

    # --------------------------------------------------------------- paths
    def _bind(self, sim) -> None:
        """Cache the logged paths of `sim`'s slots: positions with gaps filled, cumulative arc length,
        logged speed and each slot's top logged speed."""
        pos = sim.slot_log("log_pos").float()  # (W, A, T, 2)
        vel = sim.slot_log("log_vel").float()
        valid = sim.slot_log("log_valid") != 0  # (W, A, T)
        W, A, T = valid.shape
        t = torch.arange(T, device=pos.device).expand(W, A, T)
        # the last valid step at or before each step, and the first at or after it (T - 1 / 0 where none)
        prev = torch.where(valid, t, torch.zeros_like(t)).cummax(-1).values
        has_prev = valid.cumsum(-1) > 0
        nxt = torch.where(valid, t, torch.full_like(t, T - 1)).flip(-1).cummin(-1).values.flip(-1)
        has_next = valid.flip(-1).cumsum(-1).flip(-1) > 0
        take = lambda x, i: x.gather(2, i[..., None].expand(*i.shape, x.shape[-1]))  # noqa: E731
        p_prev, p_next, v_prev = take(pos, prev), take(pos, nxt), take(vel, prev)
        # gaps: linear between the valid steps around them; after the log's end: on at its last velocity
        # (a vehicle whose log stops mid-episode, leaving the sensors' range, drives on rather than
        # parking where others' logs later pass); before its start: its first position
        f = ((t - prev) / (nxt - prev).clamp(min=1)).float()[..., None]
        inner = p_prev + (p_next - p_prev) * f
        after = p_prev + v_prev * ((t - prev).float() * float(sim.model.dt))[..., None]
        pos = torch.where((has_prev & has_next)[..., None], inner, torch.where(has_prev[..., None], after, p_next))
        seg = (pos[:, :, 1:] - pos[:, :, :-1]).norm(dim=-1)
        self.path = pos
        self.arc = torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], -1)  # (W, A, T)
        speed = vel.norm(dim=-1)
        # the path's own speed where the log is missing
        step_speed = torch.cat([seg, seg[..., -1:]], -1) / float(sim.model.dt)
        self.log_speed = torch.where(valid, speed, step_speed)
        self.top_speed = self.log_speed.amax(-1)  # (W, A)
        self._model = sim.model  # held, so a rebuilt simulator's new Model is never mistaken for it

    def _progress(self, sim, w: Tensor, a: Tensor) -> Tensor:
        """(R,) the path index each row (w, a) is at: of the path points from `BEHIND` steps before its
        world's log step to `AHEAD` after it, those within 0.3 m of the nearest, the one nearest in time
        to the step. A vehicle held up behind its log is found where it is; one waiting inside a logged
        stop is placed at the stop's end once the log has moved on. It depends on the state alone, so a
        resumed run drives as the uninterrupted one."""
        T = self.arc.shape[-1]
        off = torch.arange(-self.BEHIND, self.AHEAD + 1, device=w.device)
        win = (sim.world_step.long()[w][:, None] + off).clamp(0, T - 1)  # (R, K)
        d = (self.path[w[:, None], a[:, None], win] - sim.pos[w, a].float()[:, None]).norm(dim=-1)
        near = d <= d.min(-1, keepdim=True).values + 0.3
        k = torch.where(near, off.abs(), torch.full_like(off, T)).argmin(-1)
        return win.gather(1, k[:, None]).squeeze(1)

    @staticmethod
    def _arc_at(path: Tensor, arc: Tensor, pos: Tensor, idx: Tensor) -> Tensor:
        """(R,) the arc length of `pos` (R, 2) projected onto the segments either side of point `idx` of the
        rows' paths (R, T, 2) with arc lengths (R, T)."""
        T = arc.shape[-1]
        r = torch.arange(len(idx), device=idx.device)
        best_d, best_s = None, None
        for lo in (idx - 1, idx):
            lo = lo.clamp(0, T - 2)
            p0, p1, a0 = path[r, lo], path[r, lo + 1], arc[r, lo]
            seg = p1 - p0
            n = seg.norm(dim=-1).clamp(min=1e-6)
            f = (((pos - p0) * seg).sum(-1) / (n * n)).clamp(0.0, 1.0)
            d = (p0 + seg * f[..., None] - pos).norm(dim=-1)
            s = a0 + f * n
            if best_d is None:
                best_d, best_s = d, s
            else:
                best_s = torch.where(d < best_d, s, best_s)
                best_d = torch.minimum(d, best_d)
        return best_s

    @staticmethod
    def _along(path: Tensor, arc: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
        """Points and unit tangents of the rows' paths (R, T, 2) at arc lengths `s` (R, K): (R, K, 2) each,
        linear between logged points, the last segment's tangent beyond the path's end."""
        T = arc.shape[-1]
        j = torch.searchsorted(arc.contiguous(), s.contiguous(), right=True).clamp(1, T - 1)  # (R, K)
        a0, a1 = arc.gather(1, j - 1), arc.gather(1, j)
        p0 = path.gather(1, (j - 1)[..., None].expand(*j.shape, 2))
        p1 = path.gather(1, j[..., None].expand(*j.shape, 2))
        seg = p1 - p0
        f = ((s - a0) / (a1 - a0).clamp(min=1e-6)).clamp(0.0, 1.0)
        return p0 + seg * f[..., None], seg / seg.norm(dim=-1, keepdim=True).clamp(min=1e-6)

    # --------------------------------------------------------------- control
    def _leaders(self, sim, w: Tensor, a: Tensor, s_cur: Tensor) -> tuple[Tensor, Tensor]:
        """For rows (w, a) at arc lengths `s_cur`: (the bumper gap along the path to the nearest agent across
        it, that agent's speed along the path), (R,) each; the gap is inf where the path ahead is clear.
        Rows go in chunks of CHUNK, each against every agent of its world: (chunk, agents, samples)."""
        p = self.p
        K = int(p.reach / p.spacing) + 1
        pos, yaw = sim.pos.float(), sim.yaw.float()
        head = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
        L, Wd, vel = sim.length.float(), sim.width.float(), sim.vel.float()
        present = sim.present != 0
        A = pos.shape[1]
        gaps, speeds = [], []
        for c in range(0, len(w), self.CHUNK):
            wc, ac = w[c:c + self.CHUNK], a[c:c + self.CHUNK]
            s = s_cur[c:c + self.CHUNK, None] + p.spacing * torch.arange(K, device=pos.device)  # (R, K)
            pts, tan = self._along(self.path[wc, ac], self.arc[wc, ac], s)
            P = pos[wc]  # every agent of the row's world, (R, A, 2)
            d_min, k = (P[:, :, None] - pts[:, None]).norm(dim=-1).min(-1)  # (R, A)
            t_k = tan.gather(1, k[..., None].expand(*k.shape, 2))  # the path's tangent there
            cos_t = (head[wc] * t_k).sum(-1).abs()  # the other's heading against it
            sin_t = (1.0 - cos_t ** 2).clamp(min=0.0).sqrt()
            Lo, Wo = L[wc], Wd[wc]
            across = 0.5 * (Lo * sin_t + Wo * cos_t)  # the other's half extent across the path
            along = 0.5 * (Lo * cos_t + Wo * sin_t)
            ahead = ((P - pos[wc, ac][:, None]) * head[wc, ac][:, None]).sum(-1) > 0
            hit = (present[wc] & ahead & (torch.arange(A, device=pos.device) != ac[:, None])
                   & (d_min <= across + 0.5 * Wd[wc, ac][:, None] + p.margin))
            gap = torch.where(hit, k.float() * p.spacing - 0.5 * L[wc, ac][:, None] - along,
                              torch.full_like(d_min, math.inf))
            g, o = gap.min(-1)
            r = torch.arange(len(wc), device=pos.device)
            gaps.append(g)
            speeds.append((vel[wc, o] * t_k[r, o]).sum(-1).clamp(min=0.0))
        return torch.cat(gaps), torch.cat(speeds)

    def _braking(self, sim, w: Tensor, a: Tensor, s_cur: Tensor) -> Tensor:
        """(R,) IDM's acceleration behind the nearest agent across the path ahead of rows (w, a) at arc lengths
        `s_cur`; inf where the path is clear."""
        v = sim.speed[w, a].float()
        gap, v_lead = self._leaders(sim, w, a, s_cur)
        return torch.where(torch.isfinite(gap), idm_accel(v, gap, v - v_lead, self.p), torch.full_like(v, math.inf))

    def _arc_now(self, sim, w: Tensor, a: Tensor) -> Tensor:
        """(R,) the arc length along their logged paths where rows (w, a) are now (the paths cached for
        `sim`'s scenes first)."""
        if self._model is not sim.model:
            self._bind(sim)
        return self._arc_at(self.path[w, a], self.arc[w, a], sim.pos[w, a].float(), self._progress(sim, w, a))

    def braking(self, sim, w: Tensor, a: Tensor) -> Tensor:
        """(R,) IDM's acceleration behind the nearest agent across the logged path ahead of rows (w, a); inf
        where the path is clear."""
        return self._braking(sim, w, a, self._arc_now(sim, w, a))

    def actions(self, sim, w: Tensor, a: Tensor) -> tuple[Tensor, Tensor]:
        """(acceleration, curvature) of rows (w, a), (R,) each, before the action box."""
        s_cur = self._arc_now(sim, w, a)
        p, dt = self.p, float(sim.model.dt)
        T = self.arc.shape[-1]
        path, arc = self.path[w, a], self.arc[w, a]
        pos, v = sim.pos[w, a].float(), sim.speed[w, a].float()
        # tracking: the speed that reaches the log's next-step arc position
        nxt = (sim.world_step.long()[w] + 1).clamp(max=T - 1)
        r = torch.arange(len(w), device=w.device)
        s_log, v_log = arc[r, nxt], self.log_speed[w, a, nxt]
        e_long = s_log - (s_cur + v * dt) - 0.5 * (v_log - v) * dt
        v_target = (v_log + TRACK_GAIN_LONG * e_long / dt).clamp(min=0.0)
        v_target = torch.minimum(v_target, self.top_speed[w, a] + p.catch_up)
        a_track = (v_target - v) / dt
        accel = torch.minimum(a_track, self._braking(sim, w, a, s_cur))
        # pure pursuit of the path point `lookahead` ahead
        tgt, _ = self._along(path, arc, (s_cur + (p.lookahead * v).clamp(min=p.min_lookahead))[:, None])
        d = tgt[:, 0] - pos
        yaw = sim.yaw[w, a].float()
        c, s = torch.cos(yaw), torch.sin(yaw)
        x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
        return accel, 2.0 * y / (x * x + y * y).clamp(min=1e-3)

    def __call__(self, sim) -> None:
        if sim.model.dynamics != DYNAMICS_BICYCLE:
            raise ValueError("IDMDriver drives the bicycle (action_space discrete or continuous), "
                             "not delta_local")
        w, a = driver_rows(sim, self.rows).nonzero(as_tuple=True)
        if len(w) == 0:
            return
        accel, kappa = self.actions(sim, w, a)
        m = sim.model
        accel = accel.clamp(-m.max_accel, m.max_accel)
        kappa = kappa.clamp(-m.max_curvature, m.max_curvature)
        if m.discrete:
            sim.actions_index[w, a] = nearest_index(accel, kappa, sim.cfg).to(sim.actions_index.dtype)
        else:
            sim.actions[w, a, 0] = accel.to(sim.actions.dtype)
            sim.actions[w, a, 1] = kappa.to(sim.actions.dtype)

