"""Policy checkpoints at evaluation / render time: the slots follow the scenes (no agent of a
denser scene than the training ones is dropped), and the name "shipped" resolves to the policy
packaged at tg_gpudrive/policies/shipped.pt in one place (checkpoint.checkpoint_path)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

import tg_gpudrive.policies
from tg_gpudrive import checkpoint as ckpt_mod
from tg_gpudrive import cli
from tg_gpudrive.checkpoint import checkpoint_path, policy_engine_config
from tg_gpudrive.config import REPO_CONFIGS, TrainConfig, load_config
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.control import default_controlled
from tg_gpudrive.engine.model import agents_needed

DENSE = Path(__file__).parent / "data" / "womd_db4edc9bd0c9d18c.json"  # a real WOMD scene of 81 agents
SLOTS = 4  # the tiny policy's max_agents: fewer than DENSE's eligible vehicles (11) and procedural:merge's agents (8)


def tiny_config(tmp_path, **kw) -> TrainConfig:
    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    return dataclasses.replace(cfg, num_worlds=1, num_scenes=1, rollout_steps=4, epochs=1, minibatches=1,
                               hidden=16, quantiles=4, updates=1, prior="expert", cost_limit_mode="absolute",
                               out_dir=str(tmp_path), env=dataclasses.replace(cfg.env, max_agents=SLOTS), **kw)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A run directory holding an untrained policy checkpoint (Trainer.save) of max_agents=SLOTS."""
    from tg_gpudrive.learn.train import Trainer

    run = tmp_path_factory.mktemp("tiny_run")
    Trainer(tiny_config(run), run, progress=False).save()
    return run


@pytest.fixture(scope="module")
def dense_scene():
    sc = resolve_scenes(str(DENSE), n=None, seed=0).get(0)
    assert agents_needed(sc) == 81 > SLOTS
    return sc


def test_evaluate_gives_every_agent_of_a_dense_scene_a_slot(tiny_run, dense_scene, capsys):
    assert cli.main(["evaluate", "--checkpoint", str(tiny_run), "--scenes", str(DENSE), "--episodes", "1",
                     "--device", "cpu", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["agents_dropped"] == 0
    assert out["max_agents"] == 81
    env = tiny_config(tiny_run).env
    eligible, _ = default_controlled(dense_scene, np.arange(dense_scene.num_agents), env)
    assert out["agents_controlled"] == int(eligible.sum()) > SLOTS
    assert out["episodes"] > 0


def test_policy_engine_config_sizes_to_the_scenes(tmp_path, dense_scene, caplog):
    cfg = tiny_config(tmp_path)
    assert policy_engine_config(cfg, [dense_scene]).max_agents == 81
    roomy = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, max_agents=128))
    assert policy_engine_config(roomy, [dense_scene]) == roomy.env  # never fewer slots than trained with
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive"):
        per_slot = dataclasses.replace(cfg, heads=4)
        assert policy_engine_config(per_slot, [dense_scene]).max_agents == SLOTS
    assert "per-slot heads" in caplog.text and "dropped" in caplog.text


def test_shipped_resolves_to_the_packaged_file(tmp_path, monkeypatch):
    packaged = Path(tg_gpudrive.policies.__file__).resolve().parent / "shipped.pt"
    assert ckpt_mod.SHIPPED_POLICY == packaged
    fake = tmp_path / "shipped.pt"
    fake.write_bytes(b"")
    monkeypatch.setattr(ckpt_mod, "SHIPPED_POLICY", fake)
    assert checkpoint_path("shipped", "--checkpoint") == fake
    (tmp_path / "shipped").mkdir()  # a local directory of that name is reached as ./shipped
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError, match="no checkpoint at"):
        checkpoint_path("./shipped", "--checkpoint")


def test_earlier_shipped_policies_stay_loadable_by_name():
    """The policies shipped before the current one stay packaged, "shipped_v4" to "shipped_v1",
    each a file of its own that says what it started from (its config), so that a report's CCE-gap over an
    earlier fine-tuned run starts from the policy it really started from. The current one was trained from
    scratch with configs/train/real_mix.yaml, and says how."""
    current = ckpt_mod.load_checkpoint("shipped", "--checkpoint")
    assert current["config"]["init_policy"] == "" and "real_mix.yaml" in current["provenance"]
    for name, start, update in (("shipped_v4", "", 714), ("shipped_v3", "shipped_v2", 196),
                                ("shipped_v2", "shipped_v1", 161),
                                ("shipped_v1", "", 400)):
        path = checkpoint_path(name, "--checkpoint")
        assert path == ckpt_mod.SHIPPED_EARLIER[name] and path.is_file()
        assert path.read_bytes() != ckpt_mod.SHIPPED_POLICY.read_bytes()
        ck = ckpt_mod.load_checkpoint(name, "--checkpoint")
        assert ck["config"].get("init_policy", "") == start and ck["update"] == update


