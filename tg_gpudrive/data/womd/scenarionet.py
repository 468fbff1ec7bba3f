"""Load ScenarioNet / MetaDrive scenario pickles (`sd_*.pkl`) into `Scene`, without trusting them.

ScenarioNet converts WOMD (and nuPlan, nuScenes, ...) scenarios into MetaDrive's
`ScenarioDescription`: one pickled dict per scenario, in global coordinates
(metres, radians, right-handed), logged at `metadata["ts"]` (10 Hz, 91 steps
for WOMD):

    key                   content
    id, version, length   scenario id, "MetaDrive v0.x", step count T
    tracks[tid]           type (VEHICLE / PEDESTRIAN / CYCLIST / OTHER / TRAFFIC_CONE ...),
                          state {position (T, 3), heading (T,), velocity (T, 2),
                          valid (T,), length / width / height (T,)}, metadata
    map_features[fid]     type (LANE_* / ROAD_LINE_* / ROAD_EDGE_* / STOP_SIGN / CROSSWALK /
                          SPEED_BUMP / DRIVEWAY), polyline (k, 3) or polygon (k, 3),
                          position (3,) for stop signs; lanes also entry_lanes, exit_lanes
    dynamic_map_states[l] type TRAFFIC_LIGHT, lane, stop_point (3,),
                          state {object_state: [LANE_STATE_* or None] * T}
    metadata              sdc_id, ts (T,), dataset, scenario_id, current_time_index,
                          objects_of_interest [tid], tracks_to_predict {tid: {track_index,
                          track_id, difficulty, object_type}}, ...

A directory written by ScenarioNet also holds `dataset_summary.pkl` (metadata of
every scenario) and `dataset_mapping.pkl` (file -> sub-directory); they are not
scenes, and `load_scenarionet` says so when given one.

Reading. A pickle can run any code while it loads, so `load_pickle` uses an
unpickler that resolves only the globals plain data needs (set, frozenset,
complex, OrderedDict, bytearray, empty bytes, latin-1 `_codecs.encode`, and
NumPy's array, dtype and scalar reconstruction) and refuses every other one
with a SceneError naming it. NumPy's own reconstruction functions are unsafe on
hostile input too (a dtype state can declare an object field without the object
flag, and an array then reads raw bytes as object pointers), so the NumPy
globals resolve to stand-ins that only record their arguments; once the pickle
has loaded, arrays are built from those records with `np.frombuffer`, for plain
dtypes only (bool, integer, float, complex, bytes and unicode strings; object
arrays from their item lists).

Mapping:
  * agents: tracks in file order; agent_id = the track id when every id is an
    integer (WOMD), else the track's index, with the ids in metadata["track_ids"];
    type VEHICLE / PEDESTRIAN / CYCLIST, anything else OTHER; is_sdc from
    metadata.sdc_id; is_interest from tracks_to_predict and objects_of_interest;
    goal = last valid position; box size = median over the valid steps
    (ScenarioNet stores it per step; the median is `scenario_proto`'s rule, so a
    scenario gets the same boxes by either route, and one-step outliers of the
    detector do not count); mark_as_expert: none (ScenarioNet has no such flag).
  * map: map feature id -> road_id (ids that are not all integers: the feature's
    index, ids in metadata["map_feature_ids"]); LANE_* -> LANE, ROAD_LINE_* ->
    ROAD_LINE, ROAD_EDGE_* -> ROAD_EDGE, STOP_SIGN -> STOP_SIGN (its position,
    one point); CROSSWALK / SPEED_BUMP / DRIVEWAY polygons -> their kind, stored
    open as every other loader stores them (the closing side last -> first is
    implied; a closing vertex repeating the first is dropped); ROAD_EDGE_SIDEWALK
    polygons -> ROAD_EDGE, closed explicitly since an edge has no implied side.
    metadata["road_subtype"] holds the WOMD per-kind enum (LaneType,
    RoadLineType, RoadEdgeType) as `scenario_proto` does. The bare "UNKNOWN" is
    what ScenarioNet writes for an unknown WOMD road line and an unknown road
    edge alike; MetaDrive reads it as a road boundary, so it becomes ROAD_EDGE.
    Lane entry / exit lanes -> lane_edges. Kinds this loader does not know are
    dropped and named in metadata["dropped_feature_types"]; empty geometry is
    dropped and counted in metadata["dropped_empty_roads"].
  * traffic signals: one tl_lane per dynamic_map_states entry (the controlled
    lane's road_id), its state per step (LANE_STATE_* names, MetaDrive's
    TRAFFIC_LIGHT_GREEN / YELLOW / RED, None -> UNKNOWN) and stop_point (the end
    of the lane when there is none). Entries that cannot be read are dropped and
    counted in metadata["tl_dropped"], since signals are auxiliary.
  * dt = the median step of metadata.ts to the millisecond (WOMD's logged
    timestamps jitter by ~0.01 %); 0.1 s without ts.

What was defaulted is counted in metadata["defaults"] (field -> how many):
"tracks.height" (missing: DEFAULT_HEIGHT), "tracks.id" / "map_features.id" (not
all integers: indices), "map_features.type" (unknown kinds dropped),
"map_features.UNKNOWN" (read as road edges). Every structural problem (a
missing key, a wrong type or shape, a NaN at a valid step, a reference to a
track that does not exist) raises `SceneError(path,
"tracks['1234'].state.position", problem)` rather than a KeyError from deep
inside.
"""

from __future__ import annotations

import collections
import math
import os
import pickle
import re
from pathlib import Path
from typing import Any

import numpy as np

from tg_gpudrive.data.womd.gpudrive_json import scene_origin
from tg_gpudrive.scene import FieldReader, Scene, SceneError, log_period
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

