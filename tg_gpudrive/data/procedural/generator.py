"""Procedural safety-critical scenarios: the embedded default scene source.

The six scenario types of the TrafficGamer paper (merge, dual-lane
intersection, T-junction, dense-lane intersection, roundabout, Y-junction),
generated from a seed with no dataset: road geometry (lane centrelines with
their successor graph, curbs, lane dividers, crosswalks) and a 91-step, 10 Hz
"log" of vehicles driven by a human-like drive (lane following, IDM car
following, yielding at conflict zones). Invariants of every scene, checked by
tests/test_procedural.py: no two vehicle boxes come within 0.3 m of each other,
no box touches a curb, trajectories obey a kinematic bicycle model (speed >= 0,
|accel| <= 4 m/s^2, |curvature| <= 0.25 1/m, heading = direction of motion),
every goal lies on the last lane of the vehicle's route (`metadata["routes"]`).

Street furniture of real urban scenes, off by default (`ProceduralParams.parking`, `stop_lines`,
`kerb_stops`, `lane_offset`; in a scene spec
`procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4]`): parking strips along
junction arms filled with parked cars (static agents after the moving ones, `metadata["num_parked"]`),
queues at stop lines, vehicles that end their trip parked at the kerb (`metadata["kerb_stops"]`: their
goal lies in the strip, 2-4 m off the lane centre), and drivers who keep their own offset from the
lane centre on straight road (`metadata["lane_offsets"]`, m to the right). A policy trained
without them misses such goals: the shipped one reached 9 % of them against 94 % of the others
(BENCHMARKS.md, "Real-scene transfer"), as it missed the kerbside goals of the real WOMD scenes.

Geometry lives in `geometry.py`, the drive in `traffic.py`, the invariant checks in
`checks.py`; this module only picks per-type settings, retries and exports a `Scene`. Runtime
code is NumPy only.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable

import numpy as np

from tg_gpudrive.data.procedural import geometry as geo
from tg_gpudrive.data.procedural.traffic import (Crossing, TrafficModel, draw_banded, overlapping_pairs, plan_kerb_stops,
                                                 plan_lane_changes, plan_lane_offsets, plan_long_vehicles,
                                                 plan_park_clearance, settle, spawn)
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import AgentType, RoadType

_STREET_STREAM = 0x57EE7  # third seed word of the street-furniture stream
PARK_FILL = (0.45, 0.95)  # fraction of a strip's spaces that hold a car, drawn per strip
PARK_GAP = (0.8, 2.5)  # m between consecutive parked cars
PARK_SPACE = (4.5, 7.0)  # m of an empty space
PARK_KERB_CLEAR = 0.1  # m a parked box keeps from the kerb (and may reach over the lane edge)
_WALKER_STREAM = 0xF007  # third seed word of the pedestrians' stream
_CHANGE_STREAM = 0x1C4A  # third seed word of the lane changes' stream
_LONG_STREAM = 0x7B05  # third seed word of the long vehicles' stream
WALKER_SIZE = 0.8  # m, a pedestrian's box is this square (WOMD pedestrians: about 0.9 x 0.9)
WALKER_KERB = (1.0, 3.0)  # m from the kerb, on the side away from the lanes
WALKER_SPEED = (0.8, 1.6)  # m/s of those who walk
WALKER_STAND = 0.3  # share who stand still
WALKER_LANE_CLEAR = 2.5  # m a pedestrian keeps from every lane centre line
_CROSSING_STREAM = 0xC055  # third seed word of the crossing pedestrians' stream
_REST_STREAM = 0x5E57  # third seed word of the starts from rest
CROSS_SPEED = (1.0, 1.6)  # m/s of most pedestrians crossing the road ...
# ... and (share, m/s) of those who hurry or run: on the lanes of real WOMD training scenes, pedestrians'
# speeds have percentiles 10 / 50 / 90 / 99 of 1.0 / 1.3 / 1.9 / 6.5 m/s
CROSS_HURRY = ((0.10, (1.6, 2.8)), (0.02, (2.8, 6.5)))
CROSS_KERB = 1.5  # m beyond each end of its crosswalk where a crossing starts and ends
CROSS_CLEAR = 1.0  # m every logged box keeps from a crossing pedestrian's at every step
CROSS_WAIT = 1.5  # s a pedestrian waits at the kerb for a vehicle that could not stop for it ...
CROSS_WAITS = 4  # ... at most this many times, then it does not cross

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
    parking         probability that a kerb side of a junction arm has a parking strip with parked
                    cars (static agents appended after the moving ones; none on merges and
                    roundabouts). Real urban WOMD scenes are mostly parked cars beside the lanes.
    max_parked      parked cars kept (nearest to the conflict first)
    stop_lines      probability that the scene's yielding vehicles wait at their stop line, so
                    queues form there (else they wait at the conflict zone inside the junction)
    kerb_stops      probability that a vehicle driving beside a parking strip (before or after the
                    junction) ends its trip parked in it (its goal then lies at the kerb, off the
                    lane centre)
    lane_offset     m, std of each driver's offset from the lane centre on straight road (clipped
                    to keep 0.25 m inside the lane; back on the centre through curves). Logged
                    WOMD drivers keep 0.2-1.5 m off the lane centre; procedural ones 0 by default.
    park_reach      m a parked car may stand over the lane edge into the lane beside its strip: its
                    inner side is drawn U(0, park_reach) m over the edge (else it stands in the middle
                    of its strip). Kerbside parked cars of the real WOMD scenes have their inner side
                    1.04 m from the nearest lane centre (median; 0.50 at the 10th percentile), the
                    strips' 2.0 m. Drivers on a lane beside a strip then keep left of its centre,
                    by 0.5-1 x the lane's room, wherever their route is straight; a parked car that
                    would still come within the check margin of a moving one is dropped.

    pedestrians     mean number of pedestrians on the sidewalks (a Poisson draw per scene): each
                    stands (WALKER_STAND) or walks along a kerb, 1-3 m beyond it, away from every
                    lane; one that would touch a kerb, a vehicle or another pedestrian is left out.
                    Real WOMD scenes hold 2 (median) pedestrians; procedural ones none by default.
    crossings       mean number of pedestrians crossing the road on a crosswalk (a Poisson draw per
                    scene; intersections only, where crosswalks are drawn): each waits on the sidewalk
                    CROSS_KERB m short of its crosswalk, walks across at CROSS_SPEED (some hurry or
                    run, CROSS_HURRY) from a random moment (some are mid-crossing at the first step)
                    and stands on the far side. The
                    logged traffic yields (traffic.py `Crossing`): a vehicle whose route crosses the
                    path and that can still stop waits short of it while the pedestrian crosses; a
                    crossing is kept only where every logged box stays CROSS_CLEAR m clear of the
                    pedestrian's at every step, so a driven vehicle must yield as the logged one did. In real
                    WOMD dev scenes 28 % of pedestrians come within 1.75 m of a lane centre, in 38 % of
                    the scenes; sidewalk pedestrians never do.
    lane_changes    probability that a vehicle whose route ends on a straight lane beside a parallel
                    lane of the same direction changes onto it in the episode (over 25-40 m), so its
                    goal lies on the other lane (`metadata["lane_changes"]`). Logged WOMD drivers on
                    straight paths end 1.5 m or more to the side of where they started in 17 % of
                    cases; procedural ones in 3 % by default. A vehicle in the new lane that it
                    would touch is dropped, as for every overlap.
    long_vehicles   probability that a moving vehicle is a van, truck or bus (traffic.py LONG_LENGTH:
                    5.5-14 m long, 2.0-2.6 m wide) instead of a car (4-5.5 m), where the longer box fits
                    at its start and sweeps no curb along its route. 8 % of real WOMD dev-scene
                    candidates are longer than 5.5 m; procedural ones none by default.
    rest_starts     probability that the front vehicle of a yielding approach starts at rest at its stop
                    line, stands there 1.5-5 s (traffic.py REST_HOLD) and then pulls into or across the
                    junction's traffic when it may (it gives way as every vehicle does). 13 % of the real
                    WOMD dev training candidates are at rest at the init step, most of them pulling away
                    later; procedural ones none by default.

    Street furniture (parking, stop lines, kerb stops, lane offsets) is drawn from its own random
    stream, pedestrians, crossings, lane changes and long vehicles from one each: with parking = 0,
    stop_lines = 0, lane_offset = 0, pedestrians = 0, crossings = 0, lane_changes = 0 and long_vehicles = 0
    (kerb stops need parking) every scene is what it was before these knobs existed, bit for bit.
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
    parking: float = 0.0
    max_parked: int = 32
    stop_lines: float = 0.0
    kerb_stops: float = 0.0
    lane_offset: float = 0.0
    park_reach: float = 0.0
    pedestrians: float = 0.0
    crossings: float = 0.0
    lane_changes: float = 0.0
    long_vehicles: float = 0.0
    rest_starts: float = 0.0

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
            (all(0.0 <= x <= 1.0 for x in (self.parking, self.stop_lines, self.kerb_stops, self.lane_changes,
                                           self.long_vehicles, self.rest_starts)),
             "parking, stop_lines, kerb_stops, lane_changes, long_vehicles and rest_starts must be in [0, 1]"),
            (0 <= self.max_parked <= 128, "max_parked must be in [0, 128]"),
            (0.0 <= self.lane_offset <= 1.0, "lane_offset must be in [0, 1] m"),
            (0.0 <= self.park_reach <= 2.0, "park_reach must be in [0, 2] m"),
            (0.0 <= self.pedestrians <= 32.0, "pedestrians must be in [0, 32] (a mean per scene)"),
            (0.0 <= self.crossings <= 16.0, "crossings must be in [0, 16] (a mean per scene)"),
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
    street = np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64), _STREET_STREAM])
    hold = bool(street.random() < p.stop_lines)
    lanes = None if p.num_lanes is None else int(np.clip(p.num_lanes, *cfg.lanes))
    boost = 1.0
    for attempt in range(12):
        try:
            m = cfg.build(rng, p.lane_width, p.size_scale, lanes, p.crosswalks, p.parking, street)
        except geo.GeometryError:
            continue
        tm = TrafficModel(m)
        veh = spawn(tm, rng, density=p.density * cfg.density * boost, speed_mean=p.speed_mean * cfg.speed,
                    speed_std=p.speed_std, spawn_range=p.spawn_range * cfg.spawn_range * p.size_scale,
                    headway=p.time_headway, min_gap=p.min_gap, a_max=p.max_accel, b_comf=p.comfort_decel,
                    max_vehicles=p.max_vehicles, rest_front=p.rest_starts,
                    rest_rng=np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64),
                                                    _REST_STREAM, attempt]))
        if len(veh) < p.min_vehicles:
            boost *= 1.5
            continue
        plan_long_vehicles(tm, veh, np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64),
                                                           _LONG_STREAM]), p.long_vehicles)
        plan_lane_offsets(veh, street, p.lane_offset, p.lane_width)
        if p.park_reach > 0:
            plan_park_clearance(tm, veh, street, p.lane_width)
        plans = plan_crossings(m, np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64),
                                                         _CROSSING_STREAM]), p.crossings, (p.num_steps - 1) * p.dt)
        veh, ro, dropped, plans = _settle_yielding(tm, veh, p, hold, plans)
        if veh is not None:
            # kerb stops and lane changes are drawn where the free drive shows a vehicle gets far
            # enough, then the traffic is rolled out again with them (if that cannot settle, the scene
            # goes without)
            kerb = veh.subset(np.ones(len(veh), bool))
            planned = plan_kerb_stops(tm, kerb, ro.s[:, -1], street, p.kerb_stops, PARK_KERB_CLEAR)
            if p.lane_changes > 0:
                change = np.random.default_rng([SCENARIO_TYPES.index(scenario_type), int(seed) % (1 << 64),
                                                _CHANGE_STREAM])
                planned += plan_lane_changes(tm, kerb, ro.s[:, -1], change, p.lane_changes, p.lane_width)
            if planned:
                kerb, ro_k, dropped_k, plans_k = _settle_yielding(tm, kerb, p, hold, plans)
                if kerb is not None:
                    veh, ro, dropped, plans = kerb, ro_k, dropped + dropped_k, plans_k
            parked = park_cars(m, street, *_with_crossers(ro, veh, plans, p), p.max_parked, p.park_reach)
            crossers = crossing_walkers(plans, ro, veh, parked, p.num_steps, p.dt)
            walkers = walk_sidewalks(m, np.random.default_rng([SCENARIO_TYPES.index(scenario_type),
                                                               int(seed) % (1 << 64), _WALKER_STREAM]),
                                     p.pedestrians, ro, veh, parked, p.dt, crossers) + crossers
            return _export(scenario_type, int(seed), p, m, veh, ro, len(dropped), parked, hold, walkers)
        boost *= 1.2
    raise RuntimeError(f"procedural {scenario_type} seed {seed}: no valid scene after 12 attempts")


def generate_scenes(scenario_type: str, n: int, seed: int, params: ProceduralParams | None = None) -> list[Scene]:
    """n scenes with seeds seed, seed + 1, ...; "all" cycles through SCENARIO_TYPES."""
    if scenario_type != "all":
        _check_type(scenario_type)
    kinds = SCENARIO_TYPES if scenario_type == "all" else (scenario_type,)
    return [generate_scene(kinds[i % len(kinds)], seed + i, params) for i in range(n)]


# ----------------------------------------------------------------------------- parked cars
@dataclass
class Parked:
    """Static vehicles in the map's parking strips: (K,) arrays, positions in the map frame."""

    xy: np.ndarray  # (K, 2) m
    yaw: np.ndarray  # (K,) rad
    length: np.ndarray  # (K,) m
    width: np.ndarray  # (K,) m

    def __len__(self) -> int:
        return len(self.yaw)


