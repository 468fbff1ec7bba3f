"""Engine behaviour: expert tracking on real WOMD logs, collision modes, episode bookkeeping,
determinism, bad input, and (on GPU) graph replay without allocation."""

from __future__ import annotations

import copy
import dataclasses
import json
import logging

import numpy as np
import pytest
import reference as ref
import torch
import warp as wp
from conftest import WOMD_FILES

from scenes import crossing_scene

from tg_gpudrive.config import ConfigError, EngineConfig, TrainConfig, from_dict, to_dict
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.scene import SceneError, make_scene
from tg_gpudrive.engine.model import State, StepState, view_shape
from tg_gpudrive.engine.simulator import LOG_FIELDS, Simulator
from tg_gpudrive.enums import AgentType, CollisionMode, GoalBehaviour, RoadType

T = 40


@pytest.fixture(scope="module")
def womd_scenes():
    return [load_gpudrive_json(f) for f in WOMD_FILES]


def test_expert_tracks_real_womd_logs(womd_scenes, device):
    """Inverse-then-forward on the two real scenes, vehicles valid from init_step.

    Tolerance: mean error 0.15 m and worst 1.25 m over 8 s. Why not exact: WOMD
    positions carry centimetre noise and their velocity/heading disagree with
    the displacement (sideways slips a bicycle cannot make); the closed-loop
    expert corrects each step but can only turn at <= 0.3 1/m and +-6 m/s^2.
    Measured (cpu, both scenes): mean 0.093 m, p95 0.37 m, max 0.98 m; the
    plain Waymax inverse (no feedback) gives mean 0.33 m, max 2.09 m."""
    errs = []
    for sc in womd_scenes:
        sim = Simulator([sc], EngineConfig(replay_infeasible=False, max_agents=128, action_space="continuous"), device)
        idx = sim.model.slot_agent[0]
        n = int((idx >= 0).sum())
        track = sim.slot_log("expert_track")[0, :n].cpu().numpy()
        ctrl = np.nonzero(sim.policy_agents[0, :n].cpu().numpy())[0]
        assert len(ctrl) > 0
        for a in ctrl:
            k = idx[a]
            valid = sc.log_valid[k]
            # the kernel agrees with the NumPy closed loop written out step by step
            want = ref.expert_track(sc.log_pos[k], sc.log_yaw[k], sc.log_vel[k], valid, init=10)
            np.testing.assert_allclose(track[a][valid], want[valid], atol=2e-2)
            steps = np.nonzero(valid)[0]
            steps = steps[steps > 10]
            errs.append(np.linalg.norm(track[a, steps] - sc.log_pos[k, steps], axis=-1))
    e = np.concatenate(errs)
    assert e.mean() < 0.15 and e.max() < 1.25, (e.mean(), e.max())


def head_on_scene():
    return crossing_scene(T)


def run_modes(mode, device, steps=35):
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=0, action_space="continuous", control="all_agents",
                       collision_mode=mode, road_k=8, partner_k=4)
    sim = Simulator([head_on_scene()], cfg, device)
    sim.reset()
    zero = torch.zeros((1, 4, 2), device=device)
    hist = {k: [] for k in ("pos", "collided", "terminated", "present", "done")}
    for _ in range(steps):
        sim.step(zero)
        hist["pos"].append(sim.pos[0, :3].cpu().numpy().copy())
        hist["collided"].append(sim.collided[0, :3].cpu().numpy().copy())
        hist["terminated"].append(sim.terminated[0, :3].cpu().numpy().copy())
        hist["present"].append(sim.present[0, :3].cpu().numpy().copy())
        hist["done"].append(sim.agent_done[0, :3].cpu().numpy().copy())
    return {k: np.array(v) for k, v in hist.items()}, sim


