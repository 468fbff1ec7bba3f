"""Scenes through the engine: the expert drives every procedural type and the real WOMD scenes
cleanly, random driving does not; the simulate and convert commands report what they did."""

from __future__ import annotations

import json

import numpy as np

import pytest
from conftest import WOMD_FILES

from tg_gpudrive import cli
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.procedural import SCENARIO_TYPES, ProceduralParams, generate_scene
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.agents.builtin import builtin_policy, expert_policy
from tg_gpudrive.rollout import run_rollout
from tg_gpudrive.engine.simulator import Simulator

SEEDS = (0, 1, 2)
CFG = EngineConfig(max_agents=32, road_k=16, partner_k=4)


@pytest.fixture(scope="module")
def procedural_sims():
    return {t: Simulator([generate_scene(t, s) for s in SEEDS], CFG, "cpu") for t in SCENARIO_TYPES}


@pytest.mark.parametrize("scenario", SCENARIO_TYPES)
def test_expert_drives_every_procedural_type_cleanly(procedural_sims, scenario):
    sim = procedural_sims[scenario]
    out = run_rollout(sim, expert_policy, sim.episode_length)
    assert out["episodes"] == int(sim.policy_agents.sum()) >= 2 * len(SEEDS)
    assert out["goal_rate"] >= 0.95 and out["collision_rate"] <= 0.01 and out["offroad_rate"] <= 0.01, out


@pytest.mark.parametrize("scenario", SCENARIO_TYPES)
def test_random_policy_crashes_or_leaves_the_road(procedural_sims, scenario):
    sim = procedural_sims[scenario]
    out = run_rollout(sim, builtin_policy("random", 0, "cpu"), sim.episode_length)
    assert out["collision_rate"] + out["offroad_rate"] >= 0.3, out
    assert out["goal_rate"] <= 0.5, out


def test_rates_count_each_worlds_first_episodes_only(procedural_sims):
    """With `episodes_per_world` a world whose episodes end early (random driving crashes at once) adds no
    extra episodes: the rates are those of each world's first N episodes, counted here by hand."""
    sim = procedural_sims["merge"]
    steps, cap = 3 * sim.episode_length, 2
    free = run_rollout(sim, builtin_policy("random", 0, "cpu"), steps)
    capped = run_rollout(sim, builtin_policy("random", 0, "cpu"), steps, episodes_per_world=cap)
    sim.reset()
    policy, seen = builtin_policy("random", 0, "cpu"), np.zeros(sim.num_worlds, int)
    n = goal = collided = offroad = 0
    for _ in range(steps):
        policy(sim)
        sim.step()
        for w in np.flatnonzero(sim.world_ended.cpu().numpy()):
            seen[w] += 1
            if seen[w] <= cap:
                rows = sim.policy_agents[w].cpu().numpy()
                n += int(rows.sum())
                goal += int(sim.final_goal[w].cpu().numpy()[rows].sum())
                collided += int(sim.final_collided[w].cpu().numpy()[rows].sum())
                offroad += int(sim.final_offroad[w].cpu().numpy()[rows].sum())
    assert (seen >= cap).all() and seen.max() > cap  # every world finished its quota; some ended more often
    assert free["episodes"] > capped["episodes"] == n == cap * int(sim.policy_agents.sum())
    assert capped["goal_rate"] == pytest.approx(goal / n)
    assert capped["collision_rate"] == pytest.approx(collided / n)
    assert capped["offroad_rate"] == pytest.approx(offroad / n)