__all__ = ["load_scenarionet", "load_pickle", "is_dataset_file", "DATASET_FILES", "DEFAULT_HEIGHT"]

DATASET_FILES = ("dataset_summary.pkl", "dataset_mapping.pkl")  # ScenarioNet's per-directory index files
DEFAULT_HEIGHT = 1.5  # m, for tracks without a height; only drawing and exports read it

_REFUSED = "a scenario pickle may hold only plain data and NumPy arrays"
_MAX_ELEMENTS = 1 << 31  # an array claiming more than this is a broken or hostile file, not a scenario


# ====================================================================== safe unpickling
class _Record:
    """A NumPy object the pickle asked for, not built yet: the call's arguments and the BUILD state.

    Stand-ins have no other behaviour: the pickle machinery can store them, but calling one,
    indexing one or appending to one fails, so nothing runs on half-validated NumPy objects."""

    __slots__ = ("kind", "args", "state")

    def __init__(self, kind: str, args: tuple):
        self.kind, self.args, self.state = kind, args, None

    def __setstate__(self, state: Any) -> None:
        self.state = state


class _NdarrayClass:
    """Stands for `numpy.ndarray` where a pickle names it (the first argument of `_reconstruct`)."""

    __slots__ = ()


_NDARRAY = _NdarrayClass()


class _Refused(Exception):
    """A global or argument the unpickler will not accept; becomes a SceneError naming the file."""


def _printable(text: str) -> str:
    text = str(text)
    return text if text.isprintable() and len(text) <= 100 else ascii(text)[1:-1][:100]


def _plain_items(args: tuple, what: str) -> tuple:
    if len(args) > 1 or (args and type(args[0]) not in (list, tuple, set, frozenset)):
        raise _Refused(f"{what} takes at most one list of items")
    return args


def _set(*args):
    return set(*_plain_items(args, "set"))


def _frozenset(*args):
    return frozenset(*_plain_items(args, "frozenset"))


def _complex(*args):
    if len(args) > 2 or any(type(a) not in (int, float) for a in args):
        raise _Refused("complex takes at most two numbers")
    return complex(*args)


def _ordered_dict(*args):
    # a plain dict keeps insertion order too, and unlike OrderedDict has no attributes a BUILD could set
    if args and (len(args) > 1 or type(args[0]) not in (list, tuple)):
        raise _Refused("OrderedDict takes at most one list of pairs")
    return dict(*args)


def _bytearray(*args):
    if not args:
        return bytearray()
    if type(args[0]) is bytes and len(args) == 1:
        return bytearray(args[0])
    if type(args[0]) is str and len(args) == 2 and args[1] in ("latin1", "latin-1"):
        return bytearray(args[0], "latin1")
    raise _Refused("bytearray takes bytes, or a str and 'latin1'")


def _bytes(*args):
    # protocols 0-2 write an empty bytes object as bytes()
    if args:
        raise _Refused("bytes is accepted only without arguments")
    return b""


def _codecs_encode(text, encoding="utf-8", errors="strict"):
    # what protocols 0-2 write for bytes: _codecs.encode(str, 'latin1')
    if type(text) is not str or encoding not in ("latin1", "latin-1") or errors != "strict":
        raise _Refused("_codecs.encode is accepted only for a str in 'latin1'")
    return text.encode("latin1")


_GLOBALS: dict[tuple[str, str], Any] = {}
for _mod in ("builtins", "__builtin__"):  # protocols 0-2 name the Python 2 module
    _GLOBALS.update({(_mod, "set"): _set, (_mod, "frozenset"): _frozenset, (_mod, "complex"): _complex,
                     (_mod, "bytearray"): _bytearray, (_mod, "bytes"): _bytes})
_GLOBALS[("collections", "OrderedDict")] = _ordered_dict
_GLOBALS[("_codecs", "encode")] = _codecs_encode
_GLOBALS[("numpy", "ndarray")] = _NDARRAY
_GLOBALS[("numpy", "dtype")] = lambda *args: _Record("dtype", args)
for _mod in ("numpy.core.multiarray", "numpy._core.multiarray"):  # NumPy 1.x and 2.x spellings
    _GLOBALS[(_mod, "_reconstruct")] = lambda *args: _Record("reconstruct", args)
    _GLOBALS[(_mod, "scalar")] = lambda *args: _Record("scalar", args)
for _mod in ("numpy.core.numeric", "numpy._core.numeric"):
    _GLOBALS[(_mod, "_frombuffer")] = lambda *args: _Record("frombuffer", args)


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise _Refused(f"refused to load global '{_printable(module)}.{_printable(name)}': {_REFUSED}") from None

    def persistent_load(self, pid: Any) -> Any:
        raise _Refused(f"refused a persistent id: {_REFUSED}")


# plain dtypes only: bool, integers, floats, complex, bytes / unicode strings, objects (built from lists)
_DTYPE_SPEC = re.compile(r"[?bBhHiIlLqQpPefdgFDGSUaO]|[biufcSUO]\d{1,4}")