def test_collision_modes_differ_as_specified(device):
    # A and B (4 x 2 m, both at 10 m/s towards (20, 0) from 20 m) first overlap at step 17
    ign, sim_i = run_modes("ignore", device)
    first = int(np.argmax(ign["collided"][:, 0]))
    assert first == int(np.argmax(ign["collided"][:, 1])) and 15 <= first <= 19
    # ignore: counted, keeps driving through, nobody terminated, C never hits anything
    assert ign["terminated"].sum() == 0 and ign["present"].all()
    assert ign["pos"][-1, 0, 0] > ign["pos"][first, 0, 0] + 10
    assert sim_i.ep_collided[0, :2].tolist() == [1, 1] and ign["collided"][:, 2].sum() == 0

    stop, _ = run_modes("stop", device)
    assert stop["terminated"][first, :2].tolist() == [1, 1] and stop["terminated"][:, :2].sum() == 2
    # frozen in place and still present, so C, driving on, runs into them; then everyone is
    # done and the world resets to its start
    c_hit = int(np.argmax(stop["collided"][:, 2]))
    assert c_hit > first and stop["terminated"][c_hit, 2] == 1
    np.testing.assert_allclose(stop["pos"][c_hit - 1, :2], stop["pos"][first, :2])
    assert stop["present"][first:c_hit, :2].all()
    # (positions read after a step are already those of the reset world)
    np.testing.assert_allclose(stop["pos"][c_hit, :2], [[0.0, 0.0], [20.0, -20.0]], atol=1e-5)

    rem, _ = run_modes("remove", device)
    assert rem["terminated"][first, :2].tolist() == [1, 1]
    # taken out of the scene and of later collision checks: C passes where they were
    assert not rem["present"][first + 1:, :2].any()
    assert rem["collided"][:, 2].sum() == 0 and rem["terminated"][:, 2].sum() == 0
    assert rem["pos"][-1, 2, 0] > stop["pos"][first, 0, 0]


def test_episode_bookkeeping_and_auto_reset(device):
    sc = head_on_scene()
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=5, action_space="continuous", control="all_agents",
                       collision_mode="ignore", road_k=8, partner_k=4)
    sim = Simulator([sc, sc], cfg, device)
    sim.reset()
    assert sim.episode_length == T - 1 - 5
    start = sim.pos.clone()
    zero = torch.zeros((2, 4, 2), device=device)
    for k in range(sim.episode_length):
        sim.step(zero)
        if k < sim.episode_length - 1:
            assert not sim.world_reset.any()
            assert int(sim.world_step[0]) == 5 + k + 1
    assert sim.world_reset.tolist() == [1, 1] and sim.world_truncated.tolist() == [1, 1]
    assert sim.truncated[0, :3].tolist() == [1, 1, 1] and sim.truncated[0, 3] == 0
    assert sim.final_steps[0, :3].tolist() == [sim.episode_length] * 3
    assert sim.final_collided[0, :3].tolist() == [1, 1, 0]
    # the state is the scene's again, at init_step, and a new episode starts
    torch.testing.assert_close(sim.pos, start)
    assert int(sim.world_step[0]) == 5 and sim.ep_collided.sum() == 0 and sim.episode_count.tolist() == [1, 1]
    out = sim.finished_episodes()
    assert out["collided"].tolist() == [1, 1, 0, 1, 1, 0]


def test_same_inputs_same_state_on_cpu():
    scenes = [head_on_scene() for _ in range(3)]
    runs = []
    for _ in range(2):
        sim = Simulator(scenes, EngineConfig(replay_infeasible=False, max_agents=8, control="all_agents", init_steps=2), "cpu")
        sim.reset()
        g = torch.Generator().manual_seed(7)
        for _ in range(20):
            sim.step(torch.randint(0, sim.num_actions, (3, 8), generator=g, dtype=torch.int32))
        runs.append({**sim.snapshot(), "obs": sim.obs.numpy().copy()})  # obs: derived, not in snapshots
    for name in runs[0]:
        if name in ("grid_items",):  # bucket order comes from atomics; contents are compared below
            continue
        np.testing.assert_array_equal(runs[0][name], runs[1][name], err_msg=name)


