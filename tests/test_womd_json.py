"""GPUDrive processed-JSON loader: real WOMD scenes load faithfully, broken files fail by name."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from tg_gpudrive.data.womd.gpudrive_json import SENTINEL, load_gpudrive_json
from tg_gpudrive.scene import SceneError
from tg_gpudrive.enums import AgentType, RoadType

DATA = pathlib.Path(__file__).parent / "data"
SCENES = {
    # file: (agents, polylines, {agent type: count})
    "womd_1c365f15b70ebdbf.json": (25, 118, {AgentType.VEHICLE: 23, AgentType.PEDESTRIAN: 2}),
    "womd_db4edc9bd0c9d18c.json": (81, 102, {AgentType.VEHICLE: 68, AgentType.PEDESTRIAN: 12, AgentType.CYCLIST: 1}),
}


@pytest.fixture(scope="module", params=sorted(SCENES))
def loaded(request):
    path = DATA / request.param
    raw = json.loads(path.read_text())
    return request.param, raw, load_gpudrive_json(path)


def test_counts(loaded):
    name, raw, scene = loaded
    n_agents, n_roads, types = SCENES[name]
    assert scene.num_agents == n_agents == len(raw["objects"])
    assert scene.num_steps == 91
    assert scene.num_polylines == n_roads
    assert len(scene.road_points) == sum(len(r["geometry"]) for r in raw["roads"])
    assert np.array_equal(np.diff(scene.road_offsets), [len(r["geometry"]) for r in raw["roads"]])
    got = {AgentType(t): int(c) for t, c in zip(*np.unique(scene.agent_type, return_counts=True))}
    assert got == types
    assert scene.scene_id == raw["scenario_id"]
    assert scene.metadata["source"] == str(DATA / name)
    assert scene.metadata["scenario_type"] == "womd"
    assert scene.metadata["name"] == raw["name"]


def test_trajectories_match_file(loaded):
    _, raw, scene = loaded
    assert scene.origin.dtype == np.float64
    for i, o in enumerate(raw["objects"]):
        valid = np.array(o["valid"], bool)
        assert np.array_equal(scene.log_valid[i], valid)
        xy = np.array([[p["x"], p["y"]] for p in o["position"]])[valid]
        np.testing.assert_allclose(scene.log_pos[i][valid], xy - scene.origin, atol=1e-4)
        vel = np.array([[v["x"], v["y"]] for v in o["velocity"]])[valid]
        np.testing.assert_allclose(scene.log_vel[i][valid], vel, atol=1e-5)
        np.testing.assert_allclose(scene.log_yaw[i][valid], np.array(o["heading"])[valid], atol=1e-6)
        g = o["goalPosition"]
        np.testing.assert_allclose(scene.goal[i], np.array([g["x"], g["y"]]) - scene.origin, atol=1e-4)
        assert scene.agent_id[i] == o["id"]
        assert scene.length[i] == pytest.approx(o["length"]) and scene.width[i] == pytest.approx(o["width"])
    first = raw["roads"][0]["geometry"][0]
    np.testing.assert_allclose(scene.road_points[0], np.array([first["x"], first["y"]]) - scene.origin, atol=1e-4)
    assert [RoadType(t).name.lower() for t in scene.road_type] == [r["type"] for r in raw["roads"]]
    assert scene.road_id.tolist() == [r["id"] for r in raw["roads"]]


def test_no_sentinel_survives(loaded):
    _, _, scene = loaded
    for arr in (scene.log_pos, scene.log_vel, scene.log_yaw, scene.goal, scene.road_points, scene.tl_stop_point):
        assert np.isfinite(arr).all()
        assert not (arr == SENTINEL).any()
        assert (np.abs(arr) < 1000).all()  # origin removed: everything is near the agents
    assert (~scene.log_valid).any()  # the files do contain invalid steps, now only masked
    assert (scene.log_pos[~scene.log_valid] == 0).all()


def test_sdc_and_interest(loaded):
    _, raw, scene = loaded
    meta = raw["metadata"]
    assert np.nonzero(scene.is_sdc)[0].tolist() == [meta["sdc_track_index"]]
    want = {t["track_index"] for t in meta["tracks_to_predict"]}
    want |= {i for i, o in enumerate(raw["objects"]) if o["id"] in meta["objects_of_interest"]}
    assert set(np.nonzero(scene.is_interest)[0].tolist()) == want
    assert scene.tl_state.shape == (91, 0)  # both files have tl_states {}


def test_traffic_lights_kept(tmp_path):
    raw = json.loads((DATA / "womd_1c365f15b70ebdbf.json").read_text())
    raw["tl_states"] = {
        "77": {"state": ["stop", "go", "caution"], "x": [4340.0] * 3, "y": [700.0] * 3, "z": [0.0] * 3,
               "time_index": [0, 1, 5]},
        "bad": {"state": ["go"]},
    }
    path = tmp_path / "tl.json"
    path.write_text(json.dumps(raw))
    scene = load_gpudrive_json(path)
    assert scene.tl_lane.tolist() == [77]
    np.testing.assert_allclose(scene.tl_stop_point[0], np.array([4340.0, 700.0]) - scene.origin)
    assert scene.tl_state[[0, 1, 5, 2], 0].tolist() == [4, 6, 5, 0]
    assert scene.metadata["tl_dropped"] == 1


# ---------------------------------------------------------------- broken files
def _raw():
    return json.loads((DATA / "womd_1c365f15b70ebdbf.json").read_text())


def _expect_error(tmp_path, text: str, field: str, problem: str):
    path = tmp_path / "broken.json"
    path.write_text(text)
    with pytest.raises(SceneError) as err:
        load_gpudrive_json(path)
    msg = str(err.value)
    assert str(path) in msg and f"'{field}'" in msg, msg
    assert err.value.source == str(path) and err.value.field == field
    assert problem in err.value.problem, msg


def test_corrupt_json(tmp_path):
    text = (DATA / "womd_1c365f15b70ebdbf.json").read_text()
    _expect_error(tmp_path, text[: len(text) // 2], "json", "invalid JSON")


def test_missing_key(tmp_path):
    raw = _raw()
    del raw["objects"][0]["heading"]
    _expect_error(tmp_path, json.dumps(raw), "objects[0].heading", "missing key")


def test_nan_position(tmp_path):
    raw = _raw()
    raw["objects"][3]["position"][17]["x"] = float("nan")
    _expect_error(tmp_path, json.dumps(raw), "objects[3].position[17].x", "non-finite")


def test_wrong_type(tmp_path):
    raw = _raw()
    raw["objects"][2]["width"] = "wide"
    _expect_error(tmp_path, json.dumps(raw), "objects[2].width", "expected a number")
    raw = _raw()
    raw["roads"][5]["geometry"][1] = [1.0, 2.0]
    _expect_error(tmp_path, json.dumps(raw), "roads[5].geometry[1]", "expected an object")


def test_inconsistent_steps(tmp_path):
    raw = _raw()
    raw["objects"][4]["velocity"].pop()
    _expect_error(tmp_path, json.dumps(raw), "objects[4].velocity", "expected 91 steps")


def test_unknown_road_type(tmp_path):
    raw = _raw()
    raw["roads"][0]["type"] = "bridge"
    _expect_error(tmp_path, json.dumps(raw), "roads[0].type", "unknown road type")


def test_empty_objects(tmp_path):
    raw = _raw()
    raw["objects"] = []
    _expect_error(tmp_path, json.dumps(raw), "objects", "no agents")


def test_all_invalid(tmp_path):
    raw = _raw()
    for o in raw["objects"]:
        o["valid"] = [False] * len(o["valid"])
    _expect_error(tmp_path, json.dumps(raw), "objects[*].valid", "no object has a single valid step")


def test_not_an_object(tmp_path):
    _expect_error(tmp_path, "[1, 2, 3]", "json", "expected a JSON object")


# ---------------------------------------------------------- older revisions
def _older_revision(raw: dict) -> dict:
    """`raw` as GPUDrive's and Nocturne's older files have it: no height, no object or road ids, no
    mark_as_expert, headings in degrees (the sentinel kept as it is)."""
    for o in raw["objects"]:
        for key in ("height", "id", "mark_as_expert"):
            o.pop(key, None)
        o["heading"] = [h if h == SENTINEL else float(np.degrees(h)) for h in o["heading"]]
    for r in raw["roads"]:
        r.pop("id", None)
    return raw


@pytest.mark.parametrize("name", sorted(SCENES))
def test_older_revision_loads_as_the_current_one(tmp_path, name):
    raw = json.loads((DATA / name).read_text())
    new = load_gpudrive_json(DATA / name)
    path = tmp_path / name
    path.write_text(json.dumps(_older_revision(raw)))
    old = load_gpudrive_json(path)
    np.testing.assert_allclose(old.log_yaw, new.log_yaw, atol=1e-5)
    np.testing.assert_array_equal(old.log_pos, new.log_pos)
    n, r = new.num_agents, new.num_polylines
    assert old.metadata["defaults"] == {"objects.height": n, "objects.id": n, "roads.id": r, "objects.heading": "degrees"}
    assert new.metadata["defaults"] == {}
    assert old.agent_id.tolist() == list(range(n)) and old.road_id.tolist() == list(range(r))
    vehicles = old.agent_type == AgentType.VEHICLE
    assert (old.height[vehicles] == 1.6).all()


def test_heading_unit_rule():
    from tg_gpudrive.data.womd.gpudrive_json import heading_unit

    t = np.arange(20)
    vel = np.zeros((1, 20, 2))
    vel[..., 0] = 10.0  # driving east: heading 0
    valid = np.ones((1, 20), bool)
    assert heading_unit(np.full((1, 20), 0.01), vel, valid) == "radians"
    assert heading_unit(np.full((1, 20), 7.0), vel, valid) == "degrees"  # beyond 2 pi: certain
    vel[..., 0], vel[..., 1] = np.cos(np.radians(5.0)) * 10, np.sin(np.radians(5.0)) * 10
    assert heading_unit(np.full((1, 20), 5.0), vel, valid) == "degrees"  # 5 degrees north of east: motion decides
    assert heading_unit(np.full((1, 20), np.radians(5.0)), vel, valid) == "radians"
    assert heading_unit(np.full((1, 20), 5.0), np.zeros((1, 20, 2)), valid) == "radians"  # parked: undecided
    del t


def test_placeholder_road_kinds_are_dropped_and_counted(tmp_path):
    raw = _raw()
    raw["roads"][0]["type"] = "unknown"
    path = tmp_path / "old.json"
    path.write_text(json.dumps(raw))
    sc = load_gpudrive_json(path)
    assert sc.num_polylines == len(raw["roads"]) - 1 and sc.metadata["defaults"] == {"roads.type": 1}


def test_a_scene_too_short_to_play_is_skipped_and_counted(tmp_path):
    from tg_gpudrive.data.sources import resolve_scenes, source_report

    raw = _raw()
    for o in raw["objects"]:
        for key in ("position", "velocity", "heading", "valid"):
            o[key] = o[key][:11]
    raw["scenario_id"] = "short"  # another scenario than full.json's (convert stores a scene id once)
    (tmp_path / "short.json").write_text(json.dumps(raw))
    with pytest.raises(ValueError, match="short.json.*too short to play"):
        resolve_scenes(str(tmp_path / "short.json"))  # alone: an error naming the file
    (tmp_path / "full.json").write_text((DATA / "womd_1c365f15b70ebdbf.json").read_text())
    src = resolve_scenes(str(tmp_path))
    assert len(src) == 1 and source_report(src) == {"scene_files_skipped": 0, "scenes_unplayable": 1}
    mix = resolve_scenes(f"mix:procedural:all=0.5,{tmp_path}=0.5", n=8)
    assert source_report(mix)["scenes_unplayable"] == 1
    assert all(mix.get(i).num_steps == 91 for i in range(len(mix)))  # it never fills a world
    from tg_gpudrive.data.store import convert

    report = convert([tmp_path], tmp_path / "store", progress=False)
    assert report.converted == 2 and [r[1:] for r in report.unplayable] == [(raw["scenario_id"], report.unplayable[0][2])]
    assert "too short to play" in report.unplayable[0][2]
    store = resolve_scenes(str(tmp_path / "store"))
    assert len(store) == 1 and source_report(store)["scenes_unplayable"] == 1


def test_builtin_and_trained_policies_drop_no_agent_and_write_per_scene_rates(tmp_path, capsys):
    from tg_gpudrive import cli

    csv_path = tmp_path / "scenes.csv"
    common = ["--scenes", str(DATA), "--episodes", "2", "--device", "cpu", "--json", "--per-scene", str(csv_path)]
    for who in (["--policy", "expert", "--set", "max_agents=8"], ["--policy", "constant", "--set", "max_agents=8"],
                ["--checkpoint", "shipped"]):
        assert cli.main(["evaluate", *who, *common]) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert out["agents_dropped"] == 0 and out["max_agents"] >= 81, who
        assert set(out["ci95"]) == {"goal_rate", "collision_rate", "offroad_rate", "score_rate"}
        rows = csv_path.read_text().strip().splitlines()
        assert len(rows) == 3 and rows[0].startswith("collision_mode,scene_id,source,agents,agent_episodes,goal_rate")
        assert sum(int(r.split(",")[4]) for r in rows[1:]) == out["agent_episodes"]
        # real scenes: the expert replay of the same worlds, under the same rule, beside the policy
        assert ("expert_replay" in out) == (who[1] != "expert")
        if who[1] != "expert":
            assert out["expert_replay"]["episodes"] == out["agent_episodes"]
            assert out["expert_replay"]["goal_rate"] >= 0.97 and out["expert_replay"]["collision_rate"] == 0
