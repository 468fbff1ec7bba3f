"""Load the WOMD `tf.Example` flavour of TFRecords into `Scene`, without TensorFlow.

The Waymo Open Motion Dataset ships every scenario twice: `scenario/` shards of
`Scenario` protos (read by `scenario_proto`) and `tf_example/` shards of
`tf.train.Example` protos, one per scenario, holding fixed-size tensors of the
motion features. The Example wrapper is restated here for `protowire`
(tensorflow/core/example/{example,feature}.proto, proto3):

    Example   { Features features = 1; }
    Features  { map<string, Feature> feature = 1; }   a map is a repeated {key = 1, value = 2}
    Feature   { oneof { BytesList bytes_list = 1; FloatList float_list = 2; Int64List int64_list = 3; } }
    *List     { repeated bytes / float / int64 value = 1 [packed]; }

Features read (WOMD "tf.Example proto format"; N agent rows, 128 in WOMD, and
per time part the steps past 10, current 1, future 80, concatenated to T = 91):

    key                                         shape     meaning
    scenario/id                                 bytes     scenario id
    state/id, state/type                        (N,)      float: track id, 0 unset 1 vehicle 2 pedestrian
                                                          3 cyclist 4 other
    state/is_sdc, state/tracks_to_predict,      (N,)      int64 flags
      state/objects_of_interest
    state/<part>/x, y, bbox_yaw, velocity_x,    (N, Tp)   float; m, rad, m/s; -1 where not valid
      velocity_y, length, width, height
    state/<part>/valid                          (N, Tp)   int64
    state/<part>/timestamp_micros               (N, Tp)   int64 (optional; dt, else 0.1 s)
    roadgraph_samples/xyz                       (P, 3)    float, P = 20000 in WOMD
    roadgraph_samples/type, id, valid           (P,)      int64
    traffic_light_state/<part>/state, id, valid (Tp, S)   int64, time-major, S = 16 in WOMD
    traffic_light_state/<part>/x, y             (Tp, S)   float, the stop point

Mapping to Scene (the same conventions as `scenario_proto`, so both flavours of
one scenario give the same Scene where they hold the same data):
  * agents = the rows with at least one valid step, in row order; origin by
    `gpudrive_json.scene_origin`; goal = last valid position; box size from the
    first valid step (the Example has no per-agent size, and sizes are constant
    along a WOMD track in practice); bbox_yaw kept verbatim like Scenario headings.
  * state/type 1/2/3 -> VEHICLE/PEDESTRIAN/CYCLIST, anything else -> OTHER.
  * is_interest = tracks_to_predict | objects_of_interest; metadata keeps
    tracks_to_predict as [{track_index, difficulty}] (scene indices, difficulty
    from state/difficulty_level where present) and objects_of_interest as ids, as
    `scenario_to_scene` does, so the scene writes back to a Scenario unchanged.
  * road polylines = the valid roadgraph samples cut into runs of one id (and one
    type), in file order. Types: 1-3 lane, 6-13 road line, 15-16 road edge, 17 stop
    sign, 18 crosswalk, 19 speed bump; road_subtype by `WOMD_SUBTYPE_BY_MAP_ELEMENT`
    (the same numbering). Samples of any other type are skipped and counted in
    metadata["skipped_road_samples"] {type: samples}.
  * traffic signals: keyed by the controlled lane id (slots are not stable over
    time: a slot holds different lanes at different steps), in order of first
    appearance; stop point from the first valid report; tl_state by the WOMD
    TrafficLightState numbering (unknown values -> UNKNOWN), UNKNOWN where a lane
    is not reported.

Lost compared to the Scenario flavour:
  * agents beyond the N rows (WOMD keeps the 128 most relevant tracks);
  * the map beyond P samples: Waymo samples the map into a fixed budget, so a
    large map is cut off (when every sample is valid the budget was likely
    exhausted: metadata["roadgraph_truncated"] = True and a warning is logged);
  * polyline vertices are resampled points (about 0.5 m apart), not the
    Scenario's vertices; map feature types 0, 4, 5, 14 and driveways have no
    roadgraph type here;
  * lane connectivity (entry/exit lanes -> lane_edges), lane neighbours and
    boundaries, speed limits: lane_edges is empty;
  * per-step box sizes (one size per agent here either way).
"""

