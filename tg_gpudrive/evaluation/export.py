"""Export scenes, and generated episodes, to GPUDrive's processed JSON format.

The inverse of `data.womd.gpudrive_json.load_gpudrive_json`: positions go back to the
source frame (+ `Scene.origin`), invalid steps hold the -10000 sentinel in
position, velocity and heading, road polylines keep their type names and
WOMD map_element_id (from metadata["road_subtype"] when the scene has it),
traffic signals become `tl_states`. A scene loaded from such a file and
exported again loads back into an identical Scene (every array; metadata up to
its "source" path).

A generated episode (`generated_scene`) is the scene with the recorded
trajectories of all its slot agents from init_step on (policy-driven and
replayed alike), the warm-up steps kept from the log; agents removed at their
goal are invalid from then on. The file's metadata carries what produced it
under "tg_gpudrive": label, seed, controlled ids, and the episode's risk figures.

Procedural scenes have origin (0, 0); the loader re-centres every file on the
rounded mean of its positions, so such a scene comes back translated by that
whole-metre offset (recorded in `Scene.origin`), otherwise equal.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from tg_gpudrive.data.womd.gpudrive_json import SENTINEL
from tg_gpudrive.evaluation.episodes import Trajectories
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

_TYPE_NAMES = {AgentType.VEHICLE: "vehicle", AgentType.PEDESTRIAN: "pedestrian", AgentType.CYCLIST: "cyclist"}
# WOMD per-kind subtype -> GPUDrive map_element_id (inverse of gpudrive_json._map_element_subtype)
_MID_BASE = {RoadType.LANE: 0, RoadType.ROAD_LINE: 5, RoadType.ROAD_EDGE: 14}
_MID_OTHER = {RoadType.STOP_SIGN: 17, RoadType.CROSSWALK: 18, RoadType.SPEED_BUMP: 19, RoadType.DRIVEWAY: 20}


def _f(x) -> float:
    return float(x)


def scene_to_json(scene: Scene) -> dict:
    """GPUDrive processed-JSON dict of `scene`."""
    o = np.asarray(scene.origin, np.float64)
    meta = scene.metadata or {}
    expert = set(int(i) for i in meta.get("mark_as_expert", []) or [])
    objects = []
    for i in range(scene.num_agents):
        v = scene.log_valid[i]
        pos = scene.log_pos[i].astype(np.float64) + o
        vel = scene.log_vel[i].astype(np.float64)
        yaw = scene.log_yaw[i].astype(np.float64)
        objects.append({
            "position": [{"x": _f(p[0]), "y": _f(p[1]), "z": 0.0} if ok else
                         {"x": SENTINEL, "y": SENTINEL, "z": SENTINEL} for p, ok in zip(pos, v)],
            "width": _f(scene.width[i]), "length": _f(scene.length[i]), "height": _f(scene.height[i]),
            "heading": [_f(h) if ok else SENTINEL for h, ok in zip(yaw, v)],
            "velocity": [{"x": _f(q[0]), "y": _f(q[1])} if ok else {"x": SENTINEL, "y": SENTINEL}
                         for q, ok in zip(vel, v)],
            "valid": [bool(x) for x in v],
            "goalPosition": {"x": _f(scene.goal[i, 0] + o[0]), "y": _f(scene.goal[i, 1] + o[1]), "z": 0.0},
            "type": _TYPE_NAMES.get(AgentType(int(scene.agent_type[i])), "other"),
            "id": int(scene.agent_id[i]),
            "mark_as_expert": i in expert,
        })
    sub = meta.get("road_subtype") or [0] * scene.num_polylines
    roads = []
    for r in range(scene.num_polylines):
        kind = RoadType(int(scene.road_type[r]))
        mid = _MID_BASE[kind] + int(sub[r]) if kind in _MID_BASE else _MID_OTHER.get(kind, -1)
        roads.append({
            "geometry": [{"x": _f(p[0] + o[0]), "y": _f(p[1] + o[1]), "z": 0.0}
                         for p in scene.polyline(r).astype(np.float64)],
            "type": kind.name.lower(), "map_element_id": mid, "id": int(scene.road_id[r]),
        })
    tl = {}
    for j, lane in enumerate(scene.tl_lane):
        col = scene.tl_state[:, j]
        stop = scene.tl_stop_point[j].astype(np.float64) + o
        tl[str(int(lane))] = {"state": [TrafficLightState(int(s)).name.lower() for s in col],
                              "x": [_f(stop[0])] * len(col), "y": [_f(stop[1])] * len(col),
                              "time_index": list(range(len(col)))}
    interest = [{"track_index": int(i), "difficulty": 0} for i in np.nonzero(scene.is_interest)[0]]
    md = {"sdc_track_index": meta.get("sdc_track_index",
                                      int(np.argmax(scene.is_sdc)) if scene.is_sdc.any() else None),
          "objects_of_interest": [int(x) for x in meta.get("objects_of_interest", []) or []],
          "tracks_to_predict": meta.get("tracks_to_predict", interest)}
    if md["sdc_track_index"] is None:
        del md["sdc_track_index"]
    out = {"name": meta.get("name") or f"{scene.scene_id}.json", "scenario_id": scene.scene_id,
           "objects": objects, "roads": roads, "tl_states": tl, "metadata": md}
    if "tg_gpudrive" in meta:
        out["metadata"]["tg_gpudrive"] = meta["tg_gpudrive"]
    return out


def write_scene_json(scene: Scene, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(scene_to_json(scene)))
    return path


def generated_scene(tr: Trajectories, episode: int, *, risk: dict | None = None, suffix: str | None = None) -> Scene:
    """The scene of `tr`'s episode with its recorded trajectories in place of the logs (from init_step on)."""
    base = tr.scenes[int(tr.scene_index[episode])]
    sc = base.copy()
    T0, K = tr.init_step, tr.pos.shape[2]
    steps = min(K, sc.num_steps - T0)
    controlled_ids = []
    for a, idx in enumerate(tr.slot_agent[episode]):
        if idx < 0:
            continue
        v = tr.valid[episode, a, :steps]
        sc.log_valid[idx, T0:] = False
        sc.log_valid[idx, T0:T0 + steps] = v
        sc.log_pos[idx, T0:T0 + steps] = np.where(v[:, None], tr.pos[episode, a, :steps], 0.0)
        sc.log_yaw[idx, T0:T0 + steps] = np.where(v, tr.yaw[episode, a, :steps], 0.0)
        sc.log_vel[idx, T0:T0 + steps] = np.where(v[:, None], tr.vel[episode, a, :steps], 0.0)
        sc.log_pos[idx, T0 + steps:] = 0.0
        sc.log_yaw[idx, T0 + steps:] = 0.0
        sc.log_vel[idx, T0 + steps:] = 0.0
        if tr.policy[episode, a]:
            controlled_ids.append(int(sc.agent_id[idx]))
    tag = suffix if suffix is not None else f"{tr.label or 'gen'}_s{int(tr.seed[episode])}"
    sc.scene_id = f"{base.scene_id}__{tag}"
    sc.metadata = {k: v for k, v in base.metadata.items() if _jsonable(v)}
    sc.metadata["name"] = f"{sc.scene_id}.json"
    sc.metadata["tg_gpudrive"] = {"generated": True, "label": tr.label, "seed": int(tr.seed[episode]),
                                  "source_scene": base.scene_id, "init_step": int(T0),
                                  "controlled_ids": controlled_ids, "risk": risk or {}}
    return sc.validate()


def _jsonable(v) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False


def export_episodes(tr: Trajectories, episodes, out_dir: str | Path, risk_rows: list[dict] | None = None) -> list[Path]:
    """Write the given episodes of `tr` as GPUDrive JSON files; `risk_rows[i]` goes into file i's metadata."""
    out = []
    for i, e in enumerate(episodes):
        sc = generated_scene(tr, int(e), risk=(risk_rows[i] if risk_rows else None))
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", sc.scene_id)
        out.append(write_scene_json(sc, Path(out_dir) / f"{name}.json"))
    return out
