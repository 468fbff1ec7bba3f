"""ScenarioNet / MetaDrive scenario pickles: a real WOMD scene loads faithfully and drives, hostile or
broken pickles fail by name without running anything, and the format works as a scene source."""

from __future__ import annotations

import collections
import json
import os
import pickle
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tg_gpudrive import cli
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import MixedSource, resolve_scenes
from tg_gpudrive.data.store import convert, expand_inputs, load_file, open_store
from tg_gpudrive.data.womd.scenarionet import load_pickle, load_scenarionet
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout
from tg_gpudrive.scene import SceneError
from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

# outside tests/data: directory specs of tests/data count its scenes
DATA = Path(__file__).parent / "data_scenarionet"
SD = DATA / "sd_training.tfrecord-00000-of-01000_2a1e44d405a6833f.pkl"
SUMMARY = DATA / "dataset_summary.pkl"


class _Reference(pickle.Unpickler):
    """The test's own reader of the fixture: NumPy's reconstruction and nothing else."""

    def find_class(self, module, name):
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return np.dtype
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            from numpy._core.multiarray import _reconstruct

            return _reconstruct
        raise pickle.UnpicklingError(f"{module}.{name}")


def reference(path: Path = SD) -> dict:
    with open(path, "rb") as f:
        return _Reference(f).load()


@pytest.fixture(scope="module")
def raw():
    return reference()


@pytest.fixture(scope="module")
def scene():
    return load_scenarionet(SD)


def write(path: Path, obj, protocol: int = 4) -> Path:
    path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return path


