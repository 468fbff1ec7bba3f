"""`Scene`: one driving scenario as plain NumPy arrays, whatever its source.

Every loader (GPUDrive JSON, WOMD TFRecord, procedural generator, packed
store) produces this type and the engine's Model builder consumes it. Sentinels
of the source formats (-10000 for invalid steps, ...) stop at the loader: here
validity is a mask. Coordinates are metres in a scene frame whose origin
(`origin`, in the source's global frame) was subtracted by the loader so that
float32 keeps centimetre precision.

Fields (N agents, T logged steps at `dt`, P road points, R polylines,
E lane-graph edges, L traffic-signal lanes):

    name            shape      dtype    unit / meaning
    scene_id        -          str      identifier (WOMD scenario id or generator tag)
    log_pos         (N, T, 2)  float32  m, agent centre
    log_yaw         (N, T)     float32  rad, heading
    log_vel         (N, T, 2)  float32  m/s
    log_valid       (N, T)     bool     step holds real data
    length          (N,)       float32  m
    width           (N,)       float32  m
    height          (N,)       float32  m
    agent_type      (N,)       int8     AgentType
    agent_id        (N,)       int64    source track id
    goal            (N, 2)     float32  m, goal point (last valid logged position)
    is_sdc          (N,)       bool     the autonomous vehicle that logged the scene
    is_interest     (N,)       bool     WOMD tracks_to_predict / objects_of_interest
    road_points     (P, 2)     float32  m, polyline vertices, polylines back to back
    road_offsets    (R + 1,)   int64    polyline r = road_points[off[r]:off[r + 1]]
    road_type       (R,)       int8     RoadType
    road_id         (R,)       int64    source map-feature id
    lane_edges      (E, 2)     int32    (from polyline, to polyline): lane successors
    tl_lane         (L,)       int64    road_id of the lane each signal controls
    tl_stop_point   (L, 2)     float32  m, stop point of that lane
    tl_state        (T, L)     int8     TrafficLightState per logged step
    origin          (2,)       float64  m, subtracted global offset
    dt              -          float    s, log period (0.1 for WOMD)
    metadata        -          dict     free-form: scenario_type, source, ...
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator, Sequence

import numpy as np

from tg_gpudrive.enums import AgentType, RoadType


MAX_EXTENT = 1.0e6  # m: a coordinate farther than this from the scene's centre is a broken field, not a map


class SceneError(ValueError):
    """A scene (or its source file) is malformed. The message names source and field."""

    def __init__(self, source: str, field: str, problem: str):
        self.source, self.field, self.problem = source, field, problem
        super().__init__(f"{source}: field '{field}': {problem}")


def log_period(step_seconds, default: float = 0.1) -> float:
    """The period (s) of a log from the time steps between its samples: their median, to the
    millisecond. WOMD logs are 10 Hz with tens of microseconds of jitter (0.09964 s in one file,
    0.10025 s in another); to the millisecond, scenes of one dataset share one dt and batch together."""
    steps = np.asarray(step_seconds, np.float64)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if len(steps) == 0:
        return default
    return round(float(np.median(steps)), 3) or default


class FieldReader:
    """Typed access into a parsed source file (a JSON document, an unpickled dict) that raises
    SceneError naming the file and the field path; loaders add the value readers of their format."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, field: str, problem: str):
        raise SceneError(self.source, field, problem)

    def key(self, obj: Any, key: str, path: str) -> Any:
        if not isinstance(obj, dict):
            self.fail(path, f"expected an object, got {type(obj).__name__}")
        if key not in obj:
            self.fail(f"{path}.{key}" if path else key, "missing key")
        return obj[key]


