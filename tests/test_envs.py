"""The gymnasium / PettingZoo front ends: API checkers, zero-copy device tensors, actions reaching
the engine unchanged (env vs bare Simulator, step by step), true terminal observations, and clear
errors for bad actions, finished agents and unknown scenes."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest
import torch
from conftest import WOMD_FILES
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test
from scenes import crossing_scene

import tg_gpudrive.envs  # noqa: F401  (registers the ids)
from tg_gpudrive.config import ConfigError, EngineConfig
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.engine.control import default_controlled, select_slots
from tg_gpudrive.envs.parallel import TGParallelEnv
from tg_gpudrive.envs.single import TGSingleAgentEnv
from tg_gpudrive.envs.vector import TGVectorEnv, make_config
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.enums import ActionSpace, CollisionMode

SMALL = dict(max_agents=16, road_k=16, partner_k=4)
TIME_LEFT = 9  # kernels/observation.py: last ego feature, time left (s)
T = 40


def head_on_scene():
    return crossing_scene(T)


def head_on_config(mode: str) -> dict:
    return dict(max_agents=4, init_steps=0, control="all_agents", collision_mode=mode, road_k=8, partner_k=4,
                replay_infeasible=False)  # the head-on logs collide by design


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checkers' advice about infinite obs bounds etc.
        return fn(*args, **kwargs)


# ------------------------------------------------------------ single agent
@pytest.mark.parametrize("env_id", ["tg_gpudrive/SingleAgent-v0", "tg_gpudrive/SingleAgentContinuous-v0"])
def test_single_agent_passes_check_env(env_id):
    env = gymnasium.make(env_id, scenes="procedural:merge", config=SMALL)
    quiet(check_env, env.unwrapped)
    want = gymnasium.spaces.Discrete(91) if env_id.endswith("SingleAgent-v0") else \
        gymnasium.spaces.Box(np.float32([-6, -0.3]), np.float32([6, 0.3]))
    assert env.action_space == want
    obs, info = env.reset(seed=3)
    assert obs.dtype == np.float32 and obs.shape == env.observation_space.shape
    assert env.unwrapped.scene.is_sdc[info["agent_index"]]  # the default agent is the SDC


def test_single_agent_default_config_on_real_scene():
    env = gymnasium.make("tg_gpudrive/SingleAgent-v0", scenes=str(WOMD_FILES[0]))
    obs, info = env.reset()
    assert obs.shape == (EngineConfig().road_k * 7 + EngineConfig().partner_k * 10 + 10,)
    env.action_space.seed(0)
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and isinstance(reward, float)
        assert set(info["reward_terms"]) == set(env.unwrapped.sim.reward_term_names)


@pytest.mark.parametrize("continuous", [False, True])
def test_single_agent_drives_the_engine_like_a_bare_simulator(continuous):
    """dense_intersection has more agents than its 16 slots: both keep the same ones."""

    scene = generate_scene("dense_intersection", 2)
    env = TGSingleAgentEnv(scene, config=SMALL, continuous=continuous)
    slot, cfg = env.agent_slot, env.cfg
    mask = np.zeros(scene.num_agents, bool)
    mask[env.agent_index] = True
    bare = Simulator([scene], cfg, "cpu", controlled=[mask])
    A = cfg.max_agents
    np.testing.assert_array_equal(env.world.slot_agent, bare.model.slot_agent[0])
    obs, _ = env.reset(seed=0)
    bare.reset()
    np.testing.assert_array_equal(obs, bare.obs[0, slot].numpy())
    rng = np.random.default_rng(0)
    actions = torch.zeros((1, A), dtype=torch.int32) if not continuous else torch.zeros((1, A, 2))
    for k in range(bare.episode_length - 1):  # the bare simulator resets after the last step
        a = rng.integers(0, 91) if not continuous else rng.uniform([-6, -0.3], [6, 0.3]).astype(np.float32)
        actions[0, slot] = torch.as_tensor(a)
        obs, reward, terminated, truncated, _ = env.step(a)
        bare.step(actions)
        assert reward == float(bare.reward[0, slot]) and terminated == bool(bare.terminated[0, slot])
        if terminated:  # the bare simulator has reset the world; the env kept the terminal state
            assert bare.world_reset[0] and not truncated
            break
        np.testing.assert_array_equal(env.sim.pos.numpy(), bare.pos.numpy())
        np.testing.assert_array_equal(obs, bare.obs[0, slot].numpy())  # time left included
    # an ordinary gymnasium episode ends with truncation at the scene's last step
    if not terminated:
        obs, *_, truncated, info = env.step(actions[0, slot].numpy())
        assert truncated and obs[TIME_LEFT] == 0.0 and info["final_steps"] == bare.episode_length


def test_single_agent_terminal_obs_is_the_terminal_state_and_no_auto_reset():
    """In stop mode A (the only controlled agent) ends by hitting B on step 18: the obs returned then
    is that state (collided flag set), not the next episode's first obs; stepping on is an error."""
    cfg = head_on_config("stop") | {"control": "vehicles"}
    env = TGSingleAgentEnv(head_on_scene(), agent=0, config=cfg)
    noop = env.cfg.noop_index
    first, _ = env.reset()
    for k in range(30):
        obs, reward, terminated, truncated, info = env.step(noop)
        if terminated:
            break
    assert terminated and not truncated and k + 1 == 18
    assert obs[5] == 1.0 and first[5] == 0.0  # episode collided flag of the ego features
    assert abs(float(env.sim.pos[0, 0, 0]) - 18.0) < 1e-3  # frozen where it hit, not back at the start
    assert info["final_collided"] and info["reward_terms"]["collision"] == 1.0 and info["final_steps"] == 18
    with pytest.raises(ValueError, match="action for finished agent 0 .*call reset"):
        env.step(noop)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs, first)