_NO_PARKED = Parked(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))


def park_cars(m: geo.RoadMap, rng: np.random.Generator, ro, veh, max_parked: int, reach: float = 0.0) -> Parked:
    """Fill the map's parking strips with cars, kerbside (or, with `reach` > 0, standing U(0, reach) m
    over the lane edge), facing their side's traffic; drop any that would come within the drive's
    check margin of a moving vehicle at any step (which leaves the space a kerb stop pulls into) or
    touch a kerb (by construction none should); keep the `max_parked` nearest to the conflict point."""
    rows = []
    for st in m.strips:
        fill = float(rng.uniform(*PARK_FILL))
        t = st.t0 + float(rng.uniform(0.5, 3.0))
        while True:
            L, W = float(rng.uniform(4.0, 5.5)), float(rng.uniform(1.8, 2.2))
            if t + L > st.t1 - 2.0:
                break
            if rng.random() < fill:
                dyaw = float(rng.uniform(-0.03, 0.03))
                sway = L / 2 * abs(dyaw) + PARK_KERB_CLEAR  # a turned box reaches further sideways
                lo, hi = W / 2 + sway - 0.15, st.width - W / 2 - sway
                jitter = float(rng.uniform(-0.1, 0.1))  # drawn either way: scenes without reach stay as they were
                if reach > 0:  # the inner side U(0, reach) m past the lane edge (towards the lane centre)
                    lat = min(W / 2 + sway - float(rng.uniform(0.0, reach)), max(lo, hi))
                else:  # the middle of the strip
                    lat = float(np.clip(st.width / 2 + jitter, lo, max(lo, hi)))
                x, y, h = st.pose(t + L / 2, lat)
                rows.append((math.hypot(x, y), x, y, h + dyaw, L, W))
                t += L + float(rng.uniform(*PARK_GAP))
            else:
                t += float(rng.uniform(*PARK_SPACE))
    rows.sort()
    if not rows:
        return Parked(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0))
    _, x, y, h, L, W = (np.array(c, np.float64) for c in zip(*rows))
    xy = np.stack([x, y], 1)
    ok = np.ones(len(h), bool)
    # moving vehicles at every step against the parked boxes (which never move)
    n, T = ro.yaw.shape
    all_xy = np.concatenate([ro.xy, np.repeat(xy[:, None], T, 1)])
    all_yaw = np.concatenate([ro.yaw, np.repeat(h[:, None], T, 1)])
    for _, i, j in overlapping_pairs(all_xy, all_yaw, np.concatenate([veh.length, L]),
                                     np.concatenate([veh.width, W])):
        for a in (i, j):
            if a >= n:
                ok[a - n] = False
    ok &= ~m.curb_hits(xy, h, L / 2, W / 2)
    keep = np.flatnonzero(ok)[:max_parked]
    return Parked(xy[keep], h[keep], L[keep], W[keep])