def _dtype(rec: Any, where: str) -> np.dtype:
    if type(rec) is not _Record or rec.kind != "dtype":
        raise _Refused(f"{where}: expected a NumPy dtype, got {type(rec).__name__}")
    args, state = rec.args, rec.state
    spec = args[0] if args else None
    if type(spec) is not str or not _DTYPE_SPEC.fullmatch(spec):
        raise _Refused(f"{where}: dtype {_printable(repr(spec))} is not a plain scalar type")
    dt = np.dtype(spec)
    if state is not None:
        # (version, byte order, subarray, names, fields, element size, alignment, flags[, metadata])
        if type(state) is not tuple or len(state) < 8 or state[2] is not None or state[3] is not None \
                or state[4] is not None:
            raise _Refused(f"{where}: dtype {spec} carries fields or a subarray: not a plain scalar type")
        order = state[1]
        if order not in ("<", ">", "|", "="):
            raise _Refused(f"{where}: dtype byte order {_printable(repr(order))}")
        if dt.kind in "SU" and dt.itemsize == 0 and type(state[5]) is int and 0 < state[5] <= 1 << 20:
            dt = np.dtype(f"{spec}{state[5] // (4 if dt.kind == 'U' else 1)}")
        if order in "<>" and dt.itemsize > 1:
            dt = dt.newbyteorder(order)
    if dt.fields is not None or dt.subdtype is not None:
        raise _Refused(f"{where}: dtype {spec} is not a plain scalar type")
    return dt


def _shape(shape: Any, where: str) -> tuple[int, ...]:
    if type(shape) is int:
        shape = (shape,)
    if type(shape) not in (tuple, list) or any(type(d) is not int or d < 0 for d in shape) or len(shape) > 32:
        raise _Refused(f"{where}: bad array shape {_printable(repr(shape))}")
    if math.prod(shape) > _MAX_ELEMENTS:
        raise _Refused(f"{where}: array shape {tuple(shape)} is too large")
    return tuple(shape)


def _raw_bytes(data: Any, where: str) -> bytes | bytearray:
    if type(data) is str:  # Python 2 pickles read with encoding="latin1"
        return data.encode("latin1")
    if type(data) in (bytes, bytearray):
        return data
    raise _Refused(f"{where}: array data must be bytes, got {type(data).__name__}")


def _from_bytes(data: Any, dt: np.dtype, shape: tuple[int, ...], order: str, where: str) -> np.ndarray:
    if dt.hasobject:
        raise _Refused(f"{where}: an object array cannot be built from raw bytes")
    raw = _raw_bytes(data, where)
    n = math.prod(shape)
    if len(raw) != n * dt.itemsize:
        raise _Refused(f"{where}: {len(raw)} bytes of data for {n} elements of {dt}")
    return np.frombuffer(raw, dt).reshape(shape, order=order).copy()


class _Builder:
    """Turns the unpickled structure into plain Python and NumPy values, building every array
    from its recorded arguments; shared and cyclic references stay shared."""

    def __init__(self):
        self.memo: dict[int, Any] = {}
        self.keep: list[Any] = []  # keeps ids in memo from being reused while building

    def __call__(self, obj: Any) -> Any:
        t = type(obj)
        if t in (str, bytes, int, float, bool, complex) or obj is None:
            return obj
        key = id(obj)
        if key in self.memo:
            return self.memo[key]
        self.keep.append(obj)
        if t is dict:
            out: Any = {}
            self.memo[key] = out
            for k, v in obj.items():
                out[self(k)] = self(v)
            return out
        if t is list:
            out = []
            self.memo[key] = out
            out.extend(self(v) for v in obj)
            return out
        if t is tuple:
            out = tuple(self(v) for v in obj)
        elif t in (set, frozenset):
            out = t(self(v) for v in obj)
        elif t is bytearray:
            out = obj
        elif t is _Record and obj.kind in ("reconstruct", "frombuffer", "scalar"):
            out = getattr(self, obj.kind)(obj)
        elif t is _Record:  # a dtype as a value of its own
            out = _dtype(obj, "dtype")
        else:
            what = "numpy.ndarray outside an array" if t is _NdarrayClass else f"a {t.__name__} object"
            raise _Refused(f"refused {what}: {_REFUSED}")
        self.memo[key] = out
        return out

    def reconstruct(self, rec: _Record) -> np.ndarray:
        where = "numpy array"
        if len(rec.args) != 3 or rec.args[0] is not _NDARRAY:
            raise _Refused(f"{where}: _reconstruct is accepted only for numpy.ndarray")
        state = rec.state
        if type(state) is not tuple or len(state) not in (4, 5):
            raise _Refused(f"{where}: expected the (version, shape, dtype, fortran, data) state")
        shape, dtype, fortran, data = state[-4:]
        shape, dt = _shape(shape, where), _dtype(dtype, where)
        order = "F" if fortran is True else "C"
        if not dt.hasobject:
            return _from_bytes(data, dt, shape, order, where)
        if type(data) is not list or len(data) != math.prod(shape):
            raise _Refused(f"{where}: an object array needs a list of {math.prod(shape)} items")
        flat = np.empty(len(data), object)
        for i, v in enumerate(data):
            flat[i] = self(v)
        return flat.reshape(shape, order=order)

    def frombuffer(self, rec: _Record) -> np.ndarray:
        where = "numpy array"
        if len(rec.args) not in (4, 5):
            raise _Refused(f"{where}: _frombuffer takes (buffer, dtype, shape, order[, axis order])")
        buf, dtype, shape, order = rec.args[:4]
        dt, shape = _dtype(dtype, where), _shape(shape, where)
        axes = rec.args[4] if len(rec.args) == 5 else None
        if order not in ("C", "F", "K", "A"):
            raise _Refused(f"{where}: bad array order {_printable(repr(order))}")
        if order == "K" and axes is not None:
            if type(axes) not in (tuple, list) or sorted(axes) != list(range(len(shape))):
                raise _Refused(f"{where}: bad axis order {_printable(repr(axes))}")
            return _from_bytes(buf, dt, shape, "C", where).transpose(axes)  # shape is the stored one
        return _from_bytes(buf, dt, shape, "F" if order == "F" else "C", where)

    def scalar(self, rec: _Record) -> Any:
        where = "numpy scalar"
        if len(rec.args) not in (1, 2):
            raise _Refused(f"{where}: scalar takes (dtype, data)")
        dt = _dtype(rec.args[0], where)
        data = rec.args[1] if len(rec.args) == 2 else None
        if dt.hasobject:
            return self(data)
        return _from_bytes(data, dt, (1,), "C", where)[0]


