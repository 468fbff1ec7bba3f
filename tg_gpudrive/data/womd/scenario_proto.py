"""WOMD `Scenario` protos <-> `Scene`, and Scene streams in TFRecord shards.

The message definitions below restate the public Waymo Open Motion Dataset
schema (field numbers, names and types only) for `protowire`, so raw WOMD
shards (`uncompressed/scenario/*/*.tfrecord-*`) load without protobuf or
TensorFlow.

How the field numbers were checked: read from the waymo-research/
waymo-open-dataset repository, `src/waymo_open_dataset/protos/scenario.proto`
(commit 508fb261f3b7dee9ebc969d05ff1311b5ea69dc1) and
`src/waymo_open_dataset/protos/map.proto` (commit
9d0be7c4aeed2ef5e11f2e739537bf2d27cec65b). Both are proto2. Differences from
the numbers first proposed for this module: in LaneCenter, entry_lanes = 9 and
exit_lanes = 10 (both `[packed = true]`), left_neighbors = 11, right_neighbors
= 12, left_boundaries = 13, right_boundaries = 14; StopSign.lane is an
unpacked `repeated int64`; Track.id and the Scenario indices are int32;
ObjectState centers are double, everything else in it float/bool.
Scenario fields 12 (compressed_frame_laser_data) and 13 (frame_camera_tokens)
are not defined here, so the decoder skips them without parsing.

Conversion conventions (both directions):
  * Scene coordinates are relative to `Scene.origin`; protos hold global ones.
    Reading picks the origin with `gpudrive_json.scene_origin` (rounded mean of the
    valid positions), the same rule as the JSON loader, so JSON -> Scene ->
    TFRecord -> Scene reproduces origin and float32 arrays exactly.
  * goal = last valid position (WOMD has no goal); box size per agent = median
    over its valid steps (WOMD stores it per step).
  * ObjectType 1/2/3 -> VEHICLE/PEDESTRIAN/CYCLIST, anything else -> OTHER.
  * lane entry_lanes/exit_lanes -> lane_edges between lane polylines.
  * traffic signals: one tl_lane per controlled lane, in order of first
    appearance; tl_state (T, L) is UNKNOWN where a lane is not reported.
  * lost on the way Scene -> proto: z (written as 0), goals that are not the
    last valid position, lane edges touching non-lane polylines, RoadType.NONE.
"""

from __future__ import annotations

import os
from typing import Any, Iterable, Iterator

import numpy as np

from tg_gpudrive.data.womd.protowire import DecodeError, EncodeError, Field as F, Message, decode, encode
from tg_gpudrive.data.womd.tf_example import is_tf_example, tf_example_to_scene
from tg_gpudrive.data.womd.tfrecord import iter_records, write_records
from tg_gpudrive.data.womd.gpudrive_json import scene_origin
from tg_gpudrive.scene import Scene, SceneError, log_period
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

__all__ = ["SCENARIO", "scenario_to_scene", "scene_to_scenario", "read_tfrecord_scenes",
           "write_tfrecord_scenes", "decode_scenario", "encode_scenario"]