# ----------------------------------------------------------------------------- pedestrians
@dataclass
class Walkers:
    """Pedestrians: (K, T) poses in the map frame, each walking along its heading."""

    xy: np.ndarray  # (K, T, 2) m
    yaw: np.ndarray  # (K, T) rad
    speed: np.ndarray  # (K, T) m/s
    crossing: np.ndarray  # (K,) bool: crosses the road (plan_crossings), else keeps to a sidewalk

    def __len__(self) -> int:
        return len(self.speed)

    def __add__(self, other: "Walkers") -> "Walkers":
        return Walkers(*(np.concatenate([getattr(self, f), getattr(other, f)])
                         for f in ("xy", "yaw", "speed", "crossing")))

    @staticmethod
    def none(steps: int) -> "Walkers":
        return Walkers(np.zeros((0, steps, 2)), np.zeros((0, steps)), np.zeros((0, steps)), np.zeros(0, bool))


class _Crowd:
    """The boxes a new pedestrian must keep off (logged vehicles, parked cars, earlier pedestrians) and
    the pedestrians accepted so far."""

    def __init__(self, ro, veh, parked: Parked, walkers: "Walkers | None" = None):
        T = ro.yaw.shape[1]
        self.xy = [ro.xy, np.repeat(parked.xy[:, None], T, 1)]
        self.yaw = [ro.yaw, np.repeat(parked.yaw[:, None], T, 1)]
        self.length, self.width = [veh.length, parked.length], [veh.width, parked.width]
        self.steps, self.new = T, []
        if walkers is not None and len(walkers):
            for k in range(len(walkers)):
                self._append(walkers.xy[k], walkers.yaw[k])

    def _append(self, xy: np.ndarray, yaw: np.ndarray) -> None:
        self.xy.append(xy[None])
        self.yaw.append(yaw[None])
        self.length.append([WALKER_SIZE])
        self.width.append([WALKER_SIZE])

    def fits(self, xy: np.ndarray, yaw: np.ndarray, clearance: float | None = None) -> bool:
        """Whether a pedestrian's (T, 2) path keeps its box `clearance` m from every other box at every
        step (default: the traffic check's margin on each box)."""
        all_xy = np.concatenate([*self.xy, xy[None]])
        all_yaw = np.concatenate([*self.yaw, yaw[None]])
        size_l = np.concatenate([*self.length, [WALKER_SIZE]])
        size_w = np.concatenate([*self.width, [WALKER_SIZE]])
        kw = {} if clearance is None else {"margin": clearance / 2}  # the margin grows both boxes
        return not overlapping_pairs(all_xy, all_yaw, size_l, size_w, of=len(all_xy) - 1, **kw)

    def add(self, xy: np.ndarray, yaw: np.ndarray, speed: np.ndarray) -> None:
        self._append(xy, yaw)
        self.new.append((xy, yaw, speed))

    def walkers(self, crossing: bool) -> "Walkers":
        """The pedestrians added, as Walkers."""
        if not self.new:
            return Walkers.none(self.steps)
        xy, yaw, speed = (np.stack(x) for x in zip(*self.new))
        return Walkers(xy, yaw, speed, np.full(len(self.new), crossing))