def load_pickle(path: str | os.PathLike) -> Any:
    """The plain data of a pickle file (dicts, lists, numbers, strings, NumPy arrays), loaded
    without running anything it names; SceneError(path, "pickle", problem) otherwise."""
    src = str(path)
    try:
        with open(path, "rb") as f:
            raw = _SafeUnpickler(f, encoding="latin1").load()
        return _Builder()(raw)
    except _Refused as e:
        raise SceneError(src, "pickle", str(e)) from None
    except RecursionError:
        raise SceneError(src, "pickle", "nested too deeply to be a scenario") from None
    except OSError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a truncated or foreign file makes pickle raise
        why = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise SceneError(src, "pickle", f"not a readable pickle ({type(e).__name__}{': ' + why if why else ''})") \
            from None


# ====================================================================== field access
def _describe(v: Any) -> str:
    if isinstance(v, np.ndarray):
        return f"an array of {v.dtype} with shape {v.shape}"
    return type(v).__name__


class _Reader(FieldReader):
    """Typed access into the unpickled dict that raises SceneError with the field path."""

    def dict(self, v: Any, path: str) -> dict:
        if not isinstance(v, dict):
            self.fail(path, f"expected a dict, got {_describe(v)}")
        return v

    def string(self, v: Any, path: str) -> str:
        if not isinstance(v, str):
            self.fail(path, f"expected a string, got {_describe(v)}")
        return v

    def numbers(self, v: Any, path: str) -> np.ndarray:
        """float64 array of a numeric array, list or scalar (bools count as 0 / 1)."""
        if isinstance(v, (list, tuple)):
            try:
                v = np.asarray(v)
            except ValueError:
                self.fail(path, "expected a numeric array, got a ragged list")
        elif isinstance(v, (int, float, np.number, np.bool_)):
            v = np.asarray(v)
        if not isinstance(v, np.ndarray) or v.dtype.kind not in "biuf":
            self.fail(path, f"expected a numeric array, got {_describe(v)}")
        return v.astype(np.float64)

    def steps(self, v: Any, path: str, t_steps: int, cols: tuple[int, ...] = ()) -> np.ndarray:
        """(T,) or (T, c) per-step values; (T, 1) and scalars broadcast where cols is ()."""
        arr = self.numbers(v, path)
        if not cols:
            if arr.ndim == 0:
                return np.full(t_steps, float(arr))
            if arr.ndim == 2 and arr.shape[1] == 1:
                arr = arr[:, 0]
            if arr.shape != (t_steps,):
                self.fail(path, f"expected shape ({t_steps},), got {arr.shape}")
            return arr
        if arr.ndim != 2 or arr.shape[0] != t_steps or arr.shape[1] not in cols:
            want = " or ".join(f"({t_steps}, {c})" for c in cols)
            self.fail(path, f"expected shape {want}, got {arr.shape}")
        return arr[:, :2]

    def finite(self, arr: np.ndarray, valid: np.ndarray, path: str) -> None:
        bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(-1) & valid
        if bad.any():
            t = int(np.nonzero(bad)[0][0])
            self.fail(path, f"non-finite value at valid step {t}")

    def points(self, v: Any, path: str) -> np.ndarray:
        """(k, 2) of a (k, 2 | 3) array; empty stays (0, 2); NaN rejected with the point index."""
        arr = self.numbers(v, path)
        if arr.size == 0:
            return np.zeros((0, 2))
        if arr.ndim != 2 or arr.shape[1] not in (2, 3):
            self.fail(path, f"expected shape (k, 2) or (k, 3), got {arr.shape}")
        bad = ~np.isfinite(arr[:, :2]).all(-1)
        if bad.any():
            self.fail(path, f"non-finite value at point {int(np.nonzero(bad)[0][0])}")
        return arr[:, :2]

    def point(self, v: Any, path: str) -> np.ndarray:
        arr = self.numbers(v, path).reshape(-1)
        if arr.shape not in ((2,), (3,)):
            self.fail(path, f"expected a point of shape (2,) or (3,), got {self.numbers(v, path).shape}")
        if not np.isfinite(arr[:2]).all():
            self.fail(path, "non-finite value")
        return arr[None, :2]


def _int_ids(keys: list) -> list[int] | None:
    """The keys as int64 ids when every one is an integer (or its decimal string) and no two collide."""
    out = []
    for k in keys:
        if isinstance(k, (int, np.integer)) and not isinstance(k, (bool, np.bool_)):
            v = int(k)
        elif isinstance(k, str) and re.fullmatch(r"-?\d{1,19}", k):
            v = int(k)
        else:
            return None
        if not -(1 << 63) <= v < (1 << 63):
            return None
        out.append(v)
    return out if len(set(out)) == len(out) else None


def _key(k: Any) -> str:
    """How a track / feature id is spelt wherever the file refers to it (ids are keys, references
    are often ints)."""
    return str(int(k)) if isinstance(k, (int, np.integer)) and not isinstance(k, (bool, np.bool_)) else str(k)


def _path(base: str, k: Any) -> str:
    return f"{base}[{k!r}]"


# ====================================================================== mapping tables
_AGENT_TYPES = {"VEHICLE": AgentType.VEHICLE, "PEDESTRIAN": AgentType.PEDESTRIAN, "CYCLIST": AgentType.CYCLIST}