def test_single_agent_other_policy_drives_the_others():

    scene = generate_scene("t_junction", 1)
    env = TGSingleAgentEnv(scene, config=SMALL, other_policy="expert")
    cfg = env.cfg
    idx = select_slots(scene, cfg.max_agents, cfg.init_steps)
    mask = np.zeros(scene.num_agents, bool)
    mask[idx[default_controlled(scene, idx, cfg)[0]]] = True
    bare = Simulator([scene], cfg, "cpu", controlled=[mask])
    assert mask.sum() > 1 and env.sim.integrated.sum() == mask.sum()
    env.reset()
    bare.reset()
    for _ in range(20):
        bare.use_expert_actions()
        bare.actions_index[0, env.agent_slot] = 7
        env.step(7)
        bare.step()
        np.testing.assert_array_equal(env.sim.pos.numpy(), bare.pos.numpy())


def test_single_agent_bad_actions_are_clear_errors():
    env = TGSingleAgentEnv("procedural:merge", config=SMALL)
    env.reset()
    with pytest.raises(ValueError, match=r"expected one integer action in \[0, 91\)"):
        env.step(3.0)
    with pytest.raises(ValueError, match=r"expected one integer action"):
        env.step(np.array([1, 2]))
    with pytest.raises(ValueError, match=r"discrete action 91 outside \[0, 91\)"):
        env.step(91)
    cont = TGSingleAgentEnv("procedural:merge", config=SMALL, continuous=True)
    cont.reset()
    with pytest.raises(ValueError, match=r"expected a float array of shape \(2,\)"):
        cont.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"expected a float array of shape \(2,\)"):
        cont.step(np.zeros(2, np.int64))
    with pytest.raises(ValueError, match="NaN or inf"):
        cont.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(RuntimeError, match="reset"):
        TGSingleAgentEnv("procedural:merge", config=SMALL).step(0)


