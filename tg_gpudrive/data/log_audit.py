"""Which logged trajectories no driver could reproduce cleanly: the log-infeasible agents.

On real WOMD scenes the expert replay is the reference every policy is measured against, yet some
logs cannot be driven without an event: the logged box already overlaps another agent's, or
crosses a road edge, or the track jumps (a detection swap teleports the box, or its heading flips)
where no vehicle could follow. GPUDrive marks such agents `mark_as_expert` in its processed files
(overlaps and road-edge crossings) and replays them; older files carry no mark, so the rule is
computed here, from the log alone, identically for every scene and every policy:

    reason     the agent's logged box, over its scoring window
    overlap    overlaps the logged box of another agent present at that step (any type)
    offroad    crosses a road edge (the engine's off-road test)
    jump       moves between two consecutive valid steps at a speed that differs from the
               previous step's by more than JUMP_SPEED_CHANGE (m/s), or turns by more than
               FLIP_YAW (rad) in one step: a tracking error, not motion
    kinematics travels where the vehicle model cannot, which drives forward only: more than
               BACKWARD_M backwards along its own heading, or more than SIDEWAYS_M sideways
               (and more than half as far as it travels ahead), summed step by step in the frame
               of its heading

The scoring window of an agent runs from `init_step` to the first later step at which its log is
within `goal_radius` of its goal (where the engine takes a controlled agent out) or its last valid
step. Geometry is the engine's: boxes overlap by separating axes and touch without colliding; a box
is off the road when a road-edge segment crosses it or has an end inside it.

`audit(scene, init_step, goal_radius)` returns the reasons per agent; `cached_audit` keeps them in
`scene.metadata["log_audit"]`, keyed by the two parameters. Only the candidates of
the control rule are audited (vehicles valid at `init_step` and away from their goal): others are
never the policy's. This module must not touch the engine: it is a function of a Scene.
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import AgentType, RoadType

REASONS = ("overlap", "offroad", "jump", "kinematics")
JUMP_SPEED_CHANGE = 10.0  # m/s between consecutive steps: 100 m/s^2, ten times a car's hardest braking
BACKWARD_M = 0.5  # m of net reversing (the noise of a parked car's track cancels out, a manoeuvre does not)
SIDEWAYS_M = 1.0  # m of net sideways travel
FLIP_YAW = 0.5  # rad in one step: 29 degrees in 0.1 s, beyond any vehicle's yaw rate


def _axes(yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c, s], -1), np.stack([-s, c], -1)


def _half_on(axis, u, v, length, width):
    """Half extent of boxes (axes u, v, sizes) projected on `axis`; all (..., 2) / (...)."""
    return 0.5 * length * np.abs((u * axis).sum(-1)) + 0.5 * width * np.abs((v * axis).sum(-1))


def boxes_overlap(pa, ya, la, wa, pb, yb, lb, wb) -> np.ndarray:
    """Elementwise separating-axis test of two sets of oriented boxes (touching is no overlap)."""
    ua, va = _axes(ya)
    ub, vb = _axes(yb)
    d = pb - pa
    hit = np.ones(d.shape[:-1], bool)
    for axis in (ua, va, ub, vb):
        r = _half_on(axis, ua, va, la, wa) + _half_on(axis, ub, vb, lb, wb)
        hit &= np.abs((d * axis).sum(-1)) < r
    return hit


def box_crosses_segments(c, yaw, length, width, a, b) -> np.ndarray:
    """Boxes (..., 2) against segments a -> b (..., 2), elementwise: the segment meets the box's
    interior (separating axes: the box's two axes and the segment's normal)."""
    u, v = _axes(yaw)
    seg = b - a
    n = np.stack([-seg[..., 1], seg[..., 0]], -1)
    hit = np.ones(np.broadcast_shapes(c.shape, a.shape)[:-1], bool)
    mid, half = 0.5 * (a + b) - c, 0.5 * seg
    for axis, r_box in ((u, 0.5 * length), (v, 0.5 * width)):
        hit &= np.abs((mid * axis).sum(-1)) < r_box + np.abs((half * axis).sum(-1))
    hit &= np.abs((mid * n).sum(-1)) < _half_on(n, u, v, length, width)
    return hit


def _windows(scene: Scene, init: int, goal_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(N,) first and last step of every agent's scoring window (last < first: no window)."""
    T = scene.num_steps
    steps = np.arange(T)
    valid = scene.log_valid & (steps >= init)
    near = valid & (np.linalg.norm(scene.log_pos - scene.goal[:, None], axis=-1) < goal_radius)
    near &= steps > init
    last_valid = np.where(valid.any(1), T - 1 - np.argmax(valid[:, ::-1], axis=1), -1)
    first_near = np.where(near.any(1), np.argmax(near, axis=1), T)
    return np.full(scene.num_agents, init), np.minimum(last_valid, first_near)


