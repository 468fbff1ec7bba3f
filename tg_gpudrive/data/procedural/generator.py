"""Procedural safety-critical scenarios: the embedded default scene source.

The six scenario types of the TrafficGamer paper (merge, dual-lane
intersection, T-junction, dense-lane intersection, roundabout, Y-junction),
generated from a seed with no dataset: road geometry (lane centrelines with
their successor graph, curbs, lane dividers, crosswalks) and a 91-step, 10 Hz
"log" of vehicles driven by a human-like rollout (lane following, IDM car
following, yielding at conflict zones). Invariants of every scene, checked by
tests/test_procedural.py: no two vehicle boxes come within 0.3 m of each other,
no box touches a curb, trajectories obey a kinematic bicycle model (speed >= 0,
|accel| <= 4 m/s^2, |curvature| <= 0.25 1/m, heading = direction of motion),
every goal lies on the last lane of the vehicle's route (`metadata["routes"]`).

Geometry lives in `geometry.py`, the rollout in `traffic.py`, the invariant checks in
`checks.py`; this module only picks per-type settings, retries and exports a `Scene`. Runtime
code is NumPy only.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from tg_gpudrive.data.procedural import geometry as geo
from tg_gpudrive.data.procedural.traffic import TrafficModel, settle, spawn
from tg_gpudrive.scene import Scene
from tg_gpudrive.types import AgentType, RoadType

SCENARIO_TYPES = ("merge", "dual_lane_intersection", "t_junction", "dense_intersection", "roundabout", "y_junction")


@dataclass(frozen=True)
class ProceduralParams:
    """Knobs of the generator; per-type factors below scale speed and density.

    size_scale      multiplies arm / road lengths (junction boxes follow the lanes)
    lane_width      m, 3.2 .. 4.5
    num_lanes       lanes per direction (merge: main lanes); None draws from the
                    type's range, an int is clipped to it
    density         traffic density multiplier (1.0 ~ one vehicle per 40 m of lane)
    speed_mean/std  m/s, desired speed distribution (times the type's factor)
    num_steps, dt   logged steps and period
    max_vehicles    vehicles kept (nearest to the conflict first)
    min_vehicles    fewer after all retries is an error
    time_headway    s, IDM time gap;  min_gap: m, IDM standstill gap
    max_accel       m/s^2, IDM acceleration;  comfort_decel: m/s^2, IDM braking
    spawn_range     m upstream of the junction where vehicles are placed
    crosswalks      add crosswalk polygons at intersection arms
    """

    size_scale: float = 1.0
    lane_width: float = 3.5
    num_lanes: int | None = None
    density: float = 1.0
    speed_mean: float = 10.0
    speed_std: float = 2.0
    num_steps: int = 91
    dt: float = 0.1
    max_vehicles: int = 32
    min_vehicles: int = 2
    time_headway: float = 1.3
    min_gap: float = 2.0
    max_accel: float = 1.8
    comfort_decel: float = 2.5
    spawn_range: float = 60.0
    crosswalks: bool = True

    def __post_init__(self):
        checks = [
            (0.6 <= self.size_scale <= 3.0, "size_scale must be in [0.6, 3]"),
            (3.2 <= self.lane_width <= 4.5, "lane_width must be in [3.2, 4.5] m"),
            (self.num_lanes is None or 1 <= self.num_lanes <= 4, "num_lanes must be None or 1..4"),
            (self.density > 0, "density must be positive"),
            (1.0 <= self.speed_mean <= 25.0, "speed_mean must be in [1, 25] m/s"),
            (0.0 <= self.speed_std <= 10.0, "speed_std must be in [0, 10] m/s"),
            (self.num_steps >= 12, "num_steps must be >= 12"),
            (0.01 <= self.dt <= 0.5, "dt must be in [0.01, 0.5] s"),
            (2 <= self.min_vehicles <= self.max_vehicles <= 128, "need 2 <= min_vehicles <= max_vehicles <= 128"),
            (self.time_headway > 0 and self.min_gap > 0, "time_headway and min_gap must be positive"),
            (0 < self.max_accel <= 2.5 and 0 < self.comfort_decel <= 3.5, "max_accel <= 2.5, comfort_decel <= 3.5"),
            (self.spawn_range >= 10.0, "spawn_range must be >= 10 m"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(f"ProceduralParams: {msg}")


@dataclass(frozen=True)
class _TypeConfig:
    build: Callable
    lanes: tuple[int, int]  # range of num_lanes
    speed: float  # desired-speed factor
    density: float  # density factor
    spawn_range: float  # spawn-range factor


_TYPES = {
    "merge": _TypeConfig(geo.map_merge, (1, 3), 1.3, 1.0, 1.4),
    "dual_lane_intersection": _TypeConfig(geo.map_dual_lane, (2, 2), 1.0, 1.0, 1.0),
    "t_junction": _TypeConfig(geo.map_t_junction, (1, 2), 1.0, 1.3, 1.0),
    "dense_intersection": _TypeConfig(geo.map_dense, (3, 4), 0.9, 1.2, 1.0),
    "roundabout": _TypeConfig(geo.map_roundabout, (1, 1), 0.8, 1.4, 0.85),
    "y_junction": _TypeConfig(geo.map_y_junction, (1, 2), 1.0, 1.3, 1.0),
}


def _check_type(scenario_type: str) -> None:
    if scenario_type not in _TYPES:
        raise ValueError(f"unknown scenario type {scenario_type!r}; expected one of {', '.join(SCENARIO_TYPES)}")


def generate_scene(scenario_type: str, seed: int, params: ProceduralParams | None = None) -> Scene:
    """One scene of `scenario_type`; the same (type, seed, params) gives a bit-identical scene."""
    _check_type(scenario_type)
    p = params or ProceduralParams()
    cfg = _TYPES[scenario_type]
    rng = np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64)])
    lanes = None if p.num_lanes is None else int(np.clip(p.num_lanes, *cfg.lanes))
    boost = 1.0
    for _ in range(12):
        try:
            m = cfg.build(rng, p.lane_width, p.size_scale, lanes, p.crosswalks)
        except geo.GeometryError:
            continue
        tm = TrafficModel(m)
        veh = spawn(tm, rng, density=p.density * cfg.density * boost, speed_mean=p.speed_mean * cfg.speed,
                    speed_std=p.speed_std, spawn_range=p.spawn_range * cfg.spawn_range * p.size_scale,
                    headway=p.time_headway, min_gap=p.min_gap, a_max=p.max_accel, b_comf=p.comfort_decel,
                    max_vehicles=p.max_vehicles)
        if len(veh) < p.min_vehicles:
            boost *= 1.5
            continue
        veh, ro, dropped = settle(tm, veh, p.num_steps, p.dt, p.min_vehicles)
        if veh is not None:
            return _export(scenario_type, int(seed), p, m, veh, ro, len(dropped))
        boost *= 1.2
    raise RuntimeError(f"procedural {scenario_type} seed {seed}: no valid scene after 12 attempts")


def generate_scenes(scenario_type: str, n: int, seed: int, params: ProceduralParams | None = None) -> list[Scene]:
    """n scenes with seeds seed, seed + 1, ...; "all" cycles through SCENARIO_TYPES."""
    if scenario_type != "all":
        _check_type(scenario_type)
    kinds = SCENARIO_TYPES if scenario_type == "all" else (scenario_type,)
    return [generate_scene(kinds[i % len(kinds)], seed + i, params) for i in range(n)]


# ----------------------------------------------------------------------------- export
def _export(kind: str, seed: int, p: ProceduralParams, m: geo.RoadMap, veh, ro, n_dropped: int) -> Scene:
    off = np.asarray(m.info.pop("frame_offset", (0.0, 0.0)), np.float64)
    rot = float(m.info.pop("frame_rotation", 0.0))
    c, s_ = math.cos(rot), math.sin(rot)
    rmat = np.array([[c, -s_], [s_, c]])

    def tf(xy):
        return (np.asarray(xy) - off) @ rmat.T

    roads = [(RoadType.LANE, lane.path.sample()[0]) for lane in m.lanes]
    roads += [(RoadType.ROAD_LINE, ln.sample()[0]) for ln in m.lines]
    roads += [(RoadType.ROAD_EDGE, cb.sample()[0]) for cb in m.curbs]
    roads += [(RoadType.CROSSWALK, cw) for cw in m.crosswalks]
    pts = [tf(xy).astype(np.float32) for _, xy in roads]

    n, t = ro.s.shape
    pos = tf(ro.xy.reshape(-1, 2)).reshape(n, t, 2)
    yaw = ro.yaw + rot
    vel = np.stack([ro.v * np.cos(yaw), ro.v * np.sin(yaw)], -1)
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    routes = []
    for i, lanes in enumerate(veh.routes):
        starts = np.cumsum([0.0] + [m.lanes[k].path.length for k in lanes])
        last = int(np.clip(np.searchsorted(starts, ro.s[i, -1], side="right") - 1, 0, len(lanes) - 1))
        routes.append([int(k) for k in lanes[: last + 1]])
    junction = np.array([any(m.lanes[k].prio >= 0 for k in r) for r in routes])
    d0 = np.linalg.norm(pos[:, 0], axis=-1)
    is_sdc = np.zeros(n, bool)
    is_sdc[int(np.argmin(np.where(junction, d0, d0 + 1e6)))] = True
    info = {k: (np.asarray(v).tolist() if isinstance(v, (list, tuple, np.ndarray, np.generic)) else v)
            for k, v in m.info.items()}
    metadata = dict(
        scenario_type=kind, seed=seed, params=dataclasses.asdict(p), conflict_point=[0.0, 0.0],
        source="procedural", routes=routes, geometry=info, num_dropped=n_dropped,
    )
    scene = Scene(
        scene_id=f"procedural/{kind}/{seed}",
        log_pos=pos.astype(np.float32),
        log_yaw=yaw.astype(np.float32),
        log_vel=vel.astype(np.float32),
        log_valid=np.ones((n, t), bool),
        length=veh.length.astype(np.float32),
        width=veh.width.astype(np.float32),
        height=veh.height.astype(np.float32),
        agent_type=np.full(n, int(AgentType.VEHICLE), np.int8),
        agent_id=np.arange(n, dtype=np.int64),
        goal=pos[:, -1].astype(np.float32),
        is_sdc=is_sdc,
        is_interest=junction,
        road_points=np.concatenate(pts),
        road_offsets=np.concatenate([[0], np.cumsum([len(x) for x in pts])]).astype(np.int64),
        road_type=np.array([int(k) for k, _ in roads], np.int8),
        road_id=np.arange(len(roads), dtype=np.int64),
        lane_edges=np.array(m.edges, np.int32).reshape(-1, 2),
        dt=float(p.dt),
        metadata=metadata,
    )
    return scene.validate()
