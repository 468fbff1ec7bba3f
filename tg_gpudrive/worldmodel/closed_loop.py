"""Closed-loop (DAgger-style) fine-tuning data: the model drives, a log tracker labels.

A teacher-forced model only ever sees states on the log, so small errors put
it in states it never trained on and it drifts (off-road, into others). Here
every vehicle of a scene is driven by the model's own sampled actions in the
engine (everything else replays its log) and each visited state is labelled
with the *corrective* action: what a tracking controller would do from the
state the model actually reached to bring it back to its logged trajectory,
computed in torch from the simulator's state and the Model's log arrays:

    projection  the point of the log's polyline nearest the agent (ties go to the
                segment nearest in time): arc length sigma, lateral error e_y (m,
                left +), heading error e_psi (rad) against the path there
    accel       the log's own acceleration at t, plus K_S (S(t) - sigma) + K_V (v_log(t) - v):
                closes the along-track error to where the log is now and the speed error
    curvature   the path's curvature over the agent's next move, minus
                K_Y(v) e_y + K_PSI(v) e_psi with K_Y = W_LAT^2 / v^2, K_PSI = 2 W_LAT / v
                (critically damped: the lateral error decays at a rate W_LAT whatever the speed)
    then clipped to the action box (continuous) or snapped to the nearest grid bin
    (discrete; rounding stochastically to the neighbouring bins, so that the
    label's mean is the continuous action, did no better in the measurements).

On the log and on time the feedback terms vanish and the label is the
inverse of the logged motion itself (Waymax's plain bicycle inverse; the tests
check it). Off the log the feedback is gentle on purpose. The engine's
closed-loop expert (kernels/dynamics.py `tracking_target` + `bicycle_inverse`,
`sim.corrective_expert()`) reaches the wanted speed and heading in one step,
with TRACK_GAIN_LONG 0.3 of the along-track error per 0.1 s step and an aim
at the logged position at t+2; that is right on the log but dead-beat off it
(the aim can lie behind an agent that got ahead of its log: a full-lock turn
back), and fine-tuning on its labels, or on dead-beat labels projected on the
path, made the model's roll-outs collide far more (BENCHMARKS.md, "World
model"). States whose log has no state at t or t+1, or fewer than two valid
points, get no label.

The log drives through whoever the model has put in its way, so by default
(`labels` "log_brake") a label's acceleration is also at most IDM's behind the
nearest agent across the logged path ahead (agents/idm.py, the reactive log
replay's leader search): the model learns to brake for what it sees ahead.

This module only collects samples; train.py aggregates them with the
teacher-forced set and fits.
"""

from __future__ import annotations

import dataclasses

import torch

from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import wrap_angle
from tg_gpudrive.worldmodel.data import full_horizon_env, truncate_obs
from tg_gpudrive.worldmodel.prior import WorldModelDriver

_MIN_ARC = 1.0e-3  # as kernels/dynamics.py: below this arc length curvature is undefined (0)
_TIME_WEIGHT = 0.05  # m of projection cost per step between a segment and the current step
W_LONG = 0.5  # rad/s: along-track error dynamics (critically damped): K_S = W_LONG^2, K_V = 2 W_LONG
W_LAT = 1.5  # rad/s: lateral error dynamics; the gains use the speed, at least MIN_SPEED
MIN_SPEED = 2.0  # m/s


def nearest_index(accel: torch.Tensor, kappa: torch.Tensor, cfg) -> torch.Tensor:
    """Grid index ia * curvature_bins + ik of the nearest bin, as the engine's `nearest_bin`."""
    def nb(v, hi, n):
        if n <= 1:
            return torch.zeros_like(v, dtype=torch.long)
        return torch.floor((v + hi) / (2 * hi) * (n - 1) + 0.5).long().clamp(0, n - 1)

    return nb(accel, cfg.max_accel, cfg.accel_bins) * cfg.curvature_bins + nb(kappa, cfg.max_curvature,
                                                                            cfg.curvature_bins)


@dataclasses.dataclass
class CorrectiveTarget:
    """The corrective action of every slot at the current step.

    field   shape      dtype  unit
    action  (W, A, 2)  float  m/s^2, 1/m (clipped to the action box)
    index   (W, A)     int64  nearest grid index
    valid   (W, A)     bool   the log has states at t and t+1, and a path (two valid points)"""

    action: torch.Tensor
    index: torch.Tensor
    valid: torch.Tensor


def _take(x: torch.Tensor, i: torch.Tensor) -> torch.Tensor:
    """x (W, A, T[, F]) at per-slot indices i (W, A) -> (W, A[, F])."""
    if x.dim() == 4:
        return torch.gather(x, 2, i[..., None, None].expand(*i.shape, 1, x.shape[-1]))[:, :, 0]
    return torch.gather(x, 2, i[..., None])[..., 0]


