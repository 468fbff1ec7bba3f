"""Every engine kernel against an independent NumPy reference, on random batches.

States are produced through the real step (log replay or controlled
dynamics), so the launchers and the Model builder are exercised too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import reference as ref
import torch

from tg_gpudrive.config import ConfigError, EngineConfig, RewardConfig
from tg_gpudrive.data.procedural.dense import dense_scene
from tg_gpudrive.data.simplify import simplify_scene
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.scene import make_scene
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.enums import AgentType, RoadType

T = 16
INIT = 2


def random_replay_scene(rng, n, spread, seed_id="rand", roads=(), types=None):
    """n agents with random boxes at random places, constant over time (replayed, not controlled)."""
    p = rng.uniform(-spread, spread, size=(n, 2))
    yaw = rng.uniform(-np.pi, np.pi, size=n)
    pos = np.repeat(p[:, None], T, 1)
    yaws = np.repeat(yaw[:, None], T, 1)
    return make_scene(pos, yaws, log_vel=np.zeros((n, T, 2)), length=rng.uniform(3.0, 6.0, n),
                      width=rng.uniform(1.5, 2.5, n), roads=list(roads), scene_id=seed_id,
                      agent_type=AgentType.VEHICLE if types is None else types)


def cfg(**kw):
    base = dict(replay_infeasible=False, max_agents=32, init_steps=INIT, partner_k=8, road_k=16, road_radius=30.0, partner_radius=30.0)
    base.update(kw)
    return EngineConfig(**base)


# ------------------------------------------------------------------ dynamics
def test_bicycle_forward_matches_numpy(device, rng):
    n = 20
    speed = rng.uniform(0, 20, n)
    yaw0 = rng.uniform(-np.pi, np.pi, n)
    vel0 = speed[:, None] * np.stack([np.cos(yaw0), np.sin(yaw0)], -1)
    pos0 = rng.uniform(-50, 50, (n, 2))
    pos = np.repeat(pos0[:, None], T, 1)
    pos[:, -1] += 100.0  # goals far away: nobody finishes
    scene = make_scene(pos, np.repeat(yaw0[:, None], T, 1), log_vel=np.repeat(vel0[:, None], T, 1))
    sim = Simulator([scene, scene], cfg(action_space="continuous", control="all_agents"), device)
    sim.reset()
    a = rng.uniform(-8, 8, (2, 32, 2)).astype(np.float32)  # beyond the bounds: clipping is tested too
    a[..., 1] = rng.uniform(-0.4, 0.4, (2, 32))
    sim.step(torch.tensor(a, device=device))
    acc = np.clip(a[0, :n, 0], -6, 6)
    kap = np.clip(a[0, :n, 1], -0.3, 0.3)
    p1, y1, v1 = ref.bicycle_forward(pos0, yaw0, vel0, acc, kap, 0.1)
    np.testing.assert_allclose(sim.pos[0, :n].cpu().numpy(), p1, atol=1e-4)
    np.testing.assert_allclose(ref.wrap(sim.yaw[0, :n].cpu().numpy() - y1), 0, atol=1e-5)
    np.testing.assert_allclose(sim.vel[0, :n].cpu().numpy(), v1, atol=1e-4)
    np.testing.assert_allclose(sim.applied_action[0, :n, :2].cpu().numpy(), np.stack([acc, kap], -1), atol=1e-6)


def test_discrete_grid_decoding(device):
    scene = make_scene(np.stack([np.linspace(0, 15, T) + 100 * (np.arange(T) == T - 1), np.zeros(T)], -1)[None],
                       np.zeros((1, T)))
    c = cfg(control="all_agents")
    sim = Simulator([scene], c, device)
    sim.reset()
    idx = torch.zeros((1, 32), dtype=torch.int32, device=device)
    idx[0, 0] = 3 * 13 + 12  # accel bin 3 -> 0 m/s^2, curvature bin 12 -> +0.3
    sim.step(idx)
    np.testing.assert_allclose(sim.applied_action[0, 0, :2].cpu().numpy(), [0.0, 0.3], atol=1e-6)
    accel_grid = np.linspace(-6, 6, 7)
    kappa_grid = np.linspace(-0.3, 0.3, 13)
    for k in (0, 45, 90):
        sim.reset()
        idx[0, 0] = k
        sim.step(idx)
        np.testing.assert_allclose(sim.applied_action[0, 0, :2].cpu().numpy(),
                                   [accel_grid[k // 13], kappa_grid[k % 13]], atol=1e-6)


def test_delta_local_matches_numpy(device, rng):
    n = 10
    pos0 = rng.uniform(-20, 20, (n, 2))
    yaw0 = rng.uniform(-np.pi, np.pi, n)
    pos = np.repeat(pos0[:, None], T, 1)
    pos[:, -1] += 100
    scene = make_scene(pos, np.repeat(yaw0[:, None], T, 1))
    sim = Simulator([scene], cfg(dynamics="delta_local", action_space="continuous", control="all_agents"), device)
    sim.reset()
    d = np.zeros((1, 32, 3), np.float32)
    d[0, :n] = rng.uniform(-0.5, 0.5, (n, 3)) * [4, 1, 0.5]
    sim.step(torch.tensor(d, device=device))
    p1, y1 = ref.delta_local_forward(pos0, yaw0, d[0, :n])
    np.testing.assert_allclose(sim.pos[0, :n].cpu().numpy(), p1, atol=1e-4)
    np.testing.assert_allclose(ref.wrap(sim.yaw[0, :n].cpu().numpy() - y1), 0, atol=1e-5)


def forward_generated_scene(rng, n, steps=91):
    """Trajectories produced by the bicycle itself from in-bounds random actions."""
    dt = 0.1
    pos = np.zeros((n, steps, 2))
    yaw = np.zeros((n, steps))
    vel = np.zeros((n, steps, 2))
    pos[:, 0] = rng.uniform(-50, 50, (n, 2))
    yaw[:, 0] = rng.uniform(-np.pi, np.pi, n)
    sp = rng.uniform(3, 15, n)
    vel[:, 0] = sp[:, None] * np.stack([np.cos(yaw[:, 0]), np.sin(yaw[:, 0])], -1)
    for t in range(steps - 1):
        a = rng.uniform(-2, 2, n)
        k = rng.uniform(-0.05, 0.05, n)
        pos[:, t + 1], yaw[:, t + 1], vel[:, t + 1] = ref.bicycle_forward(pos[:, t], yaw[:, t], vel[:, t], a, k, dt)
    return make_scene(pos, yaw, log_vel=vel)


def test_inverse_matches_numpy_and_recovers_forward_trajectories(device, rng):
    """Inverse kernel == NumPy inverse on the log; inverse-then-forward reproduces a bicycle-generated
    log to float32 round-off (< 5 mm over 8 s): nothing was clipped, so nothing may drift."""
    scene = forward_generated_scene(rng, 12)
    sim = Simulator([scene], EngineConfig(replay_infeasible=False, max_agents=16, action_space="continuous"), device)
    exp = sim.slot_log("expert_action")[0, :12].cpu().numpy()
    a, k = ref.bicycle_inverse(scene.log_yaw[:, :-1], scene.log_vel[:, :-1], scene.log_yaw[:, 1:],
                               scene.log_vel[:, 1:], 0.1)
    np.testing.assert_allclose(exp[:, :-1, 0], a, atol=2e-3)
    np.testing.assert_allclose(exp[:, :-1, 1], k, atol=2e-4)
    track = sim.slot_log("expert_track")[0, :12].cpu().numpy()
    err = np.linalg.norm(track - scene.log_pos, axis=-1)
    assert err.max() < 5e-3, err.max()
    # and driving the engine with them lands on the logged positions
    sim.reset()
    for _ in range(30):
        sim.use_expert_actions()
        sim.step()
    t = int(sim.world_step[0])
    np.testing.assert_allclose(sim.pos[0, :12].cpu().numpy(), scene.log_pos[:, t], atol=5e-3)


# ----------------------------------------------------------------- collision
def brute_force_collisions(scene):
    n = scene.num_agents
    p, y = scene.log_pos[:, INIT + 1], scene.log_yaw[:, INIT + 1]
    hit = np.zeros(n, bool)
    nearest = np.full(n, np.inf)
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            nearest[i] = min(nearest[i], np.linalg.norm(p[i] - p[j]))
            area = ref.box_overlap_area((*p[i], y[i], scene.length[i], scene.width[i]),
                                        (*p[j], y[j], scene.length[j], scene.width[j]))
            hit[i] |= area > 1e-6
    return hit, nearest


@pytest.mark.parametrize("spread", [6.0, 15.0, 60.0])
def test_collision_grid_matches_brute_force(device, rng, spread):
    scenes = [random_replay_scene(rng, 30, spread, f"s{k}") for k in range(3)]
    sim = Simulator(scenes, cfg(control="none"), device)
    sim.reset()
    sim.step()
    cell = sim.model.collision_cell_size.numpy()
    for w, sc in enumerate(scenes):
        hit, nearest = brute_force_collisions(sc)
        np.testing.assert_array_equal(sim.collided[w, :30].cpu().numpy().astype(bool), hit)
        np.testing.assert_allclose(sim.nearest[w, :30].cpu().numpy(), np.minimum(nearest, cell[w]), atol=1e-4)
    assert sim.collided.sum() > 0  # the dense case must actually contain collisions


@pytest.mark.parametrize(
    "b, expected",
    [
        ((4.0, 0.0, 0.0), False),  # touching end to end: zero-area contact is not a collision
        ((3.9, 0.0, 0.0), True),
        ((0.5, 0.2, 0.1), True),  # small box contained in the big one (lengths differ below)
        ((2.5, 1.5, np.pi / 4), True),  # rotated corner poking in
        ((3.6, 3.6, np.pi / 4), False),  # rotated, just apart
        ((40.0, 0.0, 0.0), False),  # far apart
    ],
)
def test_box_overlap_cases(device, b, expected):
    pos = np.zeros((2, T, 2))
    pos[1, :] = b[:2]
    yaw = np.zeros((2, T))
    yaw[1] = b[2]
    length = np.array([4.0, 4.0 if b[0] != 0.5 else 1.0])
    width = np.array([2.0, 2.0 if b[0] != 0.5 else 0.5])
    sc = make_scene(pos, yaw, log_vel=np.zeros((2, T, 2)), length=length, width=width)
    area = ref.box_overlap_area((0, 0, 0, length[0], width[0]), (*b[:2], b[2], length[1], width[1]))
    assert (area > 1e-9) == expected  # the reference agrees with the hand-made expectation
    sim = Simulator([sc], cfg(control="none"), device)
    sim.reset()
    sim.step()
    assert bool(sim.collided[0, 0]) == expected and bool(sim.collided[0, 1]) == expected


# ---------------------------------------------------------------------- road
def curved_edge(radius, n=40):
    th = np.linspace(-np.pi / 2, np.pi / 2, n)
    return np.stack([radius * np.cos(th), radius * np.sin(th)], -1)


@pytest.mark.parametrize("shape", ["straight", "curved"])
def test_offroad_edge_and_lane_distance_match_numpy(device, rng, shape):
    if shape == "straight":
        roads = [(RoadType.ROAD_EDGE, np.array([[-40.0, 3.0], [40.0, 3.0]])),
                 (RoadType.ROAD_EDGE, np.array([[-40.0, -3.0], [40.0, -3.0]])),
                 (RoadType.LANE, np.array([[-40.0, 0.0], [40.0, 0.0]]))]
    else:
        roads = [(RoadType.ROAD_EDGE, curved_edge(12.0)), (RoadType.ROAD_EDGE, curved_edge(18.0)),
                 (RoadType.LANE, curved_edge(15.0))]
    scene = random_replay_scene(rng, 30, 20.0, roads=roads)
    c = cfg(control="none", max_segment_length=2.0)
    sim = Simulator([scene], c, device)
    sim.reset()
    sim.step()
    # the engine's split segments are the reference's too (splitting is exact on straight pieces), after
    # the NumPy simplification the engine's kernel must equal
    segs = [(t, p[i], p[i + 1]) for t, p in simplify_scene(scene, c.road_simplify)[0].polylines()
            for i in range(len(p) - 1)]
    p, y = scene.log_pos[:, INIT + 1], scene.log_yaw[:, INIT + 1]
    for i in range(scene.num_agents):
        off = any(ref.box_crosses_segment(p[i], y[i], scene.length[i], scene.width[i], a, b)
                  for t, a, b in segs if t == RoadType.ROAD_EDGE)
        edge = min([ref.point_segment_distance(p[i], a, b) for t, a, b in segs if t == RoadType.ROAD_EDGE])
        lane = min([ref.point_segment_distance(p[i], a, b) for t, a, b in segs if t == RoadType.LANE])
        assert bool(sim.offroad[0, i]) == off, i
        assert sim.edge_dist[0, i].item() == pytest.approx(min(edge, c.road_query_radius), abs=1e-4)
        assert sim.lane_dist[0, i].item() == pytest.approx(min(lane, c.road_query_radius), abs=1e-4)
    assert sim.offroad[0].sum() > 0 and sim.offroad[0, :30].sum() < 30


# -------------------------------------------------------- reward and cost
def test_reward_terms_and_cost_match_hand_computation(device):
    """Two cars on a lane; the second drives at 25 m/s (over the limit) 3 m beside the lane."""
    n_steps = T
    pos = np.zeros((2, n_steps, 2))
    pos[0, :, 0] = np.arange(n_steps) * 1.0
    pos[1, :, 0] = np.arange(n_steps) * 2.5
    pos[1, :, 1] = 3.0
    pos[:, -1, 0] += 200  # far goals
    yaw = np.zeros((2, n_steps))
    vel = np.zeros((2, n_steps, 2))
    vel[0, :, 0] = 10.0
    vel[1, :, 0] = 25.0
    roads = [(RoadType.LANE, np.array([[-50.0, 0.0], [300.0, 0.0]]))]
    sc = make_scene(pos, yaw, log_vel=vel, roads=roads)
    rw = RewardConfig(goal_progress=0.5, goal_reached=2.0, collision=-3.0, offroad=-4.0, lane_deviation=-0.25,
                      overspeed=-0.125, speed_limit=20.0, lane_cap=5.0)
    c = cfg(action_space="continuous", control="all_agents", beta=6.0, reward=rw)
    sim = Simulator([sc], c, device)
    sim.reset()
    sim.step(torch.zeros((1, 32, 2), device=device))  # zero accel, straight
    terms = sim.reward_terms[0, :2].cpu().numpy()
    x0 = pos[:, INIT, 0]
    x1 = x0 + vel[:, INIT, 0] * 0.1
    goal = sc.goal
    start = np.hypot(goal[:, 0] - x0, goal[:, 1] - pos[:, INIT, 1])
    now = np.hypot(goal[:, 0] - x1, goal[:, 1] - pos[:, INIT, 1])
    np.testing.assert_allclose(terms[:, 0], start - now, atol=1e-3)  # goal progress (m)
    np.testing.assert_allclose(terms[:, 1], 0)
    np.testing.assert_allclose(terms[:, 2:4], 0)
    np.testing.assert_allclose(terms[:, 4], [0.0, 3.0], atol=1e-5)  # lane deviation (m)
    np.testing.assert_allclose(terms[:, 5], [0.0, 5.0], atol=1e-4)  # over-speed (m/s)
    np.testing.assert_allclose(terms[:, 6], 0)  # ttc: unweighted, not computed
    w = np.array([0.5, 2.0, -3.0, -4.0, -0.25, -0.125, 0.0])
    np.testing.assert_allclose(sim.reward[0, :2].cpu().numpy(), terms @ w, atol=1e-5)
    gap = np.hypot(x1[1] - x1[0], 3.0)
    assert gap < 6.0
    np.testing.assert_allclose(sim.cost[0, :2].cpu().numpy(), [1.0, 1.0])
    np.testing.assert_allclose(sim.nearest[0, :2].cpu().numpy(), [gap, gap], atol=1e-4)
    # with beta below the gap the cost vanishes
    sim2 = Simulator([sc], cfg(action_space="continuous", control="all_agents", beta=gap - 0.5, reward=rw), device)
    sim2.reset()
    sim2.step(torch.zeros((1, 32, 2), device=device))
    np.testing.assert_allclose(sim2.cost[0, :2].cpu().numpy(), [0.0, 0.0])
    # the hinge cost: how deep the neighbour is inside beta, as a share of beta
    sim3 = Simulator([sc], cfg(action_space="continuous", control="all_agents", beta=6.0, cost_shape="hinge",
                               reward=rw), device)
    sim3.reset()
    sim3.step(torch.zeros((1, 32, 2), device=device))
    np.testing.assert_allclose(sim3.cost[0, :2].cpu().numpy(), [(6.0 - gap) / 6.0] * 2, atol=1e-4)
    assert 0.0 < (6.0 - gap) / 6.0 < 1.0


def ttc_reference(pos, yaw, vel, length, width, present, horizon):
    """NumPy TTC of each agent against the present agents ahead of its motion, from evaluation/risk.py's
    disc model and constant-velocity solve; a standing agent closes on nobody."""
    from tg_gpudrive.evaluation.risk import disc_centres, pair_ttc
    A = len(pos)
    centres = disc_centres(pos[None, :, None], yaw[None, :, None], length[None], width[None])[0, :, 0]  # (A, D, 2)
    out = np.full(A, horizon)
    for i in range(A):
        if np.dot(vel[i], vel[i]) < 1e-6:
            continue
        for j in range(A):
            if j == i or not present[j] or np.dot(vel[i], pos[j] - pos[i]) <= 0:
                continue
            p = centres[j][None, :, :] - centres[i][:, None, :]
            t = pair_ttc(p, np.broadcast_to(vel[j] - vel[i], p.shape), 0.5 * (width[i] + width[j]), horizon)
            out[i] = min(out[i], t.min())
    return out


def test_ttc_term_matches_numpy_reference(device):
    """Twelve cars with random headings and speeds on a 40 m square; the ttc term of each is
    1 - TTC / horizon, TTC from the NumPy disc model against the agents ahead of its motion. Hand
    cases ride along, far from the others: a follower at 10 m/s 12 m behind a car at 4 m/s in its lane,
    the leader itself (closed on from behind, it pays nothing) and a standing car."""
    rng = np.random.default_rng(3)
    n = 12
    p0 = rng.uniform(-20, 20, (n, 2))
    p0[0], p0[1] = (100.0, 0.0), (112.0, 0.0)  # follower, leader
    yaw0 = rng.uniform(-np.pi, np.pi, n)
    yaw0[:2] = 0.0
    spd = rng.uniform(0, 12, n)
    spd[:2] = (10.0, 4.0)
    spd[2] = 0.0  # standing
    v0 = np.stack([np.cos(yaw0), np.sin(yaw0)], -1) * spd[:, None]
    pos = p0[:, None, :] + v0[:, None, :] * (np.arange(T) - INIT)[None, :, None] * 0.1
    yaw = np.repeat(yaw0[:, None], T, 1)
    vel = np.repeat(v0[:, None, :], T, 1)
    length, width = rng.uniform(3.5, 5.5, n), rng.uniform(1.6, 2.2, n)
    length[:2], width[:2] = 4.5, 2.0
    sc = make_scene(pos, yaw, log_vel=vel, length=length, width=width)
    horizon = 3.0
    rw = RewardConfig(ttc=-0.5, ttc_horizon=horizon)
    sim = Simulator([sc], cfg(action_space="continuous", control="all_agents", reward=rw), device)
    sim.reset()
    sim.step(torch.zeros((1, 32, 2), device=device))  # zero accel, straight: constant velocity
    got_pos, got_yaw = sim.pos[0, :n].cpu().numpy(), sim.yaw[0, :n].cpu().numpy()
    got_vel = sim.vel[0, :n].cpu().numpy()
    got_len, got_wid = sim.length[0, :n].cpu().numpy(), sim.width[0, :n].cpu().numpy()  # slots, not scene order
    want = ttc_reference(*(x.astype(np.float64) for x in (got_pos, got_yaw, got_vel, got_len, got_wid)),
                         np.ones(n, bool), horizon)
    np.testing.assert_allclose(sim.ttc[0, :n].cpu().numpy(), want, atol=1e-3)
    np.testing.assert_allclose(sim.reward_terms[0, :n, 6].cpu().numpy(), 1 - want / horizon, atol=1e-3)
    # after the 0.1 s step the centres are 12 - 0.6 m apart; the follower's front disc (1.25 m ahead of
    # its centre) meets the leader's rear disc (1.25 m behind) when they are 2 m apart: 11.4 - 2.5 - 2 m
    # to close at 6 m/s
    slot = {name: int(np.argmin(np.hypot(*(got_pos - at).T))) for name, at in
            (("follower", p0[0] + v0[0] * 0.1), ("leader", p0[1] + v0[1] * 0.1), ("standing", p0[2]))}
    assert sim.ttc[0, slot["follower"]].item() == pytest.approx(6.9 / 6.0, abs=1e-3)
    assert sim.ttc[0, slot["leader"]].item() == horizon
    assert sim.ttc[0, slot["standing"]].item() == horizon
    assert 0 < (want < horizon).sum() and (want == 0).sum() < n  # the random cars make conflicts, not all contacts
    # unweighted, the term is neither computed nor reported
    sim0 = Simulator([sc], cfg(action_space="continuous", control="all_agents"), device)
    sim0.reset()
    sim0.step(torch.zeros((1, 32, 2), device=device))
    assert torch.all(sim0.reward_terms[0, :, 6] == 0)


def test_cost_counts_only_the_policys_agents_with_cost_partners_players(device):
    """Cars 0 and 1 are the policy's, car 2 replays its log 3 m beside car 0 and car 1 drives 5 m ahead
    of it. The cost's distance (read through the hinge cost, beta 8) is to car 2 with `all`, to car 1
    with `players`; `nearest` stays the distance to anyone."""
    pos = np.zeros((3, T, 2))
    for a, (x, y) in enumerate([(0.0, 0.0), (5.0, 0.0), (0.0, 3.0)]):
        pos[a, :, 0] = x + np.arange(T) * 1.0
        pos[a, :, 1] = y
    pos[:, -1, 0] += 200  # far goals
    vel = np.zeros((3, T, 2))
    vel[:, :, 0] = 10.0
    roads = [(RoadType.LANE, np.array([[-50.0, 0.0], [300.0, 0.0]]))]
    sc = make_scene(pos, np.zeros((3, T)), log_vel=vel, roads=roads)
    got = {}
    for who in ("all", "players"):
        c = cfg(action_space="continuous", beta=8.0, cost_shape="hinge", cost_partners=who)
        sim = Simulator([sc], c, device, controlled=[np.array([True, True, False])])
        sim.reset()
        sim.step(torch.zeros((1, 32, 2), device=device))
        assert sim.policy_agents[0, :3].tolist() == [True, True, False]
        got[who] = sim.cost[0, :2].cpu().numpy()
        np.testing.assert_allclose(sim.nearest[0, :2].cpu().numpy(), [3.0, 5.0], atol=1e-3)
    np.testing.assert_allclose(got["all"], [(8.0 - 3.0) / 8.0, (8.0 - 5.0) / 8.0], atol=1e-4)
    np.testing.assert_allclose(got["players"], [(8.0 - 5.0) / 8.0, (8.0 - 5.0) / 8.0], atol=1e-4)


def test_cost_horizon_keeps_beta_ahead_of_time(device):
    """Car 0 drives at 10 m/s towards car 1, standing 15 m ahead and 3 m to the side; car 2 drives away
    behind. After one step the gap is hypot(14, 3) m, outside beta 8. Looking ahead 1 s, the closest
    approach is at t = 1 s: hypot(4, 3) = 5 m; 2 s reach the true closest approach, 3 m at t = 1.4 s.
    Car 1 sees the same approach; car 2 none."""
    pos = np.zeros((3, T, 2))
    pos[0, :, 0] = (np.arange(T) - INIT) * 1.0
    pos[1, :, :] = (15.0, 3.0)
    pos[2, :, 0] = -10.0 - (np.arange(T) - INIT) * 1.0
    yaw = np.zeros((3, T))
    yaw[2] = np.pi
    vel = np.zeros((3, T, 2))
    vel[0, :, 0] = 10.0
    vel[2, :, 0] = -10.0
    sc = make_scene(pos, yaw, log_vel=vel, goal=np.array([[300.0, 0.0], [300.0, 3.0], [-300.0, 0.0]]))
    got = {}
    for horizon in (0.0, 1.0, 2.0):
        c = cfg(action_space="continuous", control="all_agents", beta=8.0, cost_shape="hinge", cost_horizon=horizon)
        sim = Simulator([sc], c, device)
        sim.reset()
        sim.step(torch.zeros((1, 32, 2), device=device))
        slot = {int(np.argmin(np.hypot(*(sim.pos[0, :3].cpu().numpy() - at).T))): k
                for k, at in enumerate([(1.0, 0.0), (15.0, 3.0), (-11.0, 0.0)])}
        got[horizon] = [sim.cost[0, s].item() for s in sorted(slot, key=slot.get)]
    np.testing.assert_allclose(got[0.0], [0.0, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(got[1.0], [(8 - 5.0) / 8, (8 - 5.0) / 8, 0.0], atol=1e-4)
    np.testing.assert_allclose(got[2.0], [(8 - 3.0) / 8, (8 - 3.0) / 8, 0.0], atol=1e-4)


def test_cost_approach_charges_a_pass_its_closest_approach_once(device):
    """Car 0 drives at 10 m/s past car 1, standing 3 m beside its lane; both are the policy's. Under beta 8
    the hinge charges every step inside beta; `approach` charges only the hinge's increase since the last
    step (NumPy below), nothing at an episode's first step, and so over the whole pass the depth of the
    closest approach, (8 - 3) / 8, less the first step's depth. A car that starts inside beta pays nothing
    at its first step, in the first episode and after a reset alike."""
    n = T - 1 - INIT

    def pass_costs(shape: str, start: float, episodes: int = 1) -> np.ndarray:
        pos = np.zeros((2, T, 2))
        pos[0, :, 0] = start + (np.arange(T) - INIT) * 1.0
        pos[1, :, :] = (0.0, 3.0)
        vel = np.zeros((2, T, 2))
        vel[0, :, 0] = 10.0
        sc = make_scene(pos, np.zeros((2, T)), log_vel=vel, goal=np.array([[300.0, 0.0], [0.0, 300.0]]))
        sim = Simulator([sc], cfg(action_space="continuous", control="all_agents", beta=8.0, cost_shape=shape),
                        device)
        rows = []
        for _ in range(episodes):
            sim.reset()
            for _ in range(n):
                sim.step(torch.zeros((1, 32, 2), device=device))
                rows.append(sim.cost[0, :2].cpu().numpy().copy())
        return np.array(rows)

    def depth(start: float) -> np.ndarray:
        return np.clip((8.0 - np.hypot(start + np.arange(1, n + 1), 3.0)) / 8.0, 0.0, 1.0)

    def approach(d: np.ndarray) -> np.ndarray:
        return np.concatenate([[0.0], np.maximum(np.diff(d), 0.0)])

    hinge, got = pass_costs("hinge", -8.0), pass_costs("approach", -8.0)
    np.testing.assert_allclose(hinge[:, 0], depth(-8.0), atol=1e-4)
    np.testing.assert_allclose(got, np.stack([approach(depth(-8.0))] * 2, axis=1), atol=1e-4)
    assert got[:, 0].sum() == pytest.approx(5.0 / 8.0 - depth(-8.0)[0], abs=1e-4)
    assert hinge[:, 0].sum() > 2 * got[:, 0].sum()  # the hinge charges the time spent inside beta
    inside = pass_costs("approach", -4.0, episodes=2)  # 5 m apart at the start: depth 3 / 8
    assert depth(-4.0)[0] > 3.0 / 8.0 and np.all(inside[[0, n], :] == 0.0)
    np.testing.assert_allclose(inside[:n, 0], approach(depth(-4.0)), atol=1e-4)
    np.testing.assert_allclose(inside[n:], inside[:n], atol=1e-6)


def test_cost_collision_puts_a_contact_at_the_top_of_the_cost(device):
    """Cars 0 and 1 drive 4 m apart, nose to tail (boxes 4.5 m long: in contact); car 2 drives 30 m ahead. Under
    beta 2 the distance cost of the contact is 0 (the centres are 4 m apart); with cost_collision c the contact
    costs max(0, c), and under the hinge at beta 8 max((8 - 4) / 8, c). Car 2, in contact with no one, costs
    nothing either way."""
    pos = np.zeros((3, T, 2))
    for a, x in enumerate([0.0, 4.0, 34.0]):
        pos[a, :, 0] = x + np.arange(T) * 1.0
    pos[:, -1, 0] += 200  # far goals
    vel = np.zeros((3, T, 2))
    vel[:, :, 0] = 10.0
    sc = make_scene(pos, np.zeros((3, T)), log_vel=vel, length=np.full(3, 4.5))
    got = {}
    for beta, coll in ((2.0, 0.0), (2.0, 1.0), (2.0, 0.3), (8.0, 0.3), (8.0, 0.9)):
        c = cfg(action_space="continuous", control="all_agents", beta=beta, cost_shape="hinge", cost_collision=coll)
        sim = Simulator([sc], c, device)
        sim.reset()
        sim.step(torch.zeros((1, 32, 2), device=device))
        assert sim.collided[0, :3].tolist() == [1, 1, 0]
        got[beta, coll] = sim.cost[0, :3].cpu().numpy()
    np.testing.assert_allclose(got[2.0, 0.0], [0.0, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(got[2.0, 1.0], [1.0, 1.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(got[2.0, 0.3], [0.3, 0.3, 0.0], atol=1e-5)
    np.testing.assert_allclose(got[8.0, 0.3], [0.5, 0.5, 0.0], atol=1e-4)  # the hinge is above it
    np.testing.assert_allclose(got[8.0, 0.9], [0.9, 0.9, 0.0], atol=1e-5)
    with pytest.raises(ConfigError, match="cost_collision"):
        cfg(cost_collision=1.5)


def test_goal_reached_term(device):
    pos = np.zeros((1, T, 2))
    pos[0, :, 0] = np.arange(T) * 1.0
    sc = make_scene(pos, np.zeros((1, T)), goal=np.array([[INIT + 2.5, 0.0]]))
    sim = Simulator([sc], cfg(action_space="continuous", control="all_agents", goal_behaviour="continue"), device)
    sim.reset()
    sim.step(torch.zeros((1, 32, 2), device=device))  # 10 m/s -> moves 1 m: 1.5 m from the goal
    assert sim.reward_terms[0, 0, 1].item() == 1.0 and sim.goal_event[0, 0].item() == 1
    sim.step(torch.zeros((1, 32, 2), device=device))  # counted once per episode
    assert sim.reward_terms[0, 0, 1].item() == 0.0


def test_goal_reached_off_the_road_is_not_a_goal(device):
    """A road edge lies across the path 1 m ahead; the goal is 2.5 m ahead. The car crosses the
    edge on the first step and is within the goal radius on the second: no goal, ever, in
    that episode (reward term, event and the episode flag the rates read)."""
    pos = np.zeros((1, T, 2))
    pos[0, :, 0] = np.arange(T) * 1.0
    edge = (RoadType.ROAD_EDGE, np.array([[INIT + 1.0, -5.0], [INIT + 1.0, 5.0]]))
    sc = make_scene(pos, np.zeros((1, T)), goal=np.array([[INIT + 3.5, 0.0]]), roads=[edge])
    sim = Simulator([sc], cfg(action_space="continuous", control="all_agents", goal_behaviour="continue"), device)
    sim.reset()
    sim.step(torch.zeros((1, 32, 2), device=device))  # 1 m on: the 4.5 m box straddles the edge
    assert sim.offroad[0, 0].item() == 1
    for _ in range(3):  # 1.5, 0.5, 0.5 m from the goal: inside the 2 m radius, but it left the road
        sim.step(torch.zeros((1, 32, 2), device=device))
        assert sim.reward_terms[0, 0, 1].item() == 0.0 and sim.goal_event[0, 0].item() == 0
    assert sim.offroad[0, 0].item() == 0  # past the edge now: only the episode's flag remembers
    assert sim.ep_goal[0, 0].item() == 0 and sim.ep_offroad[0, 0].item() == 1


# --------------------------------------------------------------- observations
@pytest.mark.parametrize("view_angle", [360.0, 120.0])
def test_observation_frames_and_nearest_k_match_numpy(device, rng, view_angle):
    """Partners and road rows: the nearest within their radius and the view cone (a 120-degree one, as
    GPUDrive's agents see), in the agent's frame, nearest first."""
    roads = [(RoadType.LANE, rng.uniform(-30, 30, (6, 2))), (RoadType.ROAD_EDGE, rng.uniform(-30, 30, (8, 2))),
             (RoadType.CROSSWALK, rng.uniform(-30, 30, (4, 2))), (RoadType.STOP_SIGN, rng.uniform(-30, 30, (1, 2)))]
    types = rng.choice([AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST], 25)
    scene = random_replay_scene(rng, 25, 25.0, roads=roads, types=types)
    vel = rng.uniform(-5, 5, (25, 2))
    scene.log_vel[:] = vel[:, None]
    scene.log_pos[:, -1] += 500  # keep goals away
    scene.goal[:] = scene.log_pos[:, -1]
    c = cfg(control="all_agents", partner_k=8, road_k=16, partner_radius=20.0, road_radius=25.0,
            max_segment_length=3.0, view_angle=view_angle)
    cos_half = np.cos(np.radians(view_angle) / 2)

    def seen(d, yaw):  # offsets d (n, 2) inside the cone around heading yaw
        return d @ np.array([np.cos(yaw), np.sin(yaw)]) >= cos_half * np.linalg.norm(d, axis=-1) - 1e-9
    sim = Simulator([scene], c, device)
    sim.reset()
    obs_p = sim.obs_partners[0].cpu().numpy()
    obs_r = sim.obs_road[0].cpu().numpy()
    ego = sim.obs_ego[0].cpu().numpy()
    p, y = scene.log_pos[:, INIT], scene.log_yaw[:, INIT]
    a_seg, b_seg, t_seg = (x.copy() for x in ref.scene_segments(scene, 3.0, c.road_simplify))
    mid = 0.5 * (a_seg + b_seg)
    hidden = 0  # partners within reach that the cone hides
    for i in range(25):
        g = ref.to_local(scene.goal[i] - p[i], y[i])
        np.testing.assert_allclose(ego[i, 3:5], g, atol=1e-3)
        assert ego[i, 0] == pytest.approx(np.linalg.norm(vel[i]), abs=1e-4)
        # partners: nearest 8 within 20 m, nearest first
        d = np.linalg.norm(p - p[i], axis=1)
        d[i] = np.inf
        hidden += int(((d < 20.0) & ~seen(p - p[i], y[i])).sum())
        d[~seen(p - p[i], y[i])] = np.inf
        cand = np.argsort(d, kind="stable")
        cand = [j for j in cand if d[j] < 20.0][:8]
        assert obs_p[i, :, 0].sum() == len(cand)
        for k, j in enumerate(cand):
            row = obs_p[i, k]
            np.testing.assert_allclose(row[1:3], ref.to_local(p[j] - p[i], y[i]), atol=1e-3)
            np.testing.assert_allclose(row[3:5], [np.cos(y[j] - y[i]), np.sin(y[j] - y[i])], atol=1e-5)
            np.testing.assert_allclose(row[5:7], ref.to_local(vel[j] - vel[i], y[i]), atol=1e-3)
            np.testing.assert_allclose(row[7:10], [scene.length[j], scene.width[j], types[j]], atol=1e-5)
        # road: nearest 16 segment midpoints within 25 m, nearest first
        dm = np.linalg.norm(mid - p[i], axis=1)
        dm[~seen(mid - p[i], y[i])] = np.inf
        sel = np.argsort(dm, kind="stable")
        sel = [k for k in sel if dm[k] < 25.0][:16]
        assert obs_r[i, :, 0].sum() == len(sel)
        got = obs_r[i, : len(sel)]
        want = np.array([ref.to_local(mid[k] - p[i], y[i]) for k in sel]).reshape(-1, 2)
        np.testing.assert_allclose(got[:, 1:3], want, atol=1e-3)
        for k, row in zip(sel, got):
            dvec = b_seg[k] - a_seg[k]
            ln = np.linalg.norm(dvec)
            assert row[5] == pytest.approx(ln, abs=1e-4) and row[6] == t_seg[k]
            if ln > 0:
                np.testing.assert_allclose(row[3:5], ref.to_local(dvec / ln, y[i]), atol=1e-4)
        assert not obs_r[i, len(sel):].any() and not obs_p[i, len(cand):].any()
    assert (hidden > 0) == (view_angle < 360)


def _brute_force_road_rows(sim, scene_list, road_k, radius, max_segment_length):
    """Road rows of every integrated agent from all of its world's segments (no grid), as
    (distances (n,), features (n, 6)) per slot; features: local x, y, dir x, dir y, length, type."""
    pos = sim.pos.cpu().numpy()
    yaw = sim.yaw.cpu().numpy()
    integ = sim.integrated.cpu().numpy()
    out = {}
    for w, sc in enumerate(scene_list):
        a, b, t = ref.scene_segments(sc, max_segment_length, sim.cfg.road_simplify)
        mid = 0.5 * (a + b)
        d = b - a
        ln = np.linalg.norm(d, axis=1)
        for i in np.nonzero(integ[w])[0]:
            dm = np.linalg.norm(mid - pos[w, i], axis=1)
            sel = np.argsort(dm, kind="stable")
            sel = sel[dm[sel] < radius][:road_k]
            if len(sel) == 0:
                out[w, i] = (dm[sel], np.zeros((0, 6)))
                continue
            feats = np.concatenate([np.stack([ref.to_local(mid[k] - pos[w, i], yaw[w, i]) for k in sel]).reshape(-1, 2),
                                    # a zero-length segment points along the agent's own x axis
                                    np.stack([ref.to_local(d[k] / ln[k], yaw[w, i]) if ln[k] > 0 else [1.0, 0.0]
                                              for k in sel]).reshape(-1, 2),
                                    ln[sel, None], t[sel, None]], axis=1)
            out[w, i] = (dm[sel], feats)
    return out


def _assert_road_rows_match(sim, want):
    obs = sim.obs_road.cpu().numpy()
    for (w, i), (dist, feats) in want.items():
        rows = obs[w, i]
        n = len(dist)
        assert rows[:, 0].sum() == n, (w, i)
        assert not rows[n:].any()
        got_d = np.linalg.norm(rows[:n, 1:3], axis=1)
        np.testing.assert_allclose(got_d, dist, atol=2e-3)
        # rows whose distance is not tied with a neighbour's must be the same segment
        gap = np.diff(np.concatenate([[-1.0], dist, [np.inf]]))
        unique = (gap[:-1] > 5e-3) & (gap[1:] > 5e-3)
        np.testing.assert_allclose(rows[:n][unique, 1:7], feats[unique], atol=2e-3)


@pytest.mark.parametrize("ranked", [False, True], ids=["cpu-way", "gpu-way"])
@pytest.mark.parametrize("kind", ["womd", "dense", "outside"])
def test_road_rows_match_brute_force(device, kind, ranked):
    """The ring search with early exit returns exactly the road_k nearest midpoints within the radius
    (up to ties) on real WOMD maps, a dense generated map and agents far outside the road grid, with
    the rows ordered by either of the engine's two ways (the CPU's and the GPU's default)."""
    if kind == "womd":
        scenes = [load_gpudrive_json(f) for f in sorted((Path(__file__).parent / "data").glob("womd_*.json"))]
        c = EngineConfig(max_agents=128, control="all_agents")
    elif kind == "dense":
        scenes = [dense_scene(3)]
        c = EngineConfig(max_agents=128, control="all_agents")
    else:  # agents on the road, beside it and far beyond the grid in every direction
        rng = np.random.default_rng(7)
        roads = [(RoadType.LANE, np.cumsum(rng.uniform(-3, 3, (60, 2)), 0)),
                 (RoadType.ROAD_EDGE, rng.uniform(-40, 40, (30, 2)))]
        scene = random_replay_scene(rng, 12, 20.0, roads=roads)
        # three with nothing within the radius, three 25-40 m beyond the grid's edges (about +-40 m)
        scene.log_pos[:6] = np.array([[340.0, 0.0], [-300.0, 45.0], [0.0, -260.0], [0.0, 75.0], [-70.0, 5.0],
                                      [65.0, -70.0]])[:, None]
        scenes = [scene]
        c = cfg(control="all_agents", road_k=24, road_radius=60.0, road_cell_size=7.0)
    sim = Simulator(scenes, c, device)
    sim.model.parallel_road_rows = ranked
    sim.reset()
    _assert_road_rows_match(sim, _brute_force_road_rows(sim, scenes, c.road_k, c.road_radius, c.max_segment_length))


# ---------------------------------------------------------------- simplification
@pytest.fixture(scope="module")
def womd_scenes():
    return [load_gpudrive_json(f) for f in sorted((Path(__file__).parent / "data").glob("womd_*.json"))]


def _engine_simplified(scene, tolerance, device):
    from tg_gpudrive.engine.roads import _simplified
    pts = torch.as_tensor(np.array(scene.road_points, np.float32), device=device)
    off = torch.as_tensor(np.array(scene.road_offsets, np.int64), device=device)
    ptype = torch.as_tensor(np.array(scene.road_type, np.int32), device=device)
    p, o = _simplified(pts, off, ptype, tolerance)
    return p.cpu().numpy(), o.cpu().numpy()


@pytest.mark.parametrize("tolerance", [0.05, 0.1, 0.5])
def test_simplify_kernel_keeps_the_numpy_rdp_points(device, womd_scenes, rng, tolerance):
    """kernels/road.py simplify_kernel keeps exactly the points of the NumPy RDP (data/simplify.py) on real
    WOMD maps and on random wiggly polylines and thin polygons (a crosswalk keeps three corners)."""
    wiggle = np.cumsum(rng.normal(0, 0.3, (60, 2)) + [0.5, 0.0], 0)
    thin = np.array([[0.0, 0.0], [5.0, 0.01], [10.0, 0.0], [5.0, -0.01]])
    synthetic = random_replay_scene(rng, 2, 10.0, roads=[(RoadType.LANE, wiggle), (RoadType.CROSSWALK, thin),
                                                         (RoadType.ROAD_EDGE, wiggle[:2]), (RoadType.STOP_SIGN, wiggle[:1])])
    for scene in [*womd_scenes, synthetic]:
        want = simplify_scene(scene, tolerance)[0]
        pts, off = _engine_simplified(scene, tolerance, device)
        np.testing.assert_array_equal(off, want.road_offsets)
        np.testing.assert_array_equal(pts, want.road_points)
        assert len(pts) < len(scene.road_points)
    crosswalk = want.road_points[want.road_offsets[1]:want.road_offsets[2]]
    assert len(crosswalk) == 3


def test_simplified_roads_reach_further_ahead(device, womd_scenes):
    """On a real map (a point every 0.5 m) the road_k nearest segments an agent observes reach several
    times further once the roads are simplified."""
    reach = {}
    for tol in (0.0, 0.1):
        sim = Simulator(womd_scenes[:1], cfg(road_k=32, road_radius=50.0, road_simplify=tol), device)
        sim.reset()
        r = sim.obs_road[0][sim.policy_agents[0]].cpu().numpy()
        d = np.where(r[..., 0] > 0, np.linalg.norm(r[..., 1:3], axis=-1), 0.0).max(-1)
        reach[tol] = float(np.median(d))
    assert reach[0.1] > 2 * reach[0.0], reach