def walk_sidewalks(m: geo.RoadMap, rng: np.random.Generator, mean: float, ro, veh, parked: Parked,
                   dt: float, others: Walkers | None = None) -> Walkers:
    """Poisson(`mean`) pedestrians, each standing or walking in a straight line along a kerb, 1-3 m
    beyond it on the side away from the lanes; those whose box would touch a kerb, come within
    WALKER_LANE_CLEAR of a lane centre line, or touch a vehicle, a parked car or an earlier pedestrian
    at any step are left out (up to four tries for each)."""
    n, T = ro.yaw.shape
    want = int(rng.poisson(mean)) if mean > 0 else 0
    if want == 0 or not m.curbs:
        return Walkers.none(T)
    kerbs = [c.sample()[0] for c in m.curbs]
    kerbs = [k for k in kerbs if len(k) >= 3]
    lanes = np.concatenate([lane.path.sample()[0] for lane in m.lanes])
    segs = m.curb_segments()
    half = WALKER_SIZE / 2
    crowd = _Crowd(ro, veh, parked, others)
    t = np.arange(T) * dt
    for _ in range(4 * want):
        if len(crowd.new) == want or not kerbs:
            break
        pts = kerbs[int(rng.integers(len(kerbs)))]
        k = int(rng.integers(1, len(pts) - 1))
        d = pts[k + 1] - pts[k - 1]
        d = d / max(float(np.linalg.norm(d)), 1e-9)
        normal = np.array([-d[1], d[0]])
        near_lane = lambda q: float(np.min(np.linalg.norm(lanes - q, axis=-1)))  # noqa: E731
        side = 1.0 if near_lane(pts[k] + 2 * normal) > near_lane(pts[k] - 2 * normal) else -1.0
        start = pts[k] + side * normal * float(rng.uniform(*WALKER_KERB))
        v = 0.0 if rng.random() < WALKER_STAND else float(rng.uniform(*WALKER_SPEED))
        heading = d * (1.0 if rng.random() < 0.5 else -1.0)
        xy = start + np.outer(v * t, heading)
        yaw = np.full(T, math.atan2(heading[1], heading[0]))
        if np.min(np.linalg.norm(xy[:, None] - lanes[None], axis=-1)) < WALKER_LANE_CLEAR:
            continue
        if m.curb_hits(xy, yaw, half, half, segs).any():
            continue
        if crowd.fits(xy, yaw):
            crowd.add(xy, yaw, np.full(T, v))
    return crowd.walkers(crossing=False)