def corrective_from_log(pos, yaw, vel, step, log_pos, log_yaw, log_vel, log_valid, *, dt: float,
                        cfg) -> CorrectiveTarget:
    """Corrective labels of states (pos (W, A, 2), yaw (W, A), vel (W, A, 2)) at log steps `step`
    (W,), from the logs (W, A, T[, 2]) and `log_valid` (W, A, T) bool. See the module docstring."""
    W, A, T = log_valid.shape
    t = step.long().view(W, 1).expand(W, A)
    # the log as a polyline: segments s -> s+1 between valid points, arc length S at each point
    a, ab = log_pos[:, :, :-1], log_pos[:, :, 1:] - log_pos[:, :, :-1]
    seg_ok = log_valid[:, :, :-1] & log_valid[:, :, 1:]
    seg_len = ab.norm(dim=-1) * seg_ok
    S = torch.cat([torch.zeros_like(seg_len[..., :1]), torch.cumsum(seg_len, -1)], -1)  # (W, A, T)
    rel = pos[:, :, None] - a
    u = ((rel * ab).sum(-1) / (ab * ab).sum(-1).clamp(min=1e-9)).clamp(0.0, 1.0)
    dist = (rel - u[..., None] * ab).norm(dim=-1)
    cost = dist + _TIME_WEIGHT * (torch.arange(T - 1, device=pos.device) + u - t[..., None]).abs()
    best = torch.where(seg_ok, cost, torch.full_like(cost, float("inf"))).argmin(-1)
    sigma = _take(S, best) + _take(u, best) * _take(seg_len, best)
    has_path = seg_ok.any(-1)
    last = torch.where(log_valid, torch.arange(T, device=pos.device), 0).max(-1).values  # last valid point

    def heading_at(arc: torch.Tensor) -> torch.Tensor:
        """The path's heading (logged yaw, interpolated) at arc length `arc` (W, A); constant past its ends."""
        j = torch.searchsorted(S, arc[..., None].contiguous(), right=True)[..., 0].clamp(1, T - 1)
        s0, s1 = _take(S, j - 1), _take(S, j)
        f = ((arc - s0) / (s1 - s0).clamp(min=1e-9)).clamp(0.0, 1.0)
        y0 = _take(log_yaw, j - 1)
        return torch.where(arc > _take(S, last), _take(log_yaw, last), y0 + f * wrap_angle(_take(log_yaw, j) - y0))

    t1 = (t + 1).clamp(max=T - 1)
    ok = _take(log_valid, t) & _take(log_valid, t1) & (t + 1 < T) & has_path
    speed = vel.norm(dim=-1)
    v0, v1 = _take(log_vel, t).norm(dim=-1), _take(log_vel, t1).norm(dim=-1)
    accel = (v1 - v0) / dt + W_LONG**2 * (_take(S, t) - sigma) + 2.0 * W_LONG * (v0 - speed)
    accel = accel.clamp(-cfg.max_accel, cfg.max_accel)
    # lateral and heading errors against the segment the agent projects onto
    tangent = _take(ab, best) / _take(seg_len, best).clamp(min=1e-9)[..., None]
    off = pos - (_take(a, best) + _take(u, best)[..., None] * _take(ab, best))
    e_y = tangent[..., 0] * off[..., 1] - tangent[..., 1] * off[..., 0]
    e_psi = wrap_angle(yaw - heading_at(sigma))
    arc = speed * dt + 0.5 * accel * dt * dt
    moving = arc.abs() > _MIN_ARC
    safe_arc = torch.where(moving, arc, torch.ones_like(arc))
    kappa_ff = wrap_angle(heading_at(sigma + arc.clamp(min=0.0)) - heading_at(sigma)) / safe_arc
    v = speed.clamp(min=MIN_SPEED)
    kappa = kappa_ff - (W_LAT / v) ** 2 * e_y - 2.0 * W_LAT / v * e_psi
    kappa = torch.where(moving, kappa.clamp(-cfg.max_curvature, cfg.max_curvature), torch.zeros_like(kappa))
    return CorrectiveTarget(torch.stack([accel, kappa], -1), nearest_index(accel, kappa, cfg), ok)


def corrective_target(sim) -> CorrectiveTarget:
    """Corrective labels from `sim`'s current state (sim.pos / yaw / vel) and its Model's log."""
    tgt = corrective_from_log(sim.pos, sim.yaw, sim.vel, sim.world_step, sim.slot_log("log_pos"),
                              sim.slot_log("log_yaw"), sim.slot_log("log_vel"), sim.slot_log("log_valid") != 0,
                              dt=sim.model.dt, cfg=sim.cfg)
    tgt.valid &= sim.present != 0
    return tgt


