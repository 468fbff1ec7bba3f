"""WOMD tf.Example TFRecords load without TensorFlow; raw Scenario protos run in the engine.

Data (tests/womd_raw/): one tf.Example record (scenario a3bb37c25ce56418) and two Scenario
records (637f20cafde22ff8, ee519cf571686d19) of the Waymo Open Motion Dataset, copied unchanged.
They live outside tests/data because other tests load every scene file under tests/data.
The tf.Example is not the same scenario as either Scenario file, so agreement of the two
flavours is checked on a tf.Example written here from a Scenario file's scene.
"""

from __future__ import annotations

import logging
import pathlib
import struct

import numpy as np
import pytest

from tg_gpudrive.cli import main
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.store import load_file
from tg_gpudrive.data.womd import protowire as pw
from tg_gpudrive.data.womd.scenario_proto import read_tfrecord_scenes
from tg_gpudrive.data.womd.tf_example import EXAMPLE, FEATURE_ENTRY, is_tf_example
from tg_gpudrive.data.womd.tfrecord import iter_records, write_records
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout
from tg_gpudrive.scene import SceneError
from tg_gpudrive.enums import AgentType, RoadType

RAW = pathlib.Path(__file__).parent / "womd_raw"
EXAMPLE_FILE = RAW / "motion_data_one_example.tfrecord"
SCENARIO_FILES = [RAW / "motion_data_one_scenario.tfrecord", RAW / "womd_scenario_input.tfrecord"]
PARTS = (("past", 10), ("current", 1), ("future", 80))


# ------------------------------------------------- an independent tf.Example reader
def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        b = buf[pos]
        pos += 1
        out |= (b & 0x7F) << shift
        if b < 0x80:
            return out, pos
        shift += 7


def _fields(buf: bytes):
    """(field number, payload) of every length-delimited field of one message."""
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        assert key & 7 == 2, "the Example wrapper holds only length-delimited fields"
        n, pos = _varint(buf, pos)
        yield key >> 3, buf[pos:pos + n]
        pos += n


def raw_features(data: bytes) -> dict[str, np.ndarray | list]:
    """Decode a tf.Example by hand (struct and varints), not through protowire."""
    (num, features), = list(_fields(data))
    out = {}
    for _, entry in _fields(features):
        parts = dict(_fields(entry))
        key = parts[1].decode()
        (kind, lst), = list(_fields(parts[2]))
        vals = [v for _, v in _fields(lst)]
        if kind == 1:
            out[key] = vals
        elif kind == 2:
            body = b"".join(vals)
            out[key] = np.array(struct.unpack(f"<{len(body) // 4}f", body), np.float32)
        else:
            ints, body = [], b"".join(vals)
            pos = 0
            while pos < len(body):
                v, pos = _varint(body, pos)
                ints.append(v - (1 << 64) if v >= 1 << 63 else v)
            out[key] = np.array(ints, np.int64)
    return out


def _steps(raw: dict, name: str) -> np.ndarray:
    """(rows, 91) of one per-step agent feature, past + current + future."""
    return np.concatenate([raw[f"state/{p}/{name}"].reshape(-1, t) for p, t in PARTS], 1)


@pytest.fixture(scope="module")
def record() -> bytes:
    (data,) = list(iter_records(EXAMPLE_FILE))
    return data


@pytest.fixture(scope="module")
def raw(record):
    return raw_features(record)


@pytest.fixture(scope="module")
def scene():
    (s,) = load_file(EXAMPLE_FILE)
    return s


# ----------------------------------------------------------------- the real file
def test_example_loads_through_store_and_reader(scene, caplog):
    assert scene.scene_id == "a3bb37c25ce56418"
    assert scene.num_steps == 91 and scene.log_pos.shape == (128, 91, 2)
    meta = scene.metadata
    assert meta["format"] == "tf_example" and meta["scenario_type"] == "womd"
    assert meta["source"] == str(EXAMPLE_FILE) and meta["record_index"] == 0
    assert meta["current_time_index"] == 10
    # Waymo's 20000-sample budget is full in this scene: the map is cut, and the loader says so
    assert meta["roadgraph_truncated"] is True
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive"):
        (again,) = list(read_tfrecord_scenes(EXAMPLE_FILE))
    assert "roadgraph samples are valid" in caplog.text and "Scenario flavour" in caplog.text
    for name in ("log_pos", "log_yaw", "log_valid", "road_points", "tl_state"):
        assert np.array_equal(getattr(again, name), getattr(scene, name))
    assert scene.dt == pytest.approx(0.1, abs=1e-3)