_LINE_TYPES = ("BROKEN_SINGLE_WHITE", "SOLID_SINGLE_WHITE", "SOLID_DOUBLE_WHITE", "BROKEN_SINGLE_YELLOW",
               "BROKEN_DOUBLE_YELLOW", "SOLID_SINGLE_YELLOW", "SOLID_DOUBLE_YELLOW", "PASSING_DOUBLE_YELLOW")
# MetaDrive type -> (RoadType, WOMD per-kind subtype, geometry key(s))
_FEATURES: dict[str, tuple[RoadType, int, tuple[str, ...]]] = {
    "LANE_UNKNOWN": (RoadType.LANE, 0, ("polyline",)),
    "LANE_FREEWAY": (RoadType.LANE, 1, ("polyline",)),
    "LANE_SURFACE_STREET": (RoadType.LANE, 2, ("polyline",)),
    "LANE_BIKE_LANE": (RoadType.LANE, 3, ("polyline",)),
    "LANE_SURFACE_UNSTRUCTURE": (RoadType.LANE, 0, ("polyline",)),  # nuPlan intersections, not in WOMD
    "UNKNOWN_LINE": (RoadType.ROAD_LINE, 0, ("polyline",)),
    "ROAD_LINE_UNKNOWN": (RoadType.ROAD_LINE, 0, ("polyline",)),
    **{f"ROAD_LINE_{name}": (RoadType.ROAD_LINE, k + 1, ("polyline",)) for k, name in enumerate(_LINE_TYPES)},
    "UNKNOWN": (RoadType.ROAD_EDGE, 0, ("polyline",)),
    "ROAD_EDGE_UNKNOWN": (RoadType.ROAD_EDGE, 0, ("polyline",)),
    "ROAD_EDGE_BOUNDARY": (RoadType.ROAD_EDGE, 1, ("polyline",)),
    "ROAD_EDGE_MEDIAN": (RoadType.ROAD_EDGE, 2, ("polyline",)),
    "ROAD_EDGE_SIDEWALK": (RoadType.ROAD_EDGE, 0, ("polygon", "polyline")),
    "STOP_SIGN": (RoadType.STOP_SIGN, 0, ("position",)),
    # older MetaDrive versions wrote some polygons under "polyline"
    "CROSSWALK": (RoadType.CROSSWALK, 0, ("polygon", "polyline")),
    "SPEED_BUMP": (RoadType.SPEED_BUMP, 0, ("polygon", "polyline")),
    "DRIVEWAY": (RoadType.DRIVEWAY, 0, ("polygon", "polyline")),
}
_POLYGONS = {RoadType.CROSSWALK, RoadType.SPEED_BUMP, RoadType.DRIVEWAY}

# MetaDrive's simplified light colours (nuPlan, nuScenes conversions)
_LIGHT_COLOURS = {"TRAFFIC_LIGHT_GREEN": TrafficLightState.GO, "TRAFFIC_LIGHT_YELLOW": TrafficLightState.CAUTION,
                  "TRAFFIC_LIGHT_RED": TrafficLightState.STOP, "TRAFFIC_LIGHT_UNKNOWN": TrafficLightState.UNKNOWN}


def _tl_state(s: Any) -> int:
    if s is None:
        return 0
    if isinstance(s, str):
        name = s.upper()
        if name in _LIGHT_COLOURS:
            return int(_LIGHT_COLOURS[name])
        name = name.removeprefix("LANE_STATE_")
        return int(TrafficLightState[name]) if name in TrafficLightState.__members__ else 0
    if isinstance(s, (int, np.integer)) and not isinstance(s, (bool, np.bool_)):
        return int(s) if int(s) in TrafficLightState._value2member_map_ else 0
    raise TypeError(f"signal state {s!r}")


# ====================================================================== loading
def is_dataset_file(path: str | os.PathLike) -> bool:
    """Whether `path` is named like one of ScenarioNet's index files (not a scene)."""
    return Path(path).name.lower() in DATASET_FILES


def _not_a_scene(src: str, kind: str) -> SceneError:
    return SceneError(src, "file", f"a ScenarioNet dataset {kind}, not a scene: pass the sd_*.pkl files or the "
                                   "directory")


