"""How far one scene set is from another: per-feature statistics of the logs and maps, and a distance.

What it is for: measuring the gap between the procedural generator and real WOMD traffic, feature by
feature, so the generator's largest gaps can be found and closed (scripts/real_gap.py prints the table).
Every feature is computed from a Scene alone (logs and map), for real and generated scenes alike:

    feature            unit     samples                     definition
    speed              m/s      vehicle steps               path speed |p_t+1 - p_t| / dt over the steps of the
                                                            control rule's candidates (vehicles valid at
                                                            init_step, away from their goal), from init_step on
    accel              m/s^2    vehicle steps               change of that path speed per step / dt
    curvature          1/m      vehicle steps               change of path heading / arc, where both arcs
                                                            are at least 0.5 m
    closing_speed      m/s      vehicle steps with a leader how fast a candidate closes on the nearest
                                                            vehicle ahead in its corridor (centre within
                                                            AHEAD_M ahead and CORRIDOR_M to the side, in its
                                                            heading frame): the relative velocity along the
                                                            line between them, > 0 approaching; the fast-
                                                            onto-slow encounters (merges, queues) a driver
                                                            must brake for
    goal_distance      m        candidates                  straight line from the init position to the goal
    vehicle_length     m        candidates                  box length (vans, trucks and buses make the tail)
    route_length       m        candidates                  path length of the log from init_step to its last
                                                            valid step
    lateral_shift      m        straight candidates         how far the goal lies to the side of the init
                                                            heading (lane changes, kerb stops), over candidates
                                                            whose log heading at its last valid step is within
                                                            STRAIGHT_DEG of the init one and whose goal is at
                                                            least STRAIGHT_MIN_M away
    rest_starts        -        scenes                      candidates at rest at init_step (path speed below
                                                            REST_MPS) over candidates
    rest_crossings     -        scenes                      pulls from rest into or across fast traffic: pairs
                                                            of a candidate at rest at init_step (path speed
                                                            below REST_MPS) that then travels MOVE_M or more,
                                                            and another vehicle whose log passes the mover's
                                                            entry point (its first moving step within
                                                            CONFLICT_M of that log) at FAST_MPS or more, at a
                                                            heading ENTRY_DEG or more from the mover's there
                                                            (crossing or merging, not following), within
                                                            PET_MAX_S of the mover: the junction conflict where
                                                            a driver must yield
    rest_crossing_pet  s        such pairs, any PET         post-encroachment time of those pairs: the time
                                                            between the mover at its entry point and the other
                                                            vehicle at its nearest step to that point
    agents             -        scenes                      agents valid at some step
    controlled         -        scenes                      the rule's eligible vehicles (engine.control)
    pedestrians        -        scenes                      pedestrians valid at some step
    pedestrians_on_lanes -      scenes                      pedestrians that come within LANE_HALF_M of a lane
                                                            centre line at some valid step (crossing or
                                                            walking in the road, where a vehicle must yield)
    pedestrian_lane_speed m/s   pedestrian steps on a lane  path speed of those pedestrians over the steps they
                                                            spend within LANE_HALF_M of a lane centre line (how
                                                            fast a vehicle must expect them to step out)
    cyclists           -        scenes                      cyclists valid at some step
    parked_share       -        scenes                      vehicles whose log moves less than 1 m in all,
                                                            over vehicles
    edge_density       m/ha     scenes                      road-edge length within 50 m of the candidates'
                                                            init positions, per hectare of that area
    lane_width         m        lane points (2 per m)       twice the distance from a lane centre point to the
                                                            nearest road line or edge, where one is within 4 m
    lanes              -        scenes                      lane polylines (a proxy for the junction's size)

The distance of a feature is the Wasserstein-1 distance between the two sets' samples divided by the
first set's standard deviation (scale-free: 1 means the distributions are a standard deviation apart in
the W1 sense). Must not: touch the engine (this is a function of scenes), or tune anything.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.log_audit import segment_distance, candidates
from tg_gpudrive.engine import control
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import AgentType, RoadType

FEATURES = ("speed", "accel", "curvature", "closing_speed", "goal_distance", "vehicle_length", "route_length",
            "lateral_shift", "rest_starts", "rest_crossings", "rest_crossing_pet", "agents", "controlled",
            "pedestrians", "pedestrians_on_lanes", "pedestrian_lane_speed", "cyclists", "parked_share",
            "edge_density", "lane_width", "lanes")
UNITS = {"speed": "m/s", "accel": "m/s^2", "curvature": "1/m", "closing_speed": "m/s", "goal_distance": "m",
         "vehicle_length": "m", "route_length": "m", "lateral_shift": "m", "rest_crossing_pet": "s",
         "pedestrian_lane_speed": "m/s", "edge_density": "m/ha", "lane_width": "m"}
PARKED_M = 1.0  # m: a vehicle whose log moves less than this in all is parked
EDGE_REACH_M = 50.0  # m around the candidates' init positions where road-edge density is measured
LANE_SIDE_M = 4.0  # m: a lane's bounding line or edge lies within this of its centre
STRAIGHT_DEG = 10.0  # a log whose heading turns less than this from init to its end drives straight
STRAIGHT_MIN_M = 15.0  # m: the goal of a straight log counted for lateral_shift is at least this far
AHEAD_M = 30.0  # m: how far ahead of a candidate closing_speed looks for a leader ...
CORRIDOR_M = 2.0  # m: ... and how far to its side
LANE_HALF_M = 1.75  # m: a pedestrian this near a lane centre line stands in the lane
REST_MPS = 1.0  # m/s: a vehicle slower than this at init_step is at rest ...
MOVE_M = 5.0  # m: ... and pulls away if its log then travels this far
FAST_MPS = 8.0  # m/s: a crossing vehicle at least this fast is fast traffic
CONFLICT_M = 2.0  # m: two paths that pass this near cross (a step at 15 m/s is 1.5 m)
ENTRY_DEG = 10.0  # deg: a mover entering another's path at least this far from its heading crosses or merges into it
PET_MAX_S = 5.0  # s: a crossing within this of the mover's passing is a conflict


def _closing_speeds(scene: Scene, rows: np.ndarray, init: int) -> np.ndarray:
    """closing_speed of the module docstring: one sample per step of each candidate in `rows` that has a
    vehicle ahead in its corridor, from init_step on."""
    vehicles = np.nonzero(scene.agent_type == AgentType.VEHICLE)[0]
    pos, vel = scene.log_pos.astype(np.float64), scene.log_vel.astype(np.float64)
    out = []
    for t in range(init, scene.num_steps):
        others = vehicles[scene.log_valid[vehicles, t]]
        me = rows[scene.log_valid[rows, t]]
        if len(others) < 2 or len(me) == 0:
            continue
        d = pos[others, t][None] - pos[me, t][:, None]  # (me, others, 2)
        c, s_ = np.cos(scene.log_yaw[me, t])[:, None], np.sin(scene.log_yaw[me, t])[:, None]
        ahead, side = c * d[..., 0] + s_ * d[..., 1], -s_ * d[..., 0] + c * d[..., 1]
        dist = np.linalg.norm(d, axis=-1)
        inside = (ahead > 0) & (ahead < AHEAD_M) & (np.abs(side) < CORRIDOR_M) & (others[None] != me[:, None])
        dist = np.where(inside, dist, np.inf)
        lead = dist.argmin(1)
        has = np.isfinite(dist[np.arange(len(me)), lead])
        if not has.any():
            continue
        m, j = me[has], others[lead[has]]
        unit = (pos[j, t] - pos[m, t]) / dist[np.nonzero(has)[0], lead[has]][:, None]
        out.append(((vel[m, t] - vel[j, t]) * unit).sum(-1))
    return np.concatenate(out) if out else np.zeros(0)


def _rest_crossings(scene: Scene, rows: np.ndarray, init: int) -> tuple[int, int, np.ndarray]:
    """For the candidates `rows`: how many are at rest at init_step, and rest_crossings and rest_crossing_pet of
    the module docstring."""
    pos, dt = scene.log_pos.astype(np.float64), scene.dt
    steps = np.arange(scene.num_steps)
    vehicles = np.flatnonzero(scene.agent_type == AgentType.VEHICLE)
    tracks = {}
    for i in vehicles:
        ok = steps[init:][scene.log_valid[i, init:]]
        if len(ok) >= 2:
            step = np.diff(pos[i, ok], axis=0)
            arc = np.linalg.norm(step, axis=-1)
            tracks[i] = (ok[1:], pos[i, ok[1:]], np.arctan2(step[:, 1], step[:, 0]), arc / (np.diff(ok) * dt), arc)
    n, pets, at_rest = 0, [], 0
    for a in rows:
        if a not in tracks or tracks[a][0][0] != init + 1 or tracks[a][3][0] >= REST_MPS:
            continue
        at_rest += 1
        ta, pa, ha, va, arc = tracks[a]
        moving = va >= REST_MPS  # the mover's heading means something only once it rolls
        if arc.sum() < MOVE_M or not moving.any():
            continue
        ta, pa, ha = ta[moving], pa[moving], ha[moving]
        for b, (tb, pb, hb, vb, _) in tracks.items():
            if b == a:
                continue
            d = np.linalg.norm(pa[:, None] - pb[None], axis=-1)
            near = np.flatnonzero(d.min(1) <= CONFLICT_M)
            if len(near) == 0:
                continue
            k = near[0]  # the mover's entry point into b's path, and b's step nearest to it
            j = int(np.argmin(d[k]))
            angle = np.degrees(abs(np.angle(np.exp(1j * (ha[k] - hb[j])))))
            if angle < ENTRY_DEG or vb[j] < FAST_MPS:
                continue
            pet = abs(int(ta[k]) - int(tb[j])) * dt
            pets.append(pet)
            n += pet <= PET_MAX_S
    return at_rest, n, np.asarray(pets)


def _kinematics(scene: Scene, rows: np.ndarray, init: int) -> dict[str, np.ndarray]:
    speed, accel, curv = [], [], []
    for i in rows:
        ok = np.nonzero(scene.log_valid[i, init:])[0] + init
        if len(ok) < 3:
            continue
        steps = np.diff(scene.log_pos[i, ok].astype(np.float64), axis=0)
        dt = np.diff(ok) * scene.dt
        arc = np.linalg.norm(steps, axis=-1)
        v = arc / dt
        speed.append(v)
        accel.append(np.diff(v) / dt[1:])
        heading = np.arctan2(steps[:, 1], steps[:, 0])
        turn = (np.diff(heading) + np.pi) % (2 * np.pi) - np.pi
        both = (arc[1:] >= 0.5) & (arc[:-1] >= 0.5)
        curv.append(turn[both] / arc[1:][both])
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
    return {"speed": cat(speed), "accel": cat(accel), "curvature": cat(curv)}


def _points_along(pts: np.ndarray, spacing: float = 0.5) -> np.ndarray:
    """Points every `spacing` metres along a polyline (its vertices included)."""
    if len(pts) < 2:
        return pts.astype(np.float64)
    a, b = pts[:-1].astype(np.float64), pts[1:].astype(np.float64)
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=-1) / spacing), 1).astype(np.int64)
    seg = np.repeat(np.arange(len(a)), n)
    f = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
    return np.concatenate([a[seg] + (b[seg] - a[seg]) * f[:, None], b[-1:]])


def _lane_widths(scene: Scene, rng: np.random.Generator, per_scene: int = 400) -> np.ndarray:
    bounds_a, bounds_b, lanes = [], [], []
    for kind, pts in scene.polylines():
        if kind in (RoadType.ROAD_LINE, RoadType.ROAD_EDGE) and len(pts) >= 2:
            bounds_a.append(pts[:-1])
            bounds_b.append(pts[1:])
        elif kind == RoadType.LANE and len(pts) >= 2:
            lanes.append(_points_along(pts))
    if not bounds_a or not lanes:
        return np.zeros(0)
    a, b = np.concatenate(bounds_a).astype(np.float64), np.concatenate(bounds_b).astype(np.float64)
    p = np.concatenate(lanes)
    p = p[rng.choice(len(p), min(per_scene, len(p)), replace=False)]
    d = _nearest_segment(p, a, b)
    return 2 * d[d < LANE_SIDE_M]


def _nearest_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 256) -> np.ndarray:
    out = np.empty(len(p))
    for k in range(0, len(p), chunk):
        out[k:k + chunk] = segment_distance(p[k:k + chunk, None], a[None], b[None]).min(-1)
    return out


def _edge_density(scene: Scene, centres: np.ndarray) -> float:
    """Road-edge metres within EDGE_REACH_M of `centres`, per hectare of the area within reach (sampled
    on a 5 m grid: an edge point counts once however many centres it is near)."""
    if len(centres) == 0:
        return float("nan")
    edges = [_points_along(pts, 1.0) for kind, pts in scene.polylines() if kind == RoadType.ROAD_EDGE]
    lo, hi = centres.min(0) - EDGE_REACH_M, centres.max(0) + EDGE_REACH_M
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0], 5.0), np.arange(lo[1], hi[1], 5.0))
    grid = np.stack([gx.ravel(), gy.ravel()], -1)
    near = lambda q: (np.linalg.norm(q[:, None] - centres[None], axis=-1) < EDGE_REACH_M).any(-1)  # noqa: E731
    area_ha = near(grid).sum() * 25.0 / 1e4
    metres = sum(int(near(e).sum()) for e in edges) if edges else 0  # 1 m between edge points
    return metres / area_ha if area_ha > 0 else float("nan")


def _lane_pedestrians(scene: Scene) -> tuple[int, np.ndarray]:
    """How many pedestrians come within LANE_HALF_M of a lane centre line at some valid step, and their path
    speeds over the steps they spend there (a step counts where both its ends are valid and within reach)."""
    segs = [(p[:-1], p[1:]) for t, p in ((t, np.asarray(p, np.float64)) for t, p in scene.polylines())
            if t == RoadType.LANE and len(p) > 1]
    if not segs:
        return 0, np.zeros(0)
    a, b = (np.concatenate(x) for x in zip(*segs))
    n, speeds = 0, []
    for i in np.flatnonzero(scene.agent_type == AgentType.PEDESTRIAN):
        ok = np.flatnonzero(scene.log_valid[i])
        xy = scene.log_pos[i, ok].astype(np.float64)
        near = (np.abs(xy[:, None] - 0.5 * (a + b)[None]).max(-1) < LANE_HALF_M + 0.5 * np.abs(b - a).max(-1))
        if not near.any():
            continue
        # a segment outside `near` lies at least LANE_HALF_M away, so the plain distance decides alike
        on = segment_distance(xy[:, None], a[None], b[None]).min(-1) < LANE_HALF_M
        if on.any():
            n += 1
            step = on[:-1] & on[1:] & (np.diff(ok) == 1)
            speeds.append(np.linalg.norm(np.diff(xy, axis=0), axis=-1)[step] / scene.dt)
    return n, np.concatenate(speeds) if speeds else np.zeros(0)


def scene_features(scene: Scene, cfg: EngineConfig | None = None, seed: int = 0) -> dict[str, np.ndarray]:
    """Every feature of the module docstring for one scene: arrays of samples (one per scene for the
    per-scene features)."""
    cfg = cfg or EngineConfig()
    init = min(cfg.init_steps, scene.num_steps - 1)
    cand = np.nonzero(candidates(scene, init, cfg.goal_radius))[0]
    out = _kinematics(scene, cand, init)
    out["closing_speed"] = _closing_speeds(scene, cand, init)
    at_rest, rest_n, out["rest_crossing_pet"] = _rest_crossings(scene, cand, init)
    goal_d, route, shift = [], [], []
    for i in cand:
        ok = np.nonzero(scene.log_valid[i, init:])[0] + init
        to_goal = (scene.goal[i] - scene.log_pos[i, init]).astype(np.float64)
        goal_d.append(float(np.linalg.norm(to_goal)))
        route.append(float(np.linalg.norm(np.diff(scene.log_pos[i, ok], axis=0), axis=-1).sum()))
        yaw0, turn = float(scene.log_yaw[i, init]), float(scene.log_yaw[i, ok[-1]] - scene.log_yaw[i, init])
        if goal_d[-1] >= STRAIGHT_MIN_M and abs(np.angle(np.exp(1j * turn))) < np.radians(STRAIGHT_DEG):
            shift.append(abs(np.cos(yaw0) * to_goal[1] - np.sin(yaw0) * to_goal[0]))
    out["goal_distance"], out["route_length"] = np.asarray(goal_d), np.asarray(route)
    out["vehicle_length"] = scene.length[cand].astype(np.float64)
    out["lateral_shift"] = np.asarray(shift)
    present = scene.log_valid.any(1)
    vehicles = present & (scene.agent_type == AgentType.VEHICLE)
    lane_peds, out["pedestrian_lane_speed"] = _lane_pedestrians(scene)
    moved = np.array([np.ptp(scene.log_pos[i][scene.log_valid[i]], axis=0).max() if present[i] else 0.0
                      for i in range(scene.num_agents)])
    per_scene = {
        "rest_starts": at_rest / len(cand) if len(cand) else float("nan"),
        "rest_crossings": rest_n,
        "agents": present.sum(),
        "controlled": control.eligible(scene, cfg).sum(),
        "pedestrians": (present & (scene.agent_type == AgentType.PEDESTRIAN)).sum(),
        "pedestrians_on_lanes": lane_peds,
        "cyclists": (present & (scene.agent_type == AgentType.CYCLIST)).sum(),
        "parked_share": (vehicles & (moved < PARKED_M)).sum() / max(vehicles.sum(), 1),
        "edge_density": _edge_density(scene, scene.log_pos[cand, init].astype(np.float64)),
        "lanes": (scene.road_type == RoadType.LANE).sum(),
    }
    out.update({k: np.asarray([float(v)]) for k, v in per_scene.items()})
    out["lane_width"] = _lane_widths(scene, np.random.default_rng(seed))
    return out


def set_features(scenes: Sequence[Scene], cfg: EngineConfig | None = None) -> dict[str, np.ndarray]:
    """`scene_features` of every scene, pooled per feature (NaN samples dropped)."""
    pooled: dict[str, list[np.ndarray]] = {f: [] for f in FEATURES}
    for k, sc in enumerate(scenes):
        for f, v in scene_features(sc, cfg, seed=k).items():
            pooled[f].append(v)
    out = {f: np.concatenate(v) if v else np.zeros(0) for f, v in pooled.items()}
    return {f: v[np.isfinite(v)] for f, v in out.items()}


def w1(x: np.ndarray, y: np.ndarray) -> float:
    """Wasserstein-1 distance between two samples (the area between their empirical CDFs)."""
    x, y = np.sort(np.asarray(x, np.float64)), np.sort(np.asarray(y, np.float64))
    if len(x) == 0 or len(y) == 0:
        return float("nan")
    grid = np.concatenate([x, y])
    grid.sort()
    fx = np.searchsorted(x, grid[:-1], "right") / len(x)
    fy = np.searchsorted(y, grid[:-1], "right") / len(y)
    return float(np.sum(np.abs(fx - fy) * np.diff(grid)))


@dataclasses.dataclass(frozen=True)
class Gap:
    feature: str
    ref_median: float
    other_median: float
    ref_n: int
    other_n: int
    distance: float  # W1 / std of the reference samples


def gap_table(ref: dict[str, np.ndarray], other: dict[str, np.ndarray]) -> list[Gap]:
    """One Gap per feature, largest distance first."""
    rows = []
    for f in FEATURES:
        x, y = ref[f], other[f]
        sd = float(np.std(x)) if len(x) > 1 else float("nan")
        dist = w1(x, y) / sd if sd and sd > 0 else float("nan")
        rows.append(Gap(f, float(np.median(x)) if len(x) else float("nan"),
                        float(np.median(y)) if len(y) else float("nan"), len(x), len(y), dist))
    return sorted(rows, key=lambda g: -np.nan_to_num(g.distance, nan=-1.0))