def test_nan_positions_and_empty_scenes_are_clear_errors():
    pos = np.zeros((2, T, 2))
    pos[1, 7, 0] = np.nan
    with pytest.raises(SceneError, match=r"log_pos.*agent 1.*step 7"):
        make_scene(pos, np.zeros((2, T)), scene_id="nan_scene")
    with pytest.raises(SceneError, match=r"no agent has a single valid step"):
        make_scene(np.zeros((2, T, 2)), np.zeros((2, T)), log_valid=np.zeros((2, T), bool))
    # NaN in a step marked invalid is fine: sentinels behind the mask are zeroed
    valid = np.ones((2, T), bool)
    valid[1, 7] = False
    sc = make_scene(pos, np.zeros((2, T)), log_valid=valid)
    assert np.isfinite(sc.log_pos).all()


def test_more_agents_than_slots_is_a_counted_truncation(caplog):
    n = 12
    rng = np.random.default_rng(3)
    pos = np.repeat(rng.uniform(-100, 100, (n, 1, 2)), T, 1)
    types = np.array([AgentType.VEHICLE] * 8 + [AgentType.PEDESTRIAN] * 4)
    sc = make_scene(pos, np.zeros((n, T)), agent_type=types, scene_id="crowded")
    with caplog.at_level(logging.WARNING, logger="tg_gpudrive"):
        sim = Simulator([sc], EngineConfig(replay_infeasible=False, max_agents=8, road_k=4, partner_k=4), "cpu")
    assert sim.model.report.truncated_agents == [4]
    assert "crowded" in caplog.text and "4 agents beyond max_agents=8" in caplog.text
    # vehicles are kept before pedestrians
    assert (sim.agent_type[0].numpy() == AgentType.VEHICLE).all()


def test_bad_actions_are_rejected():
    sim = Simulator([head_on_scene()], EngineConfig(replay_infeasible=False, max_agents=4, road_k=4, partner_k=4), "cpu")
    sim.reset()
    with pytest.raises(ValueError, match="expected integer tensor of shape"):
        sim.step(torch.zeros((1, 4), dtype=torch.float32))
    with pytest.raises(ValueError, match=r"must lie in \[0, 91\)"):
        sim.step(torch.full((1, 4), 91, dtype=torch.int32))
    simc = Simulator([head_on_scene()], EngineConfig(replay_infeasible=False, max_agents=4, action_space="continuous", road_k=4,
                                                     partner_k=4), "cpu")
    with pytest.raises(ValueError, match="NaN"):
        simc.step(torch.full((1, 4, 2), float("nan")))


@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")
def test_cuda_graph_matches_cpu_and_allocates_nothing():
    rng = np.random.default_rng(5)
    scene = head_on_scene()
    scene.road_points = rng.uniform(-50, 50, (20, 2)).astype(np.float32)
    scene.road_offsets = np.array([0, 10, 20])
    scene.road_type = np.array([RoadType.LANE, RoadType.ROAD_EDGE], np.int8)
    scene.road_id = np.array([0, 1])
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=2, control="all_agents", road_k=8, partner_k=4)
    sims = {d: Simulator([scene] * 8, cfg, d) for d in ("cpu", "cuda:0")}
    acts = torch.randint(0, 91, (30, 8, 4), generator=torch.Generator().manual_seed(1), dtype=torch.int32)
    for d, sim in sims.items():
        sim.reset()
        for k in range(30):
            if k == 3 and d.startswith("cuda"):
                used = wp.get_mempool_used_mem_current(d)
            sim.step(acts[k].to(d))
        if d.startswith("cuda"):
            assert sim._graph is not None
            assert wp.get_mempool_used_mem_current(d) == used
    for name in ("pos", "obs", "reward", "cost", "collided"):
        torch.testing.assert_close(getattr(sims["cuda:0"], name).cpu(), getattr(sims["cpu"], name),
                                   atol=1e-3, rtol=1e-4, msg=name)