_AGENT_FIELDS = {
    # name: (dtype, trailing shape after N; "T" stands for the step count)
    "log_pos": (np.float32, ("T", 2)),
    "log_yaw": (np.float32, ("T",)),
    "log_vel": (np.float32, ("T", 2)),
    "log_valid": (np.bool_, ("T",)),
    "length": (np.float32, ()),
    "width": (np.float32, ()),
    "height": (np.float32, ()),
    "agent_type": (np.int8, ()),
    "agent_id": (np.int64, ()),
    "goal": (np.float32, (2,)),
    "is_sdc": (np.bool_, ()),
    "is_interest": (np.bool_, ()),
}


@dataclasses.dataclass
class Scene:
    scene_id: str
    log_pos: np.ndarray
    log_yaw: np.ndarray
    log_vel: np.ndarray
    log_valid: np.ndarray
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray
    agent_type: np.ndarray
    agent_id: np.ndarray
    goal: np.ndarray
    is_sdc: np.ndarray
    is_interest: np.ndarray
    road_points: np.ndarray
    road_offsets: np.ndarray
    road_type: np.ndarray
    road_id: np.ndarray
    lane_edges: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2), np.int32))
    tl_lane: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0,), np.int64))
    tl_stop_point: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 2), np.float32))
    tl_state: np.ndarray | None = None
    origin: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2, np.float64))
    dt: float = 0.1
    metadata: dict[str, Any] = dataclasses.field(default_factory=dict)

    # ------------------------------------------------------------------ sizes
    @property
    def num_agents(self) -> int:
        return int(self.log_pos.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.log_pos.shape[1])

    @property
    def num_polylines(self) -> int:
        return int(self.road_type.shape[0])

    def polyline(self, r: int) -> np.ndarray:
        return self.road_points[self.road_offsets[r] : self.road_offsets[r + 1]]

    def polylines(self) -> Iterator[tuple[int, np.ndarray]]:
        for r in range(self.num_polylines):
            yield int(self.road_type[r]), self.polyline(r)

    def copy(self) -> "Scene":
        return dataclasses.replace(
            self,
            **{f.name: np.array(getattr(self, f.name)) for f in dataclasses.fields(self)
               if isinstance(getattr(self, f.name), np.ndarray)},
            metadata=dict(self.metadata),
        )

    # ------------------------------------------------------------- validation
    def _check_extent(self, src: str, valid: np.ndarray) -> None:
        """Positions, goals and road points within MAX_EXTENT of the scene's centre (the median
        of the valid positions): one coordinate of 1e30 would otherwise overflow float32 in the
        recentring and flag every agent as collided and off the road."""
        centre = np.median(self.log_pos[valid].astype(np.float64), axis=0)
        present = valid.any(-1)
        for name, pts in (("log_pos", self.log_pos[valid]), ("goal", self.goal[present]),
                          ("roads.geometry", self.road_points)):
            far = np.abs(np.asarray(pts, np.float64).reshape(-1, 2) - centre).max(-1) > MAX_EXTENT
            if far.any():
                i = int(np.nonzero(far)[0][0])
                raise SceneError(src, name, f"coordinate {np.asarray(pts).reshape(-1, 2)[i].tolist()} lies more "
                                 f"than {MAX_EXTENT:.0e} m from the scene's centre {centre.round(1).tolist()}")

    def validate(self, source: str | None = None, field_prefix: str = "") -> "Scene":
        """Coerce dtypes and check shapes, finiteness and non-emptiness.

        Raises SceneError naming `source` (default: the scene id) and the field, after `field_prefix`
        (a record of a multi-scene file: "record[3]."). Returns self so loaders can write
        `return Scene(...).validate(path)`.
        """
        if field_prefix:
            try:
                return self.validate(source)
            except SceneError as e:
                raise SceneError(e.source, field_prefix + e.field, e.problem) from None
        src = source or self.metadata.get("source") or self.scene_id
        if self.log_pos.ndim != 3 or self.log_pos.shape[-1] != 2:
            raise SceneError(src, "log_pos", f"expected shape (N, T, 2), got {self.log_pos.shape}")
        n, t = self.log_pos.shape[:2]
        if n == 0:
            raise SceneError(src, "objects", "scene has no agents")
        if t < 2:
            raise SceneError(src, "log_pos", f"need at least 2 logged steps, got {t}")
        for name, (dtype, trail) in _AGENT_FIELDS.items():
            arr = np.asarray(getattr(self, name))
            want = (n,) + tuple(t if d == "T" else d for d in trail)
            if arr.shape != want:
                raise SceneError(src, name, f"expected shape {want}, got {arr.shape}")
            setattr(self, name, np.ascontiguousarray(arr, dtype=dtype))
        if not self.log_valid.any():
            raise SceneError(src, "valid", "no agent has a single valid step")
        valid = self.log_valid
        for name in ("log_pos", "log_yaw", "log_vel"):
            bad = ~np.isfinite(getattr(self, name)[valid])
            if bad.any():
                a, s = np.argwhere(valid)[np.nonzero(bad.reshape(bad.shape[0], -1).any(-1))[0][0]]
                raise SceneError(src, name, f"non-finite value at agent {a} (id {self.agent_id[a]}), step {s}")
        for name in ("length", "width", "goal"):
            arr = getattr(self, name)
            bad = ~np.isfinite(arr.reshape(n, -1)).all(-1) & valid.any(-1)
            if bad.any():
                a = int(np.nonzero(bad)[0][0])
                raise SceneError(src, name, f"non-finite value for agent {a} (id {self.agent_id[a]})")
        # invalid steps must not carry garbage into kernels: zero them
        self.log_pos[~valid] = 0.0
        self.log_yaw[~valid] = 0.0
        self.log_vel[~valid] = 0.0
        if (self.length[valid.any(-1)] <= 0).any() or (self.width[valid.any(-1)] <= 0).any():
            raise SceneError(src, "length/width", "agent box sizes must be positive")
        if not set(np.unique(self.agent_type)).issubset({int(v) for v in AgentType}):
            raise SceneError(src, "agent_type", f"unknown agent types {sorted(set(np.unique(self.agent_type)))}")

        self.road_points = np.ascontiguousarray(self.road_points, dtype=np.float32).reshape(-1, 2)
        self.road_offsets = np.ascontiguousarray(self.road_offsets, dtype=np.int64)
        self.road_type = np.ascontiguousarray(self.road_type, dtype=np.int8)
        self.road_id = np.ascontiguousarray(self.road_id, dtype=np.int64)
        r = self.road_type.shape[0]
        if self.road_offsets.shape != (r + 1,) or self.road_id.shape != (r,):
            raise SceneError(src, "road_offsets", f"expected {r + 1} offsets and {r} ids for {r} polylines")
        if r and (self.road_offsets[0] != 0 or self.road_offsets[-1] != len(self.road_points)
                  or (np.diff(self.road_offsets) < 1).any()):
            raise SceneError(src, "road_offsets", "offsets must start at 0, end at len(road_points), increase")
        if not np.isfinite(self.road_points).all():
            p = int(np.nonzero(~np.isfinite(self.road_points).all(-1))[0][0])
            poly = int(np.searchsorted(self.road_offsets, p, side="right") - 1)
            raise SceneError(src, "roads.geometry", f"non-finite point in polyline {poly} (id {self.road_id[poly]})")
        self._check_extent(src, valid)
        if not set(np.unique(self.road_type)).issubset({int(v) for v in RoadType}):
            raise SceneError(src, "road_type", f"unknown road types {sorted(set(np.unique(self.road_type)))}")
        self.lane_edges = np.ascontiguousarray(self.lane_edges, dtype=np.int32).reshape(-1, 2)
        if len(self.lane_edges) and (self.lane_edges.min() < 0 or self.lane_edges.max() >= r):
            raise SceneError(src, "lane_edges", "lane edge refers to a polyline that does not exist")
        self.tl_lane = np.ascontiguousarray(self.tl_lane, dtype=np.int64)
        self.tl_stop_point = np.ascontiguousarray(self.tl_stop_point, dtype=np.float32).reshape(-1, 2)
        if self.tl_state is None:
            self.tl_state = np.zeros((t, len(self.tl_lane)), np.int8)
        self.tl_state = np.ascontiguousarray(self.tl_state, dtype=np.int8)
        if self.tl_state.shape != (t, len(self.tl_lane)) or self.tl_stop_point.shape[0] != len(self.tl_lane):
            raise SceneError(src, "tl_states", f"expected (T={t}, L={len(self.tl_lane)}) signal states")
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(2)
        return self