def test_agents_match_independent_decode(scene, raw):
    valid = _steps(raw, "valid") != 0
    rows = np.nonzero(valid.any(1))[0]
    assert scene.num_agents == len(rows) == 128  # every one of the 128 rows is used in this scene
    assert np.array_equal(scene.log_valid, valid[rows])
    assert np.nonzero(scene.is_sdc)[0].tolist() == [8]
    assert np.nonzero(raw["state/is_sdc"])[0].tolist() == [8]
    xy = np.stack([_steps(raw, "x"), _steps(raw, "y")], -1)[rows].astype(np.float64)
    v = scene.log_valid
    np.testing.assert_allclose(scene.log_pos[v], xy[v] - scene.origin, atol=1e-3)
    np.testing.assert_array_equal(scene.log_yaw[v], _steps(raw, "bbox_yaw")[rows][v])
    vel = np.stack([_steps(raw, "velocity_x"), _steps(raw, "velocity_y")], -1)[rows]
    np.testing.assert_array_equal(scene.log_vel[v], vel[v])
    # the first agent at the current step, by hand
    assert v[0, 10]
    np.testing.assert_allclose(scene.log_pos[0, 10], [raw["state/current/x"][0] - scene.origin[0],
                                                      raw["state/current/y"][0] - scene.origin[1]], atol=1e-3)
    assert scene.log_yaw[0, 10] == raw["state/current/bbox_yaw"][0]
    # goals: the last valid position; sizes: the first valid step
    last = 90 - np.argmax(v[:, ::-1], 1)
    np.testing.assert_allclose(scene.goal, scene.log_pos[np.arange(128), last], atol=1e-6)
    first = np.argmax(v, 1)
    np.testing.assert_array_equal(scene.length, _steps(raw, "length")[rows][np.arange(128), first])
    assert scene.agent_id.tolist() == raw["state/id"][rows].astype(int).tolist()
    assert np.array_equal(scene.agent_type, raw["state/type"][rows].astype(np.int8))
    assert set(np.unique(scene.agent_type)) == {AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST}
    interest = (raw["state/tracks_to_predict"] != 0) | (raw["state/objects_of_interest"] != 0)
    assert np.array_equal(scene.is_interest, interest[rows])
    assert [q["track_index"] for q in scene.metadata["tracks_to_predict"]] == \
        np.nonzero(raw["state/tracks_to_predict"][rows])[0].tolist()


def test_map_and_signals_match_independent_decode(scene, raw):
    ok = raw["roadgraph_samples/valid"] != 0
    assert ok.all()
    ids, types = raw["roadgraph_samples/id"], raw["roadgraph_samples/type"]
    runs = np.concatenate([[0], np.nonzero(np.diff(ids))[0] + 1])
    assert scene.num_polylines == len(runs) == 254
    assert scene.road_id.tolist() == ids[runs].tolist()
    assert len(scene.road_points) == 20000
    xyz = raw["roadgraph_samples/xyz"].reshape(-1, 3)
    np.testing.assert_allclose(scene.road_points, xyz[:, :2] - scene.origin, atol=1e-3)
    want = {1: RoadType.LANE, 2: RoadType.LANE, 3: RoadType.LANE, 15: RoadType.ROAD_EDGE, 16: RoadType.ROAD_EDGE}
    want.update({t: RoadType.ROAD_LINE for t in range(6, 14)})
    assert scene.road_type.tolist() == [int(want[int(t)]) for t in types[runs]]
    assert scene.metadata["road_subtype"][:2] == [11 - 5, 15 - 14]  # a solid single yellow line, a boundary
    assert scene.metadata["skipped_road_samples"] == {}

    # signals: one lane per id seen valid, states along the 91 steps
    tl_ids = np.concatenate([raw[f"traffic_light_state/{p}/id"].reshape(t, 16) for p, t in PARTS])
    tl_ok = np.concatenate([raw[f"traffic_light_state/{p}/valid"].reshape(t, 16) for p, t in PARTS]) != 0
    tl_st = np.concatenate([raw[f"traffic_light_state/{p}/state"].reshape(t, 16) for p, t in PARTS])
    assert sorted(scene.tl_lane.tolist()) == sorted(set(tl_ids[tl_ok].tolist()))
    for t, s in zip(*np.nonzero(tl_ok)):
        l = scene.tl_lane.tolist().index(int(tl_ids[t, s]))
        assert scene.tl_state[t, l] == tl_st[t, s]
    assert scene.tl_state.shape == (91, len(scene.tl_lane))