def test_without_auto_reset_worlds_wait_frozen_until_reset(device):
    sc = head_on_scene()
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=5, action_space="continuous", control="all_agents",
                       auto_reset=False, road_k=8, partner_k=4)
    sim = Simulator([sc, sc], cfg, device)
    sim.reset()
    start = sim.pos.clone()
    zero = torch.zeros((2, 4, 2), device=device)
    for _ in range(sim.episode_length):
        sim.step(zero)
    assert sim.world_ended.tolist() == [1, 1] and sim.world_reset.tolist() == [0, 0]
    assert sim.world_done.tolist() == [1, 1] and sim.truncated[0, :3].tolist() == [1, 1, 1]
    end = sim.pos.clone()
    obs = sim.obs.clone()
    assert sim.final_steps[0, :3].tolist() == [sim.episode_length] * 3
    sim.step(zero)  # frozen: nothing moves, nothing is reported again
    torch.testing.assert_close(sim.pos, end)
    torch.testing.assert_close(sim.obs, obs)
    assert sim.world_ended.sum() == 0 and sim.alive.sum() == 0 and sim.reward.abs().sum() == 0
    assert sim.active.sum() == 0  # frozen worlds hold no agent that acts
    sim.reset(torch.tensor([False, True]))  # only world 1 starts again
    torch.testing.assert_close(sim.pos[1], start[1])
    torch.testing.assert_close(sim.pos[0], end[0])
    assert sim.world_done.tolist() == [1, 0] and int(sim.world_step[1]) == 5
    sim.step(zero)
    assert sim.alive[0].sum() == 0 and sim.alive[1].sum() == 3


def test_background_agents_are_driven_but_not_counted(device):
    sc = head_on_scene()
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=0, action_space="continuous", road_k=4, partner_k=4)
    sim = Simulator([sc], cfg, device, controlled=[np.array([False, True, False])],
                    background=[np.array([True, False, False])])
    # policy agent first, then the background one, then the replayed one
    assert sim.model.slot_agent[0, :3].tolist() == [1, 0, 2]
    assert sim.policy_agents[0].tolist() == [True, False, False, False]
    assert sim.integrated[0, :3].tolist() == [1, 1, 0] and sim.max_controlled == 1
    sim.reset()
    a = torch.zeros((1, 4, 2), device=device)
    a[0, 1, 0] = -6.0  # the background agent brakes: it follows the action buffer, not its log
    for _ in range(10):
        sim.step(a)
    assert float(sim.pos[0, 1, 0]) < 10 * 1.0 - 1.0  # behind where its log would be at t = 1 s
    assert float(sim.pos[0, 2, 0]) == pytest.approx(-15 + 10 * 1.0, abs=1e-4)  # replayed


def test_unusable_actions_written_in_place_are_counted():
    """NaN written straight into the continuous buffer, or an out-of-range grid index, is counted
    per acting row and step in sim.report() (the kernels would otherwise clamp it silently)."""
    cont = Simulator([crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4, action_space="continuous"), "cpu")
    cont.reset()
    cont.actions.zero_()
    cont.step()
    assert cont.report()["bad_actions"] == 0
    cont.actions[0, 0, 0] = float("nan")
    cont.step()
    cont.step()
    assert cont.report()["bad_actions"] == 2 and cont.report()["agents_dropped"] == 0
    disc = Simulator([crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4), "cpu")
    disc.reset()
    disc.actions_index.fill_(disc.cfg.noop_index)
    disc.actions_index[0, 1] = 10_000
    disc.step()
    assert disc.report()["bad_actions"] == 1


def test_scenes_without_road_edges_are_warned_and_counted(caplog):
    bare = make_scene(np.zeros((1, 20, 2)), np.zeros((1, 20)), scene_id="bare")  # no roads at all
    with caplog.at_level("WARNING"):
        sim = Simulator([bare, crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4), "cpu")
    assert sim.report()["worlds_without_road_edges"] == 1 + int(not (crossing_scene().road_type == 3).any())
    assert "no road edges" in caplog.text and "bare" in caplog.text


