"""Who drives the vehicles the policy does not: log replay or the world model (`background=`).

Small CPU runs (2-3 procedural worlds or a 3-car crossing, a few steps): the world model moves the
background vehicles off their logs while the policy's rows keep their slots, shapes and (for an
open-loop expert) their trajectories; the CLI and the three envs take the option; bad values are
errors naming it.
"""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pytest
import torch
from scenes import crossing_scene

import tg_gpudrive.envs  # noqa: F401  (registers the ids)
from tg_gpudrive.cli import main
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.engine.control import control_masks
from tg_gpudrive.envs.parallel import TGParallelEnv
from tg_gpudrive.envs.single import TGSingleAgentEnv
from tg_gpudrive.envs.vector import TGVectorEnv, load_scenes
from tg_gpudrive.agents.builtin import background_masks, expert_policy, make_background_driver
from tg_gpudrive.scene import make_scene
from tg_gpudrive.engine.simulator import Simulator

SMALL = dict(max_agents=16, road_k=16, partner_k=4)


def _log_gap(sim: Simulator, rows: torch.Tensor) -> torch.Tensor:
    """Distance (m) of each slot from its own log at the world's current step, on `rows` & present."""
    log_pos = torch.as_tensor(sim.model.host["log_pos"])
    W, A = rows.shape
    at = log_pos[torch.arange(W)[:, None], torch.arange(A)[None], sim.world_step.long()[:, None]]
    return (sim.pos - at).norm(dim=-1)[rows & (sim.present != 0)]


@pytest.fixture(scope="module")
def worlds():
    cfg = EngineConfig(**SMALL)
    scenes = load_scenes("procedural:all", 3)
    return scenes, cfg, control_masks(scenes, cfg, "nearest_conflict", 2)


def test_world_model_background_leaves_the_log_but_not_the_policy_rows(worlds):
    scenes, cfg, ctrl = worlds
    log_sim = Simulator(scenes, cfg, "cpu", ctrl)
    wm_sim = Simulator(scenes, cfg, "cpu", ctrl, background_masks(scenes, cfg, "world_model", ctrl))
    driver = make_background_driver(wm_sim, "world_model", seed=0)
    assert make_background_driver(log_sim, "log") is None
    bg = wm_sim.background != 0
    assert int(bg.sum()) > 0 and int((log_sim.background != 0).sum()) == 0
    # the policy's rows: same slots, count and layout either way
    assert torch.equal(wm_sim.policy_agents, log_sim.policy_agents)
    assert not bool((wm_sim.policy_agents & bg).any())
    assert wm_sim.max_controlled == log_sim.max_controlled == 2
    assert wm_sim.obs.shape == log_sim.obs.shape
    log_sim.reset()
    wm_sim.reset()
    for _ in range(15):
        expert_policy(log_sim)
        expert_policy(wm_sim)
        driver(wm_sim)
        log_sim.step()
        wm_sim.step()
    assert float(_log_gap(log_sim, bg).max()) == 0.0  # replayed exactly
    assert float(_log_gap(wm_sim, bg).max()) > 0.5  # driven by the model, reacting
    # the expert is open loop and collisions are ignored: the policy's vehicles drive the same paths
    pol = wm_sim.policy_agents
    torch.testing.assert_close(wm_sim.pos[pol], log_sim.pos[pol], rtol=0, atol=1e-5)