@pytest.mark.parametrize("path,expected", [(EXAMPLE_FILE, True)] + [(p, False) for p in SCENARIO_FILES],
                         ids=lambda x: x.name if isinstance(x, pathlib.Path) else str(x))
def test_flavour_detection(path, expected):
    (data,) = list(iter_records(path))
    assert is_tf_example(data) is expected
    assert not is_tf_example(b"") and not is_tf_example(b"\x0a\x05hello")


# ------------------------------------------------------------------ engine interop
@pytest.mark.parametrize("path", [EXAMPLE_FILE] + SCENARIO_FILES, ids=lambda p: p.name)
def test_expert_replay_reaches_goals(path):
    scenes = load_file(path)
    assert len(scenes) == 1 and scenes[0].num_steps == 91
    sim = Simulator(scenes, EngineConfig(max_agents=scenes[0].num_agents), "cpu")
    assert sim.report()["agents_dropped"] == 0
    out = run_rollout(sim, expert_policy, sim.episode_length)
    # observed: 36/37 (tf.Example; one logged contact), 20/20 and 5/5 (Scenario files)
    assert out["episodes"] >= 5
    assert out["goal_rate"] >= 0.9
    assert out["offroad_rate"] <= 0.05


def test_example_and_scenario_files_are_different_scenarios(scene):
    ids = {p.name: next(read_tfrecord_scenes(p)).scene_id for p in SCENARIO_FILES}
    assert ids == {"motion_data_one_scenario.tfrecord": "637f20cafde22ff8",
                   "womd_scenario_input.tfrecord": "ee519cf571686d19"}
    assert scene.scene_id not in ids.values()  # so the flavours are compared on a written tf.Example below


def _float(v) -> dict:
    return {"float_list": {"value": np.asarray(v, np.float32).ravel()}}


def _int(v) -> dict:
    return {"int64_list": {"value": np.asarray(v, np.int64).ravel()}}


def scene_to_example(s) -> dict[str, dict]:
    """A WOMD-layout tf.Example of a Scene (global coordinates), as Waymo's converter lays it out."""
    n, t = s.num_agents, s.num_steps
    v = s.log_valid
    world = s.log_pos.astype(np.float64) + s.origin
    per_step = {
        "x": world[..., 0], "y": world[..., 1], "z": np.zeros((n, t)), "bbox_yaw": s.log_yaw,
        "velocity_x": s.log_vel[..., 0], "velocity_y": s.log_vel[..., 1],
        "length": np.repeat(s.length[:, None], t, 1), "width": np.repeat(s.width[:, None], t, 1),
        "height": np.repeat(s.height[:, None], t, 1),
    }
    stamps = np.repeat(np.round(np.arange(t) * s.dt * 1e6)[None], n, 0)
    ttp = np.zeros(n, np.int64)
    diff = np.zeros(n, np.int64)
    for q in s.metadata["tracks_to_predict"]:
        ttp[q["track_index"]], diff[q["track_index"]] = 1, q["difficulty"]
    feats = {
        "scenario/id": {"bytes_list": {"value": [s.scene_id.encode()]}},
        "state/id": _float(s.agent_id), "state/type": _float(s.agent_type),
        "state/is_sdc": _int(s.is_sdc), "state/tracks_to_predict": _int(ttp),
        "state/objects_of_interest": _int(np.isin(s.agent_id, s.metadata["objects_of_interest"])),
        "state/difficulty_level": _int(diff),
    }
    start = 0
    for part, tp in PARTS:
        sl = slice(start, start + tp)
        for name, arr in per_step.items():
            feats[f"state/{part}/{name}"] = _float(np.where(v[:, sl], arr[:, sl], -1.0))
        feats[f"state/{part}/valid"] = _int(v[:, sl])
        feats[f"state/{part}/timestamp_micros"] = _int(np.where(v[:, sl], stamps[:, sl], -1))
        tl = s.tl_state[sl]
        lanes = np.repeat(s.tl_lane[None], tp, 0)
        stop = s.tl_stop_point.astype(np.float64) + s.origin
        feats[f"traffic_light_state/{part}/state"] = _int(tl)
        feats[f"traffic_light_state/{part}/id"] = _int(lanes)
        feats[f"traffic_light_state/{part}/valid"] = _int(np.ones_like(lanes))
        feats[f"traffic_light_state/{part}/x"] = _float(np.repeat(stop[None, :, 0], tp, 0))
        feats[f"traffic_light_state/{part}/y"] = _float(np.repeat(stop[None, :, 1], tp, 0))
        start += tp
    sub = s.metadata["road_subtype"]
    code = {RoadType.LANE: lambda k: k, RoadType.ROAD_LINE: lambda k: 5 + k, RoadType.ROAD_EDGE: lambda k: 14 + k,
            RoadType.STOP_SIGN: lambda k: 17, RoadType.CROSSWALK: lambda k: 18, RoadType.SPEED_BUMP: lambda k: 19}
    xyz, types, ids = [], [], []
    for r in range(s.num_polylines):
        p = s.polyline(r).astype(np.float64) + s.origin
        xyz.append(np.concatenate([p, np.zeros((len(p), 1))], 1))
        types += [code[RoadType(s.road_type[r])](sub[r])] * len(p)
        ids += [int(s.road_id[r])] * len(p)
    # padded to Waymo's budget of 20000 samples with invalid ones, as in the dataset
    pad = 20000 - len(ids)
    xyz = np.concatenate(xyz + [np.full((pad, 3), -1.0)])
    feats.update({"roadgraph_samples/xyz": _float(xyz), "roadgraph_samples/type": _int(types + [-1] * pad),
                  "roadgraph_samples/id": _int(ids + [-1] * pad),
                  "roadgraph_samples/valid": _int(np.arange(20000) < len(ids)),
                  "roadgraph_samples/dir": _float(np.zeros_like(xyz))})
    return feats