def cross_speed(rng: np.random.Generator) -> float:
    """A crossing pedestrian's speed: from a CROSS_HURRY band with its share, else from CROSS_SPEED."""
    return draw_banded(rng, CROSS_HURRY, CROSS_SPEED)


def plan_crossings(m: geo.RoadMap, rng: np.random.Generator, mean: float, duration: float) -> list[Crossing]:
    """Poisson(`mean`) pedestrians to cross the road on the map's crosswalks (ProceduralParams.crossings):
    from CROSS_KERB m short of one end of a crosswalk to as far past the other, within 1 m of its centre
    line, at a speed drawn from CROSS_SPEED or a band of CROSS_HURRY (`cross_speed`), leaving at a moment drawn
    so that the middle of the crossing falls within the episode (`duration` s)."""
    want = int(rng.poisson(mean)) if mean > 0 else 0
    out = []
    for _ in range(want if m.crosswalks else 0):
        cw = m.crosswalks[int(rng.integers(len(m.crosswalks)))]  # corners lo/t0, hi/t0, hi/t1, lo/t1
        a, b = 0.5 * (cw[0] + cw[3]), 0.5 * (cw[1] + cw[2])  # the two ends, across the road
        if rng.random() < 0.5:
            a, b = b, a
        u = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
        side = (cw[3] - cw[0]) / max(float(np.linalg.norm(cw[3] - cw[0])), 1e-9)  # along the road
        shift = side * float(rng.uniform(-1.0, 1.0))
        start, end = a - u * CROSS_KERB + shift, b + u * CROSS_KERB + shift
        v = cross_speed(rng)
        half_way = 0.5 * float(np.linalg.norm(end - start)) / v
        out.append(Crossing(start, end, v, float(rng.uniform(-half_way, duration - half_way))))
    return out