from __future__ import annotations

import logging
import re
from typing import Any

import numpy as np

from tg_gpudrive.data.womd.gpudrive_json import WOMD_SUBTYPE_BY_MAP_ELEMENT, scene_origin
from tg_gpudrive.data.womd.protowire import DecodeError, Field as F, Message, decode
from tg_gpudrive.scene import Scene, SceneError, log_period
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

__all__ = ["EXAMPLE", "is_tf_example", "decode_example", "tf_example_to_scene", "PARTS"]

log = logging.getLogger(__name__)

# ------------------------------------------------------------- feature.proto
BYTES_LIST = Message("BytesList", [F(1, "value", "bytes", True)])
FLOAT_LIST = Message("FloatList", [F(1, "value", "float", True, packed=True)])
INT64_LIST = Message("Int64List", [F(1, "value", "int64", True, packed=True)])
FEATURE = Message("Feature", [
    F(1, "bytes_list", "message", False, BYTES_LIST),
    F(2, "float_list", "message", False, FLOAT_LIST),
    F(3, "int64_list", "message", False, INT64_LIST),
])
FEATURE_ENTRY = Message("FeatureEntry", [F(1, "key", "string"), F(2, "value", "message", False, FEATURE)])
FEATURES = Message("Features", [F(1, "feature", "message", True, FEATURE_ENTRY)])
EXAMPLE = Message("Example", [F(1, "features", "message", False, FEATURES)])

# the same wrapper with the Feature values left as raw bytes: detection reads only the keys
_SHALLOW_ENTRY = Message("FeatureEntry", [F(1, "key", "string"), F(2, "value", "bytes")])
_SHALLOW = Message("Example", [F(1, "features", "message", False,
                                 Message("Features", [F(1, "feature", "message", True, _SHALLOW_ENTRY)]))])

PARTS = ("past", "current", "future")  # concatenated in this order to the T logged steps
_MOTION_PREFIXES = ("state/", "roadgraph_samples/")
_AGENT_TYPE = {1: AgentType.VEHICLE, 2: AgentType.PEDESTRIAN, 3: AgentType.CYCLIST}
_ROAD_TYPE = {
    **{t: RoadType.LANE for t in (1, 2, 3)},
    **{t: RoadType.ROAD_LINE for t in range(6, 14)},
    15: RoadType.ROAD_EDGE, 16: RoadType.ROAD_EDGE,
    17: RoadType.STOP_SIGN, 18: RoadType.CROSSWALK, 19: RoadType.SPEED_BUMP,
}
_TL_VALUES = {int(v) for v in TrafficLightState}
_KIND_DTYPE = {"float_list": np.float32, "int64_list": np.int64}


def is_tf_example(data: bytes) -> bool:
    """True when `data` is a tf.Example holding WOMD motion features.

    Decodes only the wrapper and the feature names (values stay raw bytes), so it
    is cheap. A Scenario record fails here: its field 1 is a packed run of doubles
    that does not parse as a feature map of `state/...` names.
    """
    try:
        msg = decode(_SHALLOW, data)
    except DecodeError:
        return False
    entries = (msg.get("features") or {}).get("feature") or []
    return any(e.get("key", "").startswith(_MOTION_PREFIXES) for e in entries)