def _encode(feats: dict[str, dict]) -> bytes:
    return pw.encode(EXAMPLE, {"features": {"feature": [{"key": k, "value": v} for k, v in feats.items()]}})


@pytest.mark.parametrize("path", SCENARIO_FILES, ids=lambda p: p.name)
def test_both_flavours_of_one_scenario_agree(path, tmp_path):
    (proto,) = load_file(path)
    out = tmp_path / "written.tfrecord"
    write_records(out, [_encode(scene_to_example(proto))])
    (ex,) = load_file(out)
    assert ex.metadata["format"] == "tf_example" and "format" not in proto.metadata
    assert ex.scene_id == proto.scene_id and ex.num_agents == proto.num_agents
    assert np.array_equal(ex.origin, proto.origin)
    assert np.array_equal(ex.log_valid, proto.log_valid)
    v = proto.log_valid
    # tf.Example stores float32 global coordinates: agreement to float32 precision at ~8 km
    np.testing.assert_allclose(ex.log_pos[v], proto.log_pos[v], atol=2e-3)
    np.testing.assert_allclose(ex.goal, proto.goal, atol=2e-3)
    for name in ("log_yaw", "log_vel", "length", "width", "height", "agent_type", "agent_id", "is_sdc",
                 "is_interest", "road_type", "road_id", "road_offsets", "tl_lane", "tl_state"):
        assert np.array_equal(getattr(ex, name), getattr(proto, name)), name
    np.testing.assert_allclose(ex.road_points, proto.road_points, atol=2e-3)
    np.testing.assert_allclose(ex.tl_stop_point, proto.tl_stop_point, atol=2e-3)
    assert ex.metadata["road_subtype"] == proto.metadata["road_subtype"]
    assert ex.dt == proto.dt
    assert sorted(map(str, ex.metadata["tracks_to_predict"])) == sorted(map(str, proto.metadata["tracks_to_predict"]))
    assert sorted(ex.metadata["objects_of_interest"]) == sorted(proto.metadata["objects_of_interest"])
    assert ex.metadata["roadgraph_truncated"] is False and ex.lane_edges.shape == (0, 2)  # no lane graph there


# ------------------------------------------------------------------- bad records
def test_record_of_neither_flavour(tmp_path):
    path = tmp_path / "noise.tfrecord"
    write_records(path, [np.random.default_rng(0).bytes(4096)])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    msg = str(err.value)
    assert "\n" not in msg and err.value.field.startswith("record[0]")
    assert "Scenario" in msg and "tf.Example" in msg


def _features_of(record: bytes) -> dict[str, dict]:
    msg = pw.decode(EXAMPLE, record)
    return {e["key"]: e["value"] for e in msg["features"]["feature"]}


