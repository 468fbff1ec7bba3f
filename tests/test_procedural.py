"""Procedural generator: invariants of every scene type, determinism, parameters.

The geometric checks here are written independently of the generator's own
(data/procedural/checks.py): box corners against segment crossings rather than its
separating-axis code, so a bug in one is not mirrored in the other.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tg_gpudrive.data.procedural import SCENARIO_TYPES, ProceduralParams, generate_scene, generate_scenes
from tg_gpudrive.enums import AgentType, RoadType

SEEDS = range(5)
MARGIN = 0.15  # m added to each half extent: boxes stay 0.3 m apart
MAX_CURV = 0.25
MAX_ACC = 4.0

_CACHE: dict = {}


def scene(kind, seed):
    if (kind, seed) not in _CACHE:
        _CACHE[kind, seed] = generate_scene(kind, seed)
    return _CACHE[kind, seed]


# ----------------------------------------------------------------------------- reference geometry
def corners(c, yaw, hl, hw):
    """(..., 4, 2) box corners, counter-clockwise."""
    u = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    v = np.stack([-u[..., 1], u[..., 0]], -1)
    hl, hw = np.asarray(hl)[..., None], np.asarray(hw)[..., None]
    return np.stack([c + hl * u + hw * v, c - hl * u + hw * v, c - hl * u - hw * v, c + hl * u - hw * v], -2)


def _cross(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def segments_cross(p1, p2, q1, q2):
    """Closed segments p1-p2 and q1-q2 intersect (orientation test, collinear touching included)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    proper = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    # exclude collinear-but-disjoint cases
    col = (d1 == 0) & (d2 == 0)
    if col.any():
        lo = np.minimum(p1, p2)
        hi = np.maximum(p1, p2)
        lo2, hi2 = np.minimum(q1, q2), np.maximum(q1, q2)
        overlap = ((lo <= hi2) & (lo2 <= hi)).all(-1)
        proper = np.where(col, overlap, proper)
    return proper


def inside_convex(pt, quad):
    """pt (..., 2) inside the ccw quad (..., 4, 2)."""
    ok = np.ones(pt.shape[:-1], bool)
    for k in range(4):
        ok &= _cross(quad[..., k, :], quad[..., (k + 1) % 4, :], pt) >= 0
    return ok


def boxes_touch(ca, cb):
    """Two convex quads intersect: an edge crossing or one containing the other's corner."""
    hit = np.zeros(ca.shape[:-2], bool)
    for k in range(4):
        for m in range(4):
            hit |= segments_cross(ca[..., k, :], ca[..., (k + 1) % 4, :], cb[..., m, :], cb[..., (m + 1) % 4, :])
    hit |= inside_convex(ca[..., 0, :], cb) | inside_convex(cb[..., 0, :], ca)
    return hit


def vehicle_overlaps(sc, margin=MARGIN):
    n, t = sc.log_valid.shape
    cs = corners(sc.log_pos.astype(np.float64), sc.log_yaw.astype(np.float64),
                 (sc.length / 2 + margin)[:, None], (sc.width / 2 + margin)[:, None])  # (N, T, 4, 2)
    bad = []
    for i in range(n):
        for j in range(i + 1, n):
            d = np.linalg.norm(sc.log_pos[i] - sc.log_pos[j], axis=-1)
            near = d < (np.hypot(sc.length[i], sc.width[i]) + np.hypot(sc.length[j], sc.width[j])) / 2 + 2 * margin
            if near.any():
                ts = np.flatnonzero(near)
                hit = boxes_touch(cs[i, ts], cs[j, ts])
                bad += [(int(s), i, j) for s in ts[hit]]
    return bad


def edge_segments(sc):
    segs = [np.stack([p[:-1], p[1:]], 1) for k, p in sc.polylines() if k == RoadType.ROAD_EDGE and len(p) > 1]
    return np.concatenate(segs).astype(np.float64)