def decode_example(data: bytes) -> dict[str, tuple[str | None, Any]]:
    """Decode a tf.Example into {key: (kind, values)}; kind is "bytes_list", "float_list",
    "int64_list" or None (a Feature with no list set); values a list of bytes or a NumPy array."""
    msg = decode(EXAMPLE, data)
    out: dict[str, tuple[str | None, Any]] = {}
    for e in (msg.get("features") or {}).get("feature") or []:
        value = e.get("value") or {}
        kind = next((k for k in ("bytes_list", "float_list", "int64_list") if k in value), None)
        if kind is None:
            out[e.get("key", "")] = (None, np.zeros(0))
        elif kind == "bytes_list":
            out[e.get("key", "")] = (kind, list(value[kind].get("value", [])))
        else:
            out[e.get("key", "")] = (kind, np.asarray(value[kind].get("value", []), _KIND_DTYPE[kind]))
    return out


def _where(data: bytes, err: DecodeError, fp: str) -> str:
    """The failing feature as `features['key']` rather than protowire's `features.feature[12]...` path."""
    m = re.match(r"features\.feature\[(\d+)\]\.value", err.field)
    if m:
        try:
            entries = decode(_SHALLOW, data)["features"]["feature"]
            return f"{fp}features['{entries[int(m.group(1))]['key']}']"
        except (DecodeError, KeyError, IndexError):
            pass
    return f"{fp}{err.field}" if err.field else fp.rstrip(".") or "example"


class _Features:
    """Typed, length-checked access to decoded features; errors name `features['key']`."""

    def __init__(self, feats: dict, source: str, prefix: str):
        self.feats, self.source, self.prefix = feats, source, prefix

    def fail(self, key: str, problem: str):
        raise SceneError(self.source, f"{self.prefix}features['{key}']", problem)

    def array(self, key: str, kind: str, size: int | None = None, what: str = "") -> np.ndarray:
        if key not in self.feats:
            self.fail(key, "missing feature")
        got_kind, vals = self.feats[key]
        if got_kind != kind:
            self.fail(key, f"expected a {kind}, got {got_kind or 'a feature with no list'}")
        if size is not None and len(vals) != size:
            self.fail(key, f"expected {size} values{what}, got {len(vals)}")
        return vals

    def optional(self, key: str, kind: str, size: int, fill, what: str = "") -> np.ndarray:
        if key not in self.feats:
            return np.full(size, fill, _KIND_DTYPE[kind])
        return self.array(key, kind, size, what)


def tf_example_to_scene(data: bytes, source: str, *, field_prefix: str = "") -> Scene:
    """Convert one serialized WOMD tf.Example to a validated Scene.

    Errors raise SceneError(source, field_prefix + "features['state/past/x']", problem)
    naming the feature; readers pass field_prefix="record[i]." so the record is named.
    """
    fp = field_prefix
    try:
        feats = decode_example(data)
    except DecodeError as e:
        raise SceneError(source, _where(data, e, fp), e.problem) from None
    fx = _Features(feats, source, fp)
    rows = _agent_rows(fx)
    state, steps = _agent_states(fx, len(rows["id"]))
    ag = _agents(fx, rows, state)
    origin = scene_origin(ag["pos"], ag["valid"])
    ag["pos"][~ag["valid"]] = origin
    t_steps, n = ag["valid"].shape[1], len(ag["keep"])
    goal = ag["pos"][np.arange(n), t_steps - 1 - np.argmax(ag["valid"][:, ::-1], axis=1)]
    inter = _interest(rows, ag["keep"], ag["agent_id"])
    dt = _log_period(state)
    rg = _roadgraph(fx, source, fp)
    road_points = (np.concatenate(rg["pts"]) - origin) if rg["pts"] else np.zeros((0, 2))
    tl = _traffic_lights(fx, steps, t_steps)
    tl_stop_point = (np.asarray(tl["stop"], np.float64) - origin) if tl["stop"] else np.zeros((0, 2))
    sid = _scenario_id(fx)
    with np.errstate(over="ignore"):  # beyond float32 -> inf, which validate reports by field
        scene = Scene(
            scene_id=sid,
            log_pos=(ag["pos"] - origin).astype(np.float32),
            log_yaw=ag["yaw"],
            log_vel=ag["vel"],
            log_valid=ag["valid"],
            length=ag["length"],
            width=ag["width"],
            height=ag["height"],
            agent_type=ag["agent_type"],
            agent_id=ag["agent_id"],
            goal=(goal - origin).astype(np.float32),
            is_sdc=inter["is_sdc"],
            is_interest=inter["is_interest"],
            road_points=road_points.astype(np.float32),
            road_offsets=np.concatenate([[0], np.cumsum([len(p) for p in rg["pts"]])]).astype(np.int64),
            road_type=np.asarray(rg["road_type"], np.int8),
            road_id=np.asarray(rg["road_id"], np.int64),
            tl_lane=np.asarray(tl["lane"], np.int64),
            tl_stop_point=tl_stop_point.astype(np.float32),
            tl_state=tl["state"],
            origin=origin,
            dt=dt,
            metadata={
                "source": source,
                "scenario_type": "womd",
                "format": "tf_example",
                "name": sid,
                "current_time_index": steps["past"],
                "sdc_track_index": inter["sdc_track_index"],
                "tracks_to_predict": inter["tracks_to_predict"],
                "objects_of_interest": inter["objects_of_interest"],
                "road_subtype": rg["subtype"],
                "roadgraph_truncated": bool(rg["truncated"]),
                "skipped_agent_rows": int(len(rows["id"]) - n),
                "skipped_road_samples": rg["skipped"],
                "tl_skipped": tl["skipped"],
            },
        )
    return scene.validate(source, field_prefix=fp)