def expect_error(path: Path, field: str, problem: str) -> SceneError:
    with pytest.raises(SceneError) as err:
        load_scenarionet(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg, msg
    assert err.value.field == field and problem in err.value.problem, msg
    return err.value


# ------------------------------------------------------------------ the real scene
def test_real_scene_matches_the_pickle(raw, scene):
    tracks, meta = raw["tracks"], raw["metadata"]
    keys = list(tracks)
    assert scene.scene_id == raw["id"] == "2a1e44d405a6833f"
    assert scene.num_agents == len(keys) == 211 and scene.num_steps == raw["length"] == 91
    assert scene.dt == pytest.approx(0.1) and scene.origin.dtype == np.float64
    assert scene.agent_id.tolist() == [int(k) for k in keys]
    for i, k in enumerate(keys):
        st = tracks[k]["state"]
        valid = np.asarray(st["valid"], bool)
        assert np.array_equal(scene.log_valid[i], valid), k
        np.testing.assert_allclose(scene.log_pos[i][valid], st["position"][valid, :2] - scene.origin, atol=1e-3)
        np.testing.assert_allclose(scene.log_yaw[i][valid], st["heading"][valid], atol=1e-6)
        np.testing.assert_allclose(scene.log_vel[i][valid], st["velocity"][valid], atol=1e-6)
        for name in ("length", "width", "height"):
            assert getattr(scene, name)[i] == pytest.approx(np.median(st[name][valid]), abs=1e-5), (k, name)
        last = np.nonzero(valid)[0][-1]
        np.testing.assert_allclose(scene.goal[i], st["position"][last, :2] - scene.origin, atol=1e-3)
    types = collections.Counter(AgentType(t).name for t in scene.agent_type)
    assert types == collections.Counter(t["type"] for t in tracks.values()) == {
        "VEHICLE": 184, "PEDESTRIAN": 25, "CYCLIST": 2}
    assert np.nonzero(scene.is_sdc)[0].tolist() == [keys.index(meta["sdc_id"])] == [meta["sdc_track_index"]]
    want = {keys.index(k) for k in meta["tracks_to_predict"]} | {keys.index(k) for k in meta["objects_of_interest"]}
    assert set(np.nonzero(scene.is_interest)[0].tolist()) == want
    assert scene.metadata["scenario_type"] == "womd" and scene.metadata["mark_as_expert"] == []
    assert scene.metadata["source"] == str(SD)


def test_real_map_matches_the_pickle(raw, scene):
    feats = raw["map_features"]
    kind = {"LANE": RoadType.LANE, "ROAD_LINE": RoadType.ROAD_LINE, "ROAD_EDGE": RoadType.ROAD_EDGE,
            "STOP_SIGN": RoadType.STOP_SIGN, "CROSSWALK": RoadType.CROSSWALK, "SPEED_BUMP": RoadType.SPEED_BUMP,
            "DRIVEWAY": RoadType.DRIVEWAY}
    want = collections.Counter(next(v for p, v in kind.items() if f["type"].startswith(p)) for f in feats.values())
    assert collections.Counter(RoadType(t) for t in scene.road_type) == want
    assert want == {RoadType.LANE: 182, RoadType.ROAD_LINE: 66, RoadType.ROAD_EDGE: 51, RoadType.DRIVEWAY: 37,
                    RoadType.CROSSWALK: 16, RoadType.STOP_SIGN: 4, RoadType.SPEED_BUMP: 2}
    assert scene.road_id.tolist() == [int(k) for k in feats]
    for r, (k, f) in enumerate(feats.items()):
        pts = f["position"][None, :2] if f["type"] == "STOP_SIGN" else f.get("polyline", f.get("polygon"))[:, :2]
        np.testing.assert_allclose(scene.polyline(r), pts - scene.origin, atol=1e-3, err_msg=k)
    subtype = dict(zip(scene.road_id.tolist(), scene.metadata["road_subtype"]))
    assert subtype[144] == 2  # LANE_SURFACE_STREET: WOMD LaneCenter.TYPE_SURFACE_STREET
    assert subtype[4] == 7  # ROAD_LINE_SOLID_DOUBLE_YELLOW
    assert subtype[11] == 2  # ROAD_EDGE_MEDIAN
    lanes = {k: r for r, k in enumerate(feats) if f"{feats[k]['type']}".startswith("LANE")}
    edges = {(lanes[str(j)], lanes[k]) for k in lanes for j in feats[k]["entry_lanes"] if str(j) in lanes}
    edges |= {(lanes[k], lanes[str(j)]) for k in lanes for j in feats[k]["exit_lanes"] if str(j) in lanes}
    assert set(map(tuple, scene.lane_edges.tolist())) == edges and len(edges) == 200


def test_real_traffic_lights_match_the_pickle(raw, scene):
    dyn = raw["dynamic_map_states"]
    assert scene.tl_lane.tolist() == [d["lane"] for d in dyn.values()]
    for l, d in enumerate(dyn.values()):
        np.testing.assert_allclose(scene.tl_stop_point[l], d["stop_point"][:2] - scene.origin, atol=1e-3)
        names = [s.removeprefix("LANE_STATE_") for s in d["state"]["object_state"]]
        assert scene.tl_state[:, l].tolist() == [int(TrafficLightState[s]) for s in names]
    assert (scene.tl_state == int(TrafficLightState.STOP)).any() and scene.metadata["tl_dropped"] == 0


def test_expert_drives_the_real_scene(scene):
    """All 14 controlled vehicles (valid at the start and away from their goal) reach it; none collides
    or leaves the road (max_agents 256 keeps all 211 tracks, so nobody is dropped)."""
    sim = Simulator([scene], EngineConfig(max_agents=256), "cpu")
    assert sim.report()["agents_dropped"] == 0
    out = run_rollout(sim, expert_policy, sim.episode_length)
    assert out["episodes"] == int(sim.policy_agents.sum()) >= 10
    assert out["goal_rate"] >= 0.9 and out["collision_rate"] <= 0.05 and out["offroad_rate"] <= 0.05, out


# ------------------------------------------------------------------ hostile pickles
class _Call:
    """Pickles as a call of `func(*args)` (then `__setstate__(state)`): what a hostile file would hold."""

    def __init__(self, func, *args, state=None):
        self.func, self.args, self.state = func, args, state

    def __reduce__(self):
        return (self.func, self.args) if self.state is None else (self.func, self.args, self.state)


def _one_line_refusal(path: Path, name: str) -> None:
    with pytest.raises(SceneError) as err:
        load_scenarionet(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and f"refused to load global '{name}'" in msg, msg
    assert "plain data and NumPy arrays" in msg and err.value.field == "pickle"


def test_hostile_globals_are_refused_and_never_run(tmp_path):
    marker = tmp_path / "pwned"
    crafted = tmp_path / "sd_crafted.pkl"  # os.system spelt out, as a hand-written exploit does
    crafted.write_bytes(b"cos\nsystem\n(S'touch " + str(marker).encode() + b"'\ntR.")
    _one_line_refusal(crafted, "os.system")
    cases = [
        (_Call(os.system, f"touch {marker}"), f"{os.system.__module__}.system"),  # posix.system here
        (_Call(eval, f"open({str(marker)!r}, 'w').write('x')"), "builtins.eval"),
        (_Call(subprocess.Popen, ["touch", str(marker)]), "subprocess.Popen"),
        (_Call(shutil.rmtree, str(tmp_path / "nothing")), "shutil.rmtree"),
    ]
    for k, (payload, name) in enumerate(cases):
        # the payload hides deep inside an otherwise ordinary scenario
        path = write(tmp_path / f"sd_{k}.pkl", {"id": "x", "tracks": {}, "metadata": {"nested": [1, {"a": payload}]}})
        _one_line_refusal(path, name)
    assert not marker.exists()


def test_numpy_reconstruction_cannot_forge_objects(tmp_path):
    """NumPy's own globals would let a dtype state declare an object field without the object flag and
    an array read raw bytes as object pointers; the loader builds only plain dtypes itself."""
    from numpy._core.multiarray import _reconstruct

    target = "a real object"  # a pointer that would not crash the test if the loader let it through
    pointer = id(target).to_bytes(8, "little")
    # flags 0: "no objects here", over a field of objects
    field = _Call(np.dtype, "V8", False, True, state=(3, "|", None, ("a",), {"a": (np.dtype("O"), 0)}, 8, 1, 0))
    plain = _Call(np.dtype, "O8", False, True, state=(3, "|", None, None, None, -1, -1, 0))
    for dtype, why in ((field, "not a plain scalar type"), (plain, "object array needs a list")):
        array = _Call(_reconstruct, np.ndarray, (0,), b"b", state=(1, (1,), dtype, False, pointer))
        path = write(tmp_path / "sd_forged.pkl", {"tracks": {"1": array}})
        with pytest.raises(SceneError) as err:
            load_scenarionet(path)
        assert "\n" not in str(err.value) and why in str(err.value), str(err.value)
    obj = write(tmp_path / "sd_obj.pkl", {"a": np.array([1, "two"], dtype=object)})
    assert load_pickle(obj)["a"].tolist() == [1, "two"]  # object arrays from their item lists still load


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_plain_data_round_trips_at_every_protocol(tmp_path, protocol):
    data = {
        "f32": np.arange(6, dtype=np.float32).reshape(2, 3), "big": np.arange(4, dtype=">i4"),
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)), "strided": np.arange(10.0)[::3],
        "bool": np.array([True, False]), "str": np.array(["ab", "c"]), "bytes": np.array([b"x"]),
        "c": np.array([1 + 2j]), "scalars": [np.float32(1.5), np.int64(7), np.bool_(True)],
        "empty": np.zeros((0, 3), np.float32), "permuted": np.arange(24.0).reshape(2, 3, 4).transpose(1, 0, 2),
        "set": {1, 2}, "frozen": frozenset({"a"}), "z": 3 - 1j,
        "od": collections.OrderedDict(b=1, a=2), "ba": bytearray(b"xy"), "objects": np.array([None, [1]], object),
    }
    got = load_pickle(write(tmp_path / "sd_plain.pkl", data, protocol))
    for k, v in data.items():
        if isinstance(v, np.ndarray):
            assert got[k].dtype == v.dtype and got[k].shape == v.shape and got[k].tolist() == v.tolist(), k
        else:
            assert got[k] == v and type(got[k]) in (type(v), dict), k
    assert list(got["od"]) == ["b", "a"] and type(got["scalars"][0]) is np.float32