def test_shipped_policy_drives_held_out_scenes(capsys):
    """The packaged policy on 32 procedural scenes never trained on (seed 90000), every vehicle, sampled at its
    own temperature behind its own guard: the quality bar (goal >= 0.95, collision <= 0.05, off-road <= 0.02;
    0.993 / 0.000 / 0.007 on 64 scenes, README.md) with room for the smaller sample, and no agent dropped."""
    assert cli.main(["evaluate", "--checkpoint", "shipped", "--scenes", "procedural:all", "--seed", "90000",
                     "--num-scenes", "32", "--episodes", "32", "--device", "cpu", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["agent_episodes"] >= 400
    assert out["goal_rate"] >= 0.93 and out["collision_rate"] <= 0.05 and out["offroad_rate"] <= 0.02, out


def test_missing_shipped_policy_names_the_option(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(ckpt_mod, "SHIPPED_POLICY", tmp_path / "nope" / "shipped.pt")
    with pytest.raises(FileNotFoundError, match=r"--policy shipped: the packaged policy .*nope.* is missing"):
        checkpoint_path("shipped", "--policy")
    assert cli.main(["evaluate", "--checkpoint", "shipped", "--scenes", str(DENSE), "--device", "cpu",
                     "--json"]) == 2
    assert "--checkpoint shipped: the packaged policy" in capsys.readouterr().err
    assert cli.main(["render", "--policy", "shipped", "--scenes", str(DENSE), "--device", "cpu",
                     "--out", str(tmp_path / "f.png")]) == 2
    assert "--policy shipped: the packaged policy" in capsys.readouterr().err
    assert cli.main(["report", "--runs", "shipped", "--out", str(tmp_path / "report")]) == 2
    assert "--runs shipped: the packaged policy" in capsys.readouterr().err


def test_render_shipped_policy_keeps_every_agent(tiny_run, monkeypatch, tmp_path, caplog):
    monkeypatch.setattr(ckpt_mod, "SHIPPED_POLICY", tiny_run / "checkpoint.pt")
    out = tmp_path / "frame.png"
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive"):
        assert cli.main(["render", "--policy", "shipped", "--scenes", str(DENSE), "--device", "cpu",
                         "--steps", "2", "--size", "64", "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    assert "dropped" not in caplog.text


def test_report_runs_the_shipped_policy(tiny_run, monkeypatch, tmp_path, caplog):
    """`report --runs shipped`: the packaged checkpoint, its config from the checkpoint, every agent kept."""
    monkeypatch.setattr(ckpt_mod, "SHIPPED_POLICY", tiny_run / "checkpoint.pt")
    out = tmp_path / "report"
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive"):
        assert cli.main(["report", "--runs", "shipped", "--out", str(out), "--scenes", "1", "--seeds", "0", "1",
                         "--br-iters", "1", "--br-seeds", "0", "--top", "1", "--device", "cpu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert "shipped" in {r["label"] for r in summary["results"]}
    assert "dropped" not in caplog.text


def test_evaluate_repeats_with_its_seed(capsys):
    """A trained policy samples its actions: `--seed` fixes the draws, so the same command gives the
    same rates."""
    def rates(seed):
        assert cli.main(["evaluate", "--checkpoint", "shipped", "--scenes", "procedural:all", "--seed", str(seed),
                         "--num-scenes", "12", "--episodes", "12", "--device", "cpu", "--json"]) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        return [out[k] for k in ("goal_rate", "collision_rate", "offroad_rate", "mean_return")]

    assert rates(90000) == rates(90000)


def test_a_checkpoint_of_the_other_kind_is_a_one_line_error(capsys):
    """A world model given where a policy goes, and a policy where a world model goes, name both kinds."""
    from tg_gpudrive.worldmodel.prior import world_model_file

    wm = world_model_file("shipped")
    assert cli.main(["evaluate", "--checkpoint", str(wm), "--scenes", "procedural:merge", "--episodes", "1",
                     "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a world model checkpoint, expected a policy checkpoint" in err[0], err
    assert "--background-model" in err[0]
    policy = checkpoint_path("shipped", "--checkpoint")
    assert cli.main(["simulate", "--scenes", "procedural:merge", "--worlds", "1", "--device", "cpu",
                     "--control", "nearest_conflict", "--control-k", "1", "--background", "world_model",
                     "--background-model", str(policy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a policy checkpoint, expected a world model checkpoint" in err[0], err
