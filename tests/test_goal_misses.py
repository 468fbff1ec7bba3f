"""scripts/goal_misses.py: its summary against hand-made outcomes, and a run on the two real WOMD test scenes
whose rates (timeouts included) match `evaluate`'s and whose clean misses all end outside the goal radius."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "goal_misses.py"
spec = importlib.util.spec_from_file_location("goal_misses", SCRIPT)
goal_misses = importlib.util.module_from_spec(spec)
spec.loader.exec_module(goal_misses)
DATA = Path(__file__).resolve().parent / "data"


def row(goal=False, collided=False, offroad=False, left=0.0, speed=0.0):
    return {"goal": goal, "collided": collided, "offroad": offroad, "left": left, "speed": speed}


def test_summary_counts_clean_misses_and_how_far_short_they_end():
    rows = [row(goal=True), row(goal=True, collided=True), row(offroad=True, left=9.0),
            row(left=3.0, speed=6.0), row(left=4.0, speed=8.0), row(left=12.0, speed=4.0)]
    s = goal_misses.summary(rows)
    assert s["episodes"] == 6
    assert (s["goal"], s["collision"], s["offroad"]) == (2 / 6, 1 / 6, 1 / 6)
    assert s["clean_miss"] == 3 / 6  # the off-road vehicle is not a clean miss
    assert s["left_median"] == 4.0 and s["near_share"] == pytest.approx(2 / 3)
    assert s["speed_median"] == 6.0 and s["short_s"] == 0.5  # 3/6, 4/8 and 12/4 s: median 0.5
    assert math.isnan(goal_misses.summary([row(goal=True)])["near_share"])


def test_outcomes_on_real_scenes_match_evaluate_and_misses_end_outside_the_goal_radius(capsys):
    import json

    from tg_gpudrive import cli
    from tg_gpudrive.agents import open_policy
    from tg_gpudrive.data.sources import resolve_scenes

    src = resolve_scenes(str(DATA))
    scenes = [src.get(i) for i in range(len(src))]
    for spec_, clean in (("expert", False), ("constant", True)):
        opened = open_policy(spec_, scenes, "cpu", collision_mode="ignore", seed=0, auto_reset=False)
        rows = goal_misses.outcomes(opened.sim, opened.policy, 0)
        s = goal_misses.summary(rows)
        assert cli.main(["evaluate", "--policy", spec_, "--scenes", str(DATA), "--episodes", str(len(scenes)),
                         "--seed", "0", "--device", "cpu", "--collision-mode", "ignore", "--json"]) == 0
        ref = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert s["episodes"] == ref["agent_episodes"]
        for k, rk in (("goal", "goal_rate"), ("collision", "collision_rate"), ("offroad", "offroad_rate")):
            assert s[k] == pytest.approx(ref[rk])
        assert s["clean_miss"] == pytest.approx(ref["timeout_rate"])  # evaluate's name for a clean miss
        radius = opened.sim.cfg.goal_radius
        misses = [r for r in rows if not (r["goal"] or r["collided"] or r["offroad"])]
        assert all(r["left"] > radius for r in misses)
        assert bool(misses) == clean  # the constant policy stops short of some goals, the logs never do