# ------------------------------------------------------------------ broken files
def test_truncated_and_foreign_files_fail_by_name(tmp_path):
    cases = {"sd_truncated.pkl": SD.read_bytes()[: 500_000], "sd_text.pkl": b"hello, not a pickle\n",
             "sd_empty.pkl": b"", "sd_json.pkl": b'{"tracks": {}}'}
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        err = expect_error(path, "pickle", "not a readable pickle")
        assert len(str(err)) < 300, str(err)


def test_dataset_index_files_are_not_scenes(tmp_path):
    expect_error(SUMMARY, "file",
                 "a ScenarioNet dataset summary, not a scene: pass the sd_*.pkl files or the directory")
    renamed = tmp_path / "index.pkl"
    shutil.copy(SUMMARY, renamed)  # recognised by its content too
    expect_error(renamed, "file", "dataset summary, not a scene")
    mapping = write(tmp_path / "dataset_mapping.pkl", {SD.name: ""})
    expect_error(mapping, "file", "a ScenarioNet dataset mapping, not a scene")
    with pytest.raises(SceneError, match="dataset summary"):
        load_file(SUMMARY)


def _broken(tmp_path: Path, edit) -> Path:
    raw = reference()
    edit(raw)
    return write(tmp_path / "sd_broken.pkl", raw)