# ------------------------------------------------------------------- map.proto
MAP_POINT = Message("MapPoint", [F(1, "x", "double"), F(2, "y", "double"), F(3, "z", "double")])
BOUNDARY_SEGMENT = Message("BoundarySegment", [
    F(1, "lane_start_index", "int32"), F(2, "lane_end_index", "int32"),
    F(3, "boundary_feature_id", "int64"), F(4, "boundary_type", "enum"),
])
LANE_NEIGHBOR = Message("LaneNeighbor", [
    F(1, "feature_id", "int64"), F(2, "self_start_index", "int32"), F(3, "self_end_index", "int32"),
    F(4, "neighbor_start_index", "int32"), F(5, "neighbor_end_index", "int32"),
    F(6, "boundaries", "message", True, BOUNDARY_SEGMENT),
])
LANE_CENTER = Message("LaneCenter", [
    F(1, "speed_limit_mph", "double"), F(2, "type", "enum"), F(3, "interpolating", "bool"),
    F(8, "polyline", "message", True, MAP_POINT, columnar=True),
    F(9, "entry_lanes", "int64", True, packed=True), F(10, "exit_lanes", "int64", True, packed=True),
    F(11, "left_neighbors", "message", True, LANE_NEIGHBOR),
    F(12, "right_neighbors", "message", True, LANE_NEIGHBOR),
    F(13, "left_boundaries", "message", True, BOUNDARY_SEGMENT),
    F(14, "right_boundaries", "message", True, BOUNDARY_SEGMENT),
])
ROAD_EDGE = Message("RoadEdge", [F(1, "type", "enum"), F(2, "polyline", "message", True, MAP_POINT, columnar=True)])
ROAD_LINE = Message("RoadLine", [F(1, "type", "enum"), F(2, "polyline", "message", True, MAP_POINT, columnar=True)])
STOP_SIGN = Message("StopSign", [F(1, "lane", "int64", True), F(2, "position", "message", False, MAP_POINT)])
CROSSWALK = Message("Crosswalk", [F(1, "polygon", "message", True, MAP_POINT, columnar=True)])
SPEED_BUMP = Message("SpeedBump", [F(1, "polygon", "message", True, MAP_POINT, columnar=True)])
DRIVEWAY = Message("Driveway", [F(1, "polygon", "message", True, MAP_POINT, columnar=True)])
MAP_FEATURE = Message("MapFeature", [  # fields 3..10 form the `feature_data` oneof
    F(1, "id", "int64"),
    F(3, "lane", "message", False, LANE_CENTER), F(4, "road_line", "message", False, ROAD_LINE),
    F(5, "road_edge", "message", False, ROAD_EDGE), F(7, "stop_sign", "message", False, STOP_SIGN),
    F(8, "crosswalk", "message", False, CROSSWALK), F(9, "speed_bump", "message", False, SPEED_BUMP),
    F(10, "driveway", "message", False, DRIVEWAY),
])
TRAFFIC_SIGNAL_LANE_STATE = Message("TrafficSignalLaneState", [
    F(1, "lane", "int64"), F(2, "state", "enum"), F(3, "stop_point", "message", False, MAP_POINT),
])

# -------------------------------------------------------------- scenario.proto
OBJECT_STATE = Message("ObjectState", [
    F(2, "center_x", "double"), F(3, "center_y", "double"), F(4, "center_z", "double"),
    F(5, "length", "float"), F(6, "width", "float"), F(7, "height", "float"),
    F(8, "heading", "float"), F(9, "velocity_x", "float"), F(10, "velocity_y", "float"),
    F(11, "valid", "bool"),
])
TRACK = Message("Track", [
    F(1, "id", "int32"), F(2, "object_type", "enum"),
    F(3, "states", "message", True, OBJECT_STATE, columnar=True),
])
DYNAMIC_MAP_STATE = Message("DynamicMapState", [F(1, "lane_states", "message", True, TRAFFIC_SIGNAL_LANE_STATE)])
REQUIRED_PREDICTION = Message("RequiredPrediction", [F(1, "track_index", "int32"), F(2, "difficulty", "enum")])
SCENARIO = Message("Scenario", [
    F(1, "timestamps_seconds", "double", True),
    F(2, "tracks", "message", True, TRACK),
    F(4, "objects_of_interest", "int32", True),
    F(5, "scenario_id", "string"),
    F(6, "sdc_track_index", "int32"),
    F(7, "dynamic_map_states", "message", True, DYNAMIC_MAP_STATE),
    F(8, "map_features", "message", True, MAP_FEATURE),
    F(10, "current_time_index", "int32"),
    F(11, "tracks_to_predict", "message", True, REQUIRED_PREDICTION),
])

_OBJECT_TYPE = {1: AgentType.VEHICLE, 2: AgentType.PEDESTRIAN, 3: AgentType.CYCLIST}
_OBJECT_TYPE_OUT = {int(AgentType.NONE): 0, int(AgentType.VEHICLE): 1, int(AgentType.PEDESTRIAN): 2,
                    int(AgentType.CYCLIST): 3, int(AgentType.OTHER): 4}
