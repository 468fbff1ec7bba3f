"""Road polyline simplification (Ramer-Douglas-Peucker) for smaller scenes.

WOMD maps sample lanes and edges densely, so long straight stretches carry many
collinear points that cost memory and per-step road-point work in the engine
without changing geometry. RDP keeps a subset of the original points such that
every dropped point lies within `tolerance` of the simplified polyline; points
are never moved. Endpoints are always kept, so polygons (crosswalks, speed
bumps, driveways, stored open with an implied closing edge last -> first) keep
their closing edge exactly, and keep at least 3 corners. Single points (stop
signs) and 2-point segments pass through unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import POLYGON_ROAD_TYPES, RoadType

__all__ = ["DEFAULT_TOLERANCE_M", "rdp_mask", "simplify_polyline", "simplify_scene", "point_segment_distance"]

DEFAULT_TOLERANCE_M = 0.1
"""Default simplification tolerance in metres.

0.1 m is far below a lane width (~3.5 m) and a vehicle width (~2 m), and below
the noise of the surveyed map itself, so collision, off-road and lane-keeping
checks move by at most 10 cm. It is also well within WOMD's ~0.5 m spacing of
map points, so only points that are (nearly) collinear with their neighbours
go: curves keep their shape and straight segments collapse to their ends.
"""



def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points `p` (..., 2) to the segment a-b (zero-length: to point a)."""
    p, a, b = (np.asarray(x, np.float64) for x in (p, a, b))
    ab = b - a
    denom = float(ab @ ab) if ab.ndim == 1 else (ab * ab).sum(-1)
    ap = p - a
    if np.ndim(denom) == 0:
        t = np.clip((ap @ ab) / denom, 0.0, 1.0) if denom > 0 else np.zeros(p.shape[:-1])
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(denom > 0, np.clip((ap * ab).sum(-1) / denom, 0.0, 1.0), 0.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


def rdp_mask(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Boolean mask of the points RDP keeps; iterative (an explicit stack, no recursion)."""
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    k = len(pts)
    keep = np.ones(k, bool)
    if k <= 2:
        return keep
    keep[1:-1] = False
    stack = [(0, k - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        d = point_segment_distance(pts[i + 1: j], pts[i], pts[j])
        m = int(np.argmax(d))
        if d[m] > tolerance:
            mid = i + 1 + m
            keep[mid] = True
            stack.append((i, mid))
            stack.append((mid, j))
    return keep


def simplify_polyline(points: np.ndarray, tolerance: float = DEFAULT_TOLERANCE_M) -> np.ndarray:
    """Simplified copy of a (k, 2) polyline: a subset of its points, endpoints kept."""
    pts = np.asarray(points)
    return pts[rdp_mask(pts, tolerance)].copy()


def _polygon_mask(pts: np.ndarray, tolerance: float) -> np.ndarray:
    keep = rdp_mask(pts, tolerance)
    if len(pts) >= 3 and keep.sum() < 3:
        # a polygon thinner than the tolerance would collapse to a segment: keep its widest corner
        d = point_segment_distance(pts[1:-1], pts[0], pts[-1])
        keep[1 + int(np.argmax(d))] = True
    return keep


def simplify_scene(scene: Scene, tolerance: float = DEFAULT_TOLERANCE_M) -> tuple[Scene, dict]:
    """Simplify every road polyline of `scene`; return (new scene, report).

    The polyline count, order, types and ids are unchanged, so lane_edges and
    traffic-signal lanes stay valid. The report (also stored in the new scene's
    metadata["simplify"]) is JSON-safe:

        {"tolerance": t, "before": P, "after": P', "removed": P - P',
         "by_type": {"lane": {"before": ., "after": ., "removed": .}, ...}}
    """
    pts = np.asarray(scene.road_points, np.float32)
    off = np.asarray(scene.road_offsets, np.int64)
    keep = np.ones(len(pts), bool)
    for r in range(scene.num_polylines):
        a, b = int(off[r]), int(off[r + 1])
        if b - a <= 2:
            continue
        rtype = int(scene.road_type[r])
        keep[a:b] = (_polygon_mask if rtype in POLYGON_ROAD_TYPES else rdp_mask)(pts[a:b], tolerance)
    counts = np.concatenate([[0], np.cumsum(keep)])
    new_off = counts[off].astype(np.int64)
    by_type: dict[str, dict[str, int]] = {}
    for rtype in RoadType:
        sel = scene.road_type == int(rtype)
        if not sel.any():
            continue
        before = int((off[1:] - off[:-1])[sel].sum())
        after = int((new_off[1:] - new_off[:-1])[sel].sum())
        by_type[rtype.name.lower()] = {"before": before, "after": after, "removed": before - after}
    report = {
        "tolerance": float(tolerance),
        "before": int(len(pts)),
        "after": int(keep.sum()),
        "removed": int(len(pts) - keep.sum()),
        "by_type": by_type,
    }
    out = dataclasses.replace(scene.copy(), road_points=pts[keep].copy(), road_offsets=new_off)
    out.metadata["simplify"] = report
    return out.validate(), report