def scene_defaults(scenes: Sequence[Scene]) -> dict[str, int]:
    """How often the loaders of `scenes` filled in a field an older format revision lacks (each scene's
    metadata["defaults"]: objects, roads or, for a unit such as degree headings, files), summed."""
    out: dict[str, int] = {}
    for sc in {id(s): s for s in scenes}.values():
        for key, v in (sc.metadata.get("defaults") or {}).items():
            out[key] = out.get(key, 0) + (v if isinstance(v, int) else 1)
    return dict(sorted(out.items()))


def make_scene(
    log_pos: np.ndarray,
    log_yaw: np.ndarray,
    *,
    log_vel: np.ndarray | None = None,
    log_valid: np.ndarray | None = None,
    length: float | np.ndarray = 4.5,
    width: float | np.ndarray = 2.0,
    agent_type: int | np.ndarray = AgentType.VEHICLE,
    goal: np.ndarray | None = None,
    roads: list[tuple[int, np.ndarray]] = (),
    lane_edges: np.ndarray | None = None,
    dt: float = 0.1,
    scene_id: str = "handmade",
    metadata: dict | None = None,
) -> Scene:
    """Build a small scene by hand (tests, examples).

    `log_pos` (N, T, 2) and `log_yaw` (N, T); velocities default to finite
    differences of the positions; goals to the last valid position; `roads` is a
    list of (RoadType, (k, 2) points) polylines.
    """
    log_pos = np.asarray(log_pos, np.float32)
    n, t = log_pos.shape[:2]
    log_valid = np.ones((n, t), bool) if log_valid is None else np.asarray(log_valid, bool)
    if log_vel is None:
        log_vel = np.zeros_like(log_pos)
        both = log_valid[:, 1:] & log_valid[:, :-1]
        with np.errstate(invalid="ignore"):
            log_vel[:, 1:] = np.where(both[..., None], np.diff(log_pos, axis=1) / dt, 0.0)
        log_vel[:, 0] = log_vel[:, 1] if t > 1 else 0.0
    if goal is None:
        last = t - 1 - np.argmax(log_valid[:, ::-1], axis=1)
        goal = log_pos[np.arange(n), last]
    pts = [np.asarray(p, np.float32).reshape(-1, 2) for _, p in roads]
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])]).astype(np.int64)
    full = lambda v, dt_: np.broadcast_to(np.asarray(v, dt_), (n,)).copy()  # noqa: E731
    return Scene(
        scene_id=scene_id,
        log_pos=log_pos,
        log_yaw=np.asarray(log_yaw, np.float32),
        log_vel=np.asarray(log_vel, np.float32),
        log_valid=log_valid,
        length=full(length, np.float32),
        width=full(width, np.float32),
        height=full(1.5, np.float32),
        agent_type=full(agent_type, np.int8),
        agent_id=np.arange(n, dtype=np.int64),
        goal=np.asarray(goal, np.float32),
        is_sdc=np.zeros(n, bool),
        is_interest=np.zeros(n, bool),
        road_points=np.concatenate(pts) if pts else np.zeros((0, 2), np.float32),
        road_offsets=offsets,
        road_type=np.asarray([int(k) for k, _ in roads], np.int8),
        road_id=np.arange(len(pts), dtype=np.int64),
        lane_edges=np.zeros((0, 2), np.int32) if lane_edges is None else lane_edges,
        dt=dt,
        metadata=dict(metadata or {}),
    ).validate()