def _agent_rows(fx: _Features) -> dict[str, np.ndarray]:
    """The per-row agent features: id, type, is_sdc, tracks_to_predict, objects_of_interest and
    difficulty (the last three optional)."""
    ids = fx.array("state/id", "float_list")
    n_rows = len(ids)
    if n_rows == 0:
        fx.fail("state/id", "no agent rows")
    rows = f" ({n_rows} agent rows)"
    return {"id": ids,
            "type": fx.array("state/type", "float_list", n_rows, rows),
            "is_sdc": fx.array("state/is_sdc", "int64_list", n_rows, rows),
            "tracks_to_predict": fx.optional("state/tracks_to_predict", "int64_list", n_rows, 0, rows),
            "objects_of_interest": fx.optional("state/objects_of_interest", "int64_list", n_rows, 0, rows),
            "difficulty": fx.optional("state/difficulty_level", "int64_list", n_rows, 0, rows)}


def _agent_states(fx: _Features, n_rows: int) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """The per-step state features, (n_rows, T) each with the parts concatenated, and the steps of each
    part; each part's valid mask fixes its step count, which every other feature of the part must match."""
    steps: dict[str, int] = {}
    cols: dict[str, list[np.ndarray]] = {k: [] for k in ("x", "y", "bbox_yaw", "velocity_x", "velocity_y",
                                                       "length", "width", "height", "valid", "timestamp_micros")}
    for part in PARTS:
        vkey = f"state/{part}/valid"
        nv = len(fx.array(vkey, "int64_list"))
        if nv == 0 or nv % n_rows:
            fx.fail(vkey, f"{nv} values are not a whole number of steps for {n_rows} agent rows")
        tp = steps[part] = nv // n_rows
        what = f" ({n_rows} agent rows x {tp} steps, as {vkey})"
        for name in cols:
            key = f"state/{part}/{name}"
            if name == "timestamp_micros":
                arr = fx.optional(key, "int64_list", n_rows * tp, -1, what)
            else:
                arr = fx.array(key, "int64_list" if name == "valid" else "float_list", n_rows * tp, what)
            cols[name].append(arr.reshape(n_rows, tp))
    state = {k: np.concatenate(v, axis=1) for k, v in cols.items()}
    t_steps = sum(steps.values())
    if t_steps < 2:
        fx.fail("state/past/valid", f"need at least 2 logged steps over past, current and future, got {t_steps}")
    return state, steps


