"""Load GPUDrive's processed WOMD JSON scenes into `Scene`.

GPUDrive (and Nocturne before it) convert each Waymo Open Motion Dataset
scenario into one JSON file:

    key                  content
    name, scenario_id    source file tag, WOMD scenario id
    objects[i]           position [{x,y,z}]*T, velocity [{x,y}]*T, heading [rad]*T,
                         valid [bool]*T, width, length, height, goalPosition {x,y,z},
                         type (vehicle/pedestrian/cyclist/...), id, mark_as_expert
    roads[r]             geometry [{x,y,z}]*k, type (lane/road_line/road_edge/stop_sign/
                         crosswalk/speed_bump/driveway), id, map_element_id
    tl_states            {lane_id: {state: [str], x: [..], y: [..], time_index: [..]}} or {}
    metadata             sdc_track_index, objects_of_interest (ids),
                         tracks_to_predict [{track_index, difficulty}]

Invalid steps hold -10000 in position, velocity and heading; here they become
`log_valid` False and never reach the Scene. Every structural problem (bad
JSON, missing key, wrong type, NaN, nothing valid) raises
`SceneError(path, "objects[3].position[17].x", problem)` rather than a KeyError
or TypeError from deep inside, so a bad file in a large dataset is easy to find.

Required keys are the ones the Scene needs (objects with their trajectories,
width, length, goal and type; roads with geometry and type). `name`,
`scenario_id`, `tl_states`, `metadata`, `map_element_id` and `mark_as_expert`
are optional. Traffic-signal entries that cannot be read are dropped and
counted in metadata["tl_dropped"], since signals are auxiliary.

Older revisions. GPUDrive's earlier files and Nocturne's (the same layout, and
many users' processed data) differ from the current revision; each difference
is filled in by one rule and counted in metadata["defaults"] (field -> how
many objects, roads or files it was used for), which `convert` and the scene
commands report:

    field                  older revision             rule
    objects[i].height      missing                    DEFAULT_HEIGHT of the agent type
    objects[i].id          missing                    a unique id: the object's index, moved past
                                                      the largest id the file does give
    roads[r].id            missing                    the same rule over roads
    objects[i].heading     degrees                    converted to radians (see `heading_unit`)
    objects[i].goalPosition missing                   the last valid position
    objects[i].type        other spellings            "car" / "bicycle" / "bike" are vehicle /
                                                      cyclist (`_TYPE_ALIASES`), unknown -> other
    roads[r].type          unknown kind (e.g. "unknown", "none")
                                                      dropped and counted as "roads.type"
    mark_as_expert         missing                    no object is marked

Headings are in degrees when any valid heading lies beyond 2 pi (+ 1e-3) in
magnitude, or else when the agents' direction of motion fits the headings read
as degrees clearly better than read as radians (`heading_unit`).
"""

from __future__ import annotations

import json
import logging
import math
import os
from typing import Any

import numpy as np

from tg_gpudrive.data.simplify import simplify_scene
from tg_gpudrive.scene import FieldReader, Scene
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

log = logging.getLogger(__name__)

__all__ = ["load_gpudrive_json", "heading_unit", "scene_origin", "SENTINEL", "WOMD_SUBTYPE_BY_MAP_ELEMENT"]

SENTINEL = -10000.0  # GPUDrive's value for fields of invalid steps

_AGENT_TYPES = {"vehicle": AgentType.VEHICLE, "pedestrian": AgentType.PEDESTRIAN, "cyclist": AgentType.CYCLIST}
_TYPE_ALIASES = {"car": AgentType.VEHICLE, "bicycle": AgentType.CYCLIST, "bike": AgentType.CYCLIST}
_ROAD_TYPES = {m.name.lower(): m for m in RoadType if m != RoadType.NONE}
_UNKNOWN_ROAD_TYPES = {"unknown", "none", "unset", "other", "invalid"}  # older files' placeholder kinds
# m, typical WOMD box heights (median of the files that carry height); only drawing and exports read it
DEFAULT_HEIGHT = {AgentType.VEHICLE: 1.6, AgentType.PEDESTRIAN: 1.75, AgentType.CYCLIST: 1.8, AgentType.OTHER: 1.5}


