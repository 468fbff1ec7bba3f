"""Reactive log replay (`agents/idm.py`, `--background idm`): IDM's formula against hand-computed values,
the leader gap against a hand-placed pair, a free vehicle against its own log, a rear-end that the plain
replay drives into and IDM stops short of, and the two real WOMD test scenes against the replay's rates."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_gpudrive.agents.builtin import background_masks, make_background_driver
from tg_gpudrive.agents.idm import IDMDriver, IDMParams, idm_accel
from tg_gpudrive.cli import main
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.scene import make_scene
from tg_gpudrive.worldmodel.closed_loop import nearest_index
from tg_gpudrive.worldmodel.metrics import background_rates, drive_steps

DATA = Path(__file__).parent / "data"
CFG = dict(max_agents=4, partner_k=4, road_k=8, init_steps=0, replay_infeasible=False)


def test_idm_accel_matches_hand_computed_values():
    p = IDMParams()  # a_max 2, b 3, s0 2, T 1
    # v 10, gap 20, closing at 5: s* = 2 + 10 + 10 * 5 / (2 sqrt 6) = 22.2062
    v, gap, dv = torch.tensor([10.0, 0.0, 10.0]), torch.tensor([20.0, 4.0, 100.0]), torch.tensor([5.0, 0.0, -10.0])
    want = [2 * (1 - (22.2062 / 20) ** 2), 2 * (1 - (2 / 4) ** 2), 2 * (1 - (2 / 100) ** 2)]  # last: s* floors at s0
    torch.testing.assert_close(idm_accel(v, gap, dv, p), torch.tensor(want), rtol=1e-4, atol=1e-4)
    grid = EngineConfig(max_accel=4.0, accel_bins=9, curvature_bins=5)  # the action grid IDM snaps to
    accel = torch.tensor([-6.0, -0.1, 0.2, 6.0])
    assert (nearest_index(accel, torch.zeros(4), grid) // 5).tolist() == [0, 4, 4, 8]
    with pytest.raises(ValueError, match="IDMParams.b"):
        IDMParams(b=0)
    with pytest.raises(ValueError, match="rows"):
        IDMDriver(rows="everyone")


def pair_scene(T: int = 60, lead_stop: float | None = 1.0, gap: float = 30.0):
    """Two 4 x 2 m cars on a straight, +x. The leader (agent 0) starts `gap` m ahead at 10 m/s and, from
    `lead_stop` s on, brakes at 5 m/s^2 to a standstill; the follower (agent 1) logs 10 m/s throughout, so
    its log runs through the stopped leader. Goals far ahead."""
    t = np.arange(T) * 0.1
    v0 = np.full(T, 10.0)
    if lead_stop is not None:
        v0 = np.maximum(10.0 - 5.0 * np.clip(t - lead_stop, 0, None), 0.0)
    x0 = gap + np.concatenate([[0.0], np.cumsum(0.5 * (v0[1:] + v0[:-1]) * 0.1)])
    pos = np.zeros((2, T, 2))
    pos[0, :, 0], pos[1, :, 0] = x0, 10 * t
    vel = np.zeros((2, T, 2))
    vel[0, :, 0], vel[1, :, 0] = v0, 10.0
    pos[:, -1, 0] += 500  # goals far away
    return make_scene(pos, np.zeros((2, T)), log_vel=vel, length=4.0, width=2.0)


def _drive(scene, device, driver, action_space="discrete", steps=None):
    cfg = EngineConfig(**CFG, action_space=action_space, control="all_agents")
    bg = [np.ones(scene.num_agents, bool)]
    sim = Simulator([scene], cfg, device, controlled=[np.zeros(scene.num_agents, bool)], background=bg)
    sim.reset()
    track, hit = [], np.zeros(scene.num_agents, bool)
    for _ in drive_steps(sim, driver, steps):
        track.append(sim.pos[0, :scene.num_agents].cpu().numpy().copy())
        hit |= sim.collided[0, :scene.num_agents].cpu().numpy() != 0
    return np.array(track), hit, sim


def test_the_leader_gap_is_the_bumper_distance_along_the_path(device):
    scene = pair_scene(lead_stop=None, gap=23.0)
    cfg = EngineConfig(**CFG, control="all_agents")
    sim = Simulator([scene], cfg, device, controlled=[np.zeros(2, bool)], background=[np.ones(2, bool)])
    sim.reset()
    drv = IDMDriver(params=IDMParams(spacing=0.25))
    drv._bind(sim)
    w, a = torch.tensor([0, 0], device=sim.pos.device), torch.tensor([0, 1], device=sim.pos.device)
    s_cur = drv._arc_at(drv.path[w, a], drv.arc[w, a], sim.pos[w, a].float(), drv._progress(sim, w, a))
    gap, v_lead = drv._leaders(sim, w, a, s_cur)
    # follower: 23 m centre to centre, minus two half lengths; the leader sees nobody ahead
    assert abs(float(gap[1]) - 19.0) <= 0.25 and math.isinf(float(gap[0]))
    assert abs(float(v_lead[1]) - 10.0) < 1e-4


@pytest.mark.parametrize("action_space", ["discrete", "continuous"])
def test_a_free_vehicle_follows_its_log(device, action_space):
    scene = pair_scene(lead_stop=2.0, gap=30.0)  # the leader alone matters: nobody is ahead of it
    track, hit, _ = _drive(scene, device, IDMDriver(), action_space)
    err = np.linalg.norm(track[:, 0] - scene.log_pos[0, 1:len(track) + 1], axis=-1)
    assert err.max() < (0.5 if action_space == "discrete" else 0.2), err.max()


@pytest.mark.parametrize("action_space", ["discrete", "continuous"])
def test_idm_stops_short_of_the_stopped_leader_that_the_replay_runs_into(device, action_space):
    scene = pair_scene()
    _, hit_replay, _ = _drive(scene, device, None, action_space)
    track, hit, _ = _drive(scene, device, IDMDriver(), action_space)
    assert hit_replay.all()  # the follower's log drives through the stopped leader
    assert not hit.any()
    bumper = track[:, 0, 0] - track[:, 1, 0] - 4.0
    assert bumper.min() > 0.5 and bumper[-1] < 6.0  # closes up behind it, then waits
    assert np.abs(track[:, 1, 1]).max() < 0.2  # in its lane


def test_on_real_scenes_idm_crashes_no_more_than_the_replay():
    scenes = [resolve_scenes(str(f), n=1).get(0) for f in sorted(DATA.glob("womd_*.json"))]
    env = EngineConfig()
    replay = background_rates(None, scenes, env)
    idm = background_rates(IDMDriver(), scenes, env)
    assert idm["vehicles"] == replay["vehicles"] > 5
    assert idm["collision_rate"] <= replay["collision_rate"] + 1e-9
    assert idm["offroad_rate"] <= replay["offroad_rate"] + 0.02


def test_background_idm_through_the_driver_factory_and_the_cli(capsys):
    scene = pair_scene()
    cfg = EngineConfig(**CFG, control="all_agents")
    ctrl = [np.array([True, False])]
    sim = Simulator([scene], cfg, "cpu", ctrl, background_masks([scene], cfg, "idm", ctrl))
    assert isinstance(make_background_driver(sim, "idm"), IDMDriver)
    assert sim.background[0, :2].tolist() == [0, 1]
    with pytest.raises(ValueError, match="background_model"):
        make_background_driver(sim, "idm", model="x.pt")
    delta = Simulator([scene], EngineConfig(**CFG, dynamics="delta_local", action_space="continuous"), "cpu")
    with pytest.raises(ValueError, match="bicycle"):
        IDMDriver()(delta)
    base = ["simulate", "--worlds", "2", "--steps", "3", "--set", "max_agents=16", "--set", "road_k=16",
            "--set", "partner_k=4", "--control", "nearest_conflict", "--control-k", "1", "--json"]
    assert main(base + ["--background", "idm"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (out["background"], out["background_model"]) == ("idm", None) and out["agents_background"] > 0


def test_render_draws_idm_traffic_around_the_policy(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    args = ["render", "--scenes", str(DATA), "--policy", "shipped", "--control", "nearest_conflict",
            "--control-k", "1", "--steps", "5", "--out", str(tmp_path / "idm.gif")]
    assert main(args + ["--background", "idm"]) == 0
    assert (tmp_path / "idm.gif").stat().st_size > 0
    assert main(args + ["--background", "idm", "--background-model", "x.pt"]) == 2
    assert "--background-model" in capsys.readouterr().err


def test_training_among_idm_vehicles_drives_the_left_out_ones_and_resumes_exactly(tmp_path):
    """augment.control_fraction leaves vehicles out of the policy; with background idm the IDM driver moves
    them (near their logs, not on them), the policy's rows are the log run's, and a resumed run ends with
    the uninterrupted one's weights."""
    import dataclasses

    from test_background import _log_gap
    from test_train import tiny

    from tg_gpudrive.config import AugmentConfig, ConfigError, TrainConfig
    from tg_gpudrive.learn.train import Trainer

    def cfg(out, **kw):
        return dataclasses.replace(tiny(out, num_worlds=4, prior="expert", **kw),
                                   augment=AugmentConfig(control_fraction=0.5))

    log_run = Trainer(cfg(tmp_path / "log", updates=1), tmp_path / "log", progress=False)
    idm_run = Trainer(cfg(tmp_path / "idm", updates=1, background="idm"), tmp_path / "idm", progress=False)
    assert torch.equal(idm_run.sim.policy_agents, log_run.sim.policy_agents)
    bg = idm_run.sim.background != 0
    assert int(bg.sum()) > 0 and not bool((log_run.sim.background != 0).any())
    assert isinstance(idm_run.collector.background, IDMDriver) and log_run.collector.background is None
    log_run.train()
    idm_run.train()
    assert float(_log_gap(log_run.sim, bg).max()) == 0.0  # replayed exactly
    gap = _log_gap(idm_run.sim, bg)
    assert 0.0 < float(gap.max()) < 2.0  # driven, along their logs

    a, b = tmp_path / "a", tmp_path / "b"
    Trainer(cfg(a, updates=2, background="idm"), a, progress=False).train()
    Trainer(cfg(b, updates=1, background="idm"), b, progress=False).train()
    Trainer(cfg(b, updates=2, background="idm"), b, resume=b, progress=False).train()
    wa, wb = (torch.load(d / "checkpoint.pt", weights_only=False)["actor"] for d in (a, b))
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0)
    with pytest.raises(ConfigError, match="background: expected one of log, world_model, idm"):
        TrainConfig(background="replay")


