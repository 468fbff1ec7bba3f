"""open_policy, the one recipe for a policy in worlds: who it drives is decided once, the same for
evaluate, render, the report, heldout_eval and the trainer's held-out check."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tg_gpudrive import cli
from tg_gpudrive.agents import open_policy
from tg_gpudrive.config import REPO_CONFIGS, EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.control import control_masks, eligible
from tg_gpudrive.engine.model import agents_needed

SMALL = REPO_CONFIGS / "train" / "small_cpu.yaml"


@pytest.fixture(scope="module")
def scenes():
    src = resolve_scenes("procedural:dual_lane_intersection", n=2, seed=90000)
    return [src.get(i) for i in range(2)]


@pytest.fixture(scope="module")
def nearest_run(tmp_path_factory):
    """A tiny run trained to drive the single vehicle nearest each conflict point."""
    run = tmp_path_factory.mktemp("agents") / "run"
    assert cli.main(["train", "--config", str(SMALL), "--out", str(run), "--set", "updates=1", "--set",
                     "num_worlds=2", "--set", "num_scenes=2", "--set", "rollout_steps=4", "--set", "hidden=16",
                     "--set", "quantiles=4", "--set", "control=nearest_conflict", "--set", "control_k=1"]) == 0
    return run


def test_a_builtin_policy_drives_every_eligible_vehicle_with_a_slot_for_every_agent(scenes):
    opened = open_policy("constant", scenes, "cpu", engine=EngineConfig(max_agents=2))
    assert opened.trained is None and opened.masks is None and opened.background is None
    assert opened.sim.max_agents >= max(agents_needed(s) for s in scenes)  # max_agents=2 grown, none dropped
    assert int(opened.sim.policy_agents.sum()) == sum(int(eligible(s, opened.sim.cfg).sum()) for s in scenes)


def test_a_trained_policy_drives_whom_it_was_trained_to_unless_told(scenes, nearest_run):
    own = open_policy(str(nearest_run), scenes, "cpu")
    want = control_masks(scenes, own.sim.cfg, "nearest_conflict", 1)
    assert all(np.array_equal(a, b) for a, b in zip(own.masks, want))
    told = open_policy(str(nearest_run), scenes, "cpu", control="vehicles")
    assert int(told.sim.policy_agents.sum()) > int(own.sim.policy_agents.sum())


def test_evaluate_uses_the_runs_control(nearest_run, capsys):
    args = ["evaluate", "--checkpoint", str(nearest_run), "--scenes", "procedural:dual_lane_intersection",
            "--seed", "90000", "--episodes", "2", "--json"]
    assert cli.main(args) == 0
    own = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert cli.main([*args, "--control", "vehicles"]) == 0
    every = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert own["control"] == "nearest_conflict" and every["control"] == "vehicles"
    assert own["agents_controlled"] < every["agents_controlled"]