# ---------------------------------------------------------------- vector
def test_vector_env_through_make_vec_stays_on_device(device):
    env = gymnasium.make_vec("tg_gpudrive/Vector-v0", num_envs=3 * 16, scenes="procedural:all", config=SMALL,
                             device=device)
    u = env.unwrapped
    assert isinstance(u, TGVectorEnv) and u.num_worlds == 3 and env.num_envs == 3 * 16
    assert env.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP
    assert env.single_action_space == gymnasium.spaces.Discrete(91)
    dev = torch.device(device)
    obs, info = env.reset(seed=0)
    assert obs.data_ptr() == u.sim.obs.data_ptr()  # the engine's buffer itself
    gen = torch.Generator(device=device).manual_seed(0)
    for _ in range(5):
        a = torch.randint(0, 91, (env.num_envs,), generator=gen, device=device)
        obs, reward, terminated, truncated, info = env.step(a)
        for t in (obs, reward, terminated, truncated, info["cost"], info["active"], info["alive"],
                  info["world_reset"], info["final_goal"], *info["reward_terms"].values()):
            assert isinstance(t, torch.Tensor) and t.device == dev
        assert obs.shape == (48, u.sim.obs_dim) and terminated.dtype == torch.bool
        assert reward.data_ptr() == u.sim.reward.data_ptr()
    assert set(info["reward_terms"]) == set(u.reward_term_names)
    # rows of slots that are not controlled are always masked
    unctrl = ~u.controlled
    assert unctrl.any() and not info["active"][unctrl].any() and not (reward[unctrl] != 0).any()
    cont = gymnasium.make_vec("tg_gpudrive/VectorContinuous-v0", num_worlds=2, scenes="procedural:merge",
                              config=SMALL, device=device)
    cont.reset()
    out = cont.step(torch.zeros((cont.num_envs, 2), device=device))
    assert out[0].device == dev and cont.single_action_space.shape == (2,)


def test_vector_env_num_envs_is_the_argument_and_the_batch_size():
    # an env is one agent slot (a row): make_vec(num_envs=N) reports num_envs == N == the batch size
    env = gymnasium.make_vec("tg_gpudrive/Vector-v0", num_envs=32, scenes="procedural:merge", config=SMALL)
    obs, info = env.reset()
    assert env.num_envs == 32 and env.unwrapped.num_worlds == 2
    assert obs.shape[0] == env.observation_space.shape[0] == env.action_space.shape[0] == 32
    assert info["active"].shape == (32,)
    # worlds instead of rows; both given must agree
    by_worlds = gymnasium.make_vec("tg_gpudrive/Vector-v0", num_worlds=2, scenes="procedural:merge", config=SMALL)
    assert by_worlds.num_envs == 32
    assert TGVectorEnv("procedural:merge", num_envs=48, config=SMALL).num_worlds == 3
    assert TGVectorEnv("procedural:merge", num_envs=32, num_worlds=2, config=SMALL).num_envs == 32
    with pytest.raises(ValueError, match=r"num_envs=33: an env is one agent slot .* multiple of max_agents=16"):
        gymnasium.make_vec("tg_gpudrive/Vector-v0", num_envs=33, scenes="procedural:merge", config=SMALL)
    with pytest.raises(ValueError, match="num_envs=32 and num_worlds=3 disagree"):
        gymnasium.make_vec("tg_gpudrive/Vector-v0", num_envs=32, num_worlds=3, scenes="procedural:merge",
                           config=SMALL)
    # make_vec's default num_envs=1 means "not given": one world per scene of a list
    scenes = [crossing_scene(T), crossing_scene(T)]
    assert gymnasium.make_vec("tg_gpudrive/Vector-v0", scenes=scenes, config=SMALL).num_envs == 2 * 16


def test_vector_env_build_shows_progress(monkeypatch, capsys):
    monkeypatch.setattr(TGVectorEnv, "progress_delay_s", 0.0)  # as if the build were slow
    env = TGVectorEnv("procedural:merge", num_worlds=3, config=SMALL)
    err = capsys.readouterr().err
    assert "TGVectorEnv: scenes" in err and "3/3" in err and "building the engine" in err
    env.reset(options={"scenes": "procedural:roundabout"})
    assert "TGVectorEnv: scenes" in capsys.readouterr().err
    TGVectorEnv("procedural:merge", num_worlds=3, config=SMALL, progress=False)
    assert "TGVectorEnv" not in capsys.readouterr().err