def _settle_yielding(tm: TrafficModel, veh, p: ProceduralParams, hold: bool, plans: list[Crossing]):
    """`settle` with the vehicles yielding to the crossings of `plans`. A pedestrian whose path the settled
    traffic does not keep CROSS_CLEAR from (a vehicle too close to stop when it set off) waits at the
    kerb CROSS_WAIT s longer, up to CROSS_WAITS times, then gives up (dropped); the traffic is rolled out
    again after each change. Returns settle's (vehicles, log, dropped) and the crossings kept."""
    nobody = SimpleNamespace(xy=np.zeros((0, p.num_steps, 2)), yaw=np.zeros((0, p.num_steps)))
    apart, kept_plans = _Crowd(nobody, SimpleNamespace(length=np.zeros(0), width=np.zeros(0)), _NO_PARKED), []
    for c in plans:  # pedestrians that would walk into each other: the later-drawn one does not cross
        xy, yaw, speed = c.path(p.num_steps, p.dt)
        if apart.fits(xy, yaw, CROSS_CLEAR):
            apart.add(xy, yaw, speed)
            kept_plans.append(c)
    plans, waits = kept_plans, [0] * len(kept_plans)
    while True:
        kept, ro, dropped = settle(tm, veh, p.num_steps, p.dt, p.min_vehicles, hold, tuple(plans))
        if kept is None or not plans:
            return kept, ro, dropped, plans
        crowd = _Crowd(ro, kept, _NO_PARKED)
        clear = [crowd.fits(*c.path(p.num_steps, p.dt)[:2], CROSS_CLEAR) for c in plans]
        if all(clear):
            return kept, ro, dropped, plans
        keep = []
        for c, w, ok in zip(plans, waits, clear):
            if ok:
                keep.append((c, w))
            elif w < CROSS_WAITS:
                keep.append((dataclasses.replace(c, t0=c.t0 + CROSS_WAIT), w + 1))
        plans, waits = [c for c, _ in keep], [w for _, w in keep]


