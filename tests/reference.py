"""Independent NumPy references for the engine's kernels.

Where possible they use a different algorithm from the kernel (box overlap by
polygon clipping instead of separating axes; segment crossing by solving the
2 x 2 system instead of orientation signs), so a shared mistake is unlikely.
"""

from __future__ import annotations

import numpy as np


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------------ dynamics
def bicycle_forward(pos, yaw, vel, accel, kappa, dt):
    speed = np.linalg.norm(vel, axis=-1)
    c, s = np.cos(yaw), np.sin(yaw)
    new_pos = pos + vel * dt + 0.5 * accel[..., None] * dt**2 * np.stack([c, s], -1)
    new_yaw = wrap(yaw + kappa * (speed * dt + 0.5 * accel * dt**2))
    new_speed = np.maximum(speed + accel * dt, 0.0)
    new_vel = new_speed[..., None] * np.stack([np.cos(new_yaw), np.sin(new_yaw)], -1)
    return new_pos, new_yaw, new_vel


def bicycle_inverse(yaw, vel, next_yaw, next_vel, dt, max_accel=6.0, max_kappa=0.3):
    speed = np.linalg.norm(vel, axis=-1)
    accel = np.clip((np.linalg.norm(next_vel, axis=-1) - speed) / dt, -max_accel, max_accel)
    arc = speed * dt + 0.5 * accel * dt**2
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(np.abs(arc) > 1e-3, wrap(next_yaw - yaw) / arc, 0.0)
    return accel, np.clip(kappa, -max_kappa, max_kappa)


def delta_local_forward(pos, yaw, delta):
    c, s = np.cos(yaw), np.sin(yaw)
    step = np.stack([c * delta[..., 0] - s * delta[..., 1], s * delta[..., 0] + c * delta[..., 1]], -1)
    return pos + step, wrap(yaw + delta[..., 2])


# ------------------------------------------------------------------ geometry
def box_corners(c, yaw, length, width):
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-np.sin(yaw), np.cos(yaw)])
    hl, hw = 0.5 * length, 0.5 * width
    return np.array([c + hl * u + hw * v, c - hl * u + hw * v, c - hl * u - hw * v, c + hl * u - hw * v])


def _clip(subject, a, b):
    """Sutherland-Hodgman: keep the part of polygon `subject` left of edge a->b (CCW clip polygon)."""
    out = []
    side = lambda p: (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])  # noqa: E731
    for i in range(len(subject)):
        p, q = subject[i], subject[(i + 1) % len(subject)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp >= 0) != (sq >= 0):
            t = sp / (sp - sq)
            out.append(p + t * (q - p))
    return out


def polygon_area(poly):
    if len(poly) < 3:
        return 0.0
    p = np.asarray(poly)
    return 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], -1)) - np.dot(p[:, 1], np.roll(p[:, 0], -1)))


def box_overlap_area(a, b):
    """Intersection area of two boxes given as (x, y, yaw, length, width)."""
    pa = box_corners(np.array(a[:2]), a[2], a[3], a[4])
    pb = list(box_corners(np.array(b[:2]), b[2], b[3], b[4]))
    for i in range(4):
        pb = _clip(pb, pa[i], pa[(i + 1) % 4])
        if not pb:
            return 0.0
    return polygon_area(pb)


def segments_intersect(p1, p2, q1, q2):
    """Proper crossing by solving p1 + s (p2 - p1) = q1 + t (q2 - q1) with 0 < s, t < 1."""
    d1, d2 = p2 - p1, q2 - q1
    m = np.array([[d1[0], -d2[0]], [d1[1], -d2[1]]])
    if abs(np.linalg.det(m)) < 1e-12:
        return False
    s, t = np.linalg.solve(m, q1 - p1)
    return 0 < s < 1 and 0 < t < 1


def point_in_box(p, c, yaw, length, width):
    d = p - c
    lu = d[0] * np.cos(yaw) + d[1] * np.sin(yaw)
    lv = -d[0] * np.sin(yaw) + d[1] * np.cos(yaw)
    return abs(lu) < 0.5 * length and abs(lv) < 0.5 * width


