"""Dense WOMD-size benchmark scenes (`procedural:dense`): sizes, layout, resampling, and that the
engine drives them like their procedural tiles (expert replay: no collision, no off-road)."""

from __future__ import annotations

import numpy as np
import pytest

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.data.procedural.dense import DENSE_AGENTS, DENSE_ROAD_POINTS, TILE_PARAMS, dense_scene, \
    resample_polylines
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout


def test_resample_polylines_hand_computed():
    pts = np.array([[0, 0], [10, 0], [5, 5], [0, 0], [0, 3], [0, 4]], np.float32)
    off = np.array([0, 2, 3, 6])  # a 10 m line, a single point, an L of 3 + 1 m
    p, o = resample_polylines(pts, off, 2.5)
    np.testing.assert_array_equal(o, [0, 5, 6, 9])
    np.testing.assert_allclose(p[:5], [[0, 0], [2.5, 0], [5, 0], [7.5, 0], [10, 0]])
    np.testing.assert_allclose(p[5], [5, 5])
    np.testing.assert_allclose(p[6:], [[0, 0], [0, 2], [0, 4]], atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_dense_scene_sizes_and_layout(seed):
    s = dense_scene(seed)
    assert DENSE_AGENTS[0] <= s.num_agents <= DENSE_AGENTS[1]
    lo, hi = DENSE_ROAD_POINTS
    assert 0.97 * lo <= len(s.road_points) <= 1.03 * hi
    assert s.is_sdc.sum() <= 1 and len(set(s.agent_id.tolist())) == s.num_agents
    # every tile is its procedural scene moved rigidly: relative log positions are kept
    first = generate_scene(s.metadata["tile_types"][0], s.metadata["tile_seeds"][0], TILE_PARAMS)
    k = min(first.num_agents, s.num_agents)
    v = first.log_valid[:k]
    d = s.log_pos[:k][v] - first.log_pos[:k][v]
    np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-3)
    np.testing.assert_allclose(s.goal[:k] - first.goal[:k], np.broadcast_to(d[0], (k, 2)), atol=1e-3)


def test_dense_scene_explicit_sizes_and_bad_input():
    s = dense_scene(5, agents=70, road_points=25_000)
    assert s.num_agents == 70 and abs(len(s.road_points) - 25_000) <= 0.03 * 25_000
    with pytest.raises(ValueError, match="agents"):
        dense_scene(5, agents=0)


def test_expert_replay_of_dense_scenes_is_clean():
    """The tiles' invariants survive the layout: the expert never collides or leaves the road."""
    src = resolve_scenes("procedural:dense", n=2, seed=3)
    scenes = [src.get(i) for i in range(2)]
    sim = Simulator(scenes, EngineConfig(max_agents=128, partner_k=8, road_k=32), "cpu")
    assert sim.report()["agents_dropped"] == 0
    out = run_rollout(sim, expert_policy, sim.episode_length)
    assert out["episodes"] >= 100
    assert out["collision_rate"] == 0.0 and out["offroad_rate"] == 0.0
    assert out["goal_rate"] > 0.9