def _agents(fx: _Features, rows: dict[str, np.ndarray], state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The agents (the rows with a valid step, `keep`): global positions (float64), yaw, vel, valid, box
    size from the first valid step, agent_type and agent_id."""
    valid_all = state["valid"] != 0
    keep = np.nonzero(valid_all.any(1))[0]
    if len(keep) == 0:
        fx.fail("state/current/valid", "no agent has a single valid step")
    valid = valid_all[keep]
    first = np.argmax(valid, axis=1)
    ag = {"keep": keep, "valid": valid,
          "pos": np.stack([state["x"][keep], state["y"][keep]], -1).astype(np.float64),
          "yaw": state["bbox_yaw"][keep].astype(np.float32),
          "vel": np.stack([state["velocity_x"][keep], state["velocity_y"][keep]], -1).astype(np.float32),
          **{name: state[name][keep, first].astype(np.float32) for name in ("length", "width", "height")},
          "agent_type": np.array([_AGENT_TYPE.get(int(k) if np.isfinite(k) else 0, AgentType.OTHER)
                                  for k in rows["type"][keep]], np.int8)}
    ids = rows["id"]
    if not np.isfinite(ids[keep]).all():
        fx.fail("state/id", f"non-finite id in agent row {int(keep[~np.isfinite(ids[keep])][0])}")
    ag["agent_id"] = np.rint(ids[keep]).astype(np.int64)  # track ids are stored as floats, exact below 2**24
    return ag


def _interest(rows: dict[str, np.ndarray], keep: np.ndarray, agent_id: np.ndarray) -> dict[str, Any]:
    """is_sdc, is_interest (tracks_to_predict | objects_of_interest) of the kept rows, and the
    metadata entries: sdc_track_index, tracks_to_predict (scene indices), objects_of_interest (ids)."""
    is_sdc = rows["is_sdc"][keep] != 0
    ttp = rows["tracks_to_predict"][keep] != 0
    ooi = rows["objects_of_interest"][keep] != 0
    difficulty = rows["difficulty"]
    return {"is_sdc": is_sdc, "is_interest": ttp | ooi,
            "tracks_to_predict": [{"track_index": int(i), "difficulty": int(difficulty[keep][i])}
                                  for i in np.nonzero(ttp)[0]],
            "objects_of_interest": [int(agent_id[i]) for i in np.nonzero(ooi)[0]],
            "sdc_track_index": int(np.argmax(is_sdc)) if is_sdc.any() else None}


def _log_period(state: dict[str, np.ndarray]) -> float:
    """The log period from the timestamps (one per step, from any valid agent); 0.1 s without two."""
    ts = state["timestamp_micros"].astype(np.float64)
    ts = np.where(state["valid"] != 0, ts, -1).max(0)
    known = np.nonzero(ts >= 0)[0]
    return log_period(np.diff(ts[known]) / np.diff(known) * 1e-6) if len(known) >= 2 else 0.1


def _roadgraph(fx: _Features, source: str, fp: str) -> dict[str, Any]:
    """The valid roadgraph samples cut into polylines, a run of samples with one id (and one type, in
    case a converter reuses ids): pts (global, float64), road_type, road_id, subtype, skipped samples
    per unknown type, and whether the sample budget was probably exhausted (truncated, with a warning)."""
    rv = fx.array("roadgraph_samples/valid", "int64_list")
    p_count = len(rv)
    what = f" ({p_count} samples, as roadgraph_samples/valid)"
    xyz = fx.array("roadgraph_samples/xyz", "float_list", 3 * p_count, f" (3 x {p_count} samples)")
    rtype = fx.array("roadgraph_samples/type", "int64_list", p_count, what)
    rid = fx.array("roadgraph_samples/id", "int64_list", p_count, what)
    sel = np.nonzero(rv != 0)[0]
    xy = xyz.reshape(p_count, 3)[sel, :2].astype(np.float64)
    rtype, rid = rtype[sel], rid[sel]
    truncated = p_count > 0 and len(sel) == p_count
    if truncated:
        log.warning("%s%s: all %d roadgraph samples are valid, so Waymo's fixed sample budget probably cut the "
                    "map short; the Scenario flavour of this scenario holds the full map",
                    source, f" {fp.rstrip('.')}" if fp else "", p_count)
    cut = np.nonzero((np.diff(rid) != 0) | (np.diff(rtype) != 0))[0] + 1
    starts = np.concatenate([[0], cut]).astype(np.int64) if len(sel) else np.zeros(0, np.int64)
    ends = np.concatenate([cut, [len(sel)]]).astype(np.int64) if len(sel) else np.zeros(0, np.int64)
    pts, road_type, road_id, subtype = [], [], [], []
    skipped: dict[str, int] = {}
    for s, e in zip(starts.tolist(), ends.tolist()):
        t = int(rtype[s])
        if t not in _ROAD_TYPE:
            skipped[str(t)] = skipped.get(str(t), 0) + (e - s)
            continue
        pts.append(xy[s:e])
        road_type.append(int(_ROAD_TYPE[t]))
        road_id.append(int(rid[s]))
        subtype.append(WOMD_SUBTYPE_BY_MAP_ELEMENT.get(t, 0))
    return {"pts": pts, "road_type": road_type, "road_id": road_id, "subtype": subtype, "skipped": skipped,
            "truncated": truncated}


def _traffic_lights(fx: _Features, steps: dict[str, int], t_steps: int) -> dict[str, Any]:
    """The traffic signals, optional as a whole (a converter may leave them out): lane ids in order of
    first appearance, stop points (global) from the first valid report, state (T, L), and the reports
    skipped for a negative lane id."""
    tl_lane, tl_stop, tl_cols = [], [], []
    tl_skipped = 0
    if any(k.startswith("traffic_light_state/") for k in fx.feats):
        t0 = 0
        index: dict[int, int] = {}
        for part in PARTS:
            tp = steps[part]
            skey = f"traffic_light_state/{part}/state"
            ns = len(fx.array(skey, "int64_list"))
            if ns % tp:
                fx.fail(skey, f"{ns} values are not a whole number of signals for {tp} steps")
            slots = ns // tp
            what = f" ({tp} steps x {slots} signals, as {skey})"
            tl = {name: fx.array(f"traffic_light_state/{part}/{name}",
                                 "float_list" if name in ("x", "y") else "int64_list", ns, what).reshape(tp, slots)
                  for name in ("state", "x", "y", "id", "valid")}
            for t, s in zip(*np.nonzero(tl["valid"] != 0)):
                lane = int(tl["id"][t, s])
                if lane < 0:
                    tl_skipped += 1
                    continue
                if lane not in index:
                    index[lane] = len(tl_lane)
                    tl_lane.append(lane)
                    tl_stop.append((float(tl["x"][t, s]), float(tl["y"][t, s])))
                    tl_cols.append(np.zeros(t_steps, np.int8))
                state_v = int(tl["state"][t, s])
                tl_cols[index[lane]][t0 + t] = state_v if state_v in _TL_VALUES else 0
            t0 += tp
    tl_state = np.stack(tl_cols, 1) if tl_cols else np.zeros((t_steps, 0), np.int8)
    return {"lane": tl_lane, "stop": tl_stop, "state": tl_state, "skipped": tl_skipped}


def _scenario_id(fx: _Features) -> str:
    """The scenario id: one UTF-8 value of scenario/id."""
    sid_vals = fx.array("scenario/id", "bytes_list")
    if len(sid_vals) != 1:
        fx.fail("scenario/id", f"expected 1 value, got {len(sid_vals)}")
    try:
        return sid_vals[0].decode("utf-8")
    except UnicodeDecodeError:
        fx.fail("scenario/id", "not UTF-8 text")