def test_vector_env_matches_bare_simulator_across_auto_reset():

    scenes = [generate_scene("merge", 0), generate_scene("roundabout", 1)]
    env = TGVectorEnv(scenes, config=SMALL)
    bare = Simulator(scenes, env.cfg, "cpu")
    first, _ = env.reset()
    first = first.clone()
    bare.reset()
    rng = torch.Generator().manual_seed(1)
    seen_reset = False
    for k in range(bare.episode_length + 3):
        a = torch.randint(0, 91, (env.num_envs,), generator=rng)
        obs, reward, terminated, truncated, info = env.step(a)
        bare.step(a.view(2, 16).to(torch.int32))
        torch.testing.assert_close(env.sim.pos, bare.pos, rtol=0, atol=0)
        torch.testing.assert_close(obs.view(2, 16, -1), bare.obs, rtol=0, atol=0)
        torch.testing.assert_close(reward.view(2, 16), bare.reward, rtol=0, atol=0)
        assert terminated.view(2, 16).tolist() == (bare.terminated != 0).tolist()
        if info["world_reset"].any():
            seen_reset = True
            rows = info["world_reset"]
            assert (rows == (bare.world_reset[:, None] != 0).expand(2, 16).reshape(-1) & env.controlled).all()
            # SAME_STEP: the obs is already the new episode's first one; outcomes in final_*
            torch.testing.assert_close(obs[rows], first[rows], rtol=0, atol=0)
            assert (truncated[rows] | terminated[rows] | ~info["alive"][rows]).all()
            assert (info["final_steps"][rows] > 0).all()
    assert seen_reset


def test_vector_env_without_auto_reset_freezes_ended_worlds_until_reset_mask():
    """auto_reset=False: DISABLED mode. In remove mode A and B leave on step 18, C runs to the limit."""
    env = TGVectorEnv([head_on_scene(), head_on_scene()], config=head_on_config("remove") | {"auto_reset": False})
    assert env.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.DISABLED
    assert TGVectorEnv.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP
    first, _ = env.reset()
    first = first.clone()
    noop = torch.full((8,), env.noop_action)
    for k in range(1, T):
        obs, reward, terminated, truncated, info = env.step(noop)
        if k == 18:
            assert terminated.tolist() == [True, True, False, False] * 2
    # the last step: C truncated, its obs the terminal one (no time left), outcomes in final_*
    assert truncated.tolist() == [False, False, True, False] * 2 and info["world_ended"][[2, 6]].all()
    assert not info["world_reset"].any() and not info["active"].any()
    assert obs[2, TIME_LEFT] == 0.0 and first[2, TIME_LEFT] > 0
    assert info["final_steps"].view(2, 4)[:, :3].tolist() == [[18, 18, T - 1]] * 2
    frozen = env.sim.pos.clone()
    obs, reward, *_ = env.step(noop)  # ended worlds stay as they are
    torch.testing.assert_close(env.sim.pos, frozen, rtol=0, atol=0)
    assert not reward.any()
    mask = torch.zeros(8, dtype=torch.bool)
    mask[5] = True  # a row of world 1
    obs, info = env.reset(options={"reset_mask": mask})
    torch.testing.assert_close(obs[4:], first[4:], rtol=0, atol=0)
    torch.testing.assert_close(env.sim.pos[0], frozen[0], rtol=0, atol=0)
    assert info["active"].tolist() == [False] * 4 + [True] * 3 + [False]
    with pytest.raises(ValueError, match=r"reset_mask must be a bool array of shape \(8,\)"):
        env.reset(options={"reset_mask": np.ones(2, bool)})


