"""The safety guard over a policy's discrete actions (agents/guard.py): its box test against an independent
polygon-intersection reference, its stopping paths against the bicycle written out by hand, hand-built
conflicts where exactly the actions that cannot stop in time are refused, and in the engine a crossing that
no-op driving collides in and the guarded driving does not."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from scenes import crossing_scene

from tg_gpudrive import cli
from tg_gpudrive.agents import open_policy
from tg_gpudrive.agents.guard import ActionGuard, boxes_overlap
from tg_gpudrive.agents.policy import action_grid, guard_for
from tg_gpudrive.config import REPO_CONFIGS, ConfigError, EngineConfig, TrainConfig, from_dict, load_config, to_dict
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM

ENV = EngineConfig()
DT = 0.1


def cross(u, v) -> float:
    return u[0] * v[1] - u[1] * v[0]


def corners(c, h, e) -> np.ndarray:
    n = np.array([-h[1], h[0]])
    return np.array([c + sx * e[0] * h + sy * e[1] * n for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))])


def inside(p, poly) -> bool:
    """Point in a convex counter-clockwise polygon, edges included."""
    return all(cross(poly[(i + 1) % 4] - poly[i], p - poly[i]) >= -1e-9 for i in range(4))


def segments_cross(a, b, c, d) -> bool:
    def orient(p, q, r):
        return np.sign(cross(q - p, r - p))
    return orient(a, b, c) * orient(a, b, d) <= 0 and orient(c, d, a) * orient(c, d, b) <= 0


def polygons_meet(p, q) -> bool:
    """Independent of the separating-axis test: a corner inside the other box, or two edges that cross."""
    if any(inside(x, q) for x in p) or any(inside(x, p) for x in q):
        return True
    return any(segments_cross(p[i], p[(i + 1) % 4], q[j], q[(j + 1) % 4]) for i in range(4) for j in range(4))


def test_box_overlap_matches_polygon_intersection(device):
    rng = np.random.default_rng(7)
    n = 3000
    c = rng.uniform(-3, 3, (n, 2, 2))
    ang = rng.uniform(-math.pi, math.pi, (n, 2))
    h = np.stack([np.cos(ang), np.sin(ang)], -1)
    e = np.stack([rng.uniform(0.3, 3, (n, 2)), rng.uniform(0.2, 1.2, (n, 2))], -1)
    want = np.array([polygons_meet(corners(c[i, 0], h[i, 0], e[i, 0]), corners(c[i, 1], h[i, 1], e[i, 1]))
                     for i in range(n)])
    t = {k: torch.tensor(v, dtype=torch.float32, device=device) for k, v in (("c", c), ("h", h), ("e", e))}
    got = boxes_overlap(t["c"][:, 0], t["h"][:, 0], t["e"][:, 0], t["c"][:, 1], t["h"][:, 1], t["e"][:, 1])
    assert 0.2 < want.mean() < 0.8  # both outcomes well represented
    assert np.array_equal(got.cpu().numpy(), want)


def test_ego_paths_take_the_action_once_then_brake_as_the_bicycle_does(device):
    guard = ActionGuard(action_grid(ENV), 1, DT, 6.0, horizon=1.0)
    acts = torch.tensor([[2.0, 0.0], [0.0, 0.1], [-6.0, 0.0]], device=device)
    centres, heads = guard.ego_paths(torch.tensor([10.0], device=device), acts)
    assert centres.shape == (3, 10, 2)
    for i, (a0, k) in enumerate(acts.cpu().numpy()):
        x = y = yaw = 0.0
        v = 10.0
        for t in range(10):
            a = a0 if t == 0 else -6.0
            arc = v * DT + 0.5 * a * DT * DT
            x, y = x + math.cos(yaw) * arc, y + math.sin(yaw) * arc
            yaw += k * arc
            v = max(v + a * DT, 0.0)
            np.testing.assert_allclose(centres[i, t].cpu().numpy(), [x, y], atol=1e-4)
            np.testing.assert_allclose(heads[i, t].cpu().numpy(), [math.cos(yaw), math.sin(yaw)], atol=1e-5)


def obs_row(speed: float, partners: list[list[float]], k: int = 4) -> torch.Tensor:
    """One observation row: the agent (4.5 x 2 m) at `speed`, partner rows (mask, x, y, cos, sin, vx, vy relative
    to the agent's velocity, length, width, type)."""
    o = torch.zeros(EGO_DIM + k * PARTNER_DIM + 7)
    o[0], o[1], o[2] = speed, 4.5, 2.0
    for j, p in enumerate(partners):
        o[EGO_DIM + j * PARTNER_DIM: EGO_DIM + (j + 1) * PARTNER_DIM] = torch.tensor(p)
    return o


def crossing_partner(x: float, arrive_s: float, speed: float = 12.0) -> list[float]:
    """A car crossing the agent's path from its left at `x` ahead, its centre on the path after `arrive_s`, seen
    by an agent at 10 m/s (relative vx -10)."""
    return [1, x, speed * arrive_s, 0.0, -1.0, -10.0, -speed, 4.5, 2.0, 1]


def grid_flags(guard, obs) -> np.ndarray:
    return guard.unsafe(obs[None], guard.grid[None]).reshape(ENV.accel_bins, ENV.curvature_bins).numpy()


def test_actions_that_cannot_stop_short_of_a_crossing_car_are_unsafe():
    guard = ActionGuard(action_grid(ENV), 4, DT, ENV.max_accel, horizon=2.0)
    straight = ENV.curvature_bins // 2
    # at 10 m/s braking from the next step stops the front 10.6 m (full brake now) to 12.6 m (full throttle now)
    # ahead; a car whose near side is 11 m ahead and crosses while the agent is still rolling
    flags = grid_flags(guard, obs_row(10.0, [crossing_partner(12.0, 1.2)]))
    assert flags[-1, straight] and not flags[0, straight]
    # the same car 30 m ahead, or already past: nothing is unsafe
    assert not grid_flags(guard, obs_row(10.0, [crossing_partner(30.0, 1.2)])).any()
    assert not grid_flags(guard, obs_row(10.0, [crossing_partner(12.0, -2.0)])).any()
    # a car abreast in the next lane (3.5 m to the left) at the agent's speed, and a masked-out partner row: going
    # straight or to the right is safe; a hard left turn held while braking sweeps into that lane
    abreast = [1, 0.0, 3.5, 1.0, 0.0, 0.0, 0.0, 4.5, 2.0, 1]
    hidden = [0] + crossing_partner(12.0, 1.2)[1:]
    flags = grid_flags(guard, obs_row(10.0, [abreast, hidden]))
    assert not flags[:, : straight + 1].any() and flags[:, -1].all()
    # a margin widens the boxes: the abreast car 1.5 m apart is unsafe for a margin over 1.5 m
    wide = ActionGuard(action_grid(ENV), 4, DT, ENV.max_accel, horizon=2.0, margin=1.6)
    assert grid_flags(wide, obs_row(10.0, [abreast])).all()


def test_the_guard_redraws_unsafe_actions_among_the_safe_ones_by_the_policy_s_odds():
    guard = ActionGuard(action_grid(ENV), 4, DT, ENV.max_accel, horizon=2.0)
    obs = obs_row(10.0, [crossing_partner(12.0, 1.2)]).expand(4000, -1)
    safe = ~torch.from_numpy(grid_flags(guard, obs[0]).reshape(-1))
    full = (ENV.accel_bins - 1) * ENV.curvature_bins + ENV.curvature_bins // 2  # full throttle, straight
    logits = torch.randn(len(safe), generator=torch.Generator().manual_seed(0)).expand(4000, -1)
    torch.manual_seed(0)
    out = guard(obs, logits, torch.full((4000,), full))
    assert safe[out].all() and guard.replaced == 4000 and guard.checked == 4000
    p = torch.softmax(logits[0].masked_fill(~safe, float("-inf")), -1).numpy()
    np.testing.assert_allclose(np.bincount(out.numpy(), minlength=len(p)) / 4000, p, atol=0.03)
    mode = guard(obs[:1], logits[:1], torch.tensor([full]), deterministic=True)
    assert int(mode) == int(torch.argmax(logits[0].masked_fill(~safe, float("-inf"))))
    # a safe sample is kept; where every action is unsafe (a partner already in contact) the sample stays
    brake = ENV.curvature_bins // 2
    assert int(guard(obs[:1], logits[:1], torch.tensor([brake]))) == brake
    contact = obs_row(10.0, [[1, 3.0, 0.0, 1.0, 0.0, -10.0, 0.0, 4.5, 2.0, 1]])
    assert guard.unsafe(contact[None], guard.grid[None]).all()
    assert int(guard(contact[None], logits[:1], torch.tensor([full]))) == full


def test_redraws_from_a_generator_repeat_whatever_the_global_stream():
    guard = ActionGuard(action_grid(ENV), 4, DT, ENV.max_accel, horizon=2.0)
    obs = obs_row(10.0, [crossing_partner(12.0, 1.2)]).expand(500, -1)
    full = (ENV.accel_bins - 1) * ENV.curvature_bins + ENV.curvature_bins // 2
    logits, sampled = torch.zeros(500, len(guard.grid)), torch.full((500,), full)

    def draw(global_seed):
        torch.manual_seed(global_seed)
        return guard(obs, logits, sampled, generator=torch.Generator().manual_seed(3))

    first = draw(0)
    assert torch.equal(first, draw(1)) and len(first.unique()) > 1


def _drive(device, guarded: bool) -> int:
    """Every agent of the hand-made crossing asks for the no-op (constant speed, straight) from the first step;
    the number of agents that collided within 30 steps."""
    env = EngineConfig(replay_infeasible=False, max_agents=4, init_steps=0, partner_k=4, road_k=8)
    sim = Simulator([crossing_scene()], env, device)
    sim.reset()
    guard = guard_for(sim, 1.0) if guarded else None
    logits = torch.full((1, 4, sim.num_actions), -20.0, device=sim.device)
    logits[..., env.noop_index] = 0.0
    hit = torch.zeros(4, dtype=torch.bool, device=sim.device)
    for _ in range(30):
        a = torch.full((1, 4), env.noop_index, device=sim.device)
        if guard is not None:
            a = guard(sim.obs, logits, a, deterministic=True)
        sim.actions_index.copy_(a.to(torch.int32))
        sim.step()
        hit |= sim.collided[0].bool()
    return int(hit.sum())


def test_in_the_engine_the_guard_avoids_the_crossing_that_no_op_driving_hits(device):
    assert _drive(device, guarded=False) == 2  # the crossing pair (tests/scenes.py: they meet at step 18)
    assert _drive(device, guarded=True) == 0  # and the follower does not run into the car that braked


@pytest.fixture(scope="module")
def guarded_run(tmp_path_factory):
    """An untrained checkpoint whose config sets a guard of 1 s."""
    from tg_gpudrive.learn.train import Trainer

    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    run = tmp_path_factory.mktemp("guarded")
    cfg = dataclasses.replace(cfg, num_worlds=1, num_scenes=1, rollout_steps=4, epochs=1, minibatches=1, hidden=16,
                              quantiles=4, updates=1, prior="expert", cost_limit_mode="absolute", act_guard_s=1.0,
                              out_dir=str(run))
    Trainer(cfg, run, progress=False).save()
    return run


def test_a_checkpoint_acts_behind_its_own_guard_unless_told(guarded_run):
    scenes = list(resolve_scenes("procedural:merge", n=1, seed=0))
    assert open_policy(str(guarded_run), scenes, "cpu").policy.guard.horizon == 1.0
    assert open_policy(str(guarded_run), scenes, "cpu", guard_s=0.0).policy.guard is None
    assert open_policy(str(guarded_run), scenes, "cpu", guard_s=0.5).guard_s == 0.5
    assert open_policy("constant", scenes, "cpu").guard_s is None


def test_evaluate_reports_the_guard_and_what_it_replaced(guarded_run, capsys):
    assert cli.main(["evaluate", "--checkpoint", str(guarded_run), "--scenes", "procedural:merge", "--episodes", "1",
                     "--device", "cpu", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["guard_s"] == 1.0 and 0.0 <= out["guard_replaced"] <= 1.0


def test_the_shipped_policy_acts_behind_a_guard():
    """The packaged policy's guard, chosen on its training scenes (BENCHMARKS.md, "A safety guard")."""
    from tg_gpudrive.checkpoint import load_checkpoint

    assert 0 < load_checkpoint("shipped", "shipped")["config"]["act_guard_s"] <= 2


def test_bad_guards_are_one_line_errors(guarded_run, capsys):
    assert cli.main(["evaluate", "--checkpoint", str(guarded_run), "--scenes", "procedural:merge", "--episodes", "1",
                     "--device", "cpu", "--guard", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--guard: expected seconds in [0, 60]" in err[0]
    with pytest.raises(ConfigError, match="act_guard_s"):
        from_dict(TrainConfig, {**to_dict(TrainConfig()), "act_guard_s": -1.0}, "run.yaml")
    cont = Simulator([crossing_scene()], EngineConfig(replay_infeasible=False, max_agents=4,
                                                      action_space="continuous"), "cpu")
    with pytest.raises(ValueError, match="discrete action space"):
        guard_for(cont, 1.0)