def _map_element_subtype(mid: int) -> int:
    """GPUDrive's map_element_id (WOMD tf.Example roadgraph type) -> the WOMD
    per-kind enum (LaneCenter.LaneType, RoadLine.RoadLineType, RoadEdge.RoadEdgeType)."""
    if 0 <= mid <= 3:
        return mid  # lane: undefined, freeway, surface street, bike lane
    if 5 <= mid <= 13:
        return mid - 5  # road line: unknown, broken single white, ...
    if 14 <= mid <= 16:
        return mid - 14  # road edge: unknown, boundary, median
    return 0


WOMD_SUBTYPE_BY_MAP_ELEMENT = {mid: _map_element_subtype(mid) for mid in range(21)}


def scene_origin(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Scene-frame origin: mean of the valid agent positions, rounded to whole metres.

    Any point near the agents keeps float32 at ~0.1 mm precision; rounding makes
    the origin reproducible from the positions themselves, so a scene written to
    a TFRecord in global coordinates and read back recovers the same origin and
    bit-identical float32 positions (WOMD coordinates are float32-representable,
    so subtracting a whole number stays exact).
    """
    pts = np.asarray(xy, np.float64)[np.asarray(valid, bool)]
    pts = pts[np.isfinite(pts).all(-1)]  # one bad point must not shift (or NaN) every position
    if len(pts) == 0:
        return np.zeros(2, np.float64)
    return np.round(pts.mean(0))


class _Reader(FieldReader):
    """Typed access into parsed JSON that raises SceneError with the field path."""

    def list(self, obj: Any, key: str, path: str) -> list:
        v = self.key(obj, key, path)
        if not isinstance(v, list):
            self.fail(f"{path}.{key}", f"expected a list, got {type(v).__name__}")
        return v

    def number(self, v: Any, path: str) -> float:
        if type(v) not in (int, float):
            self.fail(path, f"expected a number, got {type(v).__name__}")
        if not math.isfinite(v):
            self.fail(path, f"non-finite value {v}")
        return float(v)

    def integer(self, v: Any, path: str) -> int:
        if type(v) is not int:
            self.fail(path, f"expected an integer, got {type(v).__name__}")
        return v

    def points(self, lst: list, path: str, keys: tuple[str, ...] = ("x", "y")) -> np.ndarray:
        """(k, len(keys)) float64 from a list of {x, y, ...} dicts; sentinels kept, NaN rejected."""
        try:
            flat = [p[k] for p in lst for k in keys]
            ok = {type(v) for v in flat} <= {int, float}
        except (KeyError, TypeError, IndexError):
            ok = False
        if not ok:
            self._locate(lst, path, keys)
        arr = np.array(flat, np.float64).reshape(len(lst), len(keys))
        bad = ~np.isfinite(arr)
        if bad.any():
            t, k = np.argwhere(bad)[0]
            self.fail(f"{path}[{t}].{keys[k]}", f"non-finite value {arr[t, k]}")
        return arr

    def _locate(self, lst: list, path: str, keys: tuple[str, ...]):
        for t, p in enumerate(lst):
            for k in keys:
                self.number(self.key(p, k, f"{path}[{t}]"), f"{path}[{t}].{k}")
        self.fail(path, "malformed point list")  # unreachable unless the fast path and this disagree

    def numbers(self, lst: list, path: str) -> np.ndarray:
        if not {type(v) for v in lst} <= {int, float}:
            for t, v in enumerate(lst):
                self.number(v, f"{path}[{t}]")
        arr = np.array(lst, np.float64)
        bad = ~np.isfinite(arr)
        if bad.any():
            t = int(np.nonzero(bad)[0][0])
            self.fail(f"{path}[{t}]", f"non-finite value {arr[t]}")
        return arr

    def bools(self, lst: list, path: str) -> np.ndarray:
        if not {type(v) for v in lst} <= {bool}:
            for t, v in enumerate(lst):
                if type(v) is not bool and v not in (0, 1):
                    self.fail(f"{path}[{t}]", f"expected a bool, got {v!r}")
        return np.array(lst, bool)


def heading_unit(yaw: np.ndarray, vel: np.ndarray, valid: np.ndarray) -> str:
    """"degrees" or "radians": the unit of a file's headings (N, T) given velocities (N, T, 2).

    Degrees for certain when a valid heading lies beyond 2 pi (+ 1e-3) in magnitude. Otherwise the
    direction of motion decides: over the valid steps faster than 2 m/s (at least 5 of them), the
    median angle between velocity and heading must be under 0.2 rad read as degrees and exceed
    twice that plus 0.1 rad read as radians; anything less clear (headings near 0 fit both) stays
    radians, the current revision's unit."""
    h = np.abs(yaw[valid])
    if h.size and h.max() > 2 * math.pi + 1e-3:
        return "degrees"
    moving = valid & (np.hypot(vel[..., 0], vel[..., 1]) > 2.0)
    if moving.sum() < 5:
        return "radians"
    motion = np.arctan2(vel[..., 1], vel[..., 0])[moving]

    def err(theta):
        return float(np.median(np.abs((motion - theta + math.pi) % (2 * math.pi) - math.pi)))

    as_rad, as_deg = err(yaw[moving]), err(np.radians(yaw[moving]))
    return "degrees" if as_deg < 0.2 and as_rad > 2 * as_deg + 0.1 else "radians"


def _unique_ids(given: list[int | None]) -> tuple[np.ndarray, int]:
    """Ids with the missing ones (None) filled by index, moved past the largest given id so none
    collides; and how many were filled."""
    known = [v for v in given if v is not None]
    base = max(known) + 1 if known else 0
    filled = [base + i if v is None else v for i, v in enumerate(given)]
    return np.asarray(filled, np.int64), len(given) - len(known)


def _objects(rd: _Reader, objects: list, defaults: dict) -> dict:
    """The objects' arrays, sentinels still in place; older-revision fields filled and counted."""
    n = len(objects)
    t_steps = None
    pos, vel, yaw, valid = [], [], [], []
    length, width, height = np.zeros(n), np.zeros(n), np.zeros(n)
    goal = np.full((n, 2), SENTINEL)
    agent_type = np.zeros(n, np.int8)
    ids: list[int | None] = []
    expert = []
    for i, o in enumerate(objects):
        p = f"objects[{i}]"
        if not isinstance(o, dict):
            rd.fail(p, f"expected an object, got {type(o).__name__}")
        traj = {key: rd.list(o, key, p) for key in ("position", "velocity", "heading", "valid")}
        if t_steps is None:
            t_steps = len(traj["position"])
        for key, lst in traj.items():
            if len(lst) != t_steps:
                rd.fail(f"{p}.{key}", f"expected {t_steps} steps (as objects[0].position), got {len(lst)}")
        pos.append(rd.points(traj["position"], f"{p}.position"))
        vel.append(rd.points(traj["velocity"], f"{p}.velocity"))
        yaw.append(rd.numbers(traj["heading"], f"{p}.heading"))
        valid.append(rd.bools(traj["valid"], f"{p}.valid"))
        length[i] = rd.number(rd.key(o, "length", p), f"{p}.length")
        width[i] = rd.number(rd.key(o, "width", p), f"{p}.width")
        kind = rd.key(o, "type", p)
        if not isinstance(kind, str):
            rd.fail(f"{p}.type", f"expected a string, got {type(kind).__name__}")
        kind = kind.lower()
        agent_type[i] = _AGENT_TYPES.get(kind, _TYPE_ALIASES.get(kind, AgentType.OTHER))
        if kind in _TYPE_ALIASES:
            defaults["objects.type"] = defaults.get("objects.type", 0) + 1
        if "height" in o:
            height[i] = rd.number(o["height"], f"{p}.height")
        else:
            height[i] = DEFAULT_HEIGHT[AgentType(agent_type[i])]
            defaults["objects.height"] = defaults.get("objects.height", 0) + 1
        if "goalPosition" in o:
            g = o["goalPosition"]
            goal[i] = [rd.number(rd.key(g, k, f"{p}.goalPosition"), f"{p}.goalPosition.{k}") for k in ("x", "y")]
        else:
            defaults["objects.goalPosition"] = defaults.get("objects.goalPosition", 0) + 1
        ids.append(rd.integer(o["id"], f"{p}.id") if "id" in o else None)
        if o.get("mark_as_expert") is True:
            expert.append(i)
    agent_id, filled = _unique_ids(ids)
    if filled:
        defaults["objects.id"] = filled
    return {"t_steps": t_steps, "pos": np.stack(pos), "vel": np.stack(vel), "yaw": np.stack(yaw),
            "valid": np.stack(valid), "length": length, "width": width, "height": height, "goal": goal,
            "agent_type": agent_type, "agent_id": agent_id, "expert": expert}


def _roads(rd: _Reader, roads: list, origin: np.ndarray, defaults: dict) -> dict:
    """Road polylines in the scene frame; empty and unknown-kind polylines dropped and counted."""
    pts, road_type, ids, subtype = [], [], [], []
    dropped_empty = 0
    for r, road in enumerate(roads):
        p = f"roads[{r}]"
        geom = rd.points(rd.list(road, "geometry", p), f"{p}.geometry")
        kind = rd.key(road, "type", p)
        if isinstance(kind, str) and kind.lower() in _UNKNOWN_ROAD_TYPES:
            defaults["roads.type"] = defaults.get("roads.type", 0) + 1  # a placeholder kind: nothing to use
            continue
        if not isinstance(kind, str) or kind.lower() not in _ROAD_TYPES:
            rd.fail(f"{p}.type", f"unknown road type {kind!r}; expected one of {', '.join(_ROAD_TYPES)}")
        rid = rd.integer(road["id"], f"{p}.id") if "id" in road else None
        if len(geom) == 0:
            dropped_empty += 1  # an empty polyline has nothing to draw or collide with
            continue
        mid = road.get("map_element_id")
        pts.append(geom)
        road_type.append(int(_ROAD_TYPES[kind.lower()]))
        ids.append(rid)
        subtype.append(WOMD_SUBTYPE_BY_MAP_ELEMENT.get(mid, 0) if type(mid) is int else 0)
    road_id, filled = _unique_ids(ids)
    if filled:
        defaults["roads.id"] = filled
    return {
        "road_points": ((np.concatenate(pts) - origin) if pts else np.zeros((0, 2))).astype(np.float32),
        "road_offsets": np.concatenate([[0], np.cumsum([len(g) for g in pts], dtype=np.int64)]).astype(np.int64),
        "road_type": np.asarray(road_type, np.int8),
        "road_id": road_id,
        "subtype": subtype,
        "dropped_empty": dropped_empty,
    }


def _interest(rd: _Reader, meta: dict, agent_id: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """(is_sdc, is_interest, metadata entries) from the file's `metadata` object."""
    n = len(agent_id)
    is_sdc = np.zeros(n, bool)
    sdc = meta.get("sdc_track_index")
    if sdc is not None:
        sdc = rd.integer(sdc, "metadata.sdc_track_index")
        if sdc >= n:
            rd.fail("metadata.sdc_track_index", f"index {sdc} out of range for {n} objects")
        if sdc >= 0:
            is_sdc[sdc] = True
    is_interest = np.zeros(n, bool)
    tracks_to_predict = []
    for k, item in enumerate(meta.get("tracks_to_predict") or []):
        fp = f"metadata.tracks_to_predict[{k}]"
        idx = rd.integer(rd.key(item, "track_index", fp) if isinstance(item, dict) else item,
                         f"{fp}.track_index")
        if not 0 <= idx < n:
            rd.fail(f"{fp}.track_index", f"index {idx} out of range for {n} objects")
        is_interest[idx] = True
        diff = item.get("difficulty", 0) if isinstance(item, dict) else 0
        tracks_to_predict.append({"track_index": idx, "difficulty": int(diff) if type(diff) is int else 0})
    ooi = meta.get("objects_of_interest") or []
    index_of = {int(a): i for i, a in enumerate(agent_id)}
    for k, oid in enumerate(ooi):
        oid = rd.integer(oid, f"metadata.objects_of_interest[{k}]")
        if oid in index_of:  # ids absent from objects refer to nothing here
            is_interest[index_of[oid]] = True
    entries = {"sdc_track_index": sdc, "tracks_to_predict": tracks_to_predict,
               "objects_of_interest": [int(v) for v in ooi]}
    return is_sdc, is_interest, entries


def _read_json(path, rd: _Reader) -> dict:
    try:
        with open(path, "rb") as f:
            raw = json.loads(f.read())
    except json.JSONDecodeError as e:
        rd.fail("json", f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}")
    except UnicodeDecodeError as e:
        rd.fail("json", f"not UTF-8 text: {e.reason} at byte {e.start}")
    if not isinstance(raw, dict):
        rd.fail("json", f"expected a JSON object at the top level, got {type(raw).__name__}")
    return raw


def load_gpudrive_json(path: str | os.PathLike, *, simplify_tolerance: float | None = None) -> Scene:
    """Load one GPUDrive (or Nocturne) processed WOMD JSON file, of any revision, as a validated Scene.

    Positions are shifted by `scene_origin` (stored in `Scene.origin`); goals are
    `goalPosition` in the same frame (the last valid position where the file
    has a sentinel or none). Older revisions' missing fields and degree headings are
    filled in and counted in metadata["defaults"] (module docstring). With
    `simplify_tolerance` (metres) road polylines are simplified by
    `simplify.simplify_scene` and its report is stored in metadata["simplify"].
    """
    src = str(path)
    rd = _Reader(src)
    raw = _read_json(path, rd)
    objects = rd.list(raw, "objects", "")
    if not objects:
        rd.fail("objects", "scene has no agents (empty list)")
    defaults: dict[str, int | str] = {}
    ob = _agent_logs(rd, objects, defaults)
    origin = scene_origin(ob["pos"], ob["valid"])
    rs = _roads(rd, rd.list(raw, "roads", ""), origin, defaults)
    tl_lane, tl_stop, tl_state, tl_dropped = _traffic_lights(raw.get("tl_states"), ob["t_steps"], origin)
    meta = raw.get("metadata") or {}
    if not isinstance(meta, dict):
        rd.fail("metadata", f"expected an object, got {type(meta).__name__}")
    is_sdc, is_interest, interest = _interest(rd, meta, ob["agent_id"])
    if defaults:
        log.info("%s: older GPUDrive/Nocturne revision, filled in: %s", src, defaults)

    name = raw.get("name")
    scene = Scene(
        scene_id=str(raw.get("scenario_id") or name or os.path.splitext(os.path.basename(src))[0]),
        **_agent_fields(ob, origin),
        is_sdc=is_sdc,
        is_interest=is_interest,
        road_points=rs["road_points"],
        road_offsets=rs["road_offsets"],
        road_type=rs["road_type"],
        road_id=rs["road_id"],
        tl_lane=tl_lane,
        tl_stop_point=tl_stop,
        tl_state=tl_state,
        origin=origin,
        dt=0.1,
        metadata={
            "source": src,
            "scenario_type": "womd",
            "name": name if isinstance(name, str) else None,
            **interest,
            "mark_as_expert": ob["expert"],
            # WOMD per-kind subtype of each polyline (lane type, road-line type, road-edge type)
            "road_subtype": rs["subtype"],
            "dropped_empty_roads": rs["dropped_empty"],
            "tl_dropped": tl_dropped,
            "defaults": defaults,
        },
    ).validate(src)
    if simplify_tolerance is not None:
        scene, _ = simplify_scene(scene, simplify_tolerance)
    return scene


def _agent_logs(rd: _Reader, objects: list, defaults: dict) -> dict:
    """`_objects`' arrays with the validity settled: a step is real only if flagged valid and free of
    the sentinel; invalid steps zeroed, degree headings converted to radians (and counted)."""
    ob = _objects(rd, objects, defaults)
    t_steps, pos_a, vel_a, yaw_a, valid_a = ob["t_steps"], ob["pos"], ob["vel"], ob["yaw"], ob["valid"]
    sentinel = (pos_a == SENTINEL).any(-1) | (vel_a == SENTINEL).any(-1) | (yaw_a == SENTINEL)
    valid_a &= ~sentinel
    if not valid_a.any():
        rd.fail("objects[*].valid", "no object has a single valid step")
    if t_steps < 2:
        rd.fail("objects[0].position", f"need at least 2 logged steps, got {t_steps}")
    pos_a[~valid_a] = 0.0
    vel_a[~valid_a] = 0.0
    yaw_a[~valid_a] = 0.0
    if heading_unit(yaw_a, vel_a, valid_a) == "degrees":
        ob["yaw"] = np.radians(yaw_a)
        defaults["objects.heading"] = "degrees"
    return ob


def _agent_fields(ob: dict, origin: np.ndarray) -> dict[str, np.ndarray]:
    """The Scene's per-agent fields from `_agent_logs`, in the frame of `origin`; goals from the file, else
    the last valid position."""
    t_steps, pos_a, valid_a = ob["t_steps"], ob["pos"], ob["valid"]
    n = len(pos_a)
    goal = ob["goal"]
    last = t_steps - 1 - np.argmax(valid_a[:, ::-1], axis=1)
    no_goal = (goal == SENTINEL).any(-1)
    goal = np.where(no_goal[:, None], pos_a[np.arange(n), last], goal)
    goal[~valid_a.any(1)] = origin  # such agents never appear; keep their goal finite and harmless
    return dict(
        log_pos=(pos_a - origin).astype(np.float32),
        log_yaw=ob["yaw"].astype(np.float32),
        log_vel=ob["vel"].astype(np.float32),
        log_valid=valid_a,
        length=ob["length"].astype(np.float32),
        width=ob["width"].astype(np.float32),
        height=ob["height"].astype(np.float32),
        agent_type=ob["agent_type"],
        agent_id=ob["agent_id"],
        goal=(goal - origin).astype(np.float32),
    )


def _traffic_lights(tl: Any, t_steps: int, origin: np.ndarray):
    """tl_states -> (tl_lane, tl_stop_point, tl_state); unreadable entries are dropped and counted."""
    empty = (np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros((t_steps, 0), np.int8), 0)
    if not tl:
        return empty
    if isinstance(tl, dict):
        entries = list(tl.items())
    elif isinstance(tl, list):
        entries = [(e.get("lane_id", e.get("id")) if isinstance(e, dict) else None, e) for e in tl]
    else:
        return empty[:3] + (1,)
    lanes, stops, columns, dropped = [], [], [], 0
    for lane, e in entries:
        try:
            lane = int(lane)
            states, times = e["state"], e["time_index"]
            x, y = float(e["x"][0]), float(e["y"][0])
            if not (math.isfinite(x) and math.isfinite(y)) or x == SENTINEL:
                raise ValueError("stop point")
            col = np.zeros(t_steps, np.int8)
            for s, t in zip(states, times):
                t = int(t)
                if 0 <= t < t_steps:
                    col[t] = _tl_state(s)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError):
            dropped += 1
            continue
        lanes.append(lane)
        stops.append((x, y))
        columns.append(col)
    if not lanes:
        return empty[:3] + (dropped,)
    return (np.asarray(lanes, np.int64), (np.asarray(stops) - origin).astype(np.float32),
            np.stack(columns, 1), dropped)


def _tl_state(s: Any) -> int:
    if isinstance(s, str):
        name = s.upper().removeprefix("LANE_STATE_")
        return int(TrafficLightState[name]) if name in TrafficLightState.__members__ else 0
    s = int(s)
    return s if s in TrafficLightState._value2member_map_ else 0