def test_vector_env_bad_actions_are_clear_errors():
    env = TGVectorEnv("procedural:merge", num_worlds=2, config=SMALL)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(torch.zeros(32, dtype=torch.int64))
    env.reset()
    with pytest.raises(ValueError, match=r"expected shape \(32,\) \(num_envs = 2 worlds x 16 slots\)"):
        env.step(torch.zeros((2, 16), dtype=torch.int64))
    with pytest.raises(ValueError, match="must be an integer dtype, got torch.float32"):
        env.step(torch.zeros(32))
    with pytest.raises(ValueError, match=r"must lie in \[0, 91\)"):
        env.step(np.full(32, 91))
    env.step(np.zeros(32, np.int64))  # numpy works too; inactive rows are ignored by default
    strict = TGVectorEnv("procedural:merge", num_worlds=2, config=SMALL, strict=True)
    strict.reset()
    a = torch.full((32,), strict.noop_action)
    strict.step(a)  # uncontrolled rows hold the no-op: fine
    idle = int(torch.nonzero(~strict.controlled)[0])
    a[idle] = 3
    with pytest.raises(ValueError, match=rf"action for finished agent row\(s\) \[{idle}\]"):
        strict.step(a)
    cont = TGVectorEnv("procedural:merge", config=SMALL, continuous=True)
    cont.reset()
    with pytest.raises(ValueError, match=r"expected shape \(16, 2\)"):
        cont.step(torch.zeros(16, 3))
    with pytest.raises(ValueError, match="must be a float dtype"):
        cont.step(torch.zeros((16, 2), dtype=torch.int32))


# --------------------------------------------------------------- parallel
@pytest.mark.parametrize("scenes", ["procedural:dense_intersection", WOMD_FILES[0]], ids=["procedural", "womd"])
def test_parallel_env_passes_parallel_api_test(scenes):
    env = TGParallelEnv(scenes, config=SMALL | {"collision_mode": "remove"})
    assert env.possible_agents and all(a.startswith("agent_") for a in env.possible_agents)
    quiet(parallel_api_test, env, num_cycles=200)


def test_parallel_env_discrete_default_config_on_other_real_scene():
    env = TGParallelEnv(WOMD_FILES[1])
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(env.agents) == set(env.possible_agents)
    quiet(parallel_api_test, env, num_cycles=5)


@pytest.mark.parametrize("continuous", [False, True])
def test_parallel_env_drives_the_engine_like_a_bare_simulator(continuous):
    env = TGParallelEnv("procedural:roundabout", config=SMALL | {"collision_mode": "stop"}, continuous=continuous)
    bare = Simulator([env.scene], env.cfg, "cpu")
    assert [env.agent_slot(a) for a in env.possible_agents] == torch.nonzero(bare.policy_agents[0])[:, 0].tolist()
    obs, _ = env.reset(seed=0)
    bare.reset()
    actions = torch.zeros((1, 16), dtype=torch.int32) if not continuous else torch.zeros((1, 16, 2))
    for _ in range(bare.episode_length):
        acts = {a: env.action_space(a).sample() for a in env.agents}
        for a, v in acts.items():
            actions[0, env.agent_slot(a)] = torch.as_tensor(v)
        obs, rew, term, trunc, _ = env.step(acts)
        bare.step(actions)
        for a in acts:
            s = env.agent_slot(a)
            assert rew[a] == float(bare.reward[0, s]) and term[a] == bool(bare.terminated[0, s])
        if bare.world_reset[0]:
            break
        np.testing.assert_array_equal(env.sim.pos.numpy(), bare.pos.numpy())
        for a in acts:
            np.testing.assert_array_equal(obs[a], bare.obs[0, env.agent_slot(a)].numpy())
    assert not env.agents  # the episode ended in both


@pytest.mark.parametrize("mode", ["ignore", "stop", "remove"])
def test_parallel_env_agents_leave_per_collision_mode(mode):
    env = TGParallelEnv(head_on_scene(), config=head_on_config(mode))
    bare = Simulator([head_on_scene()], env.cfg, "cpu")
    assert env.possible_agents == ["agent_0", "agent_1", "agent_2"]
    noop = env.cfg.noop_index
    env.reset()
    bare.reset()
    left = {}
    for k in range(1, T):
        acting = list(env.agents)
        obs, rew, term, trunc, info = env.step({a: noop for a in env.agents})
        bare.step(torch.full((1, 4), noop, dtype=torch.int32))
        assert set(obs) == set(acting)
        if not bare.world_reset[0]:
            np.testing.assert_array_equal(env.sim.pos[0].numpy(), bare.pos[0].numpy())
        for a in acting:
            if term[a] or trunc[a]:
                left[a] = (k, term[a])
                assert info[a]["final_steps"] == k
        if not env.agents:
            break
    if mode == "ignore":  # collisions are counted only: everyone runs to the time limit
        assert left == {a: (T - 1, False) for a in env.possible_agents}
        assert info["agent_0"]["final_collided"]
    elif mode == "remove":  # A and B leave at the collision; C passes where they were
        assert left == {"agent_0": (18, True), "agent_1": (18, True), "agent_2": (T - 1, False)}
    else:  # frozen A and B stay in the scene and C runs into them
        assert left["agent_0"] == left["agent_1"] == (18, True)
        assert left["agent_2"][1] and 18 < left["agent_2"][0] < T - 1
        assert obs["agent_2"][5] == 1.0  # terminal obs: C's collided flag, not a reset obs