def test_modes_parse_print_and_round_trip_as_their_yaml_names():
    cfg = from_dict(EngineConfig, {"collision_mode": "STOP", "goal_behaviour": "continue", "control": "none"})
    assert cfg.collision_mode is CollisionMode.STOP and cfg.goal_behaviour is GoalBehaviour.CONTINUE
    assert str(cfg.collision_mode) == "stop" and f"{cfg.dynamics}" == "bicycle"
    plain = to_dict(TrainConfig(env=cfg, control="nearest_conflict"))
    assert plain["control"] == "nearest_conflict" and plain["env"]["collision_mode"] == "stop"
    assert json.loads(json.dumps(plain))["env"]["dynamics"] == "bicycle"  # names, not integers
    assert from_dict(TrainConfig, plain).env == cfg  # checkpoints store names (old ones: the same strings)
    assert (cfg.act_dim, cfg.noop_index, cfg.act_high) == (2, 45, (6.0, 0.3))
    delta = EngineConfig(dynamics="delta_local", action_space="continuous")
    assert (delta.act_dim, delta.act_high) == (3, (6.0, 1.0, 0.5))
    with pytest.raises(ConfigError, match="control: expected one of vehicles, all_agents, none"):
        EngineConfig(control="ids")
    with pytest.raises(ConfigError, match="collision_mode"):
        from_dict(EngineConfig, {"collision_mode": 1})
    with pytest.raises(ConfigError, match="cost_shape: expected one of step, hinge, approach, got 'linear'"):
        EngineConfig(cost_shape="linear")
    with pytest.raises(ConfigError, match="cost_partners: expected all or players, got 'others'"):
        EngineConfig(cost_partners="others")


def test_simulator_views_are_the_state_fields_declared_once():
    sim = Simulator([crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4, road_k=8, partner_k=2), "cpu")
    for f in dataclasses.fields(StepState):
        view = getattr(sim, f.name)
        assert view.data_ptr() == wp.to_torch(getattr(sim.state, f.name)).data_ptr(), f.name
        assert tuple(view.shape) == view_shape(f, sim.model), f.name
        assert f.name in State.__doc__
    assert tuple(sim.collided.shape) == (1, 4) and tuple(sim.world_step.shape) == (1,)
    assert bool((sim.model.nearest_cap.numpy() >= sim.model.beta).all())


def test_worlds_sharing_a_scene_match_worlds_with_their_own_copy(womd_scenes, device):
    """The builder does a scene's work once and lets its worlds share road segments, grids, logs and
    expert actions; that must be invisible: the same batch built from distinct copies of each scene
    gives the same per-world arrays, expert actions and steps (log replay, the expert and the policy)."""
    a, b = womd_scenes
    cfg = EngineConfig(max_agents=64)  # vehicles controlled, the other agents replay their logs
    shared = Simulator([a, b, a, a], cfg, device)
    copies = Simulator([copy.deepcopy(s) for s in (a, b, a, a)], cfg, device)
    assert shared.model.seg_a.shape[0] * 2 < copies.model.seg_a.shape[0]  # segments stored once per scene
    assert (shared.model.num_plans, copies.model.num_plans) == (2, 4)
    assert shared.model.log_pos.shape[0] * 2 == copies.model.log_pos.shape[0]  # logs stored once per plan
    for name, arr in copies.model.host.items():
        np.testing.assert_array_equal(shared.model.host[name], arr, err_msg=name)
    steps = torch.tensor([[10, 11, 40], [0, 90, 5], [33, 33, 1], [12, 70, 2]], device=shared.obs.device)
    for name in LOG_FIELDS:
        full = shared.slot_log(name)
        np.testing.assert_array_equal(full.cpu().numpy(), copies.slot_log(name).cpu().numpy(), err_msg=name)
        got = shared.log_at(name, steps, 5)  # (W, 5, 3, ...)
        want = torch.stack([full[w, :5, steps[w]] for w in range(4)])
        np.testing.assert_array_equal(got.cpu().numpy(), want.cpu().numpy(), err_msg=name)
    g = torch.Generator().manual_seed(3)
    acts = [torch.randint(0, shared.num_actions, shared.actions_index.shape, generator=g, dtype=torch.int32)
            for _ in range(12)]
    for sim in (shared, copies):
        sim.reset()
        for x in acts:
            sim.step(x.to(sim.actions_index.device))
        for _ in range(3):
            sim.use_expert_actions()
            sim.step()
    for name in ("obs", "reward", "cost", "collided", "offroad", "pos"):
        np.testing.assert_allclose(getattr(shared, name).cpu().numpy(), getattr(copies, name).cpu().numpy(),
                                   rtol=0, atol=1e-6, err_msg=name)
    for x, y in zip(shared.corrective_expert(), copies.corrective_expert()):
        np.testing.assert_allclose(x.cpu().numpy(), y.cpu().numpy(), rtol=0, atol=1e-6)