# MapFeature oneof member -> (RoadType, key of its points, has a subtype enum)
_FEATURES = {
    "lane": (RoadType.LANE, "polyline", True),
    "road_line": (RoadType.ROAD_LINE, "polyline", True),
    "road_edge": (RoadType.ROAD_EDGE, "polyline", True),
    "stop_sign": (RoadType.STOP_SIGN, None, False),
    "crosswalk": (RoadType.CROSSWALK, "polygon", False),
    "speed_bump": (RoadType.SPEED_BUMP, "polygon", False),
    "driveway": (RoadType.DRIVEWAY, "polygon", False),
}
_FEATURE_OF_TYPE = {int(rt): (name, key, sub) for name, (rt, key, sub) in _FEATURES.items()}
_TL_VALUES = {int(v) for v in TrafficLightState}



def _f32(x: np.ndarray) -> np.ndarray:
    """float64 -> float32 without a RuntimeWarning: a value beyond float32 becomes inf, which
    Scene.validate then reports as a field error naming the polyline or agent."""
    with np.errstate(over="ignore"):
        return np.asarray(x).astype(np.float32)

def decode_scenario(data: bytes) -> dict[str, Any]:
    """Decode one serialized WOMD Scenario into a dict (see protowire)."""
    return decode(SCENARIO, data)


def encode_scenario(msg: dict[str, Any]) -> bytes:
    return encode(SCENARIO, msg)


# -------------------------------------------------------------- proto -> Scene
def _xy(cols: dict[str, np.ndarray] | None) -> np.ndarray:
    if not cols:
        return np.zeros((0, 2))
    n = len(next(iter(cols.values())))
    return np.stack([cols.get("x", np.zeros(n)), cols.get("y", np.zeros(n))], 1).astype(np.float64)


def scenario_to_scene(msg: dict[str, Any], source: str, *, field_prefix: str = "") -> Scene:
    """Convert a decoded Scenario dict to a validated Scene.

    Errors raise SceneError(source, field_prefix + field, problem); readers pass
    field_prefix="record[i]." so the record is named.
    """
    fp = field_prefix
    tracks = msg.get("tracks") or []
    if not tracks:
        raise SceneError(source, f"{fp}tracks", "scenario has no tracks")
    n = len(tracks)
    ag = _tracks(tracks, _track_steps(tracks, source, fp))
    t_steps, pos, valid = ag["t_steps"], ag["pos"], ag["valid"]
    origin = scene_origin(pos, valid)
    pos[~valid] = origin
    last = t_steps - 1 - np.argmax(valid[:, ::-1], axis=1)
    goal = pos[np.arange(n), last]
    inter = _interest(msg, ag["agent_id"], source, fp)
    mp = _map(msg)
    pts = mp["pts"]
    road_points = (np.concatenate(pts) - origin) if pts else np.zeros((0, 2))
    tl_lane, tl_stop_point, tl_state = _traffic_signals(msg, t_steps, mp["lanes"], pts, origin)

    ts = np.asarray(msg.get("timestamps_seconds", []), np.float64)
    dt = log_period(np.diff(ts))
    sid = msg.get("scenario_id", "")
    sdc = msg.get("sdc_track_index")
    scene = Scene(
        scene_id=sid,
        log_pos=(pos - origin).astype(np.float32),
        log_yaw=ag["yaw"],
        log_vel=ag["vel"],
        log_valid=valid,
        length=ag["dims"][:, 0],
        width=ag["dims"][:, 1],
        height=ag["dims"][:, 2],
        agent_type=ag["agent_type"],
        agent_id=ag["agent_id"],
        goal=_f32(goal - origin),
        is_sdc=inter["is_sdc"],
        is_interest=inter["is_interest"],
        road_points=_f32(road_points),
        road_offsets=np.concatenate([[0], np.cumsum([len(p) for p in pts])]).astype(np.int64),
        road_type=np.asarray(mp["road_type"], np.int8),
        road_id=np.asarray(mp["road_id"], np.int64),
        lane_edges=mp["lane_edges"],
        tl_lane=tl_lane,
        tl_stop_point=tl_stop_point.astype(np.float32),
        tl_state=tl_state,
        origin=origin,
        dt=dt if dt > 0 else 0.1,
        metadata={
            "source": source,
            "scenario_type": "womd",
            "name": sid,
            "current_time_index": int(msg.get("current_time_index", 0)),
            "sdc_track_index": int(sdc) if sdc is not None and sdc >= 0 else None,
            "tracks_to_predict": inter["tracks_to_predict"],
            "objects_of_interest": inter["objects_of_interest"],
            "road_subtype": mp["subtype"],
            "dropped_empty_roads": mp["dropped"],
        },
    )
    return scene.validate(source, field_prefix=fp)


