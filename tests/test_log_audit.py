"""The rule of which agents count: log-infeasible agents (hand-made cases), agreement with the engine's
own collision and off-road flags on real WOMD scenes, the expert replay under the rule, unplayable scenes."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np
import pytest

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.log_audit import audit, candidates, infeasible_mask, unplayable
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.engine import control
from tg_gpudrive.engine.model import agents_needed
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout
from tg_gpudrive.scene import make_scene
from tg_gpudrive.enums import AgentType, RoadType

DATA = pathlib.Path(__file__).parent / "data"
T = 40


def drive(x0, y0, vx, vy=0.0, yaw=None, steps=T):
    """(steps, 2) positions of a constant-velocity log and its (steps,) heading."""
    t = np.arange(steps) * 0.1
    pos = np.stack([x0 + vx * t, y0 + vy * t], -1)
    return pos, np.full(steps, np.arctan2(vy, vx) if yaw is None else yaw)


def scene_of(*tracks, roads=(), types=AgentType.VEHICLE):
    pos = np.stack([p for p, _ in tracks])
    yaw = np.stack([y for _, y in tracks])
    return make_scene(pos, yaw, roads=list(roads), agent_type=types)


def reasons(scene, init=10, radius=2.0):
    return audit(scene, init, radius)


def test_clean_logs_are_feasible():
    sc = scene_of(drive(0, 0, 10), drive(0, 10, 10), roads=[(RoadType.ROAD_EDGE, [[-50, 5], [100, 5]])])
    assert reasons(sc) == {}


def test_overlapping_logs_flag_both_vehicles_and_a_vehicle_over_a_pedestrian():
    sc = scene_of(drive(0, 0, 10), drive(3, 0.5, 10), drive(30, 20, 10))  # 3 m apart: 4.5 m boxes overlap
    assert reasons(sc) == {0: ["overlap"], 1: ["overlap"]}
    walker = scene_of(drive(0, 0, 10), drive(12, 0.5, 0, 0, yaw=0.0), types=np.array([1, 2]))  # met at step 12
    assert reasons(walker) == {0: ["overlap"]}  # pedestrians are never the policy's: only the vehicle is audited


def test_boxes_that_only_touch_do_not_overlap():
    sc = scene_of(drive(0, 0, 10), drive(4.5, 0, 10))  # bumper to bumper, 4.5 m long boxes
    assert reasons(sc) == {}


def test_crossing_a_road_edge_is_offroad_but_not_after_the_goal():
    edge = (RoadType.ROAD_EDGE, [[20, -10], [20, 10]])  # across the path at x = 20
    sc = scene_of(drive(0, 0, 10), roads=[edge])  # reaches x = 20 at step 20, its goal is at x = 39
    assert reasons(sc) == {0: ["offroad"]}
    # the same edge beyond the goal point: the window ends where the engine would take the car out
    pos, yaw = drive(0, 0, 10)
    sc = make_scene(pos[None], yaw[None], goal=np.array([[15.0, 0.0]]), roads=[edge])
    assert reasons(sc) == {}


def test_jumps_and_heading_flips_are_tracking_errors():
    pos, yaw = drive(0, 0, 10)
    pos[25:] += [4.0, 0.0]  # a 4 m teleport in one step: 40 m/s faster than the step before
    assert reasons(scene_of((pos, yaw))) == {0: ["jump"]}
    pos, yaw = drive(0, 0, 10)
    yaw[30] = np.pi  # one step facing backwards
    assert reasons(scene_of((pos, yaw))) == {0: ["jump"]}
    pos, yaw = drive(0, 0, 10)
    pos += np.random.default_rng(0).normal(0, 0.03, pos.shape)  # position noise is motion, not a jump
    assert reasons(scene_of((pos, yaw))) == {}


def test_reversing_and_sideways_logs_cannot_be_driven_forward():
    assert reasons(scene_of(drive(0, 0, -2.0, yaw=0.0))) == {0: ["kinematics"]}  # 6 m backwards
    assert reasons(scene_of(drive(0, 0, 0.0, 2.0, yaw=0.0))) == {0: ["kinematics"]}  # 4 m sideways
    assert reasons(scene_of(drive(0, 0, 10.0, 1.0))) == {}  # heading along the motion: fine


def test_only_candidates_are_audited():
    pos, yaw = drive(0, 0, 10)
    late = np.ones((2, T), bool)
    late[1, :12] = False  # absent at init_step 10: never the policy's
    sc = make_scene(np.stack([pos, pos + [1.0, 0]]), np.stack([yaw, yaw]), log_valid=late)
    assert candidates(sc, 10, 2.0).tolist() == [True, False]
    assert reasons(sc) == {0: ["overlap"]}


def test_rule_replays_marked_and_infeasible_agents_and_counts_them():
    sc = scene_of(drive(0, 0, 10), drive(3, 0.5, 10), drive(30, 20, 10), drive(0, -20, 10))
    sc.metadata["mark_as_expert"] = [3]
    cfg = EngineConfig(max_agents=8)
    assert control.eligible(sc, cfg).tolist() == [False, False, True, False]
    ex = control.exclusions(sc, cfg)
    assert ex["log_infeasible"].tolist() == [True, True, False, False] and ex["mark_as_expert"].tolist()[3]
    sim = Simulator([sc], cfg, "cpu")
    assert int(sim.policy_agents.sum()) == 1
    assert sim.report()["agents_log_infeasible"] == 2 and sim.report()["agents_marked_expert"] == 1
    off = EngineConfig(max_agents=8, replay_infeasible=False)
    assert control.eligible(sc, off).all()
    assert "log_audit" in sc.metadata and infeasible_mask(sc, 10, 2.0).sum() == 2  # cached with its parameters


@pytest.fixture(scope="module")
def womd():
    return [load_gpudrive_json(f) for f in sorted(DATA.glob("womd_*.json"))]


def engine_events(scenes, cfg, device="cpu"):
    """{(world, scene agent): {(reason, log step)}} of the engine replaying every log (nobody driven),
    inside each audited candidate's scoring window (up to its first step within goal_radius of the goal)."""
    cfg = dataclasses.replace(cfg, max_agents=max(agents_needed(s) for s in scenes), control="none",
                              auto_reset=False)
    sim = Simulator(scenes, cfg, device)
    sim.reset()
    slot_agent = np.asarray(sim.model.slot_agent)
    out = {}
    for k in range(sim.episode_length):
        sim.step()
        t = cfg.init_steps + 1 + k
        for name, flags in (("overlap", sim.collided), ("offroad", sim.offroad)):
            for w, a in zip(*np.nonzero(flags.cpu().numpy())):
                sc, i = scenes[w], int(slot_agent[w, a])
                if not candidates(sc, cfg.init_steps, cfg.goal_radius)[i]:
                    continue
                near = np.nonzero((np.linalg.norm(sc.log_pos[i] - sc.goal[i], axis=-1) < cfg.goal_radius)
                                  & (np.arange(sc.num_steps) > cfg.init_steps))[0]
                if t <= (near[0] if len(near) else sc.num_steps - 1):
                    out.setdefault((w, i), set()).add((name, t))
    return out