def load_scenarionet(path: str | os.PathLike) -> Scene:
    """Load one ScenarioNet scenario pickle (`sd_*.pkl`) as a validated Scene.

    The pickle is read by `load_pickle` (plain data and NumPy arrays only). Positions
    are shifted by `scene_origin` (stored in `Scene.origin`); goals are the last valid
    positions; box sizes are the median over each track's valid steps (`convert --simplify`
    simplifies the road polylines when packing). `dataset_summary.pkl` / `dataset_mapping.pkl` raise a SceneError saying what they are.
    """
    src = str(path)
    rd = _Reader(src)
    raw = _scene_pickle(path, rd)
    meta = rd.dict(raw.get("metadata") or {}, "metadata")
    defaults: dict[str, int] = {}

    ag = _tracks(rd, rd.dict(rd.key(raw, "tracks", ""), "tracks"), defaults)
    t_steps, n = ag["t_steps"], len(ag["keys"])
    length = raw.get("length")
    if length is not None and (not isinstance(length, (int, np.integer)) or int(length) != t_steps):
        rd.fail("length", f"says {length!r} steps, but the tracks' states have {t_steps}")
    origin = scene_origin(ag["pos"], ag["valid"])
    pos = np.where(ag["valid"][..., None], ag["pos"], origin)
    last = t_steps - 1 - np.argmax(ag["valid"][:, ::-1], axis=1)
    goal = pos[np.arange(n), last]  # never-valid agents: the origin, finite and harmless

    mp = _map(rd, rd.dict(rd.key(raw, "map_features", ""), "map_features"), defaults)
    tl_lane, tl_stop, tl_state, tl_dropped = _traffic_lights(raw.get("dynamic_map_states"), t_steps, mp)
    inter = _interest(rd, meta, ag)

    ts = meta.get("ts")
    dt = 0.1
    if isinstance(ts, (np.ndarray, list, tuple)) and len(ts) >= 2:
        dt = log_period(np.diff(rd.numbers(ts, "metadata.ts").reshape(-1)))
    sid = raw.get("id") or meta.get("scenario_id") or meta.get("id")
    return Scene(
        scene_id=str(sid) if sid is not None else Path(src).stem,
        log_pos=(pos - origin).astype(np.float32),
        log_yaw=ag["yaw"].astype(np.float32),
        log_vel=ag["vel"].astype(np.float32),
        log_valid=ag["valid"],
        length=ag["size"][:, 0].astype(np.float32),
        width=ag["size"][:, 1].astype(np.float32),
        height=ag["size"][:, 2].astype(np.float32),
        agent_type=ag["agent_type"],
        agent_id=ag["agent_id"],
        goal=(goal - origin).astype(np.float32),
        is_sdc=inter["is_sdc"],
        is_interest=inter["is_interest"],
        road_points=((np.concatenate(mp["pts"]) - origin) if mp["pts"] else np.zeros((0, 2))).astype(np.float32),
        road_offsets=np.concatenate([[0], np.cumsum([len(p) for p in mp["pts"]])]).astype(np.int64),
        road_type=np.asarray(mp["road_type"], np.int8),
        road_id=np.asarray(mp["road_id"], np.int64),
        lane_edges=mp["lane_edges"],
        tl_lane=tl_lane,
        tl_stop_point=(tl_stop - origin).astype(np.float32),
        tl_state=tl_state,
        origin=origin,
        dt=dt,
        metadata=_metadata(src, raw, meta, ag, mp, inter, tl_dropped, defaults),
    ).validate(src)


def _scene_pickle(path: str | os.PathLike, rd: _Reader) -> dict:
    """The unpickled top-level dict of a scenario file; a dataset index file (summary or mapping, also
    renamed) or anything but a dict raises SceneError."""
    src = str(path)
    name = Path(src).name.lower()
    if name in DATASET_FILES:
        raise _not_a_scene(src, name.removeprefix("dataset_").removesuffix(".pkl"))
    raw = load_pickle(path)
    if not isinstance(raw, dict):
        rd.fail("pickle", f"expected a dict at the top level, got {_describe(raw)}")
    if "tracks" not in raw and raw and all(isinstance(k, str) and k.endswith(".pkl") for k in raw):
        # a renamed index file: the summary maps files to metadata dicts, the mapping to directories
        raise _not_a_scene(src, "summary" if all(isinstance(v, dict) for v in raw.values()) else "mapping")
    return raw


def _metadata(src: str, raw: dict, meta: dict, ag: dict, mp: dict, inter: dict, tl_dropped: int,
              defaults: dict) -> dict[str, Any]:
    """The Scene's metadata: where it came from, the prediction requests, what was dropped or filled in,
    and the original track and feature ids where they are not integers."""
    dataset = meta.get("dataset")
    return {
        "source": src,
        # per-type episode rates group on this: WOMD scenes as every other loader labels them
        "scenario_type": "womd" if dataset in (None, "waymo", "womd") else str(dataset),
        "name": Path(src).name,
        "dataset": dataset if isinstance(dataset, str) else None,
        "version": raw.get("version") if isinstance(raw.get("version"), str) else None,
        "source_file": meta.get("source_file") if isinstance(meta.get("source_file"), str) else None,
        "current_time_index": (int(meta["current_time_index"])
                               if isinstance(meta.get("current_time_index"), (int, np.integer)) else None),
        "sdc_track_index": inter["sdc_track_index"],
        "tracks_to_predict": inter["tracks_to_predict"],
        "objects_of_interest": inter["objects_of_interest"],
        "mark_as_expert": [],
        "road_subtype": mp["subtype"],
        "dropped_empty_roads": mp["dropped_empty"],
        "dropped_feature_types": sorted(mp["unknown_types"]),
        "tl_dropped": tl_dropped,
        "defaults": defaults,
        **({} if ag["ids_numeric"] else {"track_ids": [str(k) for k in ag["keys"]]}),
        **({} if mp["ids_numeric"] else {"map_feature_ids": [str(k) for k in mp["keys"]]}),
    }