def _track_steps(tracks: list, source: str, fp: str) -> int:
    """The number of states every track holds (tracks[0]'s); a track with another count, or fewer than
    two states, raises SceneError."""
    lengths = []
    for tr in tracks:
        st = tr.get("states") or {}
        lengths.append(len(next(iter(st.values()))) if st else 0)
    t_steps = lengths[0]
    for i, k in enumerate(lengths):
        if k != t_steps:
            raise SceneError(source, f"{fp}tracks[{i}].states", f"expected {t_steps} states (as tracks[0]), got {k}")
    if t_steps < 2:
        raise SceneError(source, f"{fp}tracks[0].states", f"need at least 2 states, got {t_steps}")
    return t_steps


def _tracks(tracks: list, t_steps: int) -> dict[str, Any]:
    """Per-agent arrays of the tracks, positions still global (float64): pos, yaw, vel, valid, dims
    (length, width, height: medians over the valid steps), agent_type, agent_id, and t_steps."""
    n = len(tracks)
    pos = np.zeros((n, t_steps, 2))
    yaw = np.zeros((n, t_steps), np.float32)
    vel = np.zeros((n, t_steps, 2), np.float32)
    valid = np.zeros((n, t_steps), bool)
    dims = np.zeros((n, 3), np.float32)
    agent_type = np.zeros(n, np.int8)
    agent_id = np.zeros(n, np.int64)
    zeros = np.zeros(t_steps, np.float32)
    for i, tr in enumerate(tracks):
        st = tr["states"]
        pos[i, :, 0] = st.get("center_x", zeros)
        pos[i, :, 1] = st.get("center_y", zeros)
        yaw[i] = st.get("heading", zeros)
        vel[i, :, 0] = st.get("velocity_x", zeros)
        vel[i, :, 1] = st.get("velocity_y", zeros)
        valid[i] = st.get("valid", zeros)
        steps = valid[i] if valid[i].any() else slice(None)  # never-valid agents: any step will do
        for d, name in enumerate(("length", "width", "height")):
            dims[i, d] = np.median(np.asarray(st.get(name, zeros), np.float32)[steps])
        agent_type[i] = _OBJECT_TYPE.get(int(tr.get("object_type", 0)), AgentType.OTHER)
        agent_id[i] = int(tr.get("id", i))
    return {"t_steps": t_steps, "pos": pos, "yaw": yaw, "vel": vel, "valid": valid, "dims": dims,
            "agent_type": agent_type, "agent_id": agent_id}


def _interest(msg: dict[str, Any], agent_id: np.ndarray, source: str, fp: str) -> dict[str, Any]:
    """is_sdc and is_interest (tracks_to_predict | objects_of_interest) of the agents, and the
    tracks_to_predict / objects_of_interest metadata entries; out-of-range indices raise SceneError."""
    n = len(agent_id)
    is_sdc = np.zeros(n, bool)
    sdc = msg.get("sdc_track_index")
    if sdc is not None and sdc >= 0:
        if sdc >= n:
            raise SceneError(source, f"{fp}sdc_track_index", f"index {sdc} out of range for {n} tracks")
        is_sdc[sdc] = True
    is_interest = np.zeros(n, bool)
    tracks_to_predict = []
    for k, req in enumerate(msg.get("tracks_to_predict") or []):
        idx = int(req.get("track_index", 0))
        if not 0 <= idx < n:
            raise SceneError(source, f"{fp}tracks_to_predict[{k}].track_index",
                             f"index {idx} out of range for {n} tracks")
        is_interest[idx] = True
        tracks_to_predict.append({"track_index": idx, "difficulty": int(req.get("difficulty", 0))})
    index_of = {int(a): i for i, a in enumerate(agent_id)}
    ooi = [int(v) for v in np.asarray(msg.get("objects_of_interest", []), np.int64)]
    for oid in ooi:
        if oid in index_of:
            is_interest[index_of[oid]] = True
    return {"is_sdc": is_sdc, "is_interest": is_interest, "tracks_to_predict": tracks_to_predict,
            "objects_of_interest": ooi}