def _with_crossers(ro, veh, plans: list[Crossing], p: ProceduralParams):
    """The moving boxes parked cars must keep off, as park_cars reads them (`ro.xy`, `ro.yaw`, `veh.length`,
    `veh.width`): the logged vehicles and, grown by CROSS_CLEAR, the crossing pedestrians."""
    if not plans:
        return ro, veh
    paths = [c.path(p.num_steps, p.dt) for c in plans]
    size = np.full(len(plans), WALKER_SIZE + 2 * CROSS_CLEAR)
    moving = SimpleNamespace(xy=np.concatenate([ro.xy, np.stack([q[0] for q in paths])]),
                             yaw=np.concatenate([ro.yaw, np.stack([q[1] for q in paths])]))
    return moving, SimpleNamespace(length=np.concatenate([veh.length, size]), width=np.concatenate([veh.width, size]))


def crossing_walkers(plans: list[Crossing], ro, veh, parked: Parked, num_steps: int, dt: float) -> Walkers:
    """The pedestrians of the kept crossings (parked cars were placed clear of them: `_with_crossers`; the
    check stays as a guard)."""
    crowd = _Crowd(ro, veh, parked)
    for c in plans:
        xy, yaw, speed = c.path(num_steps, dt)
        if crowd.fits(xy, yaw, CROSS_CLEAR):
            crowd.add(xy, yaw, speed)
    return crowd.walkers(crossing=True)


def _parked_at_kerb(veh, ro) -> np.ndarray:
    """(N,) bool: the kerb-stopping vehicles that end the episode in their strip (most of the way over)."""
    out = np.zeros(len(veh), bool)
    for i in np.flatnonzero(np.isfinite(veh.stop_s)):
        out[i] = veh.kerb_lateral(i, ro.s[i, -1:])[0][0] >= 0.9 * veh.kerb_off[i]
    return out


