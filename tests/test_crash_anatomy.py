"""scripts/crash_anatomy.py: its grouping of first collisions against hand-made events, and a run on the
two real WOMD test scenes that gives each colliding vehicle its row."""

from __future__ import annotations

import importlib.util
from pathlib import Path

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "crash_anatomy.py"
spec = importlib.util.spec_from_file_location("crash_anatomy", SCRIPT)
crash_anatomy = importlib.util.module_from_spec(spec)
spec.loader.exec_module(crash_anatomy)


def event(run, episode, agent, partner_policy, partner_type, standing, contact, speed, partner_speed, step, partner=0):
    return {"run": run, "episode": episode, "agent": agent, "partner": partner, "partner_policy": partner_policy,
            "partner_type": partner_type, "partner_standing": standing, "contact": contact, "speed": speed,
            "partner_speed": partner_speed, "step": step}


def test_group_counts_runs_and_ranges_most_recurrent_first():
    events = [
        event(("a", 0), 9, 18, False, "pedestrian", False, "crossing", 1.5, 2.9, 16),
        event(("a", 0), 4, 14, True, "vehicle", False, "ahead", 11.7, 3.2, 45, partner=9),
        event(("a", 1), 4, 14, True, "vehicle", False, "ahead", 12.3, 3.0, 46, partner=9),
        event(("b", 0), 4, 14, True, "vehicle", False, "crossing", 11.9, 4.2, 30, partner=5),
        event(("b", 0), 15, 35, False, "vehicle", True, "ahead", 6.8, 0.0, 21),
    ]
    rows = crash_anatomy.group(events)
    assert [(r["world"], r["agent"], r["runs"]) for r in rows] == [(4, 14, 3), (9, 18, 1), (15, 35, 1)]
    top = rows[0]
    assert top["partner"] == "policy vehicle" and top["contact"] == "ahead"
    assert top["speed"] == (11.7, 12.3) and top["partner_speed"] == (3.0, 4.2) and top["steps"] == (30, 46)
    assert top["partner_agent"] == 9  # the commonest partner of the three runs
    assert rows[1]["partner"] == "replayed pedestrian"
    assert rows[2]["partner"] == "replayed standing vehicle"


def test_script_prints_a_row_per_colliding_vehicle(capsys):
    data = Path(__file__).resolve().parent / "data"
    assert crash_anatomy.main(["--policies", "constant", "--scenes", str(data), "--seeds", "0"]) == 0
    out = capsys.readouterr().out
    n = int(out.split(" first collisions")[0].split()[-1])
    table = [ln for ln in out.splitlines() if ln.startswith("| ") and not ln.startswith("| world")]
    # the constant policy runs into someone in these scenes; with one run each vehicle's first
    # collision is one row, recurring in 1 of 1 runs
    assert n > 0 and len(table) == n
    assert all("| 1 of 1 |" in ln for ln in table)


def test_approach_follows_a_pair_from_the_logged_start():
    """--approach on a real WOMD test scene: at the first step the gap is the two logs' distance at the
    start step, the speeds are the logs', the partner's place in the agent's frame is the logs' offset turned by
    the agent's logged heading, and the agent's nearest neighbour is among its observed partner rows; a bad pair
    is refused with its name."""
    import numpy as np
    import pytest

    from tg_gpudrive.agents import open_policy
    from tg_gpudrive.data.sources import resolve_scenes

    src = resolve_scenes(str(Path(__file__).resolve().parent / "data"))
    scenes = [src.get(i) for i in range(len(src))]
    opened = open_policy("constant", scenes, "cpu", collision_mode="ignore", seed=0, option="--policies")
    sim, sc = opened.sim, scenes[0]
    t0 = int(sim.model.init_step)
    slot_agent = np.asarray(sim.model.slot_agent)[0]
    a = int(slot_agent[np.flatnonzero(sim.policy_agents[0].cpu().numpy())[0]])
    here = np.flatnonzero(sc.log_valid[:, t0])
    others = here[here != a]
    d = np.linalg.norm(sc.log_pos[others, t0] - sc.log_pos[a, t0], axis=-1)
    b = int(others[np.argmin(d)])
    rows = crash_anatomy.approach(sim, opened.policy, 0, [(0, a, b)])[(0, a, b)]
    first = rows[0]
    assert first["step"] == 0 and first["gap"] == pytest.approx(d.min(), abs=1e-3) and first["seen"]
    assert first["speed"] == pytest.approx(np.linalg.norm(sc.log_vel[a, t0]), abs=1e-3)
    assert first["partner_speed"] == pytest.approx(np.linalg.norm(sc.log_vel[b, t0]), abs=1e-3)
    # the partner's place in the agent's frame: the logs' offset turned by minus the agent's logged heading
    yaw = sc.log_yaw[a, t0]
    dx, dy = sc.log_pos[b, t0] - sc.log_pos[a, t0]
    assert first["ahead"] == pytest.approx(dx * np.cos(yaw) + dy * np.sin(yaw), abs=1e-2)
    assert first["left"] == pytest.approx(dy * np.cos(yaw) - dx * np.sin(yaw), abs=1e-2)
    assert np.hypot(first["ahead"], first["left"]) == pytest.approx(first["gap"], abs=1e-3)
    with pytest.raises(SystemExit, match="no world 7"):
        crash_anatomy.approach(sim, opened.policy, 0, [(7, a, b)])