def test_expert_replay_on_real_womd_scenes():
    """All 13 controlled vehicles of the two real scenes (valid at step 10 and not parked at their
    goal; 2 + 11) reach their goal with no collision and no off-road. The scenes' other agents are
    parked cars (scene 1c36...: 21 of 23 vehicles start within 2 m of their goal), pedestrians and a
    cyclist, which replay their logs. The closed-loop expert coasts over gaps in a log (agent 65 of
    db4e... misses step 13) and re-tracks after them."""
    for f in WOMD_FILES:
        sim = Simulator([load_gpudrive_json(f)], EngineConfig(max_agents=128), "cpu")
        out = run_rollout(sim, expert_policy, sim.episode_length)
        assert out["goal_rate"] == 1.0 and out["collision_rate"] == 0.0 and out["offroad_rate"] == 0.0, (f, out)
    assert [int(Simulator([load_gpudrive_json(f)], EngineConfig(max_agents=128), "cpu").policy_agents.sum())
            for f in WOMD_FILES] == [2, 11]


def test_simulate_json(capsys):
    assert cli.main(["simulate", "--scenes", "procedural:all", "--worlds", "6", "--steps", "20", "--policy",
                     "constant", "--collision-mode", "stop", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("worlds", "agents_controlled", "steps", "agent_steps_per_s", "goal_rate", "collision_rate",
                "offroad_rate", "device"):
        assert key in out
    assert out["worlds"] == 6 and out["steps"] == 20 and out["collision_mode"] == "stop"
    assert set(out["per_type"]) == set(SCENARIO_TYPES)
    assert cli.main(["simulate", "--scenes", "procedural:nope"]) == 2
    assert "unknown scenario type 'nope'" in capsys.readouterr().err


def test_convert_keeps_going_and_lists_bad_files(tmp_path, capsys):
    good = tmp_path / "in"
    good.mkdir()
    for f in WOMD_FILES:
        (good / f.name).write_text(f.read_text())
    (good / "broken.json").write_text(WOMD_FILES[0].read_text()[:5000])
    (good / "empty.json").write_text(json.dumps({"objects": [], "roads": []}))
    assert cli.main(["convert", str(good), "--out", str(tmp_path / "store")]) == 0
    report = capsys.readouterr().out
    assert '"converted": 2' in report and "broken.json" in report
    failed = (tmp_path / "store" / "failed.txt").read_text()
    assert "broken.json" in failed and "empty.json" in failed and "objects" in failed
    from tg_gpudrive.data.store import open_store

    store = open_store(tmp_path / "store")
    assert len(store) == 2
    sim = Simulator([store[0], store[1]], EngineConfig(max_agents=128), "cpu")
    assert run_rollout(sim, expert_policy, sim.episode_length)["goal_rate"] == 1.0


@pytest.mark.parametrize("flag", [["--steps", "-5"], ["--steps", "0"], ["--num-scenes", "0"], ["--worlds", "0"]])
def test_counts_must_be_positive(flag, capsys):
    from tg_gpudrive import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["simulate", "--scenes", "procedural:merge", "--device", "cpu", *flag])
    assert e.value.code == 2 and "expected a positive integer" in capsys.readouterr().err


def test_convert_where_every_file_failed_is_an_error(tmp_path, capsys):
    from tg_gpudrive import cli

    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.json").write_text("{not json")
    assert cli.main(["convert", str(tmp_path / "in"), "--out", str(tmp_path / "store")]) == 2
    assert "every input failed" in capsys.readouterr().err


@pytest.mark.parametrize("field", ["log_pos", "goal", "roads.geometry"])
def test_a_coordinate_far_from_the_scene_is_a_field_error(field):
    """One coordinate of 1e30 (float32 still holds it) once gave collision and off-road 1.0 for
    every agent without a word; now it is a SceneError naming the field."""
    from tg_gpudrive.scene import SceneError

    sc = generate_scene("merge", 0)
    if field == "log_pos":
        sc.log_pos[0, np.nonzero(sc.log_valid[0])[0][0], 0] = 1e30
    elif field == "goal":
        sc.goal[0, 1] = -1e30
    else:
        sc.road_points[3, 0] = 1e30
    with pytest.raises(SceneError, match=field.replace(".", r"\.")):
        sc.validate()


def test_a_bad_file_in_a_directory_is_skipped_and_counted_when_the_source_opens(tmp_path, capsys):
    """One broken JSON and one truncated TFRecord among good files: the source opens without them
    (they are listed in `skipped`), simulate reports the count, and training that resamples every
    update never meets them."""
    import shutil

    from tg_gpudrive.config import TrainConfig, load_config, REPO_CONFIGS
    from tg_gpudrive.data.sources import resolve_scenes
    from tg_gpudrive.learn.train import Trainer

    for f in WOMD_FILES:
        shutil.copy(f, tmp_path)
    (tmp_path / "broken.json").write_text('{"objects": [')
    (tmp_path / "cut.tfrecord.gz").write_bytes(b"\x1f\x8b\x08\x00garbage")
    src = resolve_scenes(str(tmp_path))
    assert len(src) == len(WOMD_FILES) and sorted(p.rsplit("/", 1)[1] for p, _ in src.skipped) == \
        ["broken.json", "cut.tfrecord.gz"]
    assert cli.main(["simulate", "--scenes", str(tmp_path), "--worlds", "3", "--steps", "2", "--device", "cpu",
                     "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["scene_files_skipped"] == 2
    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml",
                      [f"scenes={tmp_path}", "num_worlds=2", "updates=2", "resample_every=1", "rollout_steps=4",
                       "hidden=16", "quantiles=4", "epochs=1", "minibatches=1", f"out_dir={tmp_path / 'run'}",
                       "env.max_agents=128"])
    assert Trainer(cfg, progress=False).train()["scene_files_skipped"] == 2
    (tmp_path / "a.json").unlink(missing_ok=True)
    for f in WOMD_FILES:
        (tmp_path / f.name).unlink()
    with pytest.raises(ValueError, match="no scene loads"):
        resolve_scenes(str(tmp_path))


@pytest.mark.parametrize("content", [b"\x1f\x8b\x08\x00\x00\x00", b""])
def test_simulate_on_a_broken_tfrecord_is_a_one_line_error(tmp_path, capsys, content):
    bad = tmp_path / "cut.tfrecord.gz"
    bad.write_bytes(content)
    assert cli.main(["simulate", "--scenes", str(bad), "--worlds", "1", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len([line for line in err if "error" in line]) == 1 and str(bad) in err[-1]


def test_expert_reaches_kerb_stops_and_the_rates_count_them_apart():
    """Urban procedural scenes (parked cars, stop lines, kerb stops): the expert still drives them
    cleanly, kerbside goals included, and the rates carry a separate line for the kerb stops, whose
    agent-episodes are exactly the policy agents the scenes mark; the constant policy, which keeps
    its speed and heading, reaches few of them (2 of 12 here: those already turning in at step 10)."""
    params = ProceduralParams(parking=0.8, stop_lines=0.5, kerb_stops=1.0)
    scenes = [generate_scene(t, s, params) for t in ("t_junction", "dense_intersection") for s in (0, 1, 2)]
    cfg = EngineConfig(max_agents=64, road_k=16, partner_k=4)
    sim = Simulator(scenes, cfg, "cpu")
    marked = sum(np.isin(np.asarray(sim.model.slot_agent[w]), sc.metadata["kerb_stops"]).sum()
                 for w, sc in enumerate(scenes))
    assert marked >= 3
    out = run_rollout(sim, expert_policy, sim.episode_length)
    assert out["kerb_stops"]["episodes"] == marked and out["kerb_stops"]["goal_rate"] >= 0.9, out["kerb_stops"]
    assert out["goal_rate"] >= 0.95 and out["collision_rate"] <= 0.01 and out["offroad_rate"] <= 0.01, out
    const = run_rollout(sim, builtin_policy("constant", 0, "cpu"), sim.episode_length)
    assert const["kerb_stops"]["episodes"] == marked and const["kerb_stops"]["goal_rate"] <= 0.3
    plain = run_rollout(Simulator([generate_scene("t_junction", 0)], cfg, "cpu"), expert_policy, 80)
    assert "kerb_stops" not in plain
