"""RDP polyline simplification: removes only points within tolerance, keeps ends, reports counts."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from tg_gpudrive.data.simplify import DEFAULT_TOLERANCE_M, simplify_polyline, simplify_scene
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.scene import make_scene
from tg_gpudrive.enums import RoadType

DATA = pathlib.Path(__file__).parent / "data"
REAL = DATA / "womd_db4edc9bd0c9d18c.json"


def dist_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest segment of `line` (independent reference)."""
    p = np.asarray(points, np.float64)[:, None, :]
    a, b = np.asarray(line, np.float64)[:-1], np.asarray(line, np.float64)[1:]
    if len(line) == 1:
        return np.linalg.norm(points - line[0], axis=-1)
    ab = b - a
    L2 = (ab * ab).sum(-1)
    t = np.clip(((p - a) * ab).sum(-1) / np.where(L2 > 0, L2, 1), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1).min(-1)


def test_straight_line_collapses():
    pts = np.stack([np.linspace(0, 100, 1001), np.linspace(5, 55, 1001)], 1)
    out = simplify_polyline(pts, 0.01)
    assert np.array_equal(out, pts[[0, -1]])


def test_circle_within_tolerance():
    ang = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    pts = 20 * np.stack([np.cos(ang), np.sin(ang)], 1)
    for tol in (0.01, 0.1, 0.5, 2.0):
        out = simplify_polyline(pts, tol)
        assert 2 < len(out) < len(pts)
        assert np.array_equal(out[0], pts[0]) and np.array_equal(out[-1], pts[-1])
        assert (dist_to_polyline(pts, out) <= tol + 1e-9).all()
        # the kept points are original points, in order
        idx = [int(np.nonzero((pts == q).all(1))[0][0]) for q in out]
        assert idx == sorted(idx)


def test_long_polyline_is_not_recursive():
    # a zigzag keeps every point and splits next to one end each time: a recursive RDP
    # would go ~5000 frames deep here, past Python's default limit of 1000
    x = np.arange(5000, dtype=np.float64)
    pts = np.stack([x, np.where(np.arange(len(x)) % 2, 1.0, 0.0)], 1)
    assert len(simplify_polyline(pts, 0.1)) == len(pts)


def test_trivial_inputs():
    one = np.array([[1.0, 2.0]])
    assert np.array_equal(simplify_polyline(one, 1.0), one)
    two = np.array([[0.0, 0.0], [1.0, 1.0]])
    assert np.array_equal(simplify_polyline(two, 10.0), two)
    with pytest.raises(ValueError):
        simplify_polyline(two, -1.0)


def test_polygons_keep_closure_and_area():
    thin = np.array([[0, 0], [10, 0.01], [10, 0.02], [0, 0.03]], np.float32)  # thinner than tolerance
    square = np.array([[0, 0], [5, 0], [10, 0], [10, 10], [0, 10]], np.float32)
    scene = make_scene(
        np.zeros((1, 3, 2)), np.zeros((1, 3)),
        roads=[(RoadType.CROSSWALK, thin), (RoadType.DRIVEWAY, square), (RoadType.STOP_SIGN, [[3.0, 3.0]])],
    )
    out, report = simplify_scene(scene, 0.5)
    thin_out, square_out, stop = (out.polyline(r) for r in range(3))
    assert len(thin_out) == 3 and np.array_equal(thin_out[[0, -1]], thin[[0, -1]])
    assert np.array_equal(square_out, square[[0, 2, 3, 4]])  # only the mid-edge point goes
    assert np.array_equal(stop, [[3.0, 3.0]])
    assert report["removed"] == 2


def test_real_scene():
    scene = load_gpudrive_json(REAL)
    tol = DEFAULT_TOLERANCE_M
    out, report = simplify_scene(scene, tol)
    assert out.num_polylines == scene.num_polylines
    assert np.array_equal(out.road_type, scene.road_type) and np.array_equal(out.road_id, scene.road_id)
    assert len(out.road_points) < len(scene.road_points)
    assert (np.diff(out.road_offsets) >= 1).all()
    for r in range(scene.num_polylines):
        before, after = scene.polyline(r), out.polyline(r)
        assert np.array_equal(before[[0, -1]], after[[0, -1]])
        assert (dist_to_polyline(before, after) <= tol + 1e-5).all(), r
    # the report adds up
    assert report["before"] == len(scene.road_points) and report["after"] == len(out.road_points)
    assert report["removed"] == report["before"] - report["after"]
    by_type = report["by_type"]
    for key in ("before", "after", "removed"):
        assert sum(v[key] for v in by_type.values()) == report[key]
    for name, v in by_type.items():
        sel = scene.road_type == int(RoadType[name.upper()])
        assert v["before"] == int(np.diff(scene.road_offsets)[sel].sum())
        assert v["after"] == int(np.diff(out.road_offsets)[sel].sum())
        assert v["removed"] == v["before"] - v["after"]
    assert by_type["stop_sign"]["removed"] == 0
    assert out.metadata["simplify"] == report
    assert len(scene.road_points) == 5388  # the input scene is untouched


def test_loader_option():
    scene = load_gpudrive_json(REAL, simplify_tolerance=0.2)
    report = scene.metadata["simplify"]
    assert report["tolerance"] == 0.2
    assert report["after"] == len(scene.road_points) < report["before"]