def test_parallel_env_bad_actions_are_clear_errors():
    env = TGParallelEnv(head_on_scene(), config=head_on_config("remove"))
    noop = env.cfg.noop_index
    with pytest.raises(ValueError, match=r"no live agent.*call reset\(\)"):
        env.step({})
    env.reset()
    with pytest.raises(ValueError, match="missing for live agents"):
        env.step({"agent_0": noop})
    with pytest.raises(ValueError, match="action for unknown agent 'agent_9'"):
        env.step({a: noop for a in env.agents} | {"agent_9": noop})
    with pytest.raises(ValueError, match=r"action of 'agent_0': expected one integer action in \[0, 91\)"):
        env.step({a: 0.5 for a in env.agents})
    for _ in range(18):
        env.step({a: noop for a in env.agents})
    assert env.agents == ["agent_2"]
    with pytest.raises(ValueError, match="action for finished agent 'agent_0': it left env.agents "
                                         r"\(terminated at log step 18\)"):
        env.step({"agent_0": noop, "agent_2": noop})
    cont = TGParallelEnv(head_on_scene(), config=head_on_config("remove"), continuous=True)
    cont.reset()
    with pytest.raises(ValueError, match=r"expected a float array of shape \(2,\)"):
        cont.step({a: np.zeros(3, np.float32) for a in cont.agents})


# ----------------------------------------------------- config and scenes
def test_unknown_scene_spec_and_config_key_are_clear_errors():
    with pytest.raises(ValueError, match="unknown scenario type 'nope'"):
        gymnasium.make("tg_gpudrive/SingleAgent-v0", scenes="procedural:nope")
    with pytest.raises(ValueError, match="unknown scenario type 'nope'"):
        gymnasium.make_vec("tg_gpudrive/Vector-v0", num_worlds=2, scenes="procedural:nope")
    with pytest.raises(ValueError, match="unknown scenario type 'nope'"):
        TGParallelEnv("procedural:nope")
    with pytest.raises(ValueError, match="no such file or directory"):
        TGVectorEnv("no/such/scenes.json")
    with pytest.raises(ConfigError, match="unknown key 'max_agent'"):
        make_config({"max_agent": 3})
    with pytest.raises(ConfigError, match="unknown key 'reward.goal'"):
        make_config(None, ["reward.goal=3"])
    cfg = make_config(EngineConfig(replay_infeasible=False, max_agents=8), {"reward.goal_reached": 2, "collision_mode": "stop"}, True)
    assert (cfg.max_agents, cfg.reward.goal_reached, cfg.collision_mode, cfg.action_space) == \
        (8, 2.0, CollisionMode.STOP, ActionSpace.CONTINUOUS)


def test_render_is_delegated_to_the_renderer():
    try:
        import tg_gpudrive.render  # noqa: F401
    except ImportError:
        env = TGSingleAgentEnv("procedural:merge", config=SMALL, render_mode="rgb_array")
        env.reset()
        with pytest.raises(RuntimeError, match="rendering needs tg_gpudrive.render"):
            env.render()
        return
    for env in (TGSingleAgentEnv("procedural:merge", config=SMALL, render_mode="rgb_array"),
                TGParallelEnv("procedural:merge", config=SMALL, render_mode="rgb_array")):
        env.reset()
        frame = env.render()
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    vec = TGVectorEnv("procedural:merge", num_worlds=2, config=SMALL, render_mode="rgb_array",
                      render_worlds=(0, 1))
    vec.reset()
    frames = vec.render()
    assert len(frames) == 2 and frames[0].dtype == np.uint8