def _map(msg: dict[str, Any]) -> dict[str, Any]:
    """The map features as polylines (global coordinates, float64) in file order: pts, road_type, road_id,
    subtype, lanes ({feature id: polyline}), lane_edges, and how many features were dropped (no
    feature data, or no points)."""
    pts, road_type, road_id, subtype = [], [], [], []
    lanes: dict[int, int] = {}
    links: list[tuple[int, np.ndarray, np.ndarray]] = []
    dropped = 0
    for feat in msg.get("map_features") or []:
        for name, (rtype, key, has_sub) in _FEATURES.items():
            if name in feat:
                body = feat[name]
                break
        else:
            dropped += 1  # no feature_data: nothing to place on the map
            continue
        if key is None:
            p = body.get("position")
            xy = np.array([[p.get("x", 0.0), p.get("y", 0.0)]]) if p is not None else np.zeros((0, 2))
        else:
            xy = _xy(body.get(key))
        if len(xy) == 0:
            dropped += 1
            continue
        r = len(pts)
        pts.append(xy)
        road_type.append(int(rtype))
        fid = int(feat.get("id", 0))
        road_id.append(fid)
        subtype.append(int(body.get("type", 0)) if has_sub else 0)
        if rtype == RoadType.LANE:
            lanes.setdefault(fid, r)
            links.append((r, np.asarray(body.get("entry_lanes", []), np.int64),
                          np.asarray(body.get("exit_lanes", []), np.int64)))
    return {"pts": pts, "road_type": road_type, "road_id": road_id, "subtype": subtype, "lanes": lanes,
            "lane_edges": _lane_edges(links, lanes), "dropped": dropped}


def _lane_edges(links: list[tuple[int, np.ndarray, np.ndarray]], lanes: dict[int, int]) -> np.ndarray:
    """(E, 2) int32 lane successor edges between polylines from each lane's (polyline, entry lane ids,
    exit lane ids); ids of no lane polyline are left out."""
    edges = set()
    for r, entry, exit_ in links:
        edges.update((lanes[int(j)], r) for j in entry.tolist() if int(j) in lanes)
        edges.update((r, lanes[int(j)]) for j in exit_.tolist() if int(j) in lanes)
    return np.array(sorted(edges), np.int32).reshape(-1, 2)