@pytest.mark.parametrize("action_space", ["discrete", "continuous"])
def test_world_model_labels_brake_where_the_log_drives_on(device, action_space):
    """The world model's closed-loop labels (worldmodel/closed_loop.py `visited_labels`): 3 s into the pair scene
    the leader stands 16 m (bumper to bumper) ahead of the follower, whose log goes on at 10 m/s through it. The
    corrective label tracks that log (accel 0 on it); with IDM's braking it brakes as hard as the box allows
    (2 (1 - (s* / 16)^2) with s* = 2 + 10 + 10 x 10 / (2 sqrt 6) = 32.4 m, about -6.2 m/s^2) and steers as the
    corrective label does. The leader, with nobody ahead, keeps its corrective label."""
    from tg_gpudrive.worldmodel.closed_loop import corrective_target, visited_labels

    _, _, sim = _drive(pair_scene(), device, None, action_space, steps=30)
    assert abs(float(sim.pos[0, 0, 0] - sim.pos[0, 1, 0]) - 20.0) < 0.5  # the scene as described
    tgt, drv, cfg = corrective_target(sim), IDMDriver(rows="controlled"), sim.cfg
    w, a = torch.zeros(2, dtype=torch.long, device=sim.pos.device), torch.arange(2, device=sim.pos.device)
    log, brake = visited_labels(sim, w, a, tgt), visited_labels(sim, w, a, tgt, drv)
    assert torch.equal(log[0], brake[0])  # the leader
    if action_space == "discrete":
        zero = int(nearest_index(torch.zeros(1), torch.zeros(1), cfg)[0]) // cfg.curvature_bins
        assert int(log[1]) // cfg.curvature_bins == zero and int(brake[1]) // cfg.curvature_bins == 0
        assert int(brake[1]) % cfg.curvature_bins == int(log[1]) % cfg.curvature_bins
    else:
        assert abs(float(log[1, 0])) < 0.5 and float(brake[1, 0]) == -cfg.max_accel
        assert float(brake[1, 1]) == float(log[1, 1])