@pytest.mark.parametrize("edit, field, problem", [
    (lambda r: r["tracks"]["325"]["state"].pop("heading"), "tracks['325'].state.heading", "missing key"),
    (lambda r: r["tracks"]["332"]["state"]["position"].__setitem__((17, 0), np.nan),
     "tracks['332'].state.position", "non-finite value at valid step 17"),
    (lambda r: r["tracks"]["333"]["state"].__setitem__("velocity", np.zeros((90, 2))),
     "tracks['333'].state.velocity", "expected shape (91, 2) or (91, 3)"),
    (lambda r: r["tracks"]["333"]["state"].__setitem__("valid", "yes"), "tracks['333'].state.valid",
     "expected a numeric array, got str"),
    (lambda r: r["tracks"]["332"]["state"]["length"].__setitem__(slice(None), 0.0), "tracks['332'].state.length",
     "must be positive"),
    (lambda r: r["tracks"]["332"].__setitem__("type", 3), "tracks['332'].type", "expected a string"),
    (lambda r: r.__setitem__("tracks", {}), "tracks", "no tracks"),
    (lambda r: r.pop("map_features"), "map_features", "missing key"),
    (lambda r: r["map_features"]["144"].pop("type"), "map_features['144'].type", "missing key"),
    (lambda r: r["map_features"]["144"].pop("polyline"), "map_features['144'].polyline", "missing key"),
    (lambda r: r["map_features"]["377"]["polygon"].__setitem__((2, 1), np.inf), "map_features['377'].polygon",
     "non-finite value at point 2"),
    (lambda r: r["map_features"]["144"].__setitem__("exit_lanes", 5), "map_features['144'].exit_lanes",
     "expected a list of lane ids"),
    (lambda r: r["metadata"].__setitem__("sdc_id", "999999"), "metadata.sdc_id", "not in tracks"),
    (lambda r: r["metadata"]["tracks_to_predict"]["333"].__setitem__("track_id", "1"),
     "metadata.tracks_to_predict['333']", "not in tracks"),
    (lambda r: r.__setitem__("length", 90), "length", "says 90 steps"),
])
def test_structural_problems_name_the_field(tmp_path, edit, field, problem):
    expect_error(_broken(tmp_path, edit), field, problem)


def test_top_level_must_be_a_dict(tmp_path):
    expect_error(write(tmp_path / "sd_list.pkl", [1, 2]), "pickle", "expected a dict at the top level")