def test_audit_agrees_with_the_engine_replaying_the_logs(womd, device):
    """On hand-made logs the engine's collision and off-road flags and the audit name the same agents; on
    real scenes every event the engine flags inside a window is one the audit names (the audit also sees
    the init step, which the engine does not step through)."""
    cfg = EngineConfig()
    edge = (RoadType.ROAD_EDGE, [[20, -10], [20, 10]])
    made = [scene_of(drive(0, 0, 10), drive(3, 0.5, 10), drive(30, 20, 10)), scene_of(drive(0, 0, 10), roads=[edge]),
            scene_of(drive(0, 0, 10), drive(4.5, 0, 10))]
    ev = engine_events(made, cfg, device)
    for w, sc in enumerate(made):
        found = {i: {r for r in rs if r in ("overlap", "offroad")} for i, rs in audit(sc, 10, 2.0).items()}
        assert {i: {n for n, _ in e} for (ww, i), e in ev.items() if ww == w} == found
    for (w, i), e in engine_events(womd, cfg, device).items():
        for name, t in e:
            assert name in audit(womd[w], 10, 2.0).get(i, []), (womd[w].scene_id, i, name, t)


def test_expert_replay_is_clean_under_the_rule(womd, device):
    cfg = EngineConfig(max_agents=max(agents_needed(s) for s in womd))
    for mode in ("ignore", "stop", "remove"):
        sim = Simulator(womd, dataclasses.replace(cfg, collision_mode=mode), device)
        out = run_rollout(sim, expert_policy, sim.episode_length, episodes_per_world=1)
        assert out["agent_episodes"] >= 10
        assert out["goal_rate"] >= 0.97 and out["collision_rate"] == 0 and out["offroad_rate"] == 0, (mode, out)
        assert sim.report()["agents_dropped"] == 0