def visited_labels(sim, w: torch.Tensor, a: torch.Tensor, tgt: CorrectiveTarget, idm=None) -> torch.Tensor:
    """The labels of rows (w, a) in `sim`'s current state: their corrective target `tgt` (from
    corrective_target) or, given an agents.idm.IDMDriver `idm`, the same with IDM's braking for the nearest
    agent across the logged path ahead where that is harder (the log drives through whoever stands in its
    way). Grid indices (R,) for a discrete action space, else (accel, curvature) (R, 2) in the action box."""
    continuous = not sim.cfg.discrete
    if idm is None:
        return tgt.action[w, a] if continuous else tgt.index[w, a]
    accel = torch.minimum(tgt.action[w, a, 0], idm.braking(sim, w, a)).clamp(min=-sim.cfg.max_accel)
    kappa = tgt.action[w, a, 1]
    return torch.stack([accel, kappa], -1) if continuous else nearest_index(accel, kappa, sim.cfg)


@torch.no_grad()
def closed_loop_samples(model, scenes, env, *, horizon: int, history: int, max_partners: int, max_roads: int,
                        num_worlds: int = 16, device: str = "cpu", seed: int = 0,
                        temperature: float = 1.0, labels: str = "log_brake") -> tuple[dict, dict]:
    """Roll `model` out on `scenes` (every vehicle model-driven, from init_step, `horizon` steps;
    agents drive on through contacts and goals so every track lasts) and label each visited
    state of an active vehicle with its corrective target (`labels` "log"), or with the same braking as
    IDM for the nearest agent across the logged path ahead where that is harder ("log_brake",
    `visited_labels`).

    Returns (samples, stats): samples as data.collect (obs, hist, target: grid index or
    (accel, curvature), layout); stats: mean distance (m) of the visited states from the log,
    and the share of vehicles that collided / went off-road during the roll-outs."""
    env = full_horizon_env(env)
    kp, krr = min(env.partner_k, max_partners), min(env.road_k, max_roads)
    out = {"obs": [], "hist": [], "target": []}
    dev_sum = dev_n = 0.0
    n_veh = n_coll = n_off = 0
    was_training = model.training
    model.eval()
    idm = None
    if labels == "log_brake":
        from tg_gpudrive.agents.idm import IDMDriver  # agents.idm snaps to the grid with this module's nearest_index
        idm = IDMDriver(rows="controlled")
    elif labels != "log":
        raise ValueError(f"labels: expected log or log_brake, got {labels!r}")
    for b in range(0, len(scenes), num_worlds):
        batch = scenes[b:b + num_worlds]
        sim = Simulator(batch, sized_for(env, batch), device)  # every agent gets a slot: none is dropped
        sim.reset()
        driver = WorldModelDriver(model, rows="controlled", temperature=temperature, seed=seed + b)
        rows_all = sim.integrated != 0
        coll = torch.zeros_like(rows_all)
        off = torch.zeros_like(rows_all)
        for _ in range(min(horizon, sim.episode_length)):
            driver.history.sync(sim)
            tgt = corrective_target(sim)
            rows = (sim.active != 0) & rows_all & tgt.valid
            w, a = rows.nonzero(as_tuple=True)
            out["obs"].append(truncate_obs(sim.obs[w, a], env.partner_k, env.road_k, kp, krr).cpu())
            out["hist"].append(driver.history.features(sim)[w, a].cpu())
            out["target"].append(visited_labels(sim, w, a, tgt, idm).cpu())
            lp = sim.log_at("log_pos", sim.world_step)
            on_log = rows & (sim.log_at("log_valid", sim.world_step) != 0)
            dev_sum += float(((sim.pos - lp).norm(dim=-1) * on_log).sum())
            dev_n += float(on_log.sum())
            driver(sim)
            sim.step()
            coll |= sim.collided != 0
            off |= sim.offroad != 0
        n_veh += int(rows_all.sum())
        n_coll += int((coll & rows_all).sum())
        n_off += int((off & rows_all).sum())
    model.train(was_training)
    data = {k: torch.cat(v) for k, v in out.items()}
    data["layout"] = (kp, krr)
    stats = {"rollout_deviation_m": dev_sum / max(dev_n, 1.0), "rollout_collision_rate": n_coll / max(n_veh, 1),
             "rollout_offroad_rate": n_off / max(n_veh, 1), "visited_samples": int(data["target"].shape[0])}
    return data, stats


def rounds_schedule(total_steps: int, rounds: int) -> list[int]:
    """Minibatch steps of each round: `total_steps` split as evenly as possible."""
    per = [total_steps // rounds + (1 if r < total_steps % rounds else 0) for r in range(rounds)]
    return [p for p in per if p > 0]