def _traffic_signals(msg: dict[str, Any], t_steps: int, lanes: dict[int, int], pts: list[np.ndarray],
                     origin: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tl_lane, tl_stop_point in the scene frame (float64), tl_state (T, L)): one signal per controlled
    lane in order of first appearance; without a stop point, the end of the controlled lane, and a
    signal of neither is dropped."""
    tl_index: dict[int, int] = {}
    tl_stop: list[np.ndarray | None] = []
    cols: list[np.ndarray] = []
    for t, dyn in enumerate((msg.get("dynamic_map_states") or [])[:t_steps]):
        for ls in dyn.get("lane_states") or []:
            lane = ls.get("lane")
            if lane is None:
                continue
            lane = int(lane)
            if lane not in tl_index:
                tl_index[lane] = len(cols)
                cols.append(np.zeros(t_steps, np.int8))
                tl_stop.append(None)
            l = tl_index[lane]
            state = int(ls.get("state", 0))
            cols[l][t] = state if state in _TL_VALUES else 0
            sp = ls.get("stop_point")
            if tl_stop[l] is None and sp is not None:
                tl_stop[l] = np.array([sp.get("x", 0.0), sp.get("y", 0.0)])
    tl_lane, stops, keep = [], [], []
    for lane, l in tl_index.items():
        sp = tl_stop[l]
        if sp is None and lane in lanes:  # no stop point given: the end of the controlled lane
            sp = pts[lanes[lane]][-1]
        if sp is None:
            continue
        tl_lane.append(lane)
        stops.append(sp)
        keep.append(l)
    tl_state = np.stack([cols[l] for l in keep], 1) if keep else np.zeros((t_steps, 0), np.int8)
    tl_stop_point = (np.asarray(stops) - origin) if stops else np.zeros((0, 2))
    return np.asarray(tl_lane, np.int64), tl_stop_point, tl_state


# -------------------------------------------------------------- Scene -> proto
def _points(xy: np.ndarray) -> dict[str, np.ndarray]:
    return {"x": xy[:, 0], "y": xy[:, 1], "z": np.zeros(len(xy))}


def scene_to_scenario(scene: Scene) -> dict[str, Any]:
    """Convert a Scene to a Scenario dict (global coordinates) for `encode_scenario`."""
    scene = scene.copy().validate()
    t_steps = scene.num_steps
    tracks = _scenario_tracks(scene)
    features = _map_features(scene)
    dynamic = _dynamic_map_states(scene)
    meta = scene.metadata
    msg: dict[str, Any] = {
        "scenario_id": scene.scene_id,
        "timestamps_seconds": np.arange(t_steps) * float(scene.dt),
        "current_time_index": int(meta.get("current_time_index", min(10, t_steps - 1))),
        "tracks": tracks,
        "dynamic_map_states": dynamic,
        "map_features": features,
    }
    if scene.is_sdc.any():
        msg["sdc_track_index"] = int(np.argmax(scene.is_sdc))
    ttp, ooi = _prediction_requests(scene)
    msg["tracks_to_predict"] = [{"track_index": int(q["track_index"]), "difficulty": int(q.get("difficulty", 0))}
                                for q in ttp or []]
    if ooi:
        msg["objects_of_interest"] = np.asarray(ooi, np.int64)
    return msg


def _scenario_tracks(scene: Scene) -> list[dict[str, Any]]:
    """One Track per agent, its states in global coordinates (zero where invalid)."""
    t_steps = scene.num_steps
    world = scene.log_pos.astype(np.float64) + scene.origin
    valid = scene.log_valid
    tracks = []
    for i in range(scene.num_agents):
        v = valid[i]
        tracks.append({
            "id": int(scene.agent_id[i]),
            "object_type": _OBJECT_TYPE_OUT.get(int(scene.agent_type[i]), 4),
            "states": {
                "center_x": np.where(v, world[i, :, 0], 0.0),
                "center_y": np.where(v, world[i, :, 1], 0.0),
                "center_z": np.zeros(t_steps),
                # sizes on every step, so agents without a valid step keep theirs too
                "length": np.full(t_steps, scene.length[i], np.float32),
                "width": np.full(t_steps, scene.width[i], np.float32),
                "height": np.full(t_steps, scene.height[i], np.float32),
                "heading": scene.log_yaw[i],
                "velocity_x": scene.log_vel[i, :, 0],
                "velocity_y": scene.log_vel[i, :, 1],
                "valid": v,
            },
        })
    return tracks


def _map_features(scene: Scene) -> list[dict[str, Any]]:
    """One MapFeature per polyline (global coordinates), lanes with their entry and exit lanes; a road
    type without a WOMD feature kind raises SceneError."""
    r_count = scene.num_polylines
    subtypes = scene.metadata.get("road_subtype")
    if subtypes is None or len(subtypes) != r_count:
        subtypes = [0] * r_count
    is_lane = scene.road_type == int(RoadType.LANE)
    entry: dict[int, list[int]] = {r: [] for r in range(r_count)}
    exit_: dict[int, list[int]] = {r: [] for r in range(r_count)}
    for a, b in scene.lane_edges.tolist():
        if is_lane[a] and is_lane[b]:
            exit_[a].append(int(scene.road_id[b]))
            entry[b].append(int(scene.road_id[a]))
    features = []
    for r in range(r_count):
        rtype = int(scene.road_type[r])
        if rtype not in _FEATURE_OF_TYPE:
            raise SceneError(scene.scene_id, f"road_type[{r}]", f"{RoadType(rtype).name} has no WOMD MapFeature kind")
        name, key, has_sub = _FEATURE_OF_TYPE[rtype]
        xy = scene.polyline(r).astype(np.float64) + scene.origin
        if key is None:
            body: dict[str, Any] = {"position": {"x": float(xy[0, 0]), "y": float(xy[0, 1]), "z": 0.0}}
        else:
            body = {key: _points(xy)}
        if has_sub:
            body["type"] = int(subtypes[r])
        if rtype == RoadType.LANE:
            body["entry_lanes"] = np.asarray(entry[r], np.int64)
            body["exit_lanes"] = np.asarray(exit_[r], np.int64)
        features.append({"id": int(scene.road_id[r]), name: body})
    return features


def _dynamic_map_states(scene: Scene) -> list[dict[str, Any]]:
    """Per logged step, the state of every signal with its lane and stop point (global coordinates)."""
    stops = scene.tl_stop_point.astype(np.float64) + scene.origin
    return [{"lane_states": [
        {"lane": int(lane), "state": int(scene.tl_state[t, l]),
         "stop_point": {"x": float(stops[l, 0]), "y": float(stops[l, 1]), "z": 0.0}}
        for l, lane in enumerate(scene.tl_lane.tolist())]} for t in range(scene.num_steps)]


def _prediction_requests(scene: Scene) -> tuple[list | None, list | None]:
    """(tracks_to_predict, objects_of_interest): the source's split of is_interest from the metadata
    while it still matches is_interest, else every agent of interest as a track to predict."""
    meta = scene.metadata
    n = scene.num_agents
    ttp, ooi = meta.get("tracks_to_predict"), meta.get("objects_of_interest")
    index_of = {int(a): i for i, a in enumerate(scene.agent_id)}
    if ttp is not None or ooi is not None:
        union = np.zeros(n, bool)
        try:
            for req in ttp or []:
                union[int(req["track_index"])] = True
            for oid in ooi or []:
                if int(oid) in index_of:
                    union[index_of[int(oid)]] = True
        except (KeyError, TypeError, ValueError, IndexError):
            union[:] = ~scene.is_interest
        if not (union == scene.is_interest).all():
            ttp = ooi = None
    if ttp is None and ooi is None:
        ttp = [{"track_index": int(i), "difficulty": 0} for i in np.nonzero(scene.is_interest)[0]]
    return ttp, ooi


# ------------------------------------------------------------------- TFRecords
def read_tfrecord_scenes(path: str | os.PathLike) -> Iterator[Scene]:
    """Yield a Scene per record of a WOMD TFRecord shard, of either flavour.

    Each record is a `Scenario` proto (`scenario/` shards) or a `tf.Example` of the
    motion features (`tf_example/` shards, see `tf_example`), told apart record by
    record. Framing, decoding and conversion errors raise
    SceneError(path, "record[i]...", problem). metadata["record_index"] holds i.
    """
    src = str(path)
    for i, data in enumerate(iter_records(path)):
        if is_tf_example(data):
            scene = tf_example_to_scene(data, src, field_prefix=f"record[{i}].")
            scene.metadata["record_index"] = i
            yield scene
            continue
        try:
            msg = decode(SCENARIO, data)
        except DecodeError as e:
            # neither flavour: say what was tried, on one line
            raise SceneError(src, f"record[{i}].{e.field}" if e.field else f"record[{i}]",
                             f"{e.problem} (the record is neither of the two flavours understood: a WOMD "
                             f"Scenario proto, or a tf.Example of WOMD motion features)") from None
        scene = scenario_to_scene(msg, src, field_prefix=f"record[{i}].")
        scene.metadata["record_index"] = i
        yield scene


def write_tfrecord_scenes(path: str | os.PathLike, scenes: Iterable[Scene]) -> int:
    """Write scenes as WOMD Scenario records; return how many were written.

    A scene that does not fit the schema (e.g. an agent id beyond int32) raises
    SceneError(scene_id, field path in the Scenario, problem).
    """

    def records():
        for scene in scenes:
            try:
                yield encode(SCENARIO, scene_to_scenario(scene))
            except EncodeError as e:
                raise SceneError(scene.scene_id, e.field, e.problem) from None

    return write_records(path, records())