def _tracks(rd: _Reader, tracks: dict, defaults: dict) -> dict:
    """Per-agent arrays in file order; positions still global, invalid steps zeroed."""
    if not tracks:
        rd.fail("tracks", "scenario has no tracks")
    keys = list(tracks)
    n = len(keys)
    ints = _int_ids(keys)
    if ints is None:
        defaults["tracks.id"] = n
    t_steps = None
    pos, yaw, vel, valid = [], [], [], []
    size = np.zeros((n, 3))
    agent_type = np.zeros(n, np.int8)
    for i, k in enumerate(keys):
        p = _path("tracks", k)
        tr = rd.dict(tracks[k], p)
        st = rd.dict(rd.key(tr, "state", p), f"{p}.state")
        sp = f"{p}.state"
        if t_steps is None:
            first = rd.numbers(rd.key(st, "position", sp), f"{sp}.position")
            t_steps = first.shape[0] if first.ndim >= 1 else 0
            if t_steps < 2:
                rd.fail(f"{sp}.position", f"need at least 2 steps, got {t_steps}")
        xy = rd.steps(rd.key(st, "position", sp), f"{sp}.position", t_steps, (2, 3))
        v = rd.steps(rd.key(st, "velocity", sp), f"{sp}.velocity", t_steps, (2, 3))
        h = rd.steps(rd.key(st, "heading", sp), f"{sp}.heading", t_steps)
        ok_raw = rd.steps(rd.key(st, "valid", sp), f"{sp}.valid", t_steps)
        if np.isnan(ok_raw).any():
            rd.fail(f"{sp}.valid", f"NaN at step {int(np.nonzero(np.isnan(ok_raw))[0][0])}")
        ok = ok_raw != 0
        for arr, key in ((xy, "position"), (v, "velocity"), (h, "heading")):
            rd.finite(arr, ok, f"{sp}.{key}")
        steps = ok if ok.any() else np.ones(t_steps, bool)  # never-valid agents: any step will do
        for d, key in enumerate(("length", "width", "height")):
            if key == "height" and key not in st:
                size[i, d] = DEFAULT_HEIGHT
                defaults["tracks.height"] = defaults.get("tracks.height", 0) + 1
                continue
            vals = rd.steps(rd.key(st, key, sp), f"{sp}.{key}", t_steps)
            if ok.any():
                rd.finite(vals, ok, f"{sp}.{key}")
            size[i, d] = float(np.median(vals[steps])) if np.isfinite(vals[steps]).all() else 0.0
        for d, key in enumerate(("length", "width")):
            if ok.any() and size[i, d] <= 0:
                rd.fail(f"{sp}.{key}", f"must be positive at the valid steps (median {size[i, d]:g})")
        kind = tr.get("type")
        if kind is None and isinstance(tr.get("metadata"), dict):
            kind = tr["metadata"].get("type")
        if kind is None:
            rd.fail(f"{p}.type", "missing key")
        agent_type[i] = _AGENT_TYPES.get(rd.string(kind, f"{p}.type").upper(), AgentType.OTHER)
        pos.append(np.where(ok[:, None], xy, 0.0))
        vel.append(np.where(ok[:, None], v, 0.0))
        yaw.append(np.where(ok, h, 0.0))
        valid.append(ok)
    valid_a = np.stack(valid)
    if not valid_a.any():
        rd.fail("tracks[*].state.valid", "no track has a single valid step")
    return {
        "keys": keys, "t_steps": t_steps, "pos": np.stack(pos), "vel": np.stack(vel), "yaw": np.stack(yaw),
        "valid": valid_a, "size": size, "agent_type": agent_type, "ids_numeric": ints is not None,
        "agent_id": np.asarray(ints if ints is not None else range(n), np.int64),
        "index_of": {_key(k): i for i, k in enumerate(keys)},
    }


def _map(rd: _Reader, features: dict, defaults: dict) -> dict:
    """Road polylines (global frame), their kinds, ids and subtypes, and the lane graph."""
    keys = list(features)
    ints = _int_ids(keys)
    if ints is None and keys:
        defaults["map_features.id"] = len(keys)
    ids = ints if ints is not None else list(range(len(keys)))
    pts, road_type, road_id, subtype = [], [], [], []
    lanes: dict[str, int] = {}
    links: list[tuple[int, str, str, Any]] = []
    unknown: collections.Counter = collections.Counter()
    dropped_empty = 0
    for fid, k in zip(ids, keys):
        p = _path("map_features", k)
        feat = rd.dict(features[k], p)
        kind = rd.string(rd.key(feat, "type", p), f"{p}.type").upper()
        if kind not in _FEATURES:
            unknown[_printable(kind)] += 1
            continue
        rtype, sub, geom_keys = _FEATURES[kind]
        gkey = next((g for g in geom_keys if g in feat), None)
        if gkey is None:
            rd.key(feat, geom_keys[0], p)  # raises: missing key
        if gkey == "position":
            xy = rd.point(feat[gkey], f"{p}.{gkey}")
        else:
            xy = rd.points(feat[gkey], f"{p}.{gkey}")
        if rtype in _POLYGONS and len(xy) >= 4 and (xy[0] == xy[-1]).all():
            xy = xy[:-1]  # stored open, as every loader stores polygons
        elif rtype == RoadType.ROAD_EDGE and gkey == "polygon" and len(xy) >= 3 and (xy[0] != xy[-1]).any():
            xy = np.concatenate([xy, xy[:1]])  # an edge has no implied closing side: a sidewalk's is real
        if len(xy) == 0:
            dropped_empty += 1  # nothing to draw or collide with
            continue
        r = len(pts)
        pts.append(xy)
        road_type.append(int(rtype))
        road_id.append(fid)
        subtype.append(sub)
        if kind == "UNKNOWN":
            defaults["map_features.UNKNOWN"] = defaults.get("map_features.UNKNOWN", 0) + 1
        if rtype == RoadType.LANE:
            lanes.setdefault(_key(k), r)
            for side in ("entry_lanes", "exit_lanes"):
                links.append((r, side, f"{p}.{side}", feat.get(side)))
    if unknown:
        defaults["map_features.type"] = sum(unknown.values())
    edges = set()
    for r, side, fp, other in links:
        if other is None:
            continue
        if not isinstance(other, (list, tuple, np.ndarray)):
            rd.fail(fp, f"expected a list of lane ids, got {_describe(other)}")
        for j in np.asarray(other, object).reshape(-1).tolist():
            q = lanes.get(_key(j)) if isinstance(j, (str, int, np.integer)) else None
            if q is not None:  # lanes outside the map's crop refer to nothing here
                edges.add((q, r) if side == "entry_lanes" else (r, q))
    return {
        "keys": keys, "ids_numeric": ints is not None, "pts": pts, "road_type": road_type, "road_id": road_id,
        "subtype": subtype, "dropped_empty": dropped_empty, "unknown_types": set(unknown),
        "lane_edges": np.array(sorted(edges), np.int32).reshape(-1, 2),
        "lanes": lanes, "road_id_of": {_key(k): fid for k, fid in zip(keys, ids)},
    }


