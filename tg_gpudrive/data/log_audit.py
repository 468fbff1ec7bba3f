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

`audit(scene, init_step, goal_radius)` returns the reasons per agent; `infeasible_mask` caches it in
`scene.metadata["log_audit"]` (stores keep it), keyed by the two parameters. Only the candidates of
the control rule are audited (vehicles valid at `init_step` and away from their goal): others are
never the policy's. This module must not touch the engine: it is a function of a Scene.
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.scene import Scene
from tg_gpudrive.types import AgentType, RoadType

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


def _edge_segments(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    a, b = [], []
    for kind, pts in scene.polylines():
        if kind == RoadType.ROAD_EDGE and len(pts) >= 2:
            a.append(pts[:-1])
            b.append(pts[1:])
    if not a:
        return np.zeros((0, 2), np.float64), np.zeros((0, 2), np.float64)
    return np.concatenate(a).astype(np.float64), np.concatenate(b).astype(np.float64)


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
    init = min(init_step, scene.num_steps - 1)
    cand = np.nonzero(candidates(scene, init, goal_radius))[0]
    if len(cand) == 0:
        return {}
    first, last = _windows(scene, init, goal_radius)
    pos = scene.log_pos.astype(np.float64)
    yaw = scene.log_yaw.astype(np.float64)
    length, width = scene.length.astype(np.float64), scene.width.astype(np.float64)
    diag = np.hypot(length, width)
    ea, eb = _edge_segments(scene)
    out: dict[int, list[str]] = {}
    for i in cand:
        t0, t1 = int(first[i]), int(last[i])
        if t1 < t0:
            continue
        steps = np.arange(t0, t1 + 1)[scene.log_valid[i, t0:t1 + 1]]
        reasons = []
        # overlap: partners present at the same steps, near enough for their boxes to touch
        present = scene.log_valid[:, steps].T.copy()  # (S, N)
        present[:, i] = False
        d = np.linalg.norm(pos[:, steps].transpose(1, 0, 2) - pos[i, steps][:, None], axis=-1)
        s, j = np.nonzero(present & (d < 0.5 * (diag[i] + diag)[None, :]))
        if len(s) and boxes_overlap(pos[i, steps[s]], yaw[i, steps[s]], length[i], width[i],
                                    pos[j, steps[s]], yaw[j, steps[s]], length[j], width[j]).any():
            reasons.append("overlap")
        # off-road: the road-edge segments that pass within half a diagonal of the box centre
        if len(ea):
            c = pos[i, steps]
            lo, hi = c.min(0) - 0.5 * diag[i], c.max(0) + 0.5 * diag[i]
            box = ((np.minimum(ea, eb) <= hi) & (np.maximum(ea, eb) >= lo)).all(-1)
            sa, sb = ea[box], eb[box]
            near = _segment_distance(c[:, None], sa[None], sb[None]) < 0.5 * diag[i]
            s, k = np.nonzero(near)
            if len(s) and box_crosses_segments(c[s], yaw[i, steps[s]], length[i], width[i], sa[k], sb[k]).any():
                reasons.append("offroad")
        if _jumps(scene, i, t0, t1):
            reasons.append("jump")
        if _unfollowable(scene, i, t0, t1):
            reasons.append("kinematics")
        if reasons:
            out[int(i)] = reasons
    return out


def _segment_distance(p, a, b) -> np.ndarray:
    ab = b - a
    den = (ab * ab).sum(-1)
    t = np.clip(((p - a) * ab).sum(-1) / np.where(den > 0, den, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - (a + ab * t[..., None]), axis=-1)


MIN_PLAY_STEPS = 10  # logged steps a scene must offer after init_step (1 s at 10 Hz) to be played


def unplayable(scene: Scene, init_step: int = 10, goal_radius: float = 2.0) -> str | None:
    """Why `scene` cannot be played (None: it can): its log ends within MIN_PLAY_STEPS of `init_step`,
    or it has no vehicle the control rule would drive (every candidate marked or log-infeasible).
    Sources skip such scenes and count them, so they never fill worlds. The defaults are the engine's."""
    need = init_step + 1 + MIN_PLAY_STEPS
    if scene.num_steps < need:
        return (f"too short to play: {scene.num_steps} logged steps, control starts at step {init_step} "
                f"and needs {MIN_PLAY_STEPS} more")
    cand = candidates(scene, init_step, goal_radius)
    marked = np.zeros(scene.num_agents, bool)
    marked[[int(i) for i in scene.metadata.get("mark_as_expert") or [] if 0 <= int(i) < scene.num_agents]] = True
    if not (cand & ~marked & ~infeasible_mask(scene, init_step, goal_radius)).any():
        return (f"no controllable vehicle: none is present at step {init_step}, {goal_radius:g} m or more from "
                f"its goal, unmarked and with a feasible log")
    return None


def infeasible_mask(scene: Scene, init_step: int, goal_radius: float) -> np.ndarray:
    """(N,) bool: the log-infeasible agents of `scene`, from the cached audit when its parameters match
    (scene.metadata["log_audit"]: {"init_step", "goal_radius", "agents": {index: reasons}})."""
    init = min(init_step, scene.num_steps - 1)
    cached = scene.metadata.get("log_audit")
    if not (isinstance(cached, dict) and cached.get("init_step") == init
            and cached.get("goal_radius") == float(goal_radius)):
        cached = {"init_step": init, "goal_radius": float(goal_radius),
                  "agents": {str(i): r for i, r in audit(scene, init, goal_radius).items()}}
        scene.metadata["log_audit"] = cached
    mask = np.zeros(scene.num_agents, bool)
    mask[[int(i) for i in cached["agents"]]] = True
    return mask


def infeasible_reasons(scene: Scene, init_step: int, goal_radius: float) -> dict[int, list[str]]:
    """{agent index: reasons} of the cached (or fresh) audit."""
    infeasible_mask(scene, init_step, goal_radius)
    return {int(i): list(r) for i, r in scene.metadata["log_audit"]["agents"].items()}