def _lane_changes(veh, ro) -> list[list]:
    """[vehicle, the lane it changes onto, the share of the change done at the last step] of every
    vehicle that changes lanes (the share is below 1 when the episode ends mid-change)."""
    out = []
    for i in np.flatnonzero(np.isfinite(veh.change_s)):
        done = veh.change_lateral(int(i), ro.s[i, -1:])[0][0] / veh.change_off[i]
        out.append([int(i), int(veh.change_lane[i]), round(float(done), 4)])
    return out


# ----------------------------------------------------------------------------- export
def _export(kind: str, seed: int, p: ProceduralParams, m: geo.RoadMap, veh, ro, n_dropped: int,
            parked: Parked, hold_at_stop_line: bool, walkers: Walkers | None = None) -> Scene:
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
    k = len(parked)  # parked cars follow the moving ones: same pose at every step, speed 0
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
        num_parked=k, hold_at_stop_line=hold_at_stop_line,
        kerb_stops=[int(i) for i in np.flatnonzero(_parked_at_kerb(veh, ro))],
        lane_offsets=[round(float(b), 4) for b in veh.bias],
        lane_changes=_lane_changes(veh, ro),
    )
    if k:
        ppos = np.repeat(tf(parked.xy)[:, None], t, 1)
        pyaw = np.repeat(((parked.yaw + rot + np.pi) % (2 * np.pi) - np.pi)[:, None], t, 1)
        pos = np.concatenate([pos, ppos])
        yaw = np.concatenate([yaw, pyaw])
        vel = np.concatenate([vel, np.zeros((k, t, 2))])
    q = 0 if walkers is None else len(walkers)  # pedestrians follow the parked cars
    if q:
        wyaw = walkers.yaw + rot
        pos = np.concatenate([pos, tf(walkers.xy.reshape(-1, 2)).reshape(q, t, 2)])
        yaw = np.concatenate([yaw, (wyaw + np.pi) % (2 * np.pi) - np.pi])
        vel = np.concatenate([vel, walkers.speed[:, :, None] * np.stack([np.cos(wyaw), np.sin(wyaw)], -1)])
    metadata["num_pedestrians"] = q
    metadata["crossing_pedestrians"] = [] if not q else [n + k + int(i) for i in np.flatnonzero(walkers.crossing)]
    scene = Scene(
        scene_id=f"procedural/{kind}/{seed}",
        log_pos=pos.astype(np.float32),
        log_yaw=yaw.astype(np.float32),
        log_vel=vel.astype(np.float32),
        log_valid=np.ones((n + k + q, t), bool),
        length=np.concatenate([veh.length, parked.length, np.full(q, WALKER_SIZE)]).astype(np.float32),
        width=np.concatenate([veh.width, parked.width, np.full(q, WALKER_SIZE)]).astype(np.float32),
        height=np.concatenate([veh.height, np.full(k, 1.6), np.full(q, 1.75)]).astype(np.float32),
        agent_type=np.concatenate([np.full(n + k, int(AgentType.VEHICLE)),
                                   np.full(q, int(AgentType.PEDESTRIAN))]).astype(np.int8),
        agent_id=np.arange(n + k + q, dtype=np.int64),
        goal=pos[:, -1].astype(np.float32),
        is_sdc=np.concatenate([is_sdc, np.zeros(k + q, bool)]),
        is_interest=np.concatenate([junction, np.zeros(k + q, bool)]),
        road_points=np.concatenate(pts),
        road_offsets=np.concatenate([[0], np.cumsum([len(x) for x in pts])]).astype(np.int64),
        road_type=np.array([int(k) for k, _ in roads], np.int8),
        road_id=np.arange(len(roads), dtype=np.int64),
        lane_edges=np.array(m.edges, np.int32).reshape(-1, 2),
        dt=float(p.dt),
        metadata=metadata,
    )
    return scene.validate()
