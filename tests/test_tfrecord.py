"""TFRecord framing, the protobuf wire codec and WOMD Scenario <-> Scene round trips."""

from __future__ import annotations

import dataclasses
import gzip
import os
import pathlib
import struct

import numpy as np
import pytest

from tg_gpudrive.data.womd import protowire as pw
from tg_gpudrive.data.womd.scenario_proto import (
    SCENARIO, TRACK, read_tfrecord_scenes, scene_to_scenario, scenario_to_scene, write_tfrecord_scenes,
)
from tg_gpudrive.data.womd.tfrecord import _crc_loop, crc32c, iter_records, masked_crc32c, write_records
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.scene import SceneError, make_scene
from tg_gpudrive.enums import AgentType, RoadType

DATA = pathlib.Path(__file__).parent / "data"
JSONS = sorted(DATA.glob("womd_*.json"))


# ---------------------------------------------------------------------- crc32c
def test_crc32c_known_values():
    assert crc32c(b"123456789") == 0xE3069283  # the standard CRC-32C check value
    assert crc32c(b"") == 0
    assert crc32c(bytes(32)) == 0x8A9136AA  # RFC 3720 B.4 test vector
    assert crc32c(b"\xff" * 32) == 0x62A8AB43


@pytest.mark.parametrize("n", [1, 4095, 4096, 4097, 70_001, 1 << 20])
def test_crc32c_vector_path_matches_loop(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert crc32c(data) == _crc_loop(0xFFFFFFFF, data) ^ 0xFFFFFFFF
    assert crc32c(data[n // 3:], crc32c(data[: n // 3])) == crc32c(data)


# ----------------------------------------------------------------- framing
def test_records_round_trip(tmp_path):
    recs = [b"", b"a", os.urandom(10_000), bytes(5000)]
    path = tmp_path / "x.tfrecord"
    assert write_records(path, recs) == 4
    assert list(iter_records(path)) == recs
    raw = path.read_bytes()
    length = struct.pack("<Q", 1)
    assert raw[16:24] == length and struct.unpack("<I", raw[24:28])[0] == masked_crc32c(length)
    gz = tmp_path / "x.tfrecord.gz"
    gz.write_bytes(gzip.compress(raw))
    assert list(iter_records(gz)) == recs


def _offsets(path) -> list[int]:
    raw, offs, pos = path.read_bytes(), [], 0
    while pos < len(raw):
        offs.append(pos)
        pos += 16 + struct.unpack_from("<Q", raw, pos)[0]
    return offs


def _scene_file(tmp_path) -> pathlib.Path:
    path = tmp_path / "scenes.tfrecord"
    assert write_tfrecord_scenes(path, [_handmade(k) for k in range(3)]) == 3
    return path


@pytest.mark.parametrize("where, problem", [
    ("data", "truncated data"), ("header", "truncated header"), ("footer", "truncated data crc"),
])
def test_truncated_file(tmp_path, where, problem):
    path = _scene_file(tmp_path)
    raw, offs = path.read_bytes(), _offsets(path)
    cut = {"data": offs[1] + 100, "header": offs[1] + 5, "footer": offs[2] - 2}[where]
    path.write_bytes(raw[:cut])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.source == str(path) and err.value.field == "record[1]"
    assert problem in err.value.problem and str(path) in str(err.value)


@pytest.mark.parametrize("where, problem", [("data", "data crc mismatch"), ("header", "length crc mismatch")])
def test_flipped_byte(tmp_path, where, problem):
    path = _scene_file(tmp_path)
    raw, offs = bytearray(path.read_bytes()), _offsets(path)
    at = offs[1] + (40 if where == "data" else 2)
    raw[at] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.source == str(path) and err.value.field == "record[1]"
    assert problem in err.value.problem and "record[1]" in str(err.value)


def test_undecodable_records(tmp_path):
    path = tmp_path / "bad.tfrecord"
    write_records(path, [b"\x12\xff\x7f\x00"])  # tracks: length runs past the end
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.field == "record[0].tracks" and "past the end" in err.value.problem
    write_records(path, [pw.encode(SCENARIO, {"scenario_id": "empty"})])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.field == "record[0].tracks" and "no tracks" in err.value.problem


# ------------------------------------------------------------- wire format
POINT = pw.Message("P", [pw.Field(1, "x", "double"), pw.Field(2, "ok", "bool"), pw.Field(3, "k", "enum")])
ALL = pw.Message("All", [
    pw.Field(1, "a", "int32"), pw.Field(2, "s", "string"), pw.Field(3, "f", "float"),
    pw.Field(4, "packed", "int64", True, packed=True), pw.Field(5, "plain", "int32", True),
    pw.Field(6, "d", "double", True, packed=True), pw.Field(7, "z", "sint64"), pw.Field(8, "b", "bytes"),
    pw.Field(9, "sub", "message", False, POINT), pw.Field(10, "rows", "message", True, POINT, columnar=True),
    pw.Field(11, "u", "uint64"), pw.Field(12, "flags", "bool", True, packed=True),
])


def test_wire_bytes_match_protobuf_encoding():
    assert pw.encode(ALL, {"a": 150}) == b"\x08\x96\x01"
    assert pw.encode(ALL, {"a": -1}) == b"\x08" + b"\xff" * 9 + b"\x01"  # negative int32: 10 bytes
    assert pw.encode(ALL, {"s": "testing"}) == b"\x12\x07testing"
    assert pw.encode(ALL, {"packed": [3, 270, 86942]}) == bytes.fromhex("2206038e029ea705")
    assert pw.encode(ALL, {"plain": [1, 2]}) == b"\x28\x01\x28\x02"
    assert pw.encode(ALL, {"z": -2}) == b"\x38\x03"
    assert pw.encode(ALL, {"f": 1.5}) == b"\x1d" + struct.pack("<f", 1.5)
    assert pw.encode(ALL, {"sub": {"x": 2.0, "ok": True}}) == b"\x4a\x0b\x09" + struct.pack("<d", 2.0) + b"\x10\x01"
    state = {"center_x": [1.5], "valid": [True]}
    want = b"\x1a\x0b\x11" + struct.pack("<d", 1.5) + b"\x58\x01"
    assert pw.encode(TRACK, {"states": state}) == want
    assert pw.encode(TRACK, {"states": [{"center_x": 1.5, "valid": True}]}) == want


def test_wire_round_trip_and_unknown_fields():
    msg = {
        "a": -7, "s": "ü", "f": 0.25, "packed": np.array([1, -5, 1 << 40]), "plain": np.array([3, -3]),
        "d": np.array([0.5, -1e300]), "z": -123456789, "b": b"\x00\x01", "sub": {"x": -2.5, "k": 300},
        "rows": {"x": np.arange(5.0), "ok": np.array([1, 0, 1, 0, 1], bool), "k": np.array([0, 1, 2, 3, 4])},
        "u": (1 << 64) - 1, "flags": np.array([True, False]),
    }
    data = pw.encode(ALL, msg)
    # unknown fields of every wire type, in front and in between, must be skipped
    unknown = b"\xa8\x06\x05" + b"\xb1\x06" + bytes(8) + b"\xba\x06\x02hi" + b"\xc5\x06" + bytes(4)
    got = pw.decode(ALL, unknown + data + unknown)
    assert got.keys() == msg.keys()
    for k, v in msg.items():
        if isinstance(v, dict):
            for kk in v:
                assert np.array_equal(got[k][kk], v[kk]), (k, kk)
        elif isinstance(v, np.ndarray):
            assert np.array_equal(got[k], v) and got[k].dtype == ALL.by_name[k].dtype, k
        else:
            assert got[k] == v, k
    # packed and unpacked encodings of the same repeated field decode the same
    assert np.array_equal(pw.decode(ALL, b"\x28\x01\x28\x02\x2a\x02\x03\x04")["plain"], [1, 2, 3, 4])


def test_columnar_mixed_layouts():
    rows = [{"x": 1.0, "ok": True, "k": 2}, {"x": 2.0}, {"ok": True, "k": 1}, {"x": 3.0, "ok": False, "k": 200},
            {"x": 4.0, "ok": True, "k": 3}, {"k": 5, "x": 6.0}]
    data = pw.encode(ALL, {"rows": rows})
    data += b"\x52\x0b\x09" + struct.pack("<d", 7.0) + b"\x78\x09"  # a row with an unknown varint field 15
    got = pw.decode(ALL, data)["rows"]
    assert got["x"].tolist() == [1.0, 2.0, 0.0, 3.0, 4.0, 6.0, 7.0]
    assert got["ok"].tolist() == [True, False, True, False, True, False, False]
    assert got["k"].tolist() == [2, 0, 1, 200, 3, 5, 0]


def test_decode_errors_name_the_field():
    bad = pw.encode(ALL, {"sub": {"x": 1.0}})[:-3]
    with pytest.raises(pw.DecodeError) as err:
        pw.decode(ALL, b"\x4a\x09" + bad[2:] + b"\x00")
    assert err.value.field.startswith("sub")
    with pytest.raises(pw.DecodeError) as err:
        pw.decode(ALL, b"\x0d\x00\x00\x00\x00")  # fixed32 wire type for an int32 field
    assert err.value.field == "a"
    with pytest.raises(pw.EncodeError):
        pw.encode(ALL, {"nope": 1})
    with pytest.raises(pw.EncodeError):
        pw.encode(ALL, {"a": 1 << 40})


# ------------------------------------------------------- Scene round trips
def _handmade(seed: int = 0):
    rng = np.random.default_rng(seed)
    n, t = 4, 12
    pos = np.cumsum(rng.normal(0, 1, (n, t, 2)), axis=1).astype(np.float32)
    valid = np.ones((n, t), bool)
    valid[1, :3] = False
    valid[2, 8:] = False
    lane = np.stack([np.linspace(0, 30, 7), np.zeros(7)], 1)
    scene = make_scene(
        pos, rng.uniform(-3, 3, (n, t)), log_valid=valid,
        agent_type=np.array([AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST, AgentType.OTHER]),
        length=np.array([4.5, 0.8, 1.9, 3.0]), width=np.array([2.0, 0.8, 0.7, 1.5]),
        roads=[(RoadType.LANE, lane), (RoadType.LANE, lane + [30, 0]), (RoadType.LANE, lane + [30, 4]),
               (RoadType.ROAD_LINE, lane + [0, 2]), (RoadType.ROAD_EDGE, lane - [0, 2]),
               (RoadType.STOP_SIGN, [[29.0, -1.0]]), (RoadType.CROSSWALK, [[28, -2], [28, 2], [26, 2], [26, -2]]),
               (RoadType.SPEED_BUMP, [[10, -2], [10, 2], [9, 2]]), (RoadType.DRIVEWAY, [[5, -3], [7, -3], [6, -5]])],
        lane_edges=np.array([[0, 1], [0, 2]]),
        scene_id=f"handmade-{seed}",
    )
    scene.road_id = scene.road_id + 100
    scene.origin = np.array([1234.25, -567.5])
    scene.is_sdc[0] = True
    scene.is_interest[[0, 3]] = True
    scene.tl_lane = np.array([101], np.int64)
    scene.tl_stop_point = np.array([[31.0, 0.0]], np.float32)
    scene.tl_state = rng.integers(0, 9, (t, 1)).astype(np.int8)
    return scene.validate()


def _assert_same(a, b, exact: bool):
    """Fields equal; positions compared in the world frame (origin added back)."""
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ("origin", "metadata"):
            continue
        if isinstance(x, np.ndarray):
            assert x.shape == y.shape and x.dtype == y.dtype, f.name
        if f.name in ("log_pos", "goal", "road_points", "tl_stop_point"):
            x, y = x.astype(np.float64) + a.origin, y.astype(np.float64) + b.origin
            if f.name == "log_pos":
                x, y = x[a.log_valid], y[b.log_valid]
        if isinstance(x, np.ndarray):
            if exact:
                assert np.array_equal(x, y), f.name
            else:
                np.testing.assert_allclose(x, y, atol=1e-4, rtol=0, err_msg=f.name)
        else:
            assert x == y, f.name


def test_real_scenes_round_trip_exactly(tmp_path):
    scenes = [load_gpudrive_json(p) for p in JSONS]
    path = tmp_path / "womd.tfrecord"
    assert write_tfrecord_scenes(path, scenes) == len(scenes)
    back = list(read_tfrecord_scenes(path))
    assert len(back) == len(scenes)
    for i, (a, b) in enumerate(zip(scenes, back)):
        assert np.array_equal(a.origin, b.origin)
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y), f.name
        assert a.scene_id == b.scene_id and a.dt == b.dt
        for key in ("sdc_track_index", "tracks_to_predict", "objects_of_interest", "road_subtype"):
            assert a.metadata[key] == b.metadata[key], key
        assert b.metadata["source"] == str(path) and b.metadata["record_index"] == i


def test_handmade_scene_round_trip(tmp_path):
    scene = _handmade()
    path = tmp_path / "hand.tfrecord"
    write_tfrecord_scenes(path, [scene])
    (back,) = read_tfrecord_scenes(path)
    _assert_same(scene, back, exact=False)
    assert np.array_equal(back.lane_edges, [[0, 1], [0, 2]])
    assert back.tl_state.shape == (12, 1) and np.array_equal(back.tl_state, scene.tl_state)
    # origin: chosen again from the positions, consistently with the JSON loader
    assert np.array_equal(back.origin, np.round(
        (scene.log_pos.astype(np.float64) + scene.origin)[scene.log_valid].mean(0)))
    # a second trip is exact: the origin is now the one the reader picks
    write_tfrecord_scenes(path, [back])
    (again,) = read_tfrecord_scenes(path)
    _assert_same(back, again, exact=True)


def test_scenario_dict_conventions():
    scene = _handmade()
    msg = scene_to_scenario(scene)
    assert [tr["object_type"] for tr in msg["tracks"]] == [1, 2, 3, 4]
    assert msg["sdc_track_index"] == 0
    assert [q["track_index"] for q in msg["tracks_to_predict"]] == [0, 3]
    lanes = [f for f in msg["map_features"] if "lane" in f]
    assert lanes[0]["lane"]["exit_lanes"].tolist() == [101, 102]
    assert lanes[1]["lane"]["entry_lanes"].tolist() == [100]
    stop = [f for f in msg["map_features"] if "stop_sign" in f][0]["stop_sign"]["position"]
    assert (stop["x"], stop["y"]) == (29.0 + 1234.25, -1.0 - 567.5)
    # goal = last valid step on the way back
    back = scenario_to_scene(pw.decode(SCENARIO, pw.encode(SCENARIO, msg)), "mem")
    last = [11, 11, 7, 11]
    np.testing.assert_allclose(back.goal + back.origin, scene.log_pos[range(4), last] + scene.origin, atol=1e-4)


def test_dict_form_definition():
    point = pw.Message("Pt", {1: ("x", "double"), 2: ("tags", "int32", True)})
    assert pw.decode(point, pw.encode(point, {"x": 1.0, "tags": [4, 5]}))["tags"].tolist() == [4, 5]


def test_conversion_errors_name_the_record(tmp_path):
    msg = scene_to_scenario(_handmade())
    msg["tracks"][2]["states"]["center_x"][4] = np.nan  # a valid step
    path = tmp_path / "nan.tfrecord"
    write_records(path, [pw.encode(SCENARIO, scene_to_scenario(_handmade(1))), pw.encode(SCENARIO, msg)])
    with pytest.raises(SceneError) as err:
        list(read_tfrecord_scenes(path))
    assert err.value.source == str(path) and err.value.field == "record[1].log_pos"
    assert "agent 2" in err.value.problem

    scene = _handmade()
    scene.agent_id[1] = 1 << 40  # Track.id is int32
    with pytest.raises(SceneError) as err:
        write_tfrecord_scenes(tmp_path / "big.tfrecord", [scene])
    assert err.value.field == "tracks[1].id" and "out of range" in err.value.problem
