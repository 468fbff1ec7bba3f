"""Packed scene store: round trips, resumable conversion, bad inputs, crash recovery, corruption errors."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from tg_gpudrive.data import store as store_mod
from tg_gpudrive.data.store import StoreError, convert, open_store, write_store
from tg_gpudrive.scene import Scene, SceneError, make_scene
from tg_gpudrive.enums import RoadType

DATA = Path(__file__).parent / "data"
HAVE_JSON_LOADER = importlib.util.find_spec("tg_gpudrive.data.womd.gpudrive_json") is not None
HAVE_PROTO = importlib.util.find_spec("tg_gpudrive.data.womd.scenario_proto") is not None


# ------------------------------------------------------------------ helpers
def handmade(k: int, n: int = 3, t: int = 5, roads: int = 2, signals: int = 0) -> Scene:
    rng = np.random.default_rng(k)
    pos = np.cumsum(rng.normal(size=(n, t, 2)), axis=1).astype(np.float32)
    valid = np.ones((n, t), bool)
    valid[0, -1] = False  # one invalid step
    polys = [(RoadType.LANE if r % 2 == 0 else RoadType.ROAD_EDGE, rng.normal(size=(2 + r % 4, 2)))
             for r in range(roads)]
    edges = np.array([[r, r + 1] for r in range(roads - 1)], np.int32).reshape(-1, 2)
    s = make_scene(pos, rng.normal(size=(n, t)), log_valid=valid, roads=polys, lane_edges=edges,
                   dt=0.1 + 0.05 * (k % 2), scene_id=f"hand_{k}",
                   metadata={"scenario_type": "handmade", "k": k, "nested": {"a": [1, 2]}})
    s.is_sdc[0] = True
    s.is_interest[-1] = True
    s.origin = np.array([1000.5 + k, -20.25])
    if signals:
        s.tl_lane = np.arange(signals, dtype=np.int64)
        s.tl_stop_point = rng.normal(size=(signals, 2)).astype(np.float32)
        s.tl_state = rng.integers(0, 9, size=(t, signals)).astype(np.int8)
    return s.validate()


def assert_same(a: Scene, b: Scene) -> None:
    for f in dataclasses.fields(Scene):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), f.name
            assert x.dtype == y.dtype and x.shape == y.shape, (f.name, x.dtype, y.dtype, x.shape, y.shape)
            assert np.array_equal(x, y), f.name
        else:
            assert x == y, f.name


VARIED = [
    dict(n=1, t=2, roads=1),
    dict(n=3, t=5, roads=2, signals=2),
    dict(n=7, t=11, roads=0),
    dict(n=2, t=91, roads=9, signals=1),
    dict(n=5, t=3, roads=4),
]


@pytest.fixture
def fake_loader(monkeypatch):
    """Replace the real file loaders: a *.json file holds {"k": .., "n": .., "t": ..} or is corrupt."""
    calls = []

    def load(path):
        calls.append(Path(path).name)
        try:
            spec = json.loads(Path(path).read_text())
        except ValueError as e:
            raise SceneError(str(path), "json", f"not valid JSON ({e})") from e
        if spec.get("crash"):
            raise KeyboardInterrupt  # simulated kill mid-conversion
        return [handmade(spec["k"], n=spec.get("n", 3), t=spec.get("t", 5), signals=spec.get("s", 0))]

    monkeypatch.setattr(store_mod, "load_file", load)
    return calls


def write_fake(d: Path, k: int, **extra) -> Path:
    p = d / f"scene_{k:03d}.json"
    p.write_text(json.dumps({"k": k, "n": 1 + k % 4, "t": 3 + k % 5, "s": k % 3, **extra}))
    return p


# ------------------------------------------------------------- round trips
def test_round_trip_handmade(tmp_path):
    scenes = [handmade(k, **kw) for k, kw in enumerate(VARIED * 2)]
    rep = write_store(iter(scenes), tmp_path / "st", shard_size=3)
    assert rep.converted == len(scenes) and rep.num_scenes == len(scenes)
    st = open_store(tmp_path / "st")
    assert len(st) == len(scenes)
    assert st.scene_ids == [s.scene_id for s in scenes]
    assert len(list((tmp_path / "st").glob("shard_*"))) == 4
    for i, s in enumerate(scenes):
        assert_same(st[i], s)
        assert st.metadata(i) == s.metadata
        assert st.source(i) == "memory"
    assert_same(st[-1], scenes[-1])
    np.testing.assert_array_equal(st.num_agents, [s.num_agents for s in scenes])
    np.testing.assert_array_equal(st.num_steps, [s.num_steps for s in scenes])
    np.testing.assert_array_equal(st.num_road_points, [len(s.road_points) for s in scenes])
    view = st[1]
    assert not view.log_pos.flags.writeable
    copy = st.get(1, copy=True)
    copy.log_pos[:] = 0  # writable and detached
    assert_same(st[1], scenes[1])
    copy.validate()
    with pytest.raises(IndexError):
        st[len(scenes)]
    # a store-backed scene can be packed again (validation copies read-only views)
    write_store([st[3]], tmp_path / "again")
    assert_same(open_store(tmp_path / "again")[0], scenes[3])
    # workers re-map instead of copying
    st2 = pickle.loads(pickle.dumps(st))
    assert_same(st2[2], scenes[2])


def test_write_store_refuses_to_clobber(tmp_path):
    write_store([handmade(0)], tmp_path / "st")
    with pytest.raises(FileExistsError):
        write_store([handmade(1)], tmp_path / "st")
    write_store([handmade(1), handmade(2)], tmp_path / "st", overwrite=True)
    assert open_store(tmp_path / "st").scene_ids == ["hand_1", "hand_2"]


def test_empty_store(tmp_path):
    write_store([], tmp_path / "st")
    st = open_store(tmp_path / "st")
    assert len(st) == 0 and st.scene_ids == []


@pytest.mark.skipif(not HAVE_JSON_LOADER, reason="tg_gpudrive.data.womd.gpudrive_json not written yet")
def test_round_trip_real_json(tmp_path):
    from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json

    files = sorted(DATA.glob("*.json"))
    rep = convert([DATA], tmp_path / "st", progress=False)
    assert rep.failed == [] and rep.converted == len(files)
    st = open_store(tmp_path / "st")
    for i, f in enumerate(files):
        ref = load_gpudrive_json(f)
        got = st[i]
        ref_meta = json.loads(json.dumps(ref.metadata, default=store_mod._json_default))
        assert got.metadata == ref_meta
        assert_same(dataclasses.replace(got, metadata={}), dataclasses.replace(ref, metadata={}))
        assert st.source(i) == str(f.resolve())


@pytest.mark.skipif(not HAVE_JSON_LOADER, reason="tg_gpudrive.data.womd.gpudrive_json not written yet")
def test_real_corrupt_json_listed(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for f in DATA.glob("*.json"):
        shutil.copy(f, src / f.name)
    (src / "broken.json").write_text('{"objects": [')
    rep = convert([src], tmp_path / "st", progress=False, workers=2)  # also: parsing in worker processes
    assert rep.converted == 2
    assert [Path(p).name for p, _ in rep.failed] == ["broken.json"]
    assert "broken.json" in rep.failed[0][1]
    st = open_store(tmp_path / "st")
    assert [st.source(i) for i in range(2)] == [str(f.resolve()) for f in sorted(src.glob("womd_*.json"))]


@pytest.mark.skipif(not HAVE_PROTO, reason="tg_gpudrive.data.womd.scenario_proto not written yet")
def test_tfrecord_round_trip_and_truncated_shard(tmp_path):
    from tg_gpudrive.data.womd.scenario_proto import read_tfrecord_scenes, write_tfrecord_scenes

    src = tmp_path / "in"
    src.mkdir()
    good = src / "training.tfrecord-00000-of-00002"
    write_tfrecord_scenes(good, [handmade(k, n=2 + k, t=6, roads=3, signals=k % 2) for k in range(3)])
    bad = src / "training.tfrecord-00001-of-00002"
    bad.write_bytes(good.read_bytes()[:-5])
    rep = convert([src], tmp_path / "st", progress=False)
    assert rep.converted == 3 and [Path(p).name for p, _ in rep.failed] == [bad.name]
    st = open_store(tmp_path / "st")
    for i, ref in enumerate(read_tfrecord_scenes(good)):
        assert_same(st[i], ref)
        assert st.source(i) == str(good.resolve())


# ---------------------------------------------------------------- convert
def test_resume_skips_done_files(tmp_path, fake_loader):
    src = tmp_path / "in"
    src.mkdir()
    first = [write_fake(src, k) for k in range(3)]
    rep = convert([src], tmp_path / "st", progress=False, shard_size=2)
    assert (rep.converted, rep.skipped_existing, rep.failed) == (3, 0, [])
    write_fake(src, 3)
    (src / "sub").mkdir()
    write_fake(src / "sub", 4)
    fake_loader.clear()
    rep = convert([src, first[0]], tmp_path / "st", progress=False, shard_size=2)
    assert (rep.converted, rep.skipped_existing, rep.num_scenes) == (2, 3, 5)
    assert sorted(fake_loader) == ["scene_003.json", "scene_004.json"]
    st = open_store(tmp_path / "st")
    assert st.scene_ids == [f"hand_{k}" for k in range(5)]
    assert_same(st[4], handmade(4, n=1, t=7, signals=1))
    assert st.source(4) == str((src / "sub" / "scene_004.json").resolve())
    # resume=False starts over
    rep = convert([first[0]], tmp_path / "st", progress=False, resume=False)
    assert rep.num_scenes == 1 and len(open_store(tmp_path / "st")) == 1


def test_bad_files_reported_and_skipped(tmp_path, fake_loader):
    src = tmp_path / "in"
    src.mkdir()
    for k in range(3):
        write_fake(src, k)
    (src / "scene_001b.json").write_text("{not json")
    (src / "notes.txt").write_text("ignored by directory expansion")
    write_store([handmade(7)], src / "old_store")  # a store's own JSON files are not inputs
    missing = tmp_path / "nope.json"
    odd = tmp_path / "data.bin"
    odd.write_bytes(b"\0")
    rep = convert([src, missing], tmp_path / "st", progress=False)
    assert rep.converted == 3 and rep.converted_files == 3
    reasons = dict(rep.failed)
    assert set(reasons) == {str((src / "scene_001b.json").resolve()), str(missing.resolve())}
    assert "not valid JSON" in reasons[str((src / "scene_001b.json").resolve())]
    assert "no such file" in reasons[str(missing.resolve())]
    text = (tmp_path / "st" / "failed.txt").read_text()
    assert "scene_001b.json\t" in text and "nope.json" in text
    assert open_store(tmp_path / "st").scene_ids == [f"hand_{k}" for k in range(3)]
    # unknown file types named explicitly are reported, not fatal
    rep = convert([odd], tmp_path / "st", progress=False)
    assert "unknown scene file type" in rep.failed[0][1]
    # failed files are retried on resume, done ones are not
    (src / "scene_001b.json").write_text(json.dumps({"k": 9}))
    rep = convert([src], tmp_path / "st", progress=False)
    assert (rep.converted, rep.skipped_existing, rep.failed) == (1, 3, [])
    assert (tmp_path / "st" / "failed.txt").read_text() == ""


def test_crash_mid_shard_then_resume(tmp_path, fake_loader):
    src = tmp_path / "in"
    src.mkdir()
    for k in range(5):
        write_fake(src, k)
    write_fake(src, 5, crash=True)
    out = tmp_path / "st"
    with pytest.raises(KeyboardInterrupt):
        convert([src], out, progress=False, shard_size=2)
    # shard_00000 (files 0,1) and shard_00001 (files 2,3) committed; file 4 was only buffered
    # leave debris as a kill inside _write_shard / before the manifest update would
    (out / "shard_00002.tmp").mkdir()
    (out / "shard_00002.tmp" / "log_pos.npy").write_bytes(b"\x93NUMPY partial")
    shutil.copytree(out / "shard_00001", out / "shard_00002")
    (out / "manifest.json.tmp").write_text("{half a manif")
    st = open_store(out)
    assert st.scene_ids == [f"hand_{k}" for k in range(4)]
    write_fake(src, 5)  # the crashing input is fine now
    fake_loader.clear()
    rep = convert([src], out, progress=False, shard_size=2)
    assert (rep.converted, rep.skipped_existing) == (2, 4)
    assert sorted(fake_loader) == ["scene_004.json", "scene_005.json"]
    st = open_store(out)
    assert st.scene_ids == [f"hand_{k}" for k in range(6)]
    assert not (out / "shard_00002.tmp").exists()


@pytest.mark.skipif(importlib.util.find_spec("tg_gpudrive.data.simplify") is None,
                    reason="tg_gpudrive.data.simplify not written yet")
def test_simplify_tolerance(tmp_path, fake_loader):
    from tg_gpudrive.data.simplify import simplify_scene

    x = np.linspace(0, 50, 101)
    s = make_scene(np.zeros((1, 3, 2)), np.zeros((1, 3)), scene_id="simp",
                   roads=[(RoadType.ROAD_EDGE, np.stack([x, 0.001 * np.sin(x)], -1)),
                          (RoadType.LANE, np.stack([10 * np.cos(x / 20), 10 * np.sin(x / 20)], -1))])
    ref = simplify_scene(s, 0.05)[0]
    assert len(ref.road_points) < len(s.road_points)
    write_store([s], tmp_path / "st", simplify_tolerance=0.05)
    st = open_store(tmp_path / "st")
    assert st.simplify_tolerance == 0.05
    assert_same(st[0], ref)
    # a resumed conversion must not mix tolerances
    with pytest.raises(ValueError, match="simplify_tolerance"):
        convert([], tmp_path / "st", progress=False)
    src = tmp_path / "in"
    src.mkdir()
    write_fake(src, 2)
    convert([src], tmp_path / "st", progress=False, simplify_tolerance=0.05)
    assert open_store(tmp_path / "st")[1].metadata["simplify"]["tolerance"] == 0.05


# ------------------------------------------------------------- bad stores
def test_bad_store_errors_name_path_and_file(tmp_path):
    with pytest.raises(StoreError, match="no such directory"):
        open_store(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(StoreError, match="manifest.json"):
        open_store(tmp_path / "empty")
    write_store([handmade(k) for k in range(3)], tmp_path / "st")
    f = tmp_path / "st" / "shard_00000" / "road_points.npy"
    f.write_bytes(f.read_bytes()[:-8])
    with pytest.raises(StoreError, match=r"st: shard_00000/road_points\.npy"):
        open_store(tmp_path / "st")
    f.unlink()
    with pytest.raises(StoreError, match=r"road_points\.npy: missing"):
        open_store(tmp_path / "st")
    (tmp_path / "st" / "manifest.json").write_text("{")
    with pytest.raises(StoreError, match="manifest.json: unreadable"):
        open_store(tmp_path / "st")


def test_convert_stores_a_scene_id_once_and_counts_the_duplicates(tmp_path):
    store = tmp_path / "store"
    first = convert([DATA / "womd_1c365f15b70ebdbf.json"], store, progress=False)
    assert first.converted == 1 and first.duplicates == []
    again = tmp_path / "again"
    again.mkdir()
    copy = again / "renamed.json"  # the same scenario under another name: a new input, the same scene id
    copy.write_bytes((DATA / "womd_1c365f15b70ebdbf.json").read_bytes())
    (again / "other.json").write_bytes((DATA / "womd_db4edc9bd0c9d18c.json").read_bytes())
    rep = convert([again], store, progress=False)
    assert rep.converted == 1 and [sid for _, sid in rep.duplicates] == [open_store(store)[0].scene_id]
    assert rep.duplicates[0][0] == str(copy) and rep.num_scenes == 2
    ids = open_store(store).scene_ids
    assert len(ids) == len(set(ids)) == 2