SEGMENT_M = 5.0  # m: road edges are cut into pieces no longer than this, so a piece lies near its midpoint


def _edge_segments(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The road-edge segments cut to SEGMENT_M, (E, 2) start and end points, sorted by midpoint x."""
    a, b = [], []
    for kind, pts in scene.polylines():
        if kind == RoadType.ROAD_EDGE and len(pts) >= 2:
            a.append(pts[:-1])
            b.append(pts[1:])
    if not a:
        return np.zeros((0, 2), np.float64), np.zeros((0, 2), np.float64)
    a, b = np.concatenate(a).astype(np.float64), np.concatenate(b).astype(np.float64)
    pieces = np.maximum(np.ceil(np.linalg.norm(b - a, axis=-1) / SEGMENT_M), 1).astype(np.int64)
    seg = np.repeat(np.arange(len(a)), pieces)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    f0, f1 = (k / pieces[seg])[:, None], ((k + 1) / pieces[seg])[:, None]
    ea, eb = a[seg] + (b[seg] - a[seg]) * f0, a[seg] + (b[seg] - a[seg]) * f1
    order = np.argsort(0.5 * (ea[:, 0] + eb[:, 0]), kind="stable")
    return ea[order], eb[order]


def _jumps(scene: Scene, i: int, t0: int, t1: int) -> bool:
    ok = scene.log_valid[i, t0:t1 + 1]
    if ok.sum() < 2:
        return False
    pos = scene.log_pos[i, t0:t1 + 1][ok].astype(np.float64)
    yaw = scene.log_yaw[i, t0:t1 + 1][ok].astype(np.float64)
    gap = np.diff(np.nonzero(ok)[0]) * scene.dt
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=-1) / gap
    turn = np.abs((np.diff(yaw) + np.pi) % (2 * np.pi) - np.pi)
    return bool((np.abs(np.diff(speed)) > JUMP_SPEED_CHANGE).any() or (turn > FLIP_YAW).any())


def _unfollowable(scene: Scene, i: int, t0: int, t1: int) -> bool:
    ok = np.nonzero(scene.log_valid[i, t0:t1 + 1])[0] + t0
    if len(ok) < 2:
        return False
    step = np.diff(scene.log_pos[i, ok].astype(np.float64), axis=0)
    yaw = scene.log_yaw[i, ok[:-1]].astype(np.float64)
    ahead = (step[:, 0] * np.cos(yaw) + step[:, 1] * np.sin(yaw)).sum()
    side = abs((-step[:, 0] * np.sin(yaw) + step[:, 1] * np.cos(yaw)).sum())
    return bool(ahead < -BACKWARD_M or (side > SIDEWAYS_M and side > 0.5 * abs(ahead)))


def candidates(scene: Scene, init: int, goal_radius: float) -> np.ndarray:
    """(N,) bool: the agents the control rule may give the policy before the audit: vehicles valid
    at `init` and at least `goal_radius` from their goal there."""
    init = min(init, scene.num_steps - 1)
    away = np.linalg.norm(scene.log_pos[:, init] - scene.goal, axis=-1) >= goal_radius
    return scene.log_valid[:, init] & (scene.agent_type == AgentType.VEHICLE) & away


def audit(scene: Scene, init_step: int, goal_radius: float) -> dict[int, list[str]]:
    """{agent index: reasons} of the log-infeasible candidates (`candidates`) of `scene`."""
    return audits(scene, [init_step], goal_radius)[min(init_step, scene.num_steps - 1)]


def audits(scene: Scene, init_steps, goal_radius: float) -> dict[int, dict[int, list[str]]]:
    """`audit` for several start steps at once ({init: {agent: reasons}}, inits clipped to the log): the
    overlap and road-edge tests, the costly part, run once per (agent, step) for every agent any of the
    starts makes a candidate, and each start's windows then read them."""
    inits = sorted({min(int(t), scene.num_steps - 1) for t in init_steps})
    cands = {t: np.nonzero(candidates(scene, t, goal_radius))[0] for t in inits}
    rows = np.unique(np.concatenate([c for c in cands.values()] + [np.zeros(0, np.int64)])).astype(np.int64)
    steps = np.arange(scene.num_steps)
    out: dict[int, dict[int, list[str]]] = {t: {} for t in inits}
    if len(rows) == 0:
        return out
    # (R, T) per-step events of every row from the earliest start on
    span = scene.log_valid[rows] & (steps >= inits[0])
    pos = scene.log_pos.astype(np.float64)
    yaw = scene.log_yaw.astype(np.float64)
    length, width = scene.length.astype(np.float64), scene.width.astype(np.float64)
    overlap = _overlapping(scene, rows, span, pos, yaw, length, width)
    offroad = np.zeros_like(span)
    r, t = np.nonzero(span)
    offroad[r, t] = _off_road(pos[rows[r], t], yaw[rows[r], t], length[rows[r]], width[rows[r]], *_edge_segments(scene))
    row_of = {int(i): k for k, i in enumerate(rows)}
    for init in inits:
        first, last = _windows(scene, init, goal_radius)
        for i in cands[init]:
            k, t0, t1 = row_of[int(i)], int(first[i]), int(last[i])
            if t1 < t0:
                continue
            reasons = [name for name, ev in (("overlap", overlap), ("offroad", offroad)) if ev[k, t0:t1 + 1].any()]
            if _jumps(scene, i, t0, t1):
                reasons.append("jump")
            if _unfollowable(scene, i, t0, t1):
                reasons.append("kinematics")
            if reasons:
                out[init][int(i)] = reasons
    return out


def _overlapping(scene, rows, span, pos, yaw, length, width) -> np.ndarray:
    """(R, T) bool: the steps of `span` at which row r's box overlaps another present agent's."""
    out = np.zeros_like(span)
    diag = np.hypot(length, width)
    c, t = np.nonzero(span)  # rows and steps
    if len(c) == 0:
        return out
    present = scene.log_valid[:, t].T.copy()  # (P, N): who is there at each of those steps
    present[np.arange(len(c)), rows[c]] = False
    d = np.linalg.norm(pos[:, t].transpose(1, 0, 2) - pos[rows[c], t][:, None], axis=-1)  # (P, N)
    p, j = np.nonzero(present & (d < 0.5 * (diag[rows[c], None] + diag[None, :])))
    if len(p) == 0:
        return out
    i, tt = rows[c[p]], t[p]
    hit = boxes_overlap(pos[i, tt], yaw[i, tt], length[i], width[i], pos[j, tt], yaw[j, tt], length[j], width[j])
    out[c[p][hit], tt[hit]] = True
    return out


def _off_road(c, yaw, length, width, ea, eb) -> np.ndarray:
    """(P,) bool: the boxes (centres c (P, 2), yaw and sizes (P,)) that cross a road-edge segment ea -> eb
    (`_edge_segments`: at most SEGMENT_M long). Boxes meet segments through a grid whose cells are at
    least a box's reach: each segment is listed in its midpoint's cell and the eight around it, and a box
    looks in its own cell only, then tests the segments within half its diagonal exactly."""
    out = np.zeros(len(c), bool)
    if len(ea) == 0 or len(c) == 0:
        return out
    r = 0.5 * np.hypot(length, width)
    cell = float(r.max() + 0.5 * SEGMENT_M) + 1e-6
    mid = 0.5 * (ea + eb)
    lo = np.minimum(mid.min(0), c.min(0)) - 2 * cell
    ny = int(np.ceil((np.maximum(mid.max(0), c.max(0))[1] - lo[1]) / cell)) + 3
    near = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
    seg_cells = (np.floor((mid - lo) / cell).astype(np.int64)[:, None, :] + near[None]).reshape(-1, 2)
    seg_keys = seg_cells[:, 0] * ny + seg_cells[:, 1]
    seg_of = np.repeat(np.arange(len(ea)), len(near))
    order = np.argsort(seg_keys, kind="stable")
    seg_keys, seg_of = seg_keys[order], seg_of[order]
    box_cells = np.floor((c - lo) / cell).astype(np.int64)
    box_keys = box_cells[:, 0] * ny + box_cells[:, 1]
    a, b = np.searchsorted(seg_keys, box_keys, "left"), np.searchsorted(seg_keys, box_keys, "right")
    n = b - a
    box = np.repeat(np.arange(len(c)), n)
    seg = seg_of[np.repeat(a - np.cumsum(n) + n, n) + np.arange(n.sum())]
    close = segment_distance(c[box], ea[seg], eb[seg]) < r[box]
    box, seg = box[close], seg[close]
    hit = box_crosses_segments(c[box], yaw[box], length[box], width[box], ea[seg], eb[seg])
    out[box[hit]] = True
    return out


def segment_distance(p, a, b) -> np.ndarray:
    ab = b - a
    den = (ab * ab).sum(-1)
    t = np.clip(((p - a) * ab).sum(-1) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - (a + ab * t[..., None]), axis=-1)


MIN_PLAY_STEPS = 10  # logged steps a scene must offer after init_step (1 s at 10 Hz) to be played


def marked_expert(scene: Scene) -> np.ndarray:
    """(N,) bool: the agents the source file marks `mark_as_expert` (metadata["mark_as_expert"])."""
    marked = np.zeros(scene.num_agents, bool)
    marked[[int(i) for i in scene.metadata.get("mark_as_expert") or [] if 0 <= int(i) < scene.num_agents]] = True
    return marked


def too_short(num_steps: int, cfg: EngineConfig | None = None) -> str | None:
    """Why a log of `num_steps` steps is too short to play (None: it is not): it ends within
    MIN_PLAY_STEPS of `cfg`'s init_steps (default: the engine's)."""
    init_step = (cfg or ENGINE_DEFAULTS).init_steps
    if num_steps >= init_step + 1 + MIN_PLAY_STEPS:
        return None
    return (f"too short to play: {num_steps} logged steps, control starts at step {init_step} "
            f"and needs {MIN_PLAY_STEPS} more")


def unplayable(scene: Scene, cfg: EngineConfig | None = None) -> str | None:
    """Why `scene` cannot be played (None: it can) with `cfg`'s init_steps and goal_radius (default: the
    engine's defaults): its log ends within MIN_PLAY_STEPS of init_step, or it has no vehicle the control
    rule would drive (every candidate marked or log-infeasible). Sources skip such scenes and count them,
    so they never fill worlds."""
    cfg = cfg or ENGINE_DEFAULTS
    init_step, goal_radius = cfg.init_steps, cfg.goal_radius
    short = too_short(scene.num_steps, cfg)
    if short:
        return short
    cand = candidates(scene, init_step, goal_radius)
    if not (cand & ~marked_expert(scene) & ~infeasible_mask(scene, init_step, goal_radius)).any():
        return (f"no controllable vehicle: none is present at step {init_step}, {goal_radius:g} m or more from "
                f"its goal, unmarked and with a feasible log")
    return None


ENGINE_DEFAULTS = EngineConfig()  # the init step and goal radius sources audit scenes with


def _key(init: int, goal_radius: float) -> str:
    return f"{int(init)}:{float(goal_radius):g}"


def cached_audit(scene: Scene, init_step: int, goal_radius: float) -> dict[str, list[str]]:
    """{agent index (str): reasons} of `audit`, cached in scene.metadata["log_audit"] under its parameters
    ("init:goal_radius"), so each (scene, parameters) pair is audited once."""
    init = min(init_step, scene.num_steps - 1)
    cache = scene.metadata.get("log_audit")
    if not isinstance(cache, dict):
        cache = scene.metadata["log_audit"] = {}
    key = _key(init, goal_radius)
    if key not in cache:
        cache[key] = {str(i): r for i, r in audit(scene, init, goal_radius).items()}
    return cache[key]


def infeasible_mask(scene: Scene, init_step: int, goal_radius: float) -> np.ndarray:
    """(N,) bool: the log-infeasible agents of `scene` (`cached_audit`)."""
    mask = np.zeros(scene.num_agents, bool)
    mask[[int(i) for i in cached_audit(scene, init_step, goal_radius)]] = True
    return mask


def infeasible_reasons(scene: Scene, init_step: int, goal_radius: float) -> dict[int, list[str]]:
    """{agent index: reasons} of the log-infeasible agents of `scene` (`cached_audit`)."""
    return {int(i): list(r) for i, r in cached_audit(scene, init_step, goal_radius).items()}


def carry_audit(source: Scene, shifted: Scene, k: int, init_step: int, goal_radius: float,
                max_shift: int | None = None) -> None:
    """Give `shifted` (`source` with its first `k` steps cut) its audit at `init_step` from the source's
    audit at init_step + k: the same windows of the same logs. The source's audits at every shift up to
    `max_shift` are computed together on first use (`audits`) and cached on it."""
    cache = source.metadata.get("log_audit")
    if not isinstance(cache, dict):
        cache = source.metadata["log_audit"] = {}
    if _key(min(init_step + k, source.num_steps - 1), goal_radius) not in cache:
        inits = range(init_step, init_step + max(k, max_shift or k) + 1)
        for init, found in audits(source, inits, goal_radius).items():
            cache.setdefault(_key(init, goal_radius), {str(i): r for i, r in found.items()})
    shifted.metadata["log_audit"] = {_key(init_step, goal_radius): cached_audit(source, init_step + k, goal_radius)}