def test_batched_road_tables_match_the_per_scene_reference(womd_scenes, device):
    """engine/roads.py builds every distinct scene's segments and grid in one batched pass; per scene
    it must hold the reference's segments (tests/reference.py, per scene in NumPy), each in the grid
    cell its midpoint lies in, in the reference's order within a cell."""
    from tg_gpudrive.data.procedural.dense import dense_scene
    from tg_gpudrive.engine.roads import build_road_tables

    scenes = [*womd_scenes, dense_scene(5)]
    cfg = EngineConfig(max_segment_length=4.0, road_cell_size=7.0, road_simplify=0.1)
    t = build_road_tables(scenes, cfg, device)
    a, b, ty, start = (x.cpu().numpy() for x in (t.seg_a, t.seg_b, t.seg_type, t.cell_start))
    first = np.cumsum(t.segments) - t.segments
    for s, sc in enumerate(scenes):
        ra, rb, rt = ref.scene_segments(sc, 4.0, cfg.road_simplify)
        assert t.segments[s] == len(ra)
        mid = 0.5 * (ra + rb)
        lo = mid.min(0) - 1e-3
        np.testing.assert_allclose(t.origin[s], lo, atol=1e-4)
        ix = np.clip(np.floor((mid[:, 0] - lo[0]) / 7.0).astype(int), 0, t.nx[s] - 1)
        iy = np.clip(np.floor((mid[:, 1] - lo[1]) / 7.0).astype(int), 0, t.ny[s] - 1)
        order = np.argsort(iy * t.nx[s] + ix, kind="stable")
        sl = slice(first[s], first[s] + len(ra))
        np.testing.assert_allclose(a[sl], ra[order], atol=1e-5, err_msg=sc.scene_id)
        np.testing.assert_allclose(b[sl], rb[order], atol=1e-5, err_msg=sc.scene_id)
        np.testing.assert_array_equal(ty[sl], rt[order])
        cells = start[t.cell_offset[s]:t.cell_offset[s] + t.nx[s] * t.ny[s] + 1]
        assert cells[0] == first[s] and cells[-1] == first[s] + len(ra)
        want = np.bincount(iy * t.nx[s] + ix, minlength=t.nx[s] * t.ny[s])
        np.testing.assert_array_equal(np.diff(cells), want)
    # built one scene at a time (a chunk each), the tables are the same
    c = build_road_tables(scenes, cfg, device, chunk_points=1)
    for f in ("seg_a", "seg_b", "seg_type", "cell_start"):
        np.testing.assert_array_equal(getattr(c, f).cpu().numpy(), getattr(t, f).cpu().numpy(), err_msg=f)
    for f in ("origin", "nx", "ny", "cell_offset", "segments"):
        np.testing.assert_array_equal(getattr(c, f), getattr(t, f), err_msg=f)


def test_snapshots_leave_derived_fields_out_and_restore_recomputes_them():
    scenes = [head_on_scene(), crossing_scene()]
    cfg = EngineConfig(replay_infeasible=False, max_agents=8, control="all_agents", init_steps=2)
    sim = Simulator(scenes, cfg, "cpu")
    sim.reset()
    for _ in range(5):
        sim.step(torch.full((2, 8), cfg.noop_index, dtype=torch.int32))
    snap, obs, active = sim.snapshot(), sim.obs.clone(), sim.active.clone()
    assert not set(snap) & Simulator.DERIVED and "pos" in snap
    other = Simulator(scenes, cfg, "cpu")
    other.reset()
    other.restore(snap)
    torch.testing.assert_close(other.obs, obs, rtol=0, atol=0)
    torch.testing.assert_close(other.active, active, rtol=0, atol=0)