def test_unplayable_scenes():
    pos, yaw = drive(0, 0, 10, steps=15)
    assert "too short" in unplayable(scene_of((pos, yaw)))
    walkers = scene_of(drive(0, 0, 1.0), drive(0, 5, 1.0), types=AgentType.PEDESTRIAN)
    assert "no controllable vehicle" in unplayable(walkers)
    assert unplayable(scene_of(drive(0, 0, 10))) is None


def test_training_caps_the_policy_agents_and_replays_the_rest():
    sc = scene_of(*(drive(0, 10.0 * k, 10) for k in range(5)))
    sc.is_sdc[4] = True  # the most relevant agent is kept first
    mask, left = control.cap_controlled(sc, np.ones(5, bool), 3, 10)
    assert mask.sum() == 3 and mask[4] and left == 2
    assert control.cap_controlled(sc, mask, 3, 10)[1] == 0


def test_replay_events_are_put_in_their_class():
    from tg_gpudrive.evaluation.log_events import classify, first_events

    edge = (RoadType.ROAD_EDGE, [[30, -10], [30, 10]])
    scenes = [scene_of(drive(0, 0, 10), drive(3, 0.5, 10), drive(0, 30, 10)),  # two logs overlap from the start
              scene_of(drive(0, 0, 10), roads=[edge])]  # the log crosses an edge at x = 30, step 30
    cfg = EngineConfig(max_agents=4, replay_infeasible=False)  # the rule's exclusions off: the events happen
    events = first_events(scenes, cfg, "cpu")
    got = sorted((w, i, kind, classify(scenes[w], i, kind, t, off, partner, 10, 2.0))
                 for w, i, kind, t, off, partner in events)
    assert got == [(0, 0, "collision", "log overlaps another agent at the first step"),
                   (0, 1, "collision", "log overlaps another agent at the first step"),
                   (1, 0, "offroad", "log leaves the road")]
    assert first_events(scenes, EngineConfig(max_agents=4), "cpu") == []  # under the rule: replayed, no event
    # a clean log whose replay hits a pedestrian, or drifts, or grazes
    sc = scene_of(drive(0, 0, 10))
    assert classify(sc, 0, "collision", 5, 0.1, int(AgentType.PEDESTRIAN), 10, 2.0) == "with a pedestrian or cyclist"
    assert classify(sc, 0, "offroad", 5, 2.0, None, 10, 2.0).startswith("tracking")
    assert classify(sc, 0, "offroad", 5, 0.1, None, 10, 2.0).startswith("geometry")


def test_audits_of_several_starts_equal_one_audit_each(womd):
    from tg_gpudrive.data.log_audit import audits

    for sc in womd:
        many = audits(sc, [10, 20, 35, 60], 2.0)
        assert many == {t: audit(sc, t, 2.0) for t in (10, 20, 35, 60)}