def _traffic_lights(dyn: Any, t_steps: int, mp: dict):
    """dynamic_map_states -> (tl_lane, tl_stop_point global, tl_state, dropped)."""
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((t_steps, 0), np.int8))
    if not dyn:
        return empty + (0,)
    if isinstance(dyn, dict):
        entries = list(dyn.items())
    elif isinstance(dyn, list):
        entries = list(enumerate(dyn))
    else:
        return empty + (1,)
    lanes, stops, cols, dropped = [], [], [], 0
    for key, e in entries:
        try:
            if e.get("type", "TRAFFIC_LIGHT") != "TRAFFIC_LIGHT":
                raise ValueError("not a traffic light")
            lane = e.get("lane")
            lane = key if lane is None else lane
            if not isinstance(lane, (str, int, np.integer)) or isinstance(lane, (bool, np.bool_)):
                raise TypeError("lane id")
            lk = _key(lane)
            if lk in mp["road_id_of"]:
                rid = mp["road_id_of"][lk]
            elif mp["ids_numeric"] and re.fullmatch(r"-?\d{1,18}", lk):
                rid = int(lk)  # a lane outside the map's crop: its id still names it
            else:
                raise KeyError("lane")
            states = e["state"]["object_state"]
            if isinstance(states, (str, bytes, dict)) or not hasattr(states, "__len__"):
                raise TypeError("object_state")
            col = np.zeros(t_steps, np.int8)
            for t, s in enumerate(list(states)[:t_steps]):
                col[t] = _tl_state(s)
            sp = e.get("stop_point")
            if sp is not None:
                arr = np.asarray(sp, np.float64).reshape(-1)
                if arr.shape not in ((2,), (3,)) or not np.isfinite(arr[:2]).all():
                    raise ValueError("stop point")
                stop = arr[:2]
            elif lk in mp["lanes"]:
                stop = mp["pts"][mp["lanes"][lk]][-1]  # no stop point: the end of the controlled lane
            else:
                raise ValueError("no stop point")
            if rid in lanes:
                raise ValueError("second entry for one lane")
        except (KeyError, TypeError, ValueError, IndexError, AttributeError):
            dropped += 1
            continue
        lanes.append(rid)
        stops.append(stop)
        cols.append(col)
    if not lanes:
        return empty + (dropped,)
    return np.asarray(lanes, np.int64), np.asarray(stops, np.float64), np.stack(cols, 1), dropped


def _interest(rd: _Reader, meta: dict, ag: dict) -> dict:
    """is_sdc, is_interest and their metadata entries from the scenario's metadata."""
    n, index_of = len(ag["keys"]), ag["index_of"]
    is_sdc = np.zeros(n, bool)
    sdc = None
    if meta.get("sdc_id") is not None:
        sid = meta["sdc_id"]
        if not isinstance(sid, (str, int, np.integer)) or _key(sid) not in index_of:
            rd.fail("metadata.sdc_id", f"track {sid!r} is not in tracks")
        sdc = index_of[_key(sid)]
    elif isinstance(meta.get("sdc_track_index"), (int, np.integer)) and 0 <= meta["sdc_track_index"] < n:
        sdc = int(meta["sdc_track_index"])
    if sdc is not None:
        is_sdc[sdc] = True

    is_interest = np.zeros(n, bool)
    ttp_raw = meta.get("tracks_to_predict") or {}
    if isinstance(ttp_raw, dict):
        items = [(_path("metadata.tracks_to_predict", k), k, v) for k, v in ttp_raw.items()]
    elif isinstance(ttp_raw, (list, tuple)):
        items = [(f"metadata.tracks_to_predict[{j}]", None, v) for j, v in enumerate(ttp_raw)]
    else:
        rd.fail("metadata.tracks_to_predict", f"expected a dict, got {_describe(ttp_raw)}")
    tracks_to_predict = []
    for fp, k, v in items:
        tid = v.get("track_id", k) if isinstance(v, dict) else (v if k is None else k)
        if tid is None and isinstance(v, dict) and isinstance(v.get("track_index"), (int, np.integer)):
            if not 0 <= v["track_index"] < n:  # a list entry naming its track by index only
                rd.fail(f"{fp}.track_index", f"index {v['track_index']} out of range for {n} tracks")
            tid = ag["keys"][int(v["track_index"])]
        if not isinstance(tid, (str, int, np.integer)) or _key(tid) not in index_of:
            rd.fail(fp, f"track {tid!r} is not in tracks")
        idx = index_of[_key(tid)]
        is_interest[idx] = True
        diff = v.get("difficulty", 0) if isinstance(v, dict) else 0
        tracks_to_predict.append({"track_index": idx,
                                  "difficulty": int(diff) if isinstance(diff, (int, np.integer)) else 0})
    ooi = meta.get("objects_of_interest") or []
    if not isinstance(ooi, (list, tuple, np.ndarray)):
        rd.fail("metadata.objects_of_interest", f"expected a list of track ids, got {_describe(ooi)}")
    objects_of_interest = []
    for oid in list(ooi):
        if not isinstance(oid, (str, int, np.integer)):
            rd.fail("metadata.objects_of_interest", f"expected track ids, got {_describe(oid)}")
        if _key(oid) in index_of:  # ids absent from tracks refer to nothing here
            i = index_of[_key(oid)]
            is_interest[i] = True
            objects_of_interest.append(int(ag["agent_id"][i]))
    return {"is_sdc": is_sdc, "is_interest": is_interest, "sdc_track_index": sdc,
            "tracks_to_predict": tracks_to_predict, "objects_of_interest": objects_of_interest}
