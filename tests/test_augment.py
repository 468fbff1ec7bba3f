"""Augmentation knobs: each transform against what it must preserve or change, and the trainer's use."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tg_gpudrive.config import AugmentConfig, ConfigError, EngineConfig
from tg_gpudrive.data.augment import (augment_scene, delay_agents, mirror, perturb_start, rotate, shift_start,
                                     subset_mask)
from tg_gpudrive.data.log_audit import infeasible_mask
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.scene import make_scene
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout


@pytest.fixture(scope="module")
def scene():
    return generate_scene("t_junction", 3)


def pairwise(s, t):
    p = s.log_pos[:, t][s.log_valid[:, t]].astype(np.float64)
    return np.linalg.norm(p[:, None] - p[None], axis=-1)


def expert_rates(scenes):
    sim = Simulator(scenes, EngineConfig(), "cpu")
    out = run_rollout(sim, expert_policy, sim.episode_length, episodes_per_world=1)
    return out["goal_rate"], out["collision_rate"], out["offroad_rate"], out["agent_episodes"]


def test_mirror_twice_is_the_identity_and_flips_the_turns(scene):
    m = mirror(scene)
    np.testing.assert_allclose(m.log_pos[..., 1], -scene.log_pos[..., 1])
    np.testing.assert_allclose(m.log_yaw[scene.log_valid], -scene.log_yaw[scene.log_valid], atol=1e-6)
    back = mirror(m)
    for name in ("log_pos", "log_vel", "goal", "road_points"):
        np.testing.assert_allclose(getattr(back, name), getattr(scene, name), atol=1e-5)
    assert scene.log_pos[..., 1].any() and not np.shares_memory(m.log_pos, scene.log_pos)  # input untouched


def test_rotation_is_rigid_and_keeps_the_expert_replay(scene):
    r = rotate(scene, 1.1)
    np.testing.assert_allclose(pairwise(r, 10), pairwise(scene, 10), atol=1e-3)
    v = scene.log_valid
    dyaw = (r.log_yaw[v] - scene.log_yaw[v] - 1.1 + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(r.log_vel, axis=-1), np.linalg.norm(scene.log_vel, axis=-1), atol=1e-4)
    base, turned = expert_rates([scene]), expert_rates([r])
    assert turned[3] == base[3] and abs(turned[0] - base[0]) < 1e-9 and turned[1:3] == base[1:3]
    np.testing.assert_array_equal(infeasible_mask(r, 10, 2.0), infeasible_mask(scene, 10, 2.0))


def test_start_shift_cuts_the_first_steps(scene):
    s = shift_start(scene, 7)
    assert s.num_steps == scene.num_steps - 7 and s.tl_state.shape[0] == s.num_steps
    np.testing.assert_array_equal(s.log_pos[:, 0], scene.log_pos[:, 7])
    assert "log_audit" not in s.metadata and s.metadata["start_shift"] == 7
    assert shift_start(scene, 0) is scene


def test_a_shifted_scene_carries_the_audit_it_would_get_afresh():
    from tg_gpudrive.data.log_audit import audit, infeasible_reasons
    from tg_gpudrive.scene import make_scene

    t = np.arange(60) * 0.1
    pos = np.zeros((3, 60, 2))
    pos[0, :, 0] = 10 * t
    pos[1, :, 0] = 10 * t + 3.0  # overlaps car 0 throughout
    pos[2, :, 0], pos[2, :, 1] = 10 * t, 20.0
    pos[2, 30:, 0] += 5.0  # a 5 m jump at step 30: inside the window from steps 10 and 25, not from 40
    sc = make_scene(pos, np.zeros((3, 60)))
    for k in (0, 15, 30):
        shifted = shift_start(sc, k, 10, 2.0)
        fresh = audit(shifted, 10, 2.0)
        assert infeasible_reasons(shifted, 10, 2.0) == fresh
    assert 2 in audit(shift_start(sc, 15), 10, 2.0) and 2 not in audit(shift_start(sc, 30), 10, 2.0)
    assert "10:2" in sc.metadata["log_audit"] and "40:2" in sc.metadata["log_audit"]  # cached on the source


def test_perturbation_moves_the_warm_up_only(scene):
    rng = np.random.default_rng(0)
    p = perturb_start(scene, 10, 2.0, 0.5, 0.1, rng)
    moved = np.abs(p.log_pos[:, :11] - scene.log_pos[:, :11]).max(axis=(1, 2))
    assert (moved > 0).any() and moved.max() < 5 * 0.5 * 2
    np.testing.assert_array_equal(p.log_pos[:, 11:], scene.log_pos[:, 11:])
    # one offset per vehicle: its warm-up motion is kept
    i = int(np.argmax(moved))
    d = p.log_pos[i, :11] - scene.log_pos[i, :11]
    np.testing.assert_allclose(d - d[0], 0.0, atol=1e-5)
    assert perturb_start(scene, 10, 2.0, 0.0, 0.0, rng) is scene


def test_control_subsets_keep_at_least_one():
    rng = np.random.default_rng(1)
    mask = np.array([True, True, False, True, True, True, True, True])
    kept = [subset_mask(mask, 0.5, rng) for _ in range(200)]
    assert all((k <= mask).all() and k.any() for k in kept)
    assert 0.4 < np.mean([k.sum() / mask.sum() for k in kept]) < 0.6
    assert (subset_mask(mask, 1.0, rng) == mask).all() and not subset_mask(np.zeros(3, bool), 0.5, rng).any()


def test_a_delayed_vehicle_replays_its_own_log_later(scene):
    """Each delayed candidate's row reads the source's log d steps earlier (d from the cut steps of the start
    shift), invalid before the source's first step, with its goal at the delayed log's end; the others keep
    theirs."""
    k = 10
    shifted = shift_start(scene, k)
    out = delay_agents(shifted, scene, k, 10, 2.0, 1.0, 15, np.random.default_rng(3))
    delays = out.metadata["agent_delays"]
    assert delays and all(1 <= d <= 15 for d in delays.values())
    t = np.arange(out.num_steps)
    for i in range(out.num_agents):
        d = delays.get(i, 0)
        src = t + k - d
        ok = (src >= 0) & scene.log_valid[i, np.clip(src, 0, None)]
        np.testing.assert_array_equal(out.log_valid[i], ok)
        np.testing.assert_array_equal(out.log_pos[i][ok], scene.log_pos[i, src[ok]])
        np.testing.assert_array_equal(out.log_yaw[i][ok], scene.log_yaw[i, src[ok]])
        if d:
            np.testing.assert_array_equal(out.goal[i], out.log_pos[i, np.flatnonzero(ok)[-1]])
        else:
            np.testing.assert_array_equal(out.goal[i], shifted.goal[i])
    assert np.array_equal(shifted.log_pos, shift_start(scene, k).log_pos)  # the input is not changed


def test_a_delay_that_would_meet_another_box_is_not_taken():
    """A car at 5 m/s with a pedestrian-typed box of the same size 6.2 m behind it in step: a delay of d steps
    brings it 0.5 d m back, so 3 steps leave 0.2 m between the boxes and 4 or more make them meet."""
    T = 61
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    pos[0, :, 0] = 5 * t
    pos[1, :, 0] = 5 * t - 6.2
    sc = make_scene(pos, np.zeros((2, T)), agent_type=np.array([1, 2]))
    taken = set()
    for seed in range(40):
        out = delay_agents(shift_start(sc, 10), sc, 10, 10, 2.0, 1.0, 8, np.random.default_rng(seed))
        taken |= set(out.metadata["agent_delays"].values())
    assert taken == {1, 2, 3}


def test_augment_scene_off_is_the_identity_and_knobs_are_checked(scene):
    rng = np.random.default_rng(0)
    assert augment_scene(scene, AugmentConfig(), 10, 2.0, rng) is scene
    on = augment_scene(scene, AugmentConfig(mirror=1.0, rotate=True, start_shift=5), 10, 2.0, rng)
    assert on is not scene and on.num_steps >= scene.num_steps - 5
    delayed = augment_scene(scene, AugmentConfig(start_shift=20, delay_share=1.0, max_delay=25), 10, 2.0, rng)
    assert delayed.metadata["agent_delays"] and max(delayed.metadata["agent_delays"].values()) <= 25
    for bad in (dict(mirror=1.5), dict(control_fraction=0.0), dict(start_shift=-1), dict(delay_share=1.5)):
        with pytest.raises(ConfigError):
            AugmentConfig(**bad)


def test_trainer_augments_its_worlds_and_rebuilds_them_the_same(tmp_path):
    from test_train import tiny

    from tg_gpudrive.learn.train import Trainer

    cfg = tiny(tmp_path, updates=1, num_worlds=4, prior="expert")
    cfg = dataclasses.replace(cfg, augment=AugmentConfig(mirror=0.5, rotate=True, start_shift=5, control_fraction=0.5))
    a = Trainer(cfg, tmp_path / "a", progress=False)
    b = Trainer(cfg, tmp_path / "b", progress=False)
    pa, pb = a.sim.pos.numpy(), b.sim.pos.numpy()
    np.testing.assert_array_equal(pa, pb)  # the draws are seeded: the same worlds
    plain = Trainer(tiny(tmp_path, updates=1, num_worlds=4, prior="expert"), tmp_path / "c", progress=False)
    assert not np.array_equal(plain.sim.pos.numpy(), pa)
    assert int(a.sim.policy_agents.sum()) < int(plain.sim.policy_agents.sum())  # control_fraction 0.5