def test_cli_simulate_reports_the_background_driver(capsys):

    base = ["simulate", "--worlds", "2", "--steps", "3", "--set", "max_agents=16", "--set", "road_k=16",
            "--set", "partner_k=4", "--control", "nearest_conflict", "--control-k", "1", "--json"]
    assert main(base + ["--background", "world_model"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (out["background"], out["background_model"], out["control"]) == ("world_model", "shipped",
                                                                             "nearest_conflict")
    assert out["agents_controlled"] == 2 and out["agents_background"] > 0
    assert main(base) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (out["background"], out["background_model"], out["agents_background"]) == ("log", None, 0)
    assert main(base + ["--background-model", "x.pt"]) == 2
    assert "--background-model" in capsys.readouterr().err
    # the packaged CPU model by name; an unknown name lists the packaged ones
    assert main(base + ["--background", "world_model", "--background-model", "small_cpu"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["background_model"] == "small_cpu" and out["agents_background"] > 0
    assert main(base + ["--background", "world_model", "--background-model", "nope"]) == 2
    assert "packaged name: shipped, small_cpu" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(base + ["--background", "replay"])
    assert "--background" in capsys.readouterr().err


def test_vector_env_world_model_background_rows_are_masked(worlds):
    scenes, _, ctrl = worlds
    env = gymnasium.make_vec("tg_gpudrive/Vector-v0", num_worlds=len(scenes), scenes=scenes, config=SMALL,
                             controlled=ctrl, background="world_model")
    env.reset()
    bg = (env.sim.background != 0).view(-1)
    assert bool(bg.any()) and not bool((env.controlled & bg).any())
    assert int(env.controlled.sum()) == 2 * len(scenes)
    rng = torch.Generator().manual_seed(0)
    for _ in range(8):
        a = torch.randint(0, 91, (env.num_envs,), generator=rng)
        obs, reward, term, trunc, info = env.step(a)
        assert obs.shape == (env.num_envs, env.sim.obs_dim)
        for flags in (info["active"], info["alive"], term, trunc):
            assert not bool(flags[bg].any())
        assert bool((reward[bg] == 0).all()) and bool((info["cost"][bg] == 0).all())
        assert all(bool((v[bg] == 0).all()) for v in info["reward_terms"].values())
        assert bool(info["active"][env.controlled].any())
        # the policy rows still serve the engine's values
        torch.testing.assert_close(reward.view_as(env.sim.reward)[env.sim.policy_agents],
                                   env.sim.reward[env.sim.policy_agents], rtol=0, atol=0)
    # the user's values for background rows were ignored: the model drove them off their logs
    assert float(_log_gap(env.sim, bg.view(env.num_worlds, -1)).max()) > 0.2


def test_vector_env_world_model_background_across_auto_reset():
    scene = crossing_scene(T=20)  # an episode of 9 steps after init_steps=10
    mask = [np.array([True, False, False])]
    env = TGVectorEnv([scene], config=dict(max_agents=4, road_k=8, partner_k=4, replay_infeasible=False), controlled=mask,
                      background="world_model", strict=True)
    log_env = TGVectorEnv([scene], config=dict(max_agents=4, road_k=8, partner_k=4, replay_infeasible=False), controlled=mask)
    first, _ = env.reset()
    first = first.clone()
    log_env.reset()
    bg = (env.sim.background != 0)
    assert int(bg.sum()) == 2
    a = torch.full((env.num_envs,), env.cfg.noop_index, dtype=torch.int64)
    resets = 0
    for _ in range(2 * env.sim.episode_length + 1):
        obs, _, _, _, info = env.step(a)
        log_env.step(a)
        assert bool(env.sim.world_reset[0]) == bool(log_env.sim.world_reset[0])
        if info["world_reset"].any():
            resets += 1
            # SAME_STEP: the world is back at init_step, background vehicles included
            assert float(_log_gap(env.sim, bg).max()) < 1e-5
            torch.testing.assert_close(obs[env.controlled], first[env.controlled], rtol=0, atol=0)
    assert resets == 2
    assert float(_log_gap(env.sim, bg).max()) > 0.0  # driven again after the reset


def test_single_and_parallel_envs_take_the_background_option():
    scene = load_scenes("procedural:dense_intersection", 1)[0]
    env = gymnasium.make("tg_gpudrive/SingleAgent-v0", scenes=scene, config=SMALL, background="world_model")
    env.reset(seed=0)
    sim = env.unwrapped.sim
    bg = sim.background != 0
    assert int(bg.sum()) > 0 and not bool(bg[0, env.unwrapped.agent_slot])
    assert sim.policy_agents.sum() == 1
    for _ in range(6):
        env.step(env.unwrapped.cfg.noop_index)
    assert float(_log_gap(sim, bg).max()) > 0.1

    ctrl = control_masks([scene], EngineConfig(**SMALL), "nearest_conflict", 3)[0]
    par = TGParallelEnv(scene, config=SMALL, controlled=ctrl, background="world_model")
    obs, _ = par.reset()
    assert len(par.possible_agents) == 3 and len(obs) == 3
    bg_slots = set(np.nonzero((par.sim.background[0] != 0).numpy())[0].tolist())
    assert bg_slots and not bg_slots & {par.agent_slot(a) for a in par.possible_agents}
    for _ in range(3):
        obs, *_ = par.step({a: 45 for a in par.agents})
    assert set(obs) <= set(par.possible_agents)


def test_bad_background_values_are_clear_errors(tmp_path):
    scene = crossing_scene(T=20)
    cfg = dict(max_agents=4, road_k=8, partner_k=4)
    with pytest.raises(ValueError, match="background: expected one of log, world_model, idm, got 'replay'"):
        TGVectorEnv([scene], config=cfg, background="replay")
    with pytest.raises(ValueError, match="background"):
        TGSingleAgentEnv(scene, config=cfg, background="expert")
    with pytest.raises(ValueError, match="background"):
        TGParallelEnv(scene, config=cfg, background="")
    with pytest.raises(ValueError, match="other_policy"):
        TGSingleAgentEnv(scene, config=cfg, background="world_model", other_policy="expert")
    with pytest.raises(ValueError, match="background_model: only used with background world_model"):
        TGVectorEnv([scene], config=cfg, background_model="model.pt")
    with pytest.raises(FileNotFoundError, match="background_model: no world-model checkpoint"):
        TGVectorEnv([scene], config=cfg, background="world_model", background_model=tmp_path / "nope.pt")


def test_episode_ends_when_the_policy_agents_are_done_not_the_background(device):
    """Agent 0 (the policy's) reaches the end of a 20-step log; agent 1 (background) drives on to
    step 40. The episode must end with agent 0, at step 20; with agent 1 as the policy's too it
    runs on until agent 1 is done."""

    T = 41
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    pos[:, :, 0] = 10 * t
    pos[1, :, 1] = 20.0
    vel = np.zeros((2, T, 2))
    vel[:, :, 0] = 10.0
    valid = np.ones((2, T), bool)
    valid[0, 21:] = False
    scene = make_scene(pos, np.zeros((2, T)), log_vel=vel, log_valid=valid, length=4.0, width=2.0)
    cfg = EngineConfig(replay_infeasible=False, max_agents=4, road_k=8, partner_k=2, init_steps=1, goal_behaviour="remove",
                       auto_reset=False)
    ends = []
    for background in ([False, True], [False, False]):
        sim = Simulator([scene], cfg, device, controlled=[np.array([True, not background[1]])],
                        background=[np.array(background)])
        sim.reset()
        for step in range(T):
            sim.use_expert_actions()
            sim.step()
            if int(sim.world_ended[0]):
                ends.append(int(sim.world_step[0]))
                break
    assert ends[0] <= 21 < ends[1], ends