@pytest.mark.parametrize("key,change,problem", [
    ("state/past/x", "remove", "missing feature"),
    ("scenario/id", "remove", "missing feature"),
    ("state/future/y", "shorten", "expected 10240 values (128 agent rows x 80 steps"),
    ("state/type", "shorten", "expected 128 values"),
    ("roadgraph_samples/id", "shorten", "expected 20000 values"),
    ("traffic_light_state/current/x", "shorten", "expected 16 values"),
    ("state/current/valid", "shorten", "not a whole number of steps"),
    ("state/past/bbox_yaw", "as_int", "expected a float_list, got int64_list"),
])
def test_broken_feature_is_named(record, tmp_path, key, change, problem):
    feats = _features_of(record)
    if change == "remove":
        del feats[key]
    elif change == "shorten":
        (kind, body), = feats[key].items()
        body["value"] = body["value"][:-1]
    else:
        feats[key] = _int(np.zeros(len(feats[key]["float_list"]["value"])))
    path = tmp_path / "broken.tfrecord"
    write_records(path, [_encode(feats)])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.field == f"record[0].features['{key}']"
    assert problem in err.value.problem and str(path) in str(err.value)


def test_undecodable_feature_is_named(record, tmp_path):
    """A float list whose packed run is not whole floats: named by its key, not by its map index."""
    feats = _features_of(record)
    del feats["state/past/x"]
    entries = [pw.encode(FEATURE_ENTRY, {"key": k, "value": v}) for k, v in feats.items()]
    floats = b"\x0a\x05" + bytes(5)  # FloatList.value, 5 bytes
    entries.append(b"\x0a\x0cstate/past/x\x12" + pw.encode_varint(len(floats) + 2) + b"\x12"
                   + pw.encode_varint(len(floats)) + floats)
    body = b"".join(b"\x0a" + pw.encode_varint(len(e)) + e for e in entries)
    path = tmp_path / "undecodable.tfrecord"
    write_records(path, [b"\x0a" + pw.encode_varint(len(body)) + body])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.field == "record[0].features['state/past/x']"
    assert "not a multiple of 4" in err.value.problem


def test_unknown_road_types_are_skipped_and_counted(record, tmp_path):
    feats = _features_of(record)
    types = feats["roadgraph_samples/type"]["int64_list"]["value"].copy()
    ids = feats["roadgraph_samples/id"]["int64_list"]["value"]
    first = ids == ids[0]  # the first polyline becomes a type with no RoadType
    types[first] = 20
    feats["roadgraph_samples/type"] = _int(types)
    feats["roadgraph_samples/valid"] = _int(np.arange(len(types)) < len(types) - 100)  # budget not full
    path = tmp_path / "types.tfrecord"
    write_records(path, [_encode(feats)])
    (s,) = load_file(path)
    assert s.metadata["skipped_road_samples"] == {"20": int(first.sum())}
    kept = ids[:-100]
    assert s.num_polylines == np.count_nonzero(np.diff(kept)) + 1 - 1  # runs of the valid samples, less the first
    assert len(s.road_points) == 20000 - 100 - int(first.sum())
    assert s.metadata["roadgraph_truncated"] is False


# ------------------------------------------------------------------------- CLI
def test_cli_simulates_the_example_file(capsys):
    rc = main(["simulate", "--scenes", str(EXAMPLE_FILE), "--worlds", "1", "--device", "cpu", "--json"])
    assert rc == 0
    assert '"goal_rate"' in capsys.readouterr().out


def test_both_flavours_and_scenarionet_batch_together(tmp_path):
    """WOMD's logged periods jitter (0.09964 s, 0.10025 s): every loader gives 0.1 s, so scenes of all
    three forms fill one batch."""
    import shutil

    from tg_gpudrive import cli
    from tg_gpudrive.data.sources import resolve_scenes

    for f in RAW.glob("*.tfrecord"):
        shutil.copy(f, tmp_path / f.name)
    shutil.copy(next((pathlib.Path(__file__).parent / "data_scenarionet").glob("sd_*.pkl")), tmp_path)
    src = resolve_scenes(str(tmp_path))
    assert len(src) == 4 and {src.get(i).dt for i in range(4)} == {0.1}
    assert cli.main(["simulate", "--scenes", str(tmp_path), "--worlds", "4", "--device", "cpu", "--json"]) == 0