def box_crosses_segment(c, yaw, length, width, a, b):
    k = box_corners(c, yaw, length, width)
    if any(segments_intersect(k[i], k[(i + 1) % 4], a, b) for i in range(4)):
        return True
    return point_in_box(a, c, yaw, length, width) or point_in_box(b, c, yaw, length, width)


def point_segment_distance(p, a, b):
    ab = b - a
    den = float(ab @ ab)
    t = 0.0 if den == 0 else np.clip((p - a) @ ab / den, 0, 1)
    return float(np.linalg.norm(p - (a + t * ab)))


def to_local(d, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


def expert_track(pos, yaw, vel, valid, init, dt=0.1, gain_long=0.3, gain_lat=1.0, max_accel=6.0, max_kappa=0.3):
    """Closed-loop expert of one agent (kernels/dynamics.py expert_actions_kernel), written out step by step."""
    T = len(pos)
    p, y, v = pos[0].astype(np.float64), float(yaw[0]), vel[0].astype(np.float64)
    out = np.zeros((T, 2))
    seen = False
    for t in range(T):
        if t <= init or not seen:
            if valid[t]:
                p, y, v, seen = pos[t].astype(np.float64), float(yaw[t]), vel[t].astype(np.float64), True
        out[t] = p
        if t == T - 1 or not seen:
            continue
        if not valid[t + 1]:  # a gap in the log: coast with the no-op action
            if t >= init:
                p, y, v = bicycle_forward(p, np.array(y), v, np.array(0.0), np.array(0.0), dt)
                y = float(y)
            continue
        y_t, s_t = float(yaw[t + 1]), float(np.linalg.norm(vel[t + 1]))
        if t >= init:
            h = np.array([np.cos(y), np.sin(y)])
            sp = np.linalg.norm(v)
            e = (pos[t + 1] - p - v * dt) @ h - 0.5 * (s_t - sp) * dt
            s_t = max(s_t + gain_long * e / dt, 0.0)
            if t + 2 < T and valid[t + 2]:
                d = pos[t + 2] - (p + h * 0.5 * (sp + s_t) * dt)
                if np.linalg.norm(d) > 0.5:
                    y_t = y_t + gain_lat * wrap(np.arctan2(d[1], d[0]) - y_t)
        a, k = bicycle_inverse(np.array(y), v, np.array(y_t), np.array([s_t, 0.0]), dt, max_accel, max_kappa)
        if t >= init:
            p, y, v = bicycle_forward(p, np.array(y), v, a, k, dt)
            y = float(y)
    return out


def scene_segments(scene, max_len: float, tolerance: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Road polylines, simplified to `tolerance` (the NumPy RDP of tg_gpudrive.data.simplify; 0: every
    point), as segments of at most `max_len` metres: (a (S,2), b (S,2), type (S,))."""
    if tolerance > 0:
        from tg_gpudrive.data.simplify import simplify_scene
        scene = simplify_scene(scene, tolerance)[0]
    pts, off = scene.road_points, scene.road_offsets
    if scene.num_polylines == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros(0, np.int32)
    counts = np.diff(off)
    # a segment between consecutive points of the same polyline; single points become degenerate segments
    same = np.ones(len(pts) - 1, bool)
    same[off[1:-1] - 1] = False  # a polyline's last point and the next polyline's first
    starts = np.nonzero(same)[0]
    types = np.repeat(scene.road_type, counts - 1)
    single = np.nonzero(counts == 1)[0]
    # np.take: row gathers of (S, 2) arrays, an order of magnitude faster than fancy indexing
    a = np.concatenate([np.take(pts, starts, axis=0), pts[off[single]]])
    b = np.concatenate([np.take(pts, starts + 1, axis=0), pts[off[single]]])
    types = np.concatenate([types, scene.road_type[single]]).astype(np.int32)
    d = b - a
    seg_len = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    pieces = np.maximum(1, np.ceil(seg_len / max_len).astype(np.int64))
    rep = np.repeat(np.arange(len(a)), pieces)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    f0 = (k / pieces[rep])[:, None].astype(np.float32)
    f1 = ((k + 1) / pieces[rep])[:, None].astype(np.float32)
    a, d = np.take(a, rep, axis=0), np.take(d, rep, axis=0)
    return (a + f0 * d).astype(np.float32), (a + f1 * d).astype(np.float32), types[rep]