def offroad_hits(sc):
    segs = edge_segments(sc)
    n, t = sc.log_valid.shape
    cs = corners(sc.log_pos.astype(np.float64), sc.log_yaw.astype(np.float64),
                 (sc.length / 2)[:, None], (sc.width / 2)[:, None]).reshape(-1, 4, 2)
    ctr = sc.log_pos.reshape(-1, 2).astype(np.float64)
    rad = np.repeat(np.hypot(sc.length, sc.width) / 2, t)
    mid = segs.mean(1)
    half = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=-1) / 2
    hits = []
    for start in range(0, len(ctr), 256):
        sl = slice(start, start + 256)
        d = np.linalg.norm(ctr[sl, None] - mid[None], axis=-1)
        bi, si = np.nonzero(d < rad[sl, None] + half[None] + 0.01)
        bi = bi + start
        box = cs[bi]
        p, q = segs[si, 0], segs[si, 1]
        hit = inside_convex(p, box) | inside_convex(q, box)
        for k in range(4):
            hit |= segments_cross(box[:, k], box[:, (k + 1) % 4], p, q)
        hits += [(int(b // t), int(b % t), int(s)) for b, s in zip(bi[hit], si[hit])]
    return hits


def point_polyline_distance(pt, poly):
    a, b = poly[:-1].astype(np.float64), poly[1:].astype(np.float64)
    ab = b - a
    w = np.clip(((pt - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    return float(np.linalg.norm(a + w[:, None] * ab - pt, axis=-1).min())


# ----------------------------------------------------------------------------- scene checks
def check_invariants(sc, tag=""):
    sc.validate()
    n, t = sc.log_valid.shape
    p = sc.metadata["params"]
    k = sc.metadata["num_parked"]
    assert 2 <= n - k <= p["max_vehicles"] and k <= p["max_parked"], tag
    assert t == p["num_steps"] and sc.dt == pytest.approx(p["dt"]), tag
    assert sc.log_valid.all(), tag
    assert (sc.agent_type == AgentType.VEHICLE).all()
    car = (sc.length >= 4.0) & (sc.length <= 5.5) & (sc.width >= 1.8) & (sc.width <= 2.2)
    truck = (sc.length > 5.5) & (sc.length <= 14.0) & (sc.width >= 2.0) & (sc.width <= 2.6)  # long_vehicles
    assert (car | (truck if p.get("long_vehicles", 0.0) > 0 else False)).all(), tag
    for arr in (sc.log_pos, sc.log_yaw, sc.log_vel, sc.goal, sc.road_points):
        assert np.isfinite(arr).all(), tag
    md = sc.metadata
    assert md["source"] == "procedural" and md["scenario_type"] in SCENARIO_TYPES
    assert isinstance(md["params"], dict) and len(md["conflict_point"]) == 2
    assert np.linalg.norm(md["conflict_point"]) < 5.0, "coordinates centred on the conflict point"
    assert sc.is_sdc.sum() == 1, tag
    assert vehicle_overlaps(sc) == [], tag
    assert offroad_hits(sc) == [], tag


def movers(sc):
    """The moving vehicles: parked cars follow them in the agent order."""
    return slice(0, sc.num_agents - sc.metadata["num_parked"])


def check_kinematics(sc, tag=""):
    m = movers(sc)
    pos, yaw, vel = (x[m].astype(np.float64) for x in (sc.log_pos, sc.log_yaw, sc.log_vel))
    speed = np.linalg.norm(vel, axis=-1)
    # velocity along the heading
    head = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    assert np.abs(vel - speed[..., None] * head).max() < 1e-3, tag
    acc = np.diff(speed, axis=1) / sc.dt
    assert np.abs(acc).max() <= MAX_ACC + 1e-3, tag
    step = np.diff(pos, axis=1)
    dist = np.linalg.norm(step, axis=-1)
    # positions advance at the logged speed (trapezoid)
    assert np.abs(dist / sc.dt - 0.5 * (speed[:, 1:] + speed[:, :-1])).max() < 0.05, tag
    # heading is the direction of motion
    moving = dist > 0.05
    dyaw = (np.diff(yaw, axis=1) + np.pi) % (2 * np.pi) - np.pi
    mid = yaw[:, :-1] + dyaw / 2
    err = np.abs((np.arctan2(step[..., 1], step[..., 0]) - mid + np.pi) % (2 * np.pi) - np.pi)
    assert err[moving].max() < 0.05, tag
    # curvature of a kinematic bicycle
    assert (np.abs(dyaw) <= MAX_CURV * dist + 1e-5).all(), tag
    # everyone moves after the first second (scaled to the episode); most cover some ground
    t = sc.num_steps
    ref = min(10, t - 1)
    assert (dist[:, ref:].sum(1) > 5.0 * (t - 1 - ref) / 80).all(), tag
    if t == 91:  # most vehicles drive through; starts from rest stand up to 5 s of the 9 at their stop line
        assert np.mean(dist.sum(1) > 15.0) >= (0.4 if sc.metadata["params"].get("rest_starts") else 0.6), tag


def check_routes_and_goals(sc, tag=""):
    lanes = set(np.flatnonzero(sc.road_type == RoadType.LANE).tolist())
    edges = set(map(tuple, sc.lane_edges.tolist()))
    assert len(edges) and all(a in lanes and b in lanes for a, b in edges), tag
    routes = sc.metadata["routes"]
    kerb = set(sc.metadata["kerb_stops"])
    changes = {i: (lane, done) for i, lane, done in sc.metadata["lane_changes"]}
    offsets = np.abs(sc.metadata["lane_offsets"])  # drivers off the lane centre (lane_offset)
    assert len(routes) == sc.num_agents - sc.metadata["num_parked"]
    for i, route in enumerate(routes):
        assert all(k in lanes for k in route), tag
        assert all((a, b) in edges for a, b in zip(route[:-1], route[1:])), f"{tag}: illegal route {route}"
        assert np.allclose(sc.goal[i], sc.log_pos[i, -1])
        d_goal = point_polyline_distance(sc.goal[i].astype(np.float64), sc.polyline(route[-1]))
        if i in kerb:  # parked at the kerb: in the strip beside its last lane, off the lane centre
            assert 2.0 < d_goal < 4.5, tag
            continue
        if i in changes:  # changed onto the parallel lane `lane` (one lane width away), share `done` of it
            lane, done = changes[i]
            assert lane in lanes and lane not in route, tag
            width = sc.metadata["params"]["lane_width"]
            d_other = point_polyline_distance(sc.goal[i].astype(np.float64), sc.polyline(lane))
            assert abs(d_goal - done * width) < 0.35 and abs(d_other - (1 - done) * width) < 0.35, tag
            assert 0.0 < done <= 1.0 and d_goal + d_other == pytest.approx(width, abs=0.35), tag
            continue
        assert d_goal < offsets[i] + 0.05, tag
        assert point_polyline_distance(sc.log_pos[i, 0].astype(np.float64), sc.polyline(route[0])) < offsets[i] + 0.05, tag
    kinds = set(np.unique(sc.road_type).tolist())
    assert {RoadType.LANE, RoadType.ROAD_EDGE, RoadType.ROAD_LINE} <= kinds, tag
    # polylines are dense enough for observation sampling
    for k, p in sc.polylines():
        if k in (RoadType.LANE, RoadType.ROAD_EDGE) and len(p) > 1:
            assert np.linalg.norm(np.diff(p, axis=0), axis=-1).max() <= 2.0 + 1e-3, tag


def check_all(sc, tag=""):
    """Every invariant of a scene: boxes, kinematics, routes and goals."""
    check_invariants(sc, tag)
    check_kinematics(sc, tag)
    check_routes_and_goals(sc, tag)


# ----------------------------------------------------------------------------- invariants per type
@pytest.mark.parametrize("kind", SCENARIO_TYPES)
def test_invariants(kind):
    for seed in SEEDS:
        sc = scene(kind, seed)
        assert sc.metadata["scenario_type"] == kind and sc.metadata["seed"] == seed
        assert sc.num_steps == 91 and sc.dt == pytest.approx(0.1) and sc.num_agents <= 32
        check_invariants(sc, f"{kind} seed {seed}")


@pytest.mark.parametrize("kind", SCENARIO_TYPES)
def test_kinematics(kind):
    for seed in SEEDS:
        check_kinematics(scene(kind, seed), f"{kind} seed {seed}")


@pytest.mark.parametrize("kind", SCENARIO_TYPES)
def test_routes_and_goals(kind):
    for seed in SEEDS:
        check_routes_and_goals(scene(kind, seed), f"{kind} seed {seed}")


@pytest.mark.parametrize("params", [
    dict(lane_width=3.2, num_lanes=1), dict(lane_width=4.5, size_scale=1.6), dict(density=3.0, speed_mean=14.0),
    dict(num_lanes=4, time_headway=0.8, min_gap=1.0, max_accel=2.5, comfort_decel=3.5), dict(num_steps=40, dt=0.2),
], ids=lambda p: ",".join(f"{k}={v}" for k, v in p.items()))
def test_invariants_other_params(params):
    p = ProceduralParams(**params)
    for kind in SCENARIO_TYPES:
        sc = generate_scene(kind, 77, p)
        tag = f"{kind} {params}"
        check_invariants(sc, tag)
        check_kinematics(sc, tag)
        check_routes_and_goals(sc, tag)


def test_deterministic_and_distinct():
    for kind in SCENARIO_TYPES:
        a, b = generate_scene(kind, 3), scene(kind, 3)
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y), f"{kind}: {f.name} differs between runs"
        assert a.metadata == b.metadata
        firsts = [scene(kind, s).log_pos[:, 0] for s in SEEDS]
        roads = [scene(kind, s).road_points for s in SEEDS]
        for i in range(len(firsts)):
            for j in range(i + 1, len(firsts)):
                assert firsts[i].shape != firsts[j].shape or not np.allclose(firsts[i], firsts[j]), kind
                assert roads[i].shape != roads[j].shape or not np.allclose(roads[i], roads[j]), kind


def test_generate_scenes_cycles_types():
    scenes = generate_scenes("all", 7, seed=40)
    assert [s.metadata["scenario_type"] for s in scenes] == list(SCENARIO_TYPES) + [SCENARIO_TYPES[0]]
    assert [s.metadata["seed"] for s in scenes] == list(range(40, 47))
    one = generate_scenes("roundabout", 2, seed=3)
    assert np.array_equal(one[1].log_pos, scene("roundabout", 4).log_pos)


def test_density_changes_vehicle_count():
    sparse = [generate_scene("dual_lane_intersection", s, ProceduralParams(density=0.3)).num_agents for s in range(4)]
    dense = [generate_scene("dual_lane_intersection", s, ProceduralParams(density=3.0)).num_agents for s in range(4)]
    assert np.mean(dense) > np.mean(sparse) + 3, (sparse, dense)


def test_params_change_geometry():
    sc = generate_scene("t_junction", 1, ProceduralParams(num_lanes=2, lane_width=4.0, speed_mean=6.0))
    assert sc.metadata["params"]["lane_width"] == 4.0
    assert sc.metadata["geometry"]["lanes_per_direction"] == [2, 2]
    assert sc.log_vel.shape[1] == 91
    short = generate_scene("merge", 2, ProceduralParams(num_steps=40, dt=0.2))
    assert short.num_steps == 40 and short.dt == pytest.approx(0.2)


def test_unknown_type_and_bad_params():
    with pytest.raises(ValueError, match="roundabout"):
        generate_scene("spaghetti_junction", 0)
    with pytest.raises(ValueError, match="merge"):
        generate_scenes("nope", 2, 0)
    with pytest.raises(ValueError):
        ProceduralParams(lane_width=2.0)
    with pytest.raises(ValueError):
        ProceduralParams(density=0.0)


# ----------------------------------------------------------------------------- street furniture
URBAN = ProceduralParams(parking=0.8, stop_lines=0.5, kerb_stops=0.6, lane_offset=0.4)
JUNCTIONS = ("dual_lane_intersection", "t_junction", "dense_intersection", "y_junction")


@pytest.mark.parametrize("kind", SCENARIO_TYPES)
def test_urban_scenes_keep_every_invariant(kind):
    """Parked cars, stop-line queues and kerb stops: no box overlap (parked cars included), no box on
    a kerb, kinematic logs, legal routes; goals on the lane except for kerb stops."""
    for seed in range(4):
        check_all(generate_scene(kind, seed, URBAN), f"urban {kind} seed {seed}")


def test_parked_cars_stand_in_strips_beside_the_lanes():
    n_parked = n_kerb = 0
    for kind in JUNCTIONS:
        for seed in range(3):
            sc = generate_scene(kind, seed, URBAN)
            k = sc.metadata["num_parked"]
            n_parked += k
            n_kerb += len(sc.metadata["kerb_stops"])
            lanes = [p.astype(np.float64) for t, p in sc.polylines() if t == RoadType.LANE]
            for a in range(sc.num_agents - k, sc.num_agents):
                assert (sc.log_pos[a] == sc.log_pos[a, :1]).all() and (sc.log_vel[a] == 0).all()
                assert not sc.is_interest[a] and not sc.is_sdc[a]
                assert np.allclose(sc.goal[a], sc.log_pos[a, 0])  # at its goal: never a policy agent
                # beside a lane, not on it: the centre 2-4 m from the nearest lane centre
                d = min(point_polyline_distance(sc.log_pos[a, 0].astype(np.float64), p) for p in lanes)
                assert 1.9 < d < 4.5, (kind, seed, a, d)
    assert n_parked > 50 and n_kerb > 0  # the knobs did something
    for kind in ("merge", "roundabout"):  # no kerbside parking there
        assert generate_scene(kind, 0, URBAN).metadata["num_parked"] == 0


NARROW = dataclasses.replace(URBAN, park_reach=1.5)


def _parked_inner_sides(params: ProceduralParams, seeds=range(3)) -> np.ndarray:
    """Per parked car of the junction types, its inner side's distance to the nearest lane centre (m):
    the centre's distance less half the width."""
    out = []
    for kind in JUNCTIONS:
        for seed in seeds:
            sc = generate_scene(kind, seed, params)
            k = sc.metadata["num_parked"]
            lanes = [p.astype(np.float64) for t, p in sc.polylines() if t == RoadType.LANE]
            for a in range(sc.num_agents - k, sc.num_agents):
                d = min(point_polyline_distance(sc.log_pos[a, 0].astype(np.float64), p) for p in lanes)
                out.append(d - sc.width[a] / 2)
    return np.asarray(out)


def test_park_reach_puts_parked_cars_over_the_lane_edge_and_drivers_give_room():
    """park_reach: parked cars stand into the lane (inner side < half a lane from its centre, as in
    the real scenes), the logs stay collision-free with them, and the drivers beside them keep left."""
    strip, narrow = _parked_inner_sides(URBAN), _parked_inner_sides(NARROW)
    half_lane = URBAN.lane_width / 2
    assert strip.min() > half_lane - 0.2  # in the strip: at most 0.15 m over the edge (+ a turned box)
    assert (narrow < half_lane - 0.5).mean() > 0.3 and np.median(narrow) < np.median(strip) - 0.4
    assert len(narrow) > 0.8 * len(strip)  # few dropped for standing in the traffic's way
    left = 0
    for kind in JUNCTIONS:
        for seed in range(3):
            sc = generate_scene(kind, seed, NARROW)
            check_all(sc, f"park_reach {kind} seed {seed}")  # no overlap with the parked boxes at any step
            left += sum(b < -0.2 for b in sc.metadata["lane_offsets"])
    assert left > 20
    with pytest.raises(ValueError, match="park_reach"):
        ProceduralParams(park_reach=2.5)


def test_park_reach_zero_changes_nothing():
    a = generate_scene("t_junction", 4, URBAN)
    b = generate_scene("t_junction", 4, dataclasses.replace(URBAN, park_reach=0.0))
    assert np.array_equal(a.log_pos, b.log_pos) and a.metadata["lane_offsets"] == b.metadata["lane_offsets"]


def test_lane_offsets_move_drivers_and_goals_off_the_centre():
    """With lane_offset, drivers keep their own offset from the lane centre on straight road (within
    the lane: check_routes_and_goals bounds every goal by it), so goals lie off the centre too."""
    offs, goal_d = [], []
    for kind in SCENARIO_TYPES:
        sc = generate_scene(kind, 2, ProceduralParams(lane_offset=0.4))
        lanes = sc.metadata["routes"]
        for i, b in enumerate(sc.metadata["lane_offsets"]):
            offs.append(abs(b))
            if abs(b) >= 0.2:
                goal_d.append(point_polyline_distance(sc.goal[i].astype(np.float64), sc.polyline(lanes[i][-1])))
        check_routes_and_goals(sc, kind)
        check_kinematics(sc, kind)
    assert np.mean(offs) > 0.15 and max(offs) <= 0.65  # at most (4.5 - 1.8) / 2 - 0.25 m
    assert np.mean(goal_d) > 0.1


def test_lane_changes_end_on_the_parallel_lane():
    """With lane_changes, vehicles whose route ends on a straight lane beside a parallel one move onto
    it (check_routes_and_goals puts their goal at the drawn share of a lane width between the two),
    keeping every invariant; a straight path then ends a lane width or so to the side, as in the logs."""
    params = ProceduralParams(lane_changes=1.0)
    shifts = []
    for kind in ("merge", "dual_lane_intersection", "t_junction", "y_junction"):
        for seed in range(3):
            sc = generate_scene(kind, seed, params)
            check_all(sc, f"lane changes {kind} seed {seed}")
            for i, _, done in sc.metadata["lane_changes"]:
                fwd = np.array([np.cos(sc.log_yaw[i, 0]), np.sin(sc.log_yaw[i, 0])])
                d = sc.goal[i] - sc.log_pos[i, 0]
                if abs(np.sin(sc.log_yaw[i, -1] - sc.log_yaw[i, 0])) < 0.1:  # a straight path
                    shifts.append(abs(fwd[0] * d[1] - fwd[1] * d[0]) / done)
    assert len(shifts) >= 5
    assert np.allclose(shifts, ProceduralParams().lane_width, atol=0.4)
    plain = generate_scene("merge", 0)
    assert plain.metadata["lane_changes"] == []
    assert np.array_equal(plain.log_pos, generate_scene("merge", 0, ProceduralParams(lane_changes=0.0)).log_pos)
    with pytest.raises(ValueError, match="lane_changes"):
        ProceduralParams(lane_changes=1.5)


def test_long_vehicles_keep_every_invariant():
    """With long_vehicles, vans, trucks and buses (5.5-14 m long, 2.0-2.6 m wide) drive among the cars with
    every invariant kept and their logs clear of the road edges and of each other (the log audit finds
    nothing); a share of those drawn keep a car's size where the longer box would not fit. Off by default:
    no moving vehicle is longer than 5.5 m and the scene is the same."""
    from tg_gpudrive.data.log_audit import audit
    from tg_gpudrive.data.procedural.traffic import LONG_LENGTH, LONG_WIDTH

    params = ProceduralParams(long_vehicles=0.5, parking=0.8)
    lengths, widths = [], []
    for kind in SCENARIO_TYPES:
        for seed in range(2):
            sc = generate_scene(kind, seed, params)
            check_all(sc, f"long vehicles {kind} seed {seed}")
            assert audit(sc, 10, 2.0) == {}, (kind, seed)
            moving = (sc.agent_type == AgentType.VEHICLE) & (np.ptp(sc.log_pos, axis=1).max(-1) > 1.0)
            lengths += sc.length[moving].tolist()
            widths += sc.width[moving].tolist()
    L, W = np.array(lengths), np.array(widths)
    long = L > 5.5 + 1e-6
    assert 0.2 <= long.mean() <= 0.5, long.mean()
    assert L[long].max() <= LONG_LENGTH[-1][1][1] and (L[long] > LONG_LENGTH[0][1][1]).any()
    assert W[long].min() >= LONG_WIDTH[0] and W[long].max() <= LONG_WIDTH[1]
    plain = generate_scene("dual_lane_intersection", 0)
    assert plain.length.max() <= 5.5
    off = generate_scene("dual_lane_intersection", 0, ProceduralParams(long_vehicles=0.0))
    assert np.array_equal(plain.log_pos, off.log_pos) and np.array_equal(plain.length, off.length)
    with pytest.raises(ValueError, match="long_vehicles"):
        ProceduralParams(long_vehicles=1.5)


def test_rest_starts_pull_away_from_the_stop_line_with_every_invariant():
    """With rest_starts, the front vehicles of yielding approaches stand at rest at the init step (1 s),
    as 13 % of the real dev candidates do, and pull away later, with every invariant kept and logs the audit
    finds nothing in; without it no candidate is at rest at the init step, and the scene is the same."""
    from tg_gpudrive.data.log_audit import audit, candidates

    def starts(params):
        at_rest = pulled = n = 0
        for kind in JUNCTIONS:
            for seed in range(2):
                sc = generate_scene(kind, seed, params)
                if params.rest_starts:
                    check_all(sc, f"rest starts {kind} seed {seed}")
                    assert audit(sc, 10, 2.0) == {}, (kind, seed)
                cand = np.flatnonzero(candidates(sc, 10, 2.0))
                still = np.linalg.norm(sc.log_pos[cand, 11] - sc.log_pos[cand, 10], axis=-1) < 0.1  # < 1 m/s
                travel = np.linalg.norm(np.diff(sc.log_pos[cand, 10:], axis=1), axis=-1).sum(1)
                at_rest, pulled, n = at_rest + still.sum(), pulled + (still & (travel >= 5.0)).sum(), n + len(cand)
        return at_rest, pulled, n

    at_rest, pulled, n = starts(ProceduralParams(rest_starts=1.0, stop_lines=0.5))
    assert at_rest >= 0.1 * n and pulled >= 0.5 * at_rest, (at_rest, pulled, n)
    assert starts(ProceduralParams())[0] == 0
    plain = generate_scene("t_junction", 4)
    off = generate_scene("t_junction", 4, ProceduralParams(rest_starts=0.0))
    np.testing.assert_array_equal(plain.log_pos, off.log_pos)
    with pytest.raises(ValueError, match="rest_starts"):
        ProceduralParams(rest_starts=1.5)


def test_street_knobs_are_deterministic_and_off_by_default():
    sc = generate_scene("t_junction", 5)
    assert sc.metadata["num_parked"] == 0 and sc.metadata["kerb_stops"] == [] and not sc.metadata["hold_at_stop_line"]
    assert not any(sc.metadata["lane_offsets"])
    a, b = generate_scene("t_junction", 5, URBAN), generate_scene("t_junction", 5, URBAN)
    assert np.array_equal(a.log_pos, b.log_pos) and np.array_equal(a.road_points, b.road_points)
    # the street stream is separate: the moving traffic of a scene without kerb stops does not change
    # with parking (the maps differ only in their kerbs)
    plain = generate_scene("dual_lane_intersection", 3)
    parked = generate_scene("dual_lane_intersection", 3, ProceduralParams(parking=1.0))
    n = plain.num_agents
    assert parked.num_agents - parked.metadata["num_parked"] == n
    assert np.array_equal(plain.log_pos, parked.log_pos[:n])
    with pytest.raises(ValueError, match="kerb_stops"):
        ProceduralParams(kerb_stops=1.5)


def test_stop_lines_hold_yielding_vehicles_before_the_junction():
    """With stop lines, vehicles that give way wait behind their stop line instead of inside the
    junction box: fewer slow steps (< 1 m/s) inside the box and more outside it, over the same scenes
    (2026-11-25: 3,045 / 1,158 without, 1,092 / 3,542 with, on 6 seeds of each type)."""
    def slow_steps(params):
        inside = outside = 0
        for kind in JUNCTIONS:
            for seed in range(3):
                sc = generate_scene(kind, seed, params)
                r = np.linalg.norm(sc.log_pos, axis=-1)
                slow = np.linalg.norm(sc.log_vel, axis=-1) < 1.0
                r_stop = sc.metadata["geometry"]["r_stop"]
                inside += int((slow & (r < min(r_stop) - 1.0)).sum())
                outside += int((slow & (r > max(r_stop) + 1.0)).sum())
        return inside, outside

    (in0, out0), (in1, out1) = slow_steps(ProceduralParams()), slow_steps(ProceduralParams(stop_lines=1.0))
    assert in1 < 0.7 * in0 and out1 > 1.5 * out0


def test_kerb_ramp_keeps_the_turned_box_off_the_kerb():
    from tg_gpudrive.data.procedural.traffic import _kerb_offset

    # a box with no length does not swing out: the limit is met at the ramp's end, d + hw
    assert _kerb_offset(3.0, 4.1, 10.0, 0.0, 1.0) == pytest.approx(3.0)
    assert _kerb_offset(3.0, 3.5, 1e9, 0.0, 1.0) == pytest.approx(2.5, abs=1e-6)
    # a long box on a short ramp: its front corner swings out, so the offset is cut below limit - hw
    d = _kerb_offset(3.0, 4.1, 10.0, 2.5, 1.0)
    assert d < 3.0 - 0.2
    x = np.linspace(0, 1, 2001)
    ang = np.arctan(d * 6 * x * (1 - x) / 10.0)
    reach = d * x * x * (3 - 2 * x) + 2.5 * np.sin(ang) + 1.0 * np.cos(ang)
    assert reach.max() == pytest.approx(4.1, abs=2e-3)


def test_sidewalk_pedestrians_keep_off_the_lanes_and_touch_nobody():
    from tg_gpudrive.data.log_audit import audit, boxes_overlap
    from tg_gpudrive.data.procedural.generator import WALKER_LANE_CLEAR, WALKER_SPEED

    p = ProceduralParams(pedestrians=5.0, parking=0.8)
    total = 0
    for k, kind in enumerate(SCENARIO_TYPES):
        sc = generate_scene(kind, 40 + k, p)
        walk = np.nonzero(sc.agent_type == AgentType.PEDESTRIAN)[0]
        total += len(walk)
        assert sc.metadata["num_pedestrians"] == len(walk)
        if not len(walk):
            continue
        lanes = np.concatenate([pts for kind_, pts in sc.polylines() if kind_ == RoadType.LANE])
        xy = sc.log_pos[walk].reshape(-1, 2)
        # lane centre points lie at most 0.5 m apart: the clearance holds up to that sampling
        assert np.linalg.norm(xy[:, None] - lanes[None], axis=-1).min() > WALKER_LANE_CLEAR - 0.3
        speed = np.linalg.norm(sc.log_vel[walk], axis=-1)
        assert speed.max() <= WALKER_SPEED[1] + 1e-5
        for t in range(0, sc.num_steps, 10):  # nobody's box touches a pedestrian's
            for i in walk:
                others = np.arange(sc.num_agents) != i
                hit = boxes_overlap(sc.log_pos[i, t], sc.log_yaw[i, t], sc.length[i], sc.width[i],
                                    sc.log_pos[others, t], sc.log_yaw[others, t], sc.length[others], sc.width[others])
                assert not hit.any(), (kind, i, t)
        assert audit(sc, 10, 2.0) == {}  # no vehicle's log meets a pedestrian
    assert total >= 12  # about five a scene, a few left out where they would not fit


def test_crossing_pedestrians_walk_across_the_lanes_clear_of_the_logs():
    """Crossing pedestrians walk over the lanes on a crosswalk, at the speed their positions move, and
    every logged box keeps CROSS_CLEAR from theirs at every step: the logs need not yield to them."""
    from tg_gpudrive.data.log_audit import audit, boxes_overlap
    from tg_gpudrive.data.procedural.generator import CROSS_CLEAR, CROSS_HURRY

    fastest = CROSS_HURRY[-1][1][1]
    p = ProceduralParams(crossings=4.0, pedestrians=2.0, parking=0.8)
    total = reached = 0
    for k, kind in enumerate(("dual_lane_intersection", "t_junction", "dense_intersection", "y_junction") * 2):
        sc = generate_scene(kind, 60 + k, p)
        cross = np.asarray(sc.metadata["crossing_pedestrians"], int)
        total += len(cross)
        assert np.all(sc.agent_type[cross] == AgentType.PEDESTRIAN)
        if not len(cross):
            continue
        lanes = np.concatenate([pts for kind_, pts in sc.polylines() if kind_ == RoadType.LANE])
        crosswalks = [pts for kind_, pts in sc.polylines() if kind_ == RoadType.CROSSWALK]
        for i in cross:
            xy = sc.log_pos[i]
            # over a lane centre, unless waiting at the kerb for the traffic held it there to the episode's end
            if np.linalg.norm(xy[:, None] - lanes[None], axis=-1).min() >= 1.0:
                continue
            reached += 1
            # on a crosswalk: its midpoint across the road lies inside one (the polygon's bounding box)
            mid = xy[np.argmin(np.linalg.norm(xy[:, None] - lanes[None], axis=-1).min(-1))]
            assert any(np.all(mid >= cw.min(0) - 1.01) and np.all(mid <= cw.max(0) + 1.01) for cw in crosswalks)
            step = np.linalg.norm(np.diff(xy, axis=0), axis=-1) / 0.1
            speed = np.linalg.norm(sc.log_vel[i], axis=-1)
            assert speed.max() <= fastest + 1e-5 and step.max() <= fastest + 1e-3
            moving = step > 1e-3
            np.testing.assert_allclose(step[moving][1:-1], speed[:-1][moving][1:-1], atol=1e-3)
            others = np.arange(sc.num_agents) != i
            for t in range(sc.num_steps):
                hit = boxes_overlap(sc.log_pos[i, t], sc.log_yaw[i, t], sc.length[i] + 2 * CROSS_CLEAR,
                                    sc.width[i] + 2 * CROSS_CLEAR, sc.log_pos[others, t], sc.log_yaw[others, t],
                                    sc.length[others], sc.width[others])
                assert not hit.any(), (kind, i, t)
        assert audit(sc, 10, 2.0) == {}
    assert total >= 4 and reached >= 0.75 * total


def test_crossing_speeds_have_the_real_tail():
    """Crossing pedestrians' speeds: 88 % walk at 1.0-1.6 m/s, 10 % hurry at 1.6-2.8 and 2 % run at 2.8-6.5,
    so the percentiles 50 / 90 / 99 are 1.0 + 0.6 * 0.5 / 0.88, 1.6 + 1.2 * 0.02 / 0.10 and 2.8 + 3.7 * 0.5
    (1.34, 1.84 and 4.65 m/s; real lanes' pedestrians: 1.3, 1.9, 6.5)."""
    from tg_gpudrive.data.procedural.generator import cross_speed

    rng = np.random.default_rng(0)
    v = np.array([cross_speed(rng) for _ in range(40000)])
    assert v.min() >= 1.0 and v.max() <= 6.5
    assert np.mean(v > 1.6) == pytest.approx(0.12, abs=0.006) and np.mean(v > 2.8) == pytest.approx(0.02, abs=0.003)
    p50, p90, p99 = np.percentile(v, [50, 90, 99])
    assert p50 == pytest.approx(1.341, abs=0.01) and p90 == pytest.approx(1.84, abs=0.03)
    assert p99 == pytest.approx(4.65, abs=0.25)


def test_logged_vehicles_wait_for_crossing_pedestrians():
    """While a crossing pedestrian walks, logged vehicles stand just short of its path (within CROSS_STOP
    plus their half length and a metre of the line it walks, at under 0.3 m/s), then drive over that
    line once it has crossed. (With the yielding switched off, none of these scenes has such a wait.)"""
    from tg_gpudrive.data.log_audit import segment_distance
    from tg_gpudrive.data.procedural.traffic import CROSS_STOP

    p = ProceduralParams(crossings=4.0, parking=0.8)
    waits = 0
    for k, kind in enumerate(("dual_lane_intersection", "t_junction", "dense_intersection", "y_junction") * 8):
        sc = generate_scene(kind, 60 + k, p)
        cars = np.flatnonzero((sc.agent_type == AgentType.VEHICLE) & (np.ptp(sc.log_pos, axis=1).max(-1) > 1.0))
        for i in sc.metadata["crossing_pedestrians"]:
            a, b = sc.log_pos[i, 0].astype(float), sc.log_pos[i, -1].astype(float)
            walking = np.linalg.norm(sc.log_vel[i], axis=-1) > 0
            if not walking.any():
                continue
            done = np.flatnonzero(walking)[-1]
            for j in cars:
                d = segment_distance(sc.log_pos[j].astype(float), a, b)
                stand = np.linalg.norm(sc.log_vel[j], axis=-1) < 0.3
                waited = np.any(walking & stand & (d < sc.length[j] / 2 + CROSS_STOP + 1.0))
                waits += bool(waited and np.any(d[done:] < 0.5))
    assert waits >= 2


def test_crossing_path_and_where_a_route_crosses_it():
    from tg_gpudrive.data.procedural.traffic import DS, Crossing, _crossing_s

    c = Crossing(np.array([10.0, -6.0]), np.array([10.0, 6.0]), 1.2, 0.5)  # 12 m at 1.2 m/s from t = 0.5 s
    xy, yaw, speed = c.path(121, 0.1)
    assert c.t_off == pytest.approx(10.5)
    np.testing.assert_allclose(xy[:6], [[10.0, -6.0]] * 6)  # waits at the kerb until 0.5 s
    np.testing.assert_allclose(xy[25], [10.0, -6.0 + 1.2 * 2.0], atol=1e-9)
    np.testing.assert_allclose(xy[110:], [[10.0, 6.0]] * 11, atol=1e-9)  # arrived at 10.5 s
    assert yaw[0] == pytest.approx(np.pi / 2) and speed[5] == 0 and speed[6] == 1.2 and speed[-1] == 0
    route = np.stack([np.arange(0, 40, DS), np.full(80, 1.5)], 1)  # a straight lane along y = 1.5
    assert _crossing_s(route, c.a, c.b) == pytest.approx(10.0)
    assert _crossing_s(route + [0.0, 10.0], c.a, c.b) == np.inf  # passes beyond the far kerb


def test_no_crossings_leaves_scenes_bit_for_bit():
    base = ProceduralParams(pedestrians=2.0, parking=0.8)
    a = generate_scene("t_junction", 5, base)
    b = generate_scene("t_junction", 5, ProceduralParams(pedestrians=2.0, parking=0.8, crossings=0.0))
    np.testing.assert_array_equal(a.log_pos, b.log_pos)
    assert a.metadata["crossing_pedestrians"] == []
    with pytest.raises(ValueError, match="crossings"):
        ProceduralParams(crossings=-1.0)


def test_no_pedestrians_leaves_scenes_bit_for_bit():
    a = generate_scene("dual_lane_intersection", 7)
    b = generate_scene("dual_lane_intersection", 7, ProceduralParams(pedestrians=0.0))
    np.testing.assert_array_equal(a.log_pos, b.log_pos)
    with pytest.raises(ValueError, match="pedestrians"):
        ProceduralParams(pedestrians=-1.0)