def test_tolerated_variants(tmp_path):
    """Auxiliary oddities are dropped and counted; id and shape variants load."""
    def edit(r):
        r["map_features"]["9001"] = {"type": "GUARDRAIL", "polyline": np.zeros((2, 3))}
        r["map_features"]["9002"] = {"type": "CROSSWALK", "polygon": np.zeros((0, 3))}
        r["map_features"]["9003"] = {"type": "UNKNOWN", "polyline": np.ones((2, 2))}
        square = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]) + [2900, -3300, 0]
        r["map_features"]["9004"] = {"type": "ROAD_EDGE_SIDEWALK", "polygon": square}
        r["map_features"]["9005"] = {"type": "CROSSWALK", "polygon": np.concatenate([square, square[:1]])}
        r["dynamic_map_states"]["226"]["state"]["object_state"] = 7  # unreadable: dropped
        r["dynamic_map_states"]["227"]["state"]["object_state"][:3] = [None, "TRAFFIC_LIGHT_GREEN", 5]
        r["tracks"]["325"]["state"]["heading"] = r["tracks"]["325"]["state"]["heading"][:, None]
        r["tracks"]["325"]["state"]["valid"] = r["tracks"]["325"]["state"]["valid"].astype(np.float32)
        del r["tracks"]["327"]["state"]["height"]

    s = load_scenarionet(_broken(tmp_path, edit))
    meta = s.metadata
    assert meta["dropped_feature_types"] == ["GUARDRAIL"] and meta["dropped_empty_roads"] == 1
    assert meta["defaults"] == {"map_features.type": 1, "map_features.UNKNOWN": 1, "tracks.height": 1}
    ids = s.road_id.tolist()
    assert s.road_type[ids.index(9003)] == RoadType.ROAD_EDGE
    sidewalk, crosswalk = s.polyline(ids.index(9004)), s.polyline(ids.index(9005))
    assert s.road_type[ids.index(9004)] == RoadType.ROAD_EDGE and len(sidewalk) == 5  # an edge: closed
    assert (sidewalk[0] == sidewalk[-1]).all() and len(crosswalk) == 4  # a polygon: stored open
    assert meta["tl_dropped"] == 1 and 226 not in s.tl_lane.tolist()
    col = s.tl_lane.tolist().index(227)
    assert s.tl_state[:3, col].tolist() == [0, int(TrafficLightState.GO), int(TrafficLightState.CAUTION)]
    assert s.log_valid[0].sum() == 3 and s.height[1] == pytest.approx(1.5)

    def rename(r):  # nuScenes-style token ids
        r["tracks"] = {f"tok{k}": v for k, v in r["tracks"].items()}
        r["metadata"]["sdc_id"] = "tok1629"
        r["metadata"]["objects_of_interest"] = ["tok490"]
        r["metadata"]["tracks_to_predict"] = {}

    s = load_scenarionet(_broken(tmp_path, rename))
    assert s.agent_id.tolist() == list(range(211)) and s.metadata["track_ids"][:2] == ["tok325", "tok327"]
    assert s.is_sdc[210] and np.nonzero(s.is_interest)[0].tolist() == [49]


# ------------------------------------------------------------------ as a scene source
def test_directory_and_mix_specs():
    assert expand_inputs([DATA]) == [SD.resolve()]  # the summary is an index, not a scene
    src = resolve_scenes(str(DATA))
    assert len(src) == 1 and src.get(0).scene_id == "2a1e44d405a6833f"
    assert len(resolve_scenes(str(SD))) == 1
    mix = resolve_scenes(f"mix:procedural:all=0.5,{DATA}=0.5", n=4, seed=0)
    assert isinstance(mix, MixedSource) and mix.counts == [3, 1]
    kinds = collections.Counter(sc.metadata["scenario_type"] for sc in mix.get_many(range(len(mix))))
    assert kinds["womd"] == mix.slots[1] and sum(kinds.values()) == len(mix)


def test_convert_and_store_round_trip(tmp_path, scene):
    rep = convert([DATA], tmp_path / "store", progress=False)
    assert rep.converted == 1 and rep.failed == [] and rep.converted_files == 1
    got = open_store(tmp_path / "store")[0]
    for name in ("log_pos", "log_yaw", "log_vel", "log_valid", "length", "width", "agent_id", "agent_type",
                 "goal", "is_sdc", "is_interest", "road_points", "road_offsets", "road_type", "road_id",
                 "lane_edges", "tl_lane", "tl_stop_point", "tl_state", "origin"):
        assert np.array_equal(getattr(got, name), getattr(scene, name)), name
    assert got.scene_id == scene.scene_id and got.dt == scene.dt
    assert got.metadata["road_subtype"] == scene.metadata["road_subtype"]
    direct = convert([SUMMARY], tmp_path / "store2", progress=False)  # named directly: a clear failure
    assert direct.converted == 0 and "dataset summary, not a scene" in direct.failed[0][1]


def test_cli_simulate(capsys):
    assert cli.main(["simulate", "--scenes", str(DATA), "--worlds", "1", "--device", "cpu", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["worlds"] == 1 and out["agents_controlled"] > 0
