"""Scenario-quality evaluation: divergences against hand-computed values, Wasserstein against
scipy, CCE-gap zero / positive, exporter round trip, and the report on a tiny CPU run."""

from __future__ import annotations

import dataclasses
import json
import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import scipy.stats
import torch
import yaml

from conftest import WOMD_FILES
from test_report_markdown import csv_rows, per_agent_lines
from tg_gpudrive.config import REPO_CONFIGS, EngineConfig, TrainConfig, load_config
from tg_gpudrive.data.procedural import generate_scene
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.evaluation import diversity as div
from tg_gpudrive.evaluation import exploitability as ex
from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import report_markdown as rm
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.export import generated_scene, write_scene_json
from tg_gpudrive.engine.control import control_masks
from tg_gpudrive.evaluation.episodes import (Trajectories, logged_episodes, nearest_distance, path_kinematics,
                                             record_episodes, record_rollouts, replay_episodes)
from tg_gpudrive.agents.builtin import expert_policy, make_random_policy
from tg_gpudrive.scene import make_scene
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.enums import AgentType, RoadType

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def one_thread():
    # tiny per-step batches: torch's thread pool only adds overhead (and contends on shared cores)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ------------------------------------------------------------ divergences
def test_divergences_by_hand():
    p, q = np.array([1.0, 0.0]), np.array([0.5, 0.5])
    assert fid.hellinger(p, q) == pytest.approx(math.sqrt(1 - math.sqrt(0.5)))
    assert fid.hellinger(p, p) == pytest.approx(0.0, abs=1e-12)
    assert fid.hellinger([1, 0], [0, 1]) == pytest.approx(1.0)
    # KL with eps smoothing: p' = (p + e) / (1 + 2e)
    e = 1e-6
    pp = (np.array([1.0, 0.0]) + e) / (1 + 2 * e)
    qq = (np.array([0.5, 0.5]) + e) / (1 + 2 * e)
    assert fid.kl_divergence(p, q, eps=e) == pytest.approx((pp * np.log(pp / qq)).sum())
    assert fid.kl_divergence([2, 2], [1, 3]) == pytest.approx(0.5 * math.log(0.5 / 0.25) + 0.5 * math.log(0.5 / 0.75),
                                                               rel=1e-5)
    # counts are normalised; W1 of a point mass shifted by two bins of width 0.5 is 1.0
    assert fid.wasserstein1([0, 4, 0, 0], [0, 0, 0, 1], 0.5) == pytest.approx(1.0)


def test_wasserstein_matches_scipy(rng):
    b = fid.FEATURES["speed"]
    p, q = fid.histogram(rng.normal(10, 3, 500), b), fid.histogram(rng.normal(13, 2, 700), b)
    want = scipy.stats.wasserstein_distance(b.centers, b.centers, p, q)
    assert fid.wasserstein1(p, q, b.width) == pytest.approx(want, rel=1e-9)


def test_histogram_clips_into_the_edge_bins():
    b = fid.FEATURES["accel"]
    h = fid.histogram([-100.0, 100.0, 0.1], b)
    assert h.sum() == 3 and h[0] == 1 and h[-1] == 1 and h[b.num_bins // 2] == 1


def test_realism_likelihood():
    b = fid.Binning(0.0, 2.0, 1.0, "m")
    q = np.array([3.0, 1.0])
    # logged samples: one in each bin -> mean log of the smoothed masses
    qs = (q / 4 + fid.REALISM_EPS) / (1 + 2 * fid.REALISM_EPS)
    assert fid.log_likelihood([0.5, 1.5], q, b) == pytest.approx(np.log(qs).mean())


# ---------------------------------------------------------- rollouts & risk
def test_path_kinematics_by_hand():
    """Finite differences of positions: constant acceleration on a line gives it exactly, a circle at
    constant speed gives 1/R (chord headings: theta / (2 R sin(theta / 2))), standing still gives 0."""
    dt, a, R, v = 0.1, 1.5, 20.0, 8.0
    t = dt * np.arange(12)
    line = np.stack([0.5 * a * t**2 + 3.0 * t, np.zeros_like(t)], -1)
    th = v * t / R
    circle = np.stack([R * np.sin(th), R * (1 - np.cos(th))], -1)
    still = np.zeros_like(line)
    pos = np.stack([line, circle, still])[None]  # (1, 3, K, 2)
    valid = np.ones(pos.shape[:3], bool)
    valid[0, 1, 6] = False  # a gap: no accel / curvature at steps 6, 7 and 8
    accel, curv, ok = path_kinematics(pos, valid, dt)
    assert not ok[0, :, :2].any()
    np.testing.assert_allclose(accel[0, 0, 2:], a, atol=1e-4)
    np.testing.assert_allclose(curv[0, 0, 2:], 0.0, atol=1e-6)
    step = v * dt / R
    want = step / (2 * R * np.sin(step / 2))
    got = curv[0, 1][ok[0, 1]]
    assert ok[0, 1].sum() == 12 - 2 - 3 and np.allclose(got, want, rtol=1e-4) and want == pytest.approx(1 / R, rel=1e-3)
    np.testing.assert_allclose(accel[0, 1][ok[0, 1]], 0.0, atol=1e-3)
    assert ok[0, 2, 2:].all() and not accel[0, 2].any() and not curv[0, 2].any()


def test_log_replay_scores_near_zero_and_the_grid_shows():
    """On real WOMD scenes the engine replaying the logs is within Hellinger 0.05 of the logs on every
    feature (acceleration and curvature come from positions on both sides); the discrete expert,
    which can only pick 2 m/s^2 steps, is far from them in acceleration."""
    scenes = [load_gpudrive_json(f) for f in WOMD_FILES]
    cfg = EngineConfig(max_agents=128)
    masks = control_masks(scenes, cfg, "vehicles", 0, None)
    sim = Simulator(scenes, cfg, "cpu", controlled=masks)
    logged = logged_episodes(sim)
    replay = fid.compare(logged, replay_episodes(scenes, masks, cfg, "cpu"))["per_feature"]
    for name, v in replay.items():
        assert v["n_generated"] > 0.9 * v["n_logged"] > 500, name
        assert v["hellinger"] < 0.05, (name, v["hellinger"])
    expert = fid.compare(logged, record_episodes(sim, expert_policy))["per_feature"]
    assert expert["accel"]["hellinger"] > 0.3


@pytest.fixture(scope="module")
def merge_sim():
    scenes = [generate_scene("merge", s) for s in range(2)]
    return Simulator(scenes, EngineConfig(max_agents=16, partner_k=4, road_k=8), "cpu")


def test_episode_histograms_add_up_to_the_fidelity_histograms(merge_sim):
    """The per-agent-episode rows the Hellinger bootstrap resamples: all rows summed give compare()'s
    histograms and its mean Hellinger distance; one agent-episode's row is that agent's own histogram;
    a resample's weights go straight through the sums."""
    logged = logged_episodes(merge_sim)
    gen = record_episodes(merge_sim, make_random_policy(0, "cpu"), label="random")
    agents = gen.policy & gen.valid.any(-1)
    rows = fid.episode_histograms(gen, agents)
    assert rows.shape == (agents.sum(), sum(b.num_bins for b in fid.FEATURES.values()))
    whole = np.concatenate(list(fid.histograms(gen, agents).values()))
    np.testing.assert_array_equal(rows.sum(0), whole)
    per = fid.compare(logged, gen)["per_feature"]
    assert fid.hellinger_of_sums(fid.histograms(logged), rows.sum(0)) == pytest.approx(
        np.mean([v["hellinger"] for v in per.values()]), rel=1e-9)
    one = np.zeros_like(agents)
    one[np.argwhere(agents)[3][0], np.argwhere(agents)[3][1]] = True
    np.testing.assert_array_equal(rows[3], np.concatenate(list(fid.histograms(gen, one).values())))
    twice = fid.hellinger_of_sums(fid.histograms(logged), np.stack([rows.sum(0), 2 * rows.sum(0)]))
    assert twice[0] == pytest.approx(twice[1])  # a distance between distributions: counts scale away


def test_expert_is_close_to_the_logs_and_random_is_not(merge_sim):
    logged = logged_episodes(merge_sim)
    expert = record_episodes(merge_sim, expert_policy, label="expert")
    rand = record_episodes(merge_sim, make_random_policy(0, "cpu"), label="random")
    fe, fr = fid.compare(logged, expert), fid.compare(logged, rand)
    for name in ("speed", "nearest"):
        assert fe["per_feature"][name]["hellinger"] < fr["per_feature"][name]["hellinger"]
    assert fe["realism_ours"] > fr["realism_ours"]
    # log replay is one trajectory per scene: no diversity; random rollouts differ
    both = record_rollouts(merge_sim, make_random_policy(1, "cpu"), seeds=[0, 1])
    assert div.diversity(both)["mean"] > 0.5
    two = record_rollouts(merge_sim, expert_policy, seeds=[0, 1])
    assert div.diversity(two)["mean"] == pytest.approx(0.0, abs=1e-6)


def test_ttc_closed_form_head_on():
    # two discs 20 m apart closing at 10 m/s, radii 1 + 1: contact after (20 - 2) / 10 s
    t = rk.pair_ttc(np.array([20.0, 0.0]), np.array([-10.0, 0.0]), np.array(2.0))
    assert float(t) == pytest.approx(1.8)
    assert float(rk.pair_ttc(np.array([1.0, 0.0]), np.array([0.0, 0.0]), np.array(2.0))) == 0.0  # overlap
    assert float(rk.pair_ttc(np.array([20.0, 0.0]), np.array([10.0, 0.0]), np.array(2.0))) == rk.TTC_HORIZON


def _behind_a_stopped_car(lead_x: float, accel_bin: int = 3):
    """The recorded episode of a policy car starting at x = 0 at 10 m/s behind a stopped log car at `lead_x`, both
    4 x 2 m on one lane, the policy holding acceleration bin `accel_bin` (3: 0 m/s^2, 0: -6 m/s^2) and no turn."""
    T = 40
    lead = np.stack([np.full(T, lead_x), np.zeros(T)], -1)
    follow = np.stack([np.arange(T) * 1.0, np.zeros(T)], -1)  # 10 m/s, dt 0.1
    sc = make_scene(np.stack([lead, follow]), np.zeros((2, T)), length=4.0, width=2.0,
                    roads=[(RoadType.LANE, np.array([[-10.0, 0.0], [100.0, 0.0]]))])
    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=4, init_steps=1)
    sim = Simulator([sc], cfg, "cpu", controlled=[np.array([False, True])])
    return record_episodes(sim, lambda s: s.actions_index.fill_(accel_bin * cfg.curvature_bins
                                                                 + cfg.curvature_bins // 2))


def test_risk_of_a_rear_end_scene():
    """A fast car behind a stopped one: TTC from the closed form, collision and hard braking found."""
    tr = _behind_a_stopped_car(30.0)
    r = rk.episode_risk(tr)
    slot = int(np.nonzero(tr.policy[0])[0][0])
    # at k = 0: gap 29 m between centres, 3 discs of radius 1, outer discs 1 m from the centre:
    # contact when the gap closes to 2 + 2 * 1 = 4 m -> (29 - 4) / 10 s
    assert r["min_ttc"][0, slot] <= (29.0 - 4.0) / 10.0 + 1e-4
    assert r["collided"][0, slot]
    assert r["min_gap"][0, slot] < 4.0
    # close_time: the share of its steps with the lead's centre within 5 m, from the positions by hand
    lead_slot = 1 - slot
    ok = tr.valid[0, slot]
    d = np.linalg.norm(tr.pos[0, slot] - tr.pos[0, lead_slot], axis=-1)
    want = ((d < rk.CLOSE_DISTANCE) & ok & tr.valid[0, lead_slot]).sum() / ok.sum()
    assert 0.0 < want < 1.0 and r["close_time"][0, slot] == pytest.approx(want)
    assert rk.summarize(tr, r)["close_time_share"] == pytest.approx(want)
    # braking at the last grid value (-6 m/s^2) from 10 m/s is one event
    tr2 = _behind_a_stopped_car(30.0, accel_bin=0)
    assert rk.hard_brakes(tr2)[0, slot] == 1
    assert not rk.episode_risk(tr2)["collided"][0, slot]
    ranked = rk.rank_scenarios(tr.concat([tr2, tr]))
    assert ranked[0]["collisions"] == 1 and ranked[-1]["collisions"] == 0


def _gap_ahead_by_sampling(tr, horizon: float, samples: int = 2001) -> np.ndarray:
    """min_gap_ahead's reference: every pair's constant-velocity distance read on a fine grid of look-ahead times."""
    E, A, K = tr.valid.shape
    out = np.full((E, A), np.inf)
    ts = np.linspace(0.0, horizon, samples)
    for e, i, j, k in zip(*np.nonzero(tr.policy[:, :, None, None] & tr.valid[:, :, None, :] & tr.valid[:, None])):
        if i != j:
            p, v = tr.pos[e, j, k] - tr.pos[e, i, k], tr.vel[e, j, k] - tr.vel[e, i, k]
            out[e, i] = min(out[e, i], np.linalg.norm(p[None] + ts[:, None] * v[None], axis=-1).min())
    return out


def test_min_gap_ahead_is_the_least_gap_over_the_next_second():
    """A car drives past a standing one 4 m to its side: over a second's look-ahead the least gap is exactly the
    4 m of the closed form, which the recorded steps only approach; a car closing on a stopped one at 10 m/s
    has its gap ahead 10 m below its gap, as a fine sampling of the look-ahead reads it."""
    tr = record_episodes(_passing_cars(), expert_policy, seed=0)
    ahead, now = rk.min_gap_ahead(tr), rk.min_gap(tr)
    assert ahead[0, 0] == pytest.approx(4.0, abs=0.02) and ahead[0, 0] <= now[0, 0] + 1e-6
    assert ahead == pytest.approx(_gap_ahead_by_sampling(tr, rk.ANTICIPATION), abs=1e-3)
    far = dataclasses.replace(tr, pos=tr.pos.copy())
    far.pos[0, 1] += 1000.0  # no one within the recording's cap: capped there, as min_gap is
    assert rk.min_gap_ahead(far)[0, 0] == rk.NEAREST_CAP
    tr = _behind_a_stopped_car(60.0)
    slot = int(np.nonzero(tr.policy[0])[0][0])
    assert rk.min_gap_ahead(tr) == pytest.approx(_gap_ahead_by_sampling(tr, rk.ANTICIPATION), abs=1e-3)
    assert rk.min_gap_ahead(tr)[0, slot] == pytest.approx(rk.min_gap(tr)[0, slot] - 10.0, abs=0.2)
    # no look-ahead: the recording's own nearest distance
    assert rk.min_gap_ahead(tr, 0.0)[0, slot] == pytest.approx(rk.min_gap(tr)[0, slot], abs=1e-3)
    assert rk.episode_risk(tr)["min_gap_ahead"][0, slot] == rk.min_gap_ahead(tr)[0, slot]


def test_collision_partners_by_hand():
    """Who hit whom, on hand-made scenes (first contact, nearest centre, geometry in the agent's frame):
    a policy car running into a slow log car is "ahead" with a non-policy partner; a slow policy car
    that a log car drives into is hit "from behind"; a log car crossing its path is "crossing". (Cars
    that start within goal_radius of their goal are not controlled, hence the slow car moves.)"""
    T = 40
    stopped = np.stack([30.0 + np.arange(T) * 0.2, np.zeros(T)], -1)  # 2 m/s
    behind = np.stack([np.arange(T) * 1.5, np.zeros(T)], -1)  # 15 m/s: reaches the slow car at ~2 s
    across = np.stack([np.full(T, 33.0), -25.0 + np.arange(T) * 1.0], -1)  # 10 m/s northwards
    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=4, init_steps=1)
    keep = lambda s: s.actions_index.fill_(3 * cfg.curvature_bins + cfg.curvature_bins // 2)  # 0 m/s^2, straight
    road = [(RoadType.LANE, np.array([[-10.0, 0.0], [100.0, 0.0]]))]

    def partners(trajs, yaws, controlled):
        sc = make_scene(np.stack(trajs), np.stack(yaws), length=4.0, width=2.0, roads=road)
        tr = record_episodes(Simulator([sc], cfg, "cpu", controlled=[np.array(controlled)]), keep)
        return rk.collision_partners(tr), rk.summarize(tr)

    zeros, north = np.zeros(T), np.full(T, np.pi / 2)
    rows, summary = partners([stopped, behind], [zeros, zeros], [False, True])
    assert [(r["contact"], r["partner_policy"]) for r in rows] == [("ahead", False)]
    assert rows[0]["speed"] == pytest.approx(15.0, abs=0.2) and rows[0]["partner_speed"] == pytest.approx(2.0, abs=0.2)
    assert summary["collision_with_other_rate"] == summary["collision_ahead_rate"] == summary["collision_rate"] == 1.0
    rows, summary = partners([stopped, behind], [zeros, zeros], [True, False])
    assert [(r["contact"], r["partner_policy"]) for r in rows] == [("from behind", False)]
    assert summary["collision_from_behind_rate"] == 1.0 and summary["collision_with_policy_rate"] == 0.0
    rows, _ = partners([stopped, across], [zeros, north], [True, False])
    assert [r["contact"] for r in rows] == ["crossing"]
    # two policy cars: each sees the other as a policy partner, from its own side
    rows, summary = partners([stopped, behind], [zeros, zeros], [True, True])
    assert sorted((r["contact"], r["partner_policy"]) for r in rows) == [("ahead", True), ("from behind", True)]
    assert summary["collision_with_policy_rate"] == 1.0
    # the car ahead leaves the scene in the step of the contact (its goal reached, goal_behaviour remove):
    # still the partner, not some farther agent that stays
    sc = make_scene(np.stack([stopped, behind, across + [40.0, 0.0]]), np.stack([zeros, zeros, north]), length=4.0,
                    width=2.0, roads=road)
    tr = record_episodes(Simulator([sc], cfg, "cpu", controlled=[np.array([True, True, False])]), keep)
    k = int(np.argmax(tr.collided[0, 1]))
    of_1 = lambda: [(r["partner"], r["contact"], r["partner_policy"]) for r in rk.collision_partners(tr)  # noqa: E731
                    if r["agent"] == 1]
    assert k > 0 and tr.valid[0, 2, k] and of_1() == [(0, "ahead", True)]
    tr.valid[0, 0, k:] = False
    assert of_1() == [(0, "ahead", True)]


def _passing_cars():
    """Car 0 drives along y = 0 from x = 0 to 20 m over 3 s; car 1 stands at (10, 4): by hand, the least
    centre distance is 4 m, when car 0 passes x = 10 (half way, about step 15 of 30)."""
    t = 31
    x = np.linspace(0.0, 20.0, t)
    pos = np.stack([np.stack([x, np.zeros(t)], -1), np.tile([10.0, 4.0], (t, 1))])
    roads = [(RoadType.ROAD_EDGE, [[-20, -8], [40, -8]]), (RoadType.ROAD_EDGE, [[-20, 14], [40, 14]])]
    scene = make_scene(pos, np.zeros((2, t)), roads=roads, agent_type=AgentType.VEHICLE)
    return Simulator([scene], EngineConfig(replay_infeasible=False, init_steps=1, auto_reset=False))


def test_closest_moment_is_the_least_distance_of_the_episode():
    sim = _passing_cars()
    k, i, j, d = rk.closest_moment(record_episodes(sim, expert_policy, seed=0))
    # against the positions read step by step from the same episode
    sim.reset()
    least, at = np.inf, -1
    for step in range(sim.episode_length + 1):
        p = sim.pos[0].numpy().astype(np.float64)
        if np.linalg.norm(p[0] - p[1]) < least:
            least, at = float(np.linalg.norm(p[0] - p[1])), step
        if step == sim.episode_length or int(sim.world_ended[0]):
            break
        expert_policy(sim)
        sim.step()
    assert {i, j} == {0, 1} and k == at and d == pytest.approx(least, abs=1e-4)
    assert d == pytest.approx(4.0, abs=0.3) and abs(k - 14) <= 3
    tr = record_episodes(sim, expert_policy, seed=0)
    tr.nearest[:] = rk.NEAREST_CAP  # no one ever within the recording's cap: no moment to draw
    assert rk.closest_moment(tr) is None


def test_closest_frame_draws_that_moment_zoomed_in(tmp_path):
    from tg_gpudrive.evaluation.report import _closest_frame
    from tg_gpudrive.render import render_episode

    sim = _passing_cars()
    k, *_ = rk.closest_moment(record_episodes(sim, expert_policy, seed=0))
    sim.reset()
    start = int(sim.world_step[0])
    kw = dict(world=0, size=(200, 200), legend=False, seed=0)
    near = _closest_frame(sim, lambda: expert_policy, tmp_path / "near.png", kw)
    assert near.shape == (200, 200, 3) and int(sim.world_step[0]) == start + k  # stopped at the moment found
    assert (tmp_path / "near.png").stat().st_size > 0
    whole = render_episode(sim, expert_policy, **kw)[-1]
    assert not np.array_equal(near, whole)

def test_closest_partners_by_hand():
    """Where the closest approach is, on hand-made scenes: a policy car passing a parked car at the kerb has it
    abreast and parked; one closing on a slower car in its lane has it ahead, moving; two policy cars in one lane
    see each other ahead and behind, as policy partners."""
    T = 40
    zeros = np.zeros(T)
    driver = np.stack([np.arange(T) * 1.0, zeros], -1)  # 10 m/s along the lane
    kerb = np.stack([np.full(T, 20.0), np.full(T, 3.5)], -1)  # parked 3.5 m to the side, passed at 2 s
    slow = np.stack([40.0 + np.arange(T) * 0.5, zeros], -1)  # 5 m/s, 40 m ahead: the gap closes to 20.5 m
    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=4, init_steps=1)
    keep = lambda s: s.actions_index.fill_(3 * cfg.curvature_bins + cfg.curvature_bins // 2)  # 0 m/s^2, straight
    road = [(RoadType.LANE, np.array([[-10.0, 0.0], [100.0, 0.0]]))]

    def closest(trajs, controlled):
        sc = make_scene(np.stack(trajs), np.zeros((len(trajs), T)), length=4.0, width=2.0, roads=road)
        tr = record_episodes(Simulator([sc], cfg, "cpu", controlled=[np.array(controlled)]), keep)
        got = rk.closest_partners(tr)
        place = lambda a: rk.PLACES[got["place"][0, a]] if got["place"][0, a] >= 0 else None  # noqa: E731
        rows = {int(a): (place(a), bool(got["parked"][0, a]), bool(got["policy"][0, a]))
                for a in np.nonzero(tr.policy[0])[0]}
        return rows, rk.summarize(tr), tr

    rows, summary, tr = closest([driver, kerb], [True, False])
    assert list(rows.values()) == [("abreast", True, False)]
    a = next(iter(rows))
    assert rk.min_gap(tr)[0, a] == pytest.approx(3.5, abs=0.2)  # the closest step is the pass, 3.5 m beside it
    first = int(np.argmax(tr.valid[0, a])) + cfg.init_steps  # the log's step the recording starts from
    assert rk.start_gap(tr)[0, a] == pytest.approx(np.linalg.norm(driver[first] - kerb[first]), abs=0.05)  # 19.3 m
    assert summary["closest_abreast_share"] == summary["closest_parked_share"] == 1.0
    assert summary["closest_policy_share"] == summary["closest_ahead_share"] == 0.0
    rows, summary, _ = closest([driver, slow], [True, False])
    assert list(rows.values()) == [("ahead", False, False)]
    far = kerb + [0.0, 60.0]  # never within the recording's cap of the driver: no closest moment to place
    rows, summary, _ = closest([driver, far], [True, False])
    assert list(rows.values()) == [(None, False, False)]
    assert sum(summary[k] for k in rk.PLACE_KEYS) == 0.0
    rows, summary, _ = closest([driver, slow], [True, True])
    assert sorted(rows.values()) == [("ahead", False, True), ("behind", False, True)]
    assert summary["closest_policy_share"] == 1.0 and summary["closest_behind_share"] == 0.5
    # the report's table reads the same shares
    table = "".join(rm._closest_section([{"label": "p", "risk": summary}]))
    assert "| p | 0 | 0.5 | 0.5 | 0 | 1 |" in table
    assert rm._closest_section([{"label": "old cache", "risk": {"collision_rate": 0.0}}]) == []


def _hand_episode(pos, yaw, valid=None, policy=(True,)) -> Trajectories:
    """One recorded episode built by hand from each agent's centres (A, K, 2) and headings (A, K) alone: what the
    moments of risk.py read (the rest zero; `policy` marks the first agents as the policy's)."""
    pos = np.asarray(pos, np.float32)[None]
    A, K = pos.shape[1:3]
    valid = np.ones((1, A, K), bool) if valid is None else np.asarray(valid, bool)[None]
    zero = np.zeros((1, A, K), np.float32)
    return Trajectories(pos=pos, yaw=np.broadcast_to(np.asarray(yaw, np.float32), (A, K))[None].copy(),
                        vel=np.zeros_like(pos), speed=zero, accel=zero, curvature=zero,
                        nearest=nearest_distance(pos, valid), valid=valid, kin_valid=np.zeros_like(valid),
                        collided=np.zeros_like(valid), offroad=np.zeros_like(valid),
                        policy=(np.arange(A) < len(policy))[None] & np.pad(policy, (0, A - len(policy)))[None],
                        length=np.full((1, A), 4.0, np.float32), width=np.full((1, A), 2.0, np.float32),
                        slot_agent=np.arange(A)[None], scene_index=np.zeros(1, np.int64), seed=np.zeros(1, np.int64),
                        scenes=[], init_step=0, dt=0.1)


def _lane_and_abreast(ahead_gap=(20.0, 14.0, 10.0, 8.0, 7.0, 6.0, 8.0, 12.0)):
    """A policy car heading north (yaw pi/2) up x = 0, 1 m a step; a replayed car abreast in the next lane (3.5 m
    to its right, beside it throughout); a replayed car ahead in its lane, 0.5 m to the side, `ahead_gap` m ahead
    along the lane at each step. In the world's frame the abreast car is the one with the same y: a test of the
    agent's frame."""
    y = np.arange(len(ahead_gap), dtype=np.float64)
    pos = np.stack([np.stack([np.zeros_like(y), y], -1), np.stack([np.full_like(y, 3.5), y], -1),
                    np.stack([np.full_like(y, -0.5), y + np.asarray(ahead_gap)], -1)])
    return _hand_episode(pos, np.pi / 2)


def test_lane_approach_moment_takes_the_car_ahead_not_the_one_abreast():
    tr = _lane_and_abreast()
    assert rk.closest_moment(tr)[2:] == (1, pytest.approx(3.5))  # the nearest of all: abreast, 3.5 m all along
    k, a, b, d = rk.lane_approach_moment(tr)
    assert (k, a, b) == (5, 0, 2) and d == pytest.approx(np.hypot(6.0, 0.5), abs=1e-5)
    assert rk.lane_gap(tr, 0, 0, 5) == (2, pytest.approx(d), True)
    assert rk.lane_gap(tr, 0, 2, 5) == (0, pytest.approx(d), False)  # the policy car is behind the one ahead
    assert rk.lane_gap(tr, 0, 1, 5) is None  # the abreast car has no one in its lane
    tr.valid[0, 0, 5] = False
    assert rk.lane_gap(tr, 0, 0, 5) is None  # gone then
    assert rk.lane_approach_moment(tr)[:3] == (4, 0, 2)  # the next nearest step it is there


def test_lane_approach_moment_leaves_out_the_agents_first_step():
    """The nearest in-lane approach is the agent's first step (the state the log hands over) and, before that,
    a step it was not there: both left out, the least later one taken."""
    tr = _lane_and_abreast((1.0, 4.0, 8.0, 9.0, 7.0, 10.0))
    tr.valid[0, 0, 0] = False  # the agent enters at step 1, 4 m behind the car ahead
    assert rk.lane_approach_moment(tr)[:3] == (4, 0, 2)
    assert rk.lane_approach_moment(tr)[3] == pytest.approx(np.hypot(7.0, 0.5), abs=1e-5)


def test_lane_approach_moment_is_none_without_anyone_in_the_lane():
    tr = _lane_and_abreast()
    tr.valid[0, 2, 1:] = False  # the car ahead is there only at the agent's first step
    assert rk.lane_approach_moment(tr) is None and rk.closest_moment(tr) is not None
    tr = _lane_and_abreast()
    tr.policy[0] = [False, True, False]  # the abreast car drives: it has no one ahead or behind in its lane
    assert rk.lane_approach_moment(tr) is None


def test_grid_moment_is_the_most_pressing_cells_lane_approach_drawn_in_every_cell():
    from tg_gpudrive.evaluation.report import grid_moment

    ref = _lane_and_abreast()
    wider = _lane_and_abreast((20.0, 18.0, 16.0, 15.0, 14.0, 12.0, 12.0, 12.0))
    far = _lane_and_abreast((30.0,) * 8)
    cells = {(6.0, 0.125): far, (0.5, 0.875): wider, (0.5, 0.125): ref}  # least beta, then least alpha: ref
    m = grid_moment(cells, margin=8.0)
    assert (m.step, m.agent, m.cell) == (5, 0, (0.5, 0.125)) and m.centre == pytest.approx((0.0, 5.0))
    assert m.gaps[(0.5, 0.875)][1] == pytest.approx(np.hypot(12.0, 0.5), abs=1e-5)
    assert m.gaps[(6.0, 0.125)][1] == pytest.approx(np.hypot(30.0, 0.5), abs=1e-5)
    assert all(m.present.values())
    # the far car is left out of view rather than widen every zoom: twice the pressing cell's gap fits
    assert m.radius == pytest.approx(2 * np.hypot(6.0, 0.5) + 8.0, abs=1e-5)
    # a cell whose car leaves the road at step 4 (its goal, a step sooner): the moment is the reference cell's
    # nearest while the car is there in every cell, step 3 at 8 m
    gone = _lane_and_abreast((5.0,) * 8)
    gone.valid[0, 0, 4:] = False
    m = grid_moment({(2.0, 0.125): gone, (0.5, 0.875): wider, (0.5, 0.125): ref}, margin=8.0)
    assert (m.step, m.agent) == (3, 0) and all(m.present.values())
    assert m.gaps[(2.0, 0.125)][1] == pytest.approx(np.hypot(5.0, 0.5), abs=1e-5)
    assert m.radius == pytest.approx(np.hypot(15.0, 0.5) + 8.0, abs=1e-5)  # the widest cell's gap fits
    # a cell without the car after its first step shares no such moment: the reference cell's own, that cell
    # drawn without it
    gone.valid[0, 0, 1:] = False
    m = grid_moment({(2.0, 0.125): gone, (0.5, 0.125): ref})
    assert m.step == 5 and m.gaps[(2.0, 0.125)] is None and m.present == {(2.0, 0.125): False, (0.5, 0.125): True}
    # a cell with a nearer lane approach but a larger beta does not choose the moment; without one in the
    # most pressing cell, none is shared
    ref.valid[0, 2, 1:] = False
    assert grid_moment(cells) is None and grid_moment({}) is None


def test_moment_frame_draws_the_shared_moment_and_a_car_that_has_left(tmp_path):
    from tg_gpudrive.evaluation.report import GridMoment, _moment_frame
    from tg_gpudrive.render import render_episode

    sim = _passing_cars()
    kw = dict(world=0, size=(200, 200), legend=False, seed=0)
    cell = (0.5, 0.125)
    here = GridMoment(5, 0, cell, (5.0, 0.0), 12.0, {cell: (1, 4.0, True)}, {cell: True})
    sim.reset()
    start = int(sim.world_step[0])
    near = _moment_frame(here, cell)(sim, lambda: expert_policy, tmp_path / "here.png", kw)
    assert near.shape == (200, 200, 3) and int(sim.world_step[0]) == start + 5
    # the car has left this cell's episode: the view holds still at its place in the reference cell
    gone = dataclasses.replace(here, agent=1, centre=(10.0, 4.0), gaps={cell: None}, present={cell: False})
    left = _moment_frame(gone, cell)(sim, lambda: expert_policy, tmp_path / "gone.png", kw)
    on_car = render_episode(sim, expert_policy, steps=5, **dict(kw, center_agent=1, view_radius=12.0,
                                                                 title="0.5 s: car 1 has left the scene"))[-1]
    # car 1 stands at (10, 4): centred on its place or on it, the same picture
    assert left.shape == (200, 200, 3) and np.abs(left.astype(int) - on_car.astype(int)).mean() < 2.0
    assert not np.array_equal(near, left)


# ----------------------------------------------------------------- CCE-gap
def test_plateau_rule_stops_on_flat_and_continues_on_rising():
    rule = ex.PlateauRule(window=3, patience=5, tol=0.01, max_iters=50, min_iters=0)
    flat = [2.0] * 50
    # flat: the first w + p iterations are always played, then no new best -> stop
    assert [rule.stop(flat[:n]) for n in range(1, 10)] == [False] * 7 + [True] * 2
    assert rule.plateaued(flat[:8])
    # rising by 0.1 per iteration (> tol * max(1, |best|)): never plateaus, only the cap stops it
    rising = [0.1 * k for k in range(60)]
    assert not any(rule.stop(rising[:n]) for n in range(1, 50))
    assert rule.stop(rising[:50]) and not rule.plateaued(rising[:50])
    # a rise that ends: stops p iterations after the last new best
    ramp = [min(k, 10) * 1.0 for k in range(40)]
    first = next(n for n in range(1, 41) if rule.stop(ramp[:n]))
    # the best moving mean is reached at n = 11 + w - 1 (the first window of three 10s), then p more
    assert first == 11 + rule.window - 1 + rule.patience
    # the tolerance is relative to max(1, |best|): a rise of 0.1 % per iteration on returns ~ 100 (0.6 % over
    # the p iterations and the window's lag) is a plateau at tol = 1 %, not at 0.1 %
    slow = [100.0 * 1.001 ** k for k in range(40)]
    assert rule.stop(slow[:8])
    assert not ex.PlateauRule(window=3, patience=5, tol=0.001, max_iters=50, min_iters=0).stop(slow[:30])
    # min_iters holds it back; noise around a flat mean stops it too (no ever-new best)
    assert not ex.PlateauRule(window=1, patience=1, tol=0.01, min_iters=5).stop(flat[:4])
    noisy = list(np.random.default_rng(0).normal(1.0, 0.3, 200))
    assert any(rule.stop(noisy[:n]) for n in range(1, 50))


def test_cce_gap_matrix_game():
    """PPO best responses recover the closed-form gaps of normal-form games: pure profiles of the
    prisoner's dilemma (Nash: 0, cooperation: 2), a mixed profile of it and a random 3 x 3 game."""
    A = np.array([[3.0, 0.0], [5.0, 1.0]])  # prisoner's dilemma, row player; column player gets A.T
    rng = np.random.default_rng(0)
    P3 = [rng.normal(size=(3, 3)), rng.normal(size=(3, 3))]
    cases = [([A, A.T], [np.array([0.0, 1.0]), np.array([0.0, 1.0])], [0.0, 0.0]),
             ([A, A.T], [np.array([1.0, 0.0]), np.array([1.0, 0.0])], [2.0, 2.0]),
             ([A, A.T], [np.array([0.6, 0.4]), np.array([0.3, 0.7])], None),
             (P3, [np.array([0.2, 0.5, 0.3]), np.array([0.6, 0.1, 0.3])], None)]
    for pay, prof, want in cases:
        exact = ex.MatrixGame(pay, prof).exact_gaps()
        if want is not None:
            assert exact == pytest.approx(want)
        assert (exact > 0.2).all() or want is not None  # the mixed profiles are exploitable
        res = ex.cce_gap(lambda s: ex.MatrixGame(pay, prof, batch=1024, seed=s), seeds=(0, 1), lr=0.1, critic_lr=0.1,
                         eval_rounds=4, max_iters=60, min_iters=20)
        assert res["gap_per_agent"] == pytest.approx(exact.tolist(), abs=0.12), (exact, res["gap_per_agent"])
        assert res["mean_gap"] == pytest.approx(exact.mean(), abs=0.1)
        # every best response stopped at a plateau, well before the cap
        assert np.all(res["plateaued"]) and np.max(res["iters"]) < 60, res["iters"]
        assert set(res["per_type"]) == {"matrix"} and res["per_type"]["matrix"]["agents"] == 2


def _straight_scene():
    T = 60
    pos = np.stack([np.arange(T) * 1.0, np.zeros(T)], -1)[None]  # 10 m/s along a lane to its goal
    return make_scene(pos, np.zeros((1, T)), roads=[(RoadType.LANE, np.array([[-10.0, 0.0], [100.0, 0.0]]))])


def test_cce_gap_single_agent_engine_game():
    """One vehicle on a lane: the expert already reaches the goal (best response, gap ~ 0); a policy
    that always brakes is beaten by a best response by about the goal reward plus the progress
    (discounted)."""
    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=8)
    sim = Simulator([_straight_scene()] * 4, cfg, "cpu")

    def brake(s):
        s.actions_index.fill_(0 * cfg.curvature_bins + cfg.curvature_bins // 2)

    kw = dict(seeds=(0, 1), max_iters=4, window=1, patience=1, min_iters=0, eval_rounds=1)
    good = ex.cce_gap(lambda s: ex.SimGame(sim, expert_policy), **kw)
    bad = ex.cce_gap(lambda s: ex.SimGame(sim, brake), **kw)
    assert len(good["agents"]) == 1
    assert good["mean_gap"] < 0.3, good
    assert bad["mean_gap"] > 1.5, bad
    assert bad["j_br_per_agent"][0] > good["j_pi_per_agent"][0] - 0.5


def test_best_response_corrects_the_learned_actor():
    """With a learned actor each agent's response is a small network on the frozen actor's output: it
    starts exactly at the actor's distribution (discrete and continuous), and against an actor that
    mostly brakes on a free lane it learns to drive on (a positive gain)."""
    from tg_gpudrive.agents.policy import PolicyHead, build_actor

    for space in ("discrete", "continuous"):
        cfg = EngineConfig(max_agents=4, partner_k=2, road_k=8, action_space=space)
        sim = Simulator([_straight_scene()] * 8, cfg, "cpu")
        actor = build_actor(cfg, sim.num_actions, hidden=16)
        with torch.no_grad():  # a braking bias: the hard-brake cell, or a mean near the lowest acceleration
            actor.head_w.zero_()
            actor.head_b.zero_()
            actor.head_b[0, cfg.curvature_bins // 2 if cfg.discrete else 0] = 4.0 if cfg.discrete else -3.0
        head = PolicyHead(cfg.discrete)
        game = ex.SimGame(sim, actor=actor)  # the actor, sampled, is everyone's profile
        with pytest.raises(ValueError, match="either"):  # one profile: a policy or an actor
            ex.SimGame(sim)
        ep = game.play(game.make_response(0))
        with torch.no_grad():
            own = head.dist(actor(ep.inputs["obs"], game.slot)).log_prob(ep.act)
        m = ep.mask
        assert m.any()
        np.testing.assert_allclose(ep.logp[m].numpy(), own[m].numpy(), atol=1e-5)
        if cfg.discrete:  # 32 copies: a batch large enough that the gain stands out of the noise
            game = ex.SimGame(Simulator([_straight_scene()] * 32, cfg, "cpu"), actor=actor)
            res = ex.train_best_response(game, seed=0, max_iters=30, min_iters=30, eval_rounds=2, lr=0.03)
            assert res["gain"][0] > 1.0 and res["gain"][0] > 3 * res["gain_se"][0], res


@pytest.mark.slow
def test_best_response_finds_the_known_gain_against_a_speed_capped_profile():
    """The check the CCE-gap rests on: a profile capped at 3 m/s on a free lane (SpeedCapped) cannot
    reach the goal that the logged driver, at 10 m/s, reaches. The expert's return minus the capped
    profile's is a gain a deviator can have; the best response, which starts at the capped policy
    itself, must find most of it."""
    from tg_gpudrive.agents.policy import build_actor

    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=8)
    sim = Simulator([_straight_scene()] * 32, cfg, "cpu")
    actor = build_actor(cfg, sim.num_actions, hidden=16)
    with torch.no_grad():  # a driver that keeps its speed
        actor.head_w.zero_()
        actor.head_b.zero_()
        actor.head_b[0, cfg.noop_index] = 4.0
    capped = ex.SpeedCapped(actor, cfg, cap=3.0)
    j_expert = ex.evaluate_returns(ex.SimGame(sim, expert_policy), None, 2, 0.99)[0].mean()
    j_capped = ex.evaluate_returns(ex.SimGame(sim, actor=capped), None, 2, 0.99)[0].mean()
    known = j_expert - j_capped
    assert known > 3.0, (j_expert, j_capped)
    res = ex.train_best_response(ex.SimGame(sim, actor=capped), seed=0, max_iters=60, min_iters=60, lr=0.03)
    assert res["gain"][0] >= 0.6 * known, (res["gain"], known, res["curve"])
    assert res["best_iter"][0] > 0  # a trained iterate, not the profile
    # the capped policy's logits: unchanged below the cap, every non-braking action lowered above it
    obs = torch.zeros(2, sim.obs_dim)
    obs[:, 0] = torch.tensor([2.0, 5.0])
    slot = torch.zeros(2, dtype=torch.long)
    d = capped(obs, slot) - actor(obs, slot)
    accel = torch.linspace(-cfg.max_accel, cfg.max_accel, cfg.accel_bins).repeat_interleave(cfg.curvature_bins)
    assert torch.equal(d[0], torch.zeros_like(d[0]))
    assert torch.equal(d[1], torch.where(accel >= 0, -6.0, 0.0))


def test_best_response_in_pieces_is_the_same_update():
    """max_samples splits a minibatch's backward into column pieces (memory); the gradients add up to
    the whole minibatch's, so the trained responses, their curves and returns are the same."""
    A = np.array([[3.0, 0.0], [5.0, 1.0]])
    prof = [np.array([0.6, 0.4]), np.array([0.3, 0.7])]
    cfg = EngineConfig(max_agents=4, partner_k=2, road_k=8)
    sim = Simulator([_straight_scene()] * 4, cfg, "cpu")
    games = [lambda: ex.MatrixGame([A, A.T], prof, batch=256, seed=0), lambda: ex.SimGame(sim, expert_policy)]
    for make in games:
        kw = dict(max_iters=3, window=1, patience=1, min_iters=0, eval_rounds=1, critic_warmup=2, lr=0.05)
        whole = ex.train_best_response(make(), seed=3, **kw)
        pieces = ex.train_best_response(make(), seed=3, max_samples=1, **kw)  # one column per piece
        assert [len(c) for c in pieces["curve"]] == [len(c) for c in whole["curve"]]
        for a, b in zip(pieces["curve"], whole["curve"]):
            assert a == pytest.approx(b, abs=1e-4)
        assert pieces["j_br"] == pytest.approx(whole["j_br"], abs=1e-4)
        assert pieces["gain"] == pytest.approx(whole["gain"], abs=1e-4)


def test_cce_gap_engine_expert_below_constant_and_random(device):
    """Procedural merge and T-junction scenes, two policy agents each, every other agent frozen at
    the profile: the expert profile is hardly exploitable, the constant (keep speed and heading)
    and the uniformly random profiles are; reported per agent and per scenario type, with the PPO
    iterations each best response took."""
    from tg_gpudrive.agents.builtin import constant_policy

    scenes = [generate_scene("merge", 0), generate_scene("t_junction", 0)]
    cfg = EngineConfig(max_agents=16, partner_k=4, road_k=8)
    masks = control_masks(scenes, cfg, "nearest_conflict", 2, None)
    copies = 2
    sim = ex.deviation_sim(scenes, masks, cfg, device, copies)
    kw = dict(seeds=(0,), max_iters=5, window=2, patience=2, min_iters=0, tol=0.02, eval_rounds=2)
    res = {name: ex.cce_gap(lambda s: ex.SimGame(sim, pol), **kw)
           for name, pol in (("expert", expert_policy), ("constant", constant_policy),
                             ("random", make_random_policy(0, device)))}
    for name, r in res.items():
        assert len(r["agents"]) == 4 and set(r["per_type"]) == {"merge", "t_junction"}, name
        assert all(v["agents"] == 2 for v in r["per_type"].values())
        assert all(4 <= i <= 5 for i in r["iters"][0]), r["iters"]  # w + p = 4 at least, the cap 5
        assert np.isfinite(r["ci95"]) and len(r["gain_ci95_per_agent"]) == 4
    assert res["expert"]["mean_gap"] < res["constant"]["mean_gap"], {n: r["mean_gap"] for n, r in res.items()}
    assert res["expert"]["mean_gap"] < res["random"]["mean_gap"]
    assert res["random"]["mean_gap"] > 1.0


# ------------------------------------------------------------------ export
@pytest.mark.parametrize("path", WOMD_FILES[:1])
def test_export_round_trip_is_identical(path, tmp_path):
    a = load_gpudrive_json(path)
    b = load_gpudrive_json(write_scene_json(a, tmp_path / "x.json"))
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), f.name
        elif f.name == "metadata":
            assert {k: v for k, v in x.items() if k != "source"} == {k: v for k, v in y.items() if k != "source"}
        else:
            assert x == y, f.name


def test_export_generated_episode_carries_the_rollout(merge_sim, tmp_path):
    tr = record_episodes(merge_sim, make_random_policy(3, "cpu"), seed=3, label="rand")
    risk = rk.rank_scenarios(tr, top=5)
    e = risk[0]["episode"]
    path = write_scene_json(generated_scene(tr, e, risk=risk[0]), tmp_path / "gen.json")
    sc = load_gpudrive_json(path)
    meta = json.loads(path.read_text())["metadata"]["tg_gpudrive"]
    assert meta["generated"] and meta["risk"]["min_ttc_s"] == risk[0]["min_ttc_s"]
    src = tr.scenes[int(tr.scene_index[e])]
    shift = (sc.origin - src.origin).astype(np.float32)  # the loader re-centres on its own origin
    T0 = tr.init_step
    moved = 0
    for a in np.nonzero(tr.policy[e])[0]:
        idx = tr.slot_agent[e, a]
        v = tr.valid[e, a]
        K = min(len(v), sc.num_steps - T0)
        assert np.array_equal(sc.log_valid[idx, T0:T0 + K], v[:K])
        got = sc.log_pos[idx, T0:T0 + K][v[:K]] + shift
        np.testing.assert_allclose(got, tr.pos[e, a, :K][v[:K]], atol=1e-3)
        moved += np.abs(tr.pos[e, a, :K][v[:K]] - src.log_pos[idx, T0:T0 + K][v[:K]]).max() > 1.0
        assert meta["controlled_ids"].count(int(src.agent_id[idx])) == 1
    assert moved  # the random policy left the log: the file holds the generated paths, not the log


# ------------------------------------------------------------------ report
def test_report_refuses_two_runs_of_one_name(tmp_path):
    """The report labels a run by its folder's name (tables, cache, grid cells): two grids' cells of one name
    would overwrite each other, so it stops before evaluating anything and names both."""
    from tg_gpudrive.evaluation.report import report_main
    a, b = tmp_path / "grid" / "beta2.0_alpha0.125_s0", tmp_path / "other" / "beta2.0_alpha0.125_s0"
    with pytest.raises(ValueError, match="grid/beta2.0_alpha0.125_s0 and .*other/beta2.0_alpha0.125_s0 share"):
        report_main([a, b], tmp_path / "report")
    assert not (tmp_path / "report").exists()


def test_report_on_tiny_runs(tmp_path):
    from PIL import Image

    from tg_gpudrive.cli import main as cli_main
    from tg_gpudrive.evaluation.report import FILES
    from tg_gpudrive.evaluation.report_markdown import PER_AGENT_COLUMNS
    from tg_gpudrive.learn.train import Trainer

    def main(argv):  # `tg-gpudrive report ...`
        return cli_main(["report", *argv])

    base = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    runs = []
    # mappo fine-tunes the cce run's policy: its CCE-gap curve starts there (update 0)
    for name, kw in (("cce", dict(keep_policy_every=1)),
                     ("mappo", dict(eta1=0.0, eta2=math.inf, constraint=False, init_policy=str(tmp_path / "cce")))):
        cfg = dataclasses.replace(base, num_worlds=2, num_scenes=2, rollout_steps=8, epochs=1, minibatches=1,
                                  hidden=16, quantiles=4, updates=2, checkpoint_every=2, control="nearest_conflict",
                                  control_k=2, out_dir=str(tmp_path / name), **kw)
        Trainer(cfg, tmp_path / name, progress=False).train()
        runs.append(str(tmp_path / name))
    out = tmp_path / "report"
    args = ["--scenes", "2", "--seeds", "0", "1", "--br-iters", "1", "--br-window", "1", "--br-patience", "1",
            "--br-tol", "0.05", "--br-copies", "2", "--br-rounds", "1", "--br-seeds", "0", "--br-scenes", "1",
            "--top", "1", "--grid-scene", "1", "--grid-gifs"]
    assert main(["--runs", *runs, "--out", str(out), *args]) == 0
    for f in FILES:
        assert (out / f).stat().st_size > 0, f
    assert (out / "frames" / "cce.gif").stat().st_size > 0 and not (out / "frames" / "mappo.png").exists()
    # the grid's cell: its whole paths beside its zoom on the grid's shared moment, both as frames/ keeps them
    whole, near = (np.asarray(Image.open(out / "frames" / f)) for f in ("cce.png", "cce_closest.png"))
    assert near.shape == whole.shape
    md = (out / "report.md").read_text()
    for label in ("log replay", "expert (inverse dynamics)", "behaviour prior", "world model",
                  "| cce | CCE-MAPPO | T 1 |", "| mappo | MAPPO | T 1 |", "acts at", "realism (ours)",
                  "grid.png shows scene ", "ahead of or behind it in its lane",
                  "bottom right, the mean over that run's episodes", "| bar out of reach (train) |"):
        assert label in md
    summary = json.loads((out / "summary.json").read_text())
    assert summary["meta"]["grid_zoom"] and f"on the right {summary['meta']['grid_zoom']}." in md
    assert {r["label"] for r in summary["results"]} == {"log replay", "expert (inverse dynamics)", "behaviour prior",
                                                         "world model", "cce", "mappo"}
    wm = next(r for r in summary["results"] if r["label"] == "world model")
    assert wm["cce_gap"] and math.isfinite(wm["cce_gap"]["mean_gap"])  # exploitability of the world model alone
    # the deviation game holds the first scene's policy agents only (--br-scenes 1)
    first = {a.split("/")[0] for a in wm["cce_gap"]["agents"]}
    assert len(first) == 1 and summary["meta"]["best_response"]["scenes"] == 1
    # held-out scenes: procedural seeds from 90000 on, never the runs' training seeds 0 .. 1
    played = {int(a.split("/")[-2]) for r in summary["results"] if r["cce_gap"] for a in r["cce_gap"]["agents"]}
    assert played and min(played) >= 90000 and summary["meta"]["eval_scenes"].startswith("held out:")
    assert main(["--runs", *runs, "--out", str(tmp_path / "overlap"), "--scenes", "2", "--scene-seed", "1"]) == 2
    assert list((out / "scenarios" / "cce").glob("*.json"))
    # the CCE-gap over training: the cce run kept its policy after updates 1 and 2 (the second is its final
    # checkpoint, not evaluated twice); mappo kept none, but started from the cce run's final policy
    curve = {r["label"]: r.get("gap_curve") for r in summary["results"]}
    assert [p["update"] for p in curve["cce"]] == [1, 2] and [p["update"] for p in curve["mappo"]] == [0, 2]
    assert all(math.isfinite(p["mean_gap"]) for p in curve["cce"] + curve["mappo"])
    assert (out / "cce_gap_curve.png").stat().st_size > 0 and "## CCE-gap over training" in md
    worst = summary["meta"]["worst_scenes"]
    assert worst["label"] == "cce" and worst["scenes"] and "## Worst scenes of cce" in md
    _check_report_tables(out, summary, md)
    # the CCE-MAPPO run's gap in its own constrained game too, beside the task game; MAPPO has no multipliers
    by = {r["label"]: r for r in summary["results"]}
    con = by["cce"]["cce_gap_constrained"]
    assert math.isfinite(con["mean_gap"]) and con["agents"] == by["cce"]["cce_gap"]["agents"]
    assert "cce_gap_constrained" not in by["mappo"] and "| cce (constrained game) |" in md
    assert all(k in con for k in ("median_gap", "trimmed_mean_gap", "exploitable_agents"))

    assert main(["--runs", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert main(["--runs", *runs, "--out", str(out), "--scenes", "2", "--grid-scene", "2"]) == 2
    # every policy's evaluation is cached: the same report again reads it all back, nothing is recomputed
    cache = {f.name: f.stat().st_mtime_ns for f in (out / "cache").glob("*.pkl")}
    starts = {f for f in cache if f.startswith("start_")}  # the starting policy's gap, once
    assert len(starts) == 1 and set(cache) - starts == {
        "log_replay.pkl", "expert_(inverse_dynamics).pkl", "behaviour_prior.pkl", "world_model.pkl", "cce.pkl",
        "mappo.pkl"}
    assert main(["--runs", *runs, "--out", str(out), *args]) == 0
    assert {f.name: f.stat().st_mtime_ns for f in (out / "cache").glob("*.pkl")} == cache
    again = json.loads((out / "summary.json").read_text())
    assert json.dumps(again["results"], sort_keys=True) == json.dumps(summary["results"], sort_keys=True)
    # another option is another evaluation; a process with some of the runs and no baselines
    assert main(["--runs", runs[1], "--out", str(out), "--no-baselines", *args[:-5], "--top", "2", "--grid-scene", "1"]) == 0
    assert [r["label"] for r in json.loads((out / "summary.json").read_text())["results"]] == ["mappo"]
    assert (out / "cache" / "mappo.pkl").stat().st_mtime_ns != cache["mappo.pkl"]
    # rollouts only: no best response, no CCE-gap anywhere, the rest of the report as before
    assert main(["--runs", *runs, "--out", str(tmp_path / "nogap"), "--no-cce-gap", *args]) == 0
    nogap = json.loads((tmp_path / "nogap" / "summary.json").read_text())
    assert not any(r["cce_gap"] or r.get("gap_curve") or r.get("cce_gap_constrained") for r in nogap["results"])
    assert len(nogap["results"]) == 6
    md = (tmp_path / "nogap" / "report.md").read_text()
    assert "not computed (--no-cce-gap)" in md and "Not computed (--no-cce-gap)" in md
    assert not csv_rows(tmp_path / "nogap" / "per_agent.csv", PER_AGENT_COLUMNS)  # the header alone
    assert "## CCE-gap per agent" not in md and not (tmp_path / "nogap" / "cce_gap.png").exists()


def _check_report_tables(out: Path, summary: dict, md: str) -> None:
    """Per-agent and per-scene rows are in the CSV files that report.md names (one row per agent of every
    policy's deviation game, per exported scenario), never in report.md."""
    from tg_gpudrive.evaluation.report_markdown import PER_AGENT_COLUMNS, PER_SCENE_COLUMNS

    agents = csv_rows(out / "per_agent.csv", PER_AGENT_COLUMNS)
    gapped = [r for r in summary["results"] if r["cce_gap"]]
    assert len(agents) == sum(len(r["cce_gap"]["agents"]) for r in gapped) > 0
    assert {(a["policy"], a["agent"]) for a in agents} == {(r["label"], x) for r in gapped for x in r["cce_gap"]["agents"]}
    scenes = csv_rows(out / "per_scene.csv", PER_SCENE_COLUMNS)
    assert [s["run"] for s in scenes] == ["cce", "mappo"] and all((out / s["exported"]).exists() for s in scenes)
    assert "(per_agent.csv)" in md and "(per_scene.csv)" in md
    assert not per_agent_lines(md, agents)


def test_the_report_says_whether_its_scenes_are_held_out():
    """Procedural runs are evaluated on other seeds; a directory of files has no seed, so the report
    says its scenes are the training ones unless --eval-scenes names others."""
    from tg_gpudrive.evaluation.report import ReportOptions, eval_scenes_text

    proc, files = TrainConfig(scenes="procedural:all"), TrainConfig(scenes="tests/data")
    assert eval_scenes_text(proc, ReportOptions()).startswith("held out: procedural:all, procedural seeds from 90000")
    assert "not held out" in eval_scenes_text(proc, ReportOptions(scene_seed=None))
    assert "not held out" in eval_scenes_text(files, ReportOptions()) and "--eval-scenes" in eval_scenes_text(
        files, ReportOptions())
    assert eval_scenes_text(files, ReportOptions(eval_scenes="womd/validation")) == "womd/validation"


def _script(name: str):
    """scripts/<name>.py as a module (scripts/ is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_heldout_eval_drives_the_agents_the_run_was_trained_to_drive(tmp_path, capsys):
    """scripts/heldout_eval.py evaluates a run trained on the 2 vehicles nearest each conflict point
    with those 2 only (the rest replay their logs), and a built-in policy after it likewise."""
    from tg_gpudrive.learn.train import Trainer

    mod = _script("heldout_eval")
    base = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    cfg = dataclasses.replace(base, num_worlds=2, num_scenes=2, rollout_steps=8, epochs=1, minibatches=1, hidden=16,
                              quantiles=4, updates=1, checkpoint_every=1, control="nearest_conflict", control_k=2,
                              out_dir=str(tmp_path / "run"))
    Trainer(cfg, tmp_path / "run", progress=False).train()
    out = tmp_path / "h.jsonl"
    assert mod.main(["--runs", str(tmp_path / "run"), "expert", "--scenes", "procedural:merge", "--num-scenes", "3",
                     "--seed", "90000", "--modes", "ignore", "--device", "cpu", "--out", str(out)]) in (0, None)
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["episodes"] for r in rows] == [6, 6]  # 3 worlds x the 2 nearest the conflict point
    # --control vehicles: the same run driving every vehicle, as a policy trained on all of them is evaluated
    every = tmp_path / "all.jsonl"
    assert mod.main(["--runs", str(tmp_path / "run"), "--scenes", "procedural:merge", "--num-scenes", "3", "--seed",
                     "90000", "--modes", "ignore", "--device", "cpu", "--out", str(every), "--control", "vehicles"]) in (0, None)
    from tg_gpudrive.data.sources import resolve_scenes
    src = resolve_scenes("procedural:merge", n=3, seed=90000)
    vehicles = sum(int(m.sum()) for m in control_masks([src.get(i) for i in range(3)], cfg.env, "vehicles"))
    assert json.loads(every.read_text())["episodes"] == vehicles > 6
    # --own-scenes: the run on the scenes it trained on (its 2), and a built-in policy on the same
    own = tmp_path / "own.jsonl"
    assert mod.main(["--runs", str(tmp_path / "run"), "expert", "--own-scenes", "--num-scenes", "3", "--modes", "ignore",
                     "--device", "cpu", "--out", str(own)]) in (0, None)
    rows = [json.loads(line) for line in own.read_text().splitlines()]
    assert [(r["worlds"], r["episodes"]) for r in rows] == [(2, 4), (2, 4)]
    assert rows[0]["scenes"] == f"own: {cfg.scenes} from seed {cfg.seed}" == rows[1]["scenes"]


def test_run_experiments_deals_the_runs_over_the_gpus(tmp_path, capsys):
    mod = _script("run_experiments")
    exp = tmp_path / "grid.yaml"
    exp.write_text("base: small_cpu.yaml\nbeta: [2.0, 4.0]\nalpha: [0.5]\nbaselines:\n  mappo: {eta1: 0.0}\nbatch: 3\n")
    assert mod.main(["--config", str(exp), "--out", str(tmp_path / "g"), "--gpus", "0,1", "--dry-run"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if " train " in x]
    assert [x.split()[0] for x in lines] == ["CUDA_VISIBLE_DEVICES=0", "CUDA_VISIBLE_DEVICES=1", "CUDA_VISIBLE_DEVICES=0"]
    assert [x.split("--out ")[1].split()[0].rsplit("/", 1)[1] for x in lines] == ["beta2.0_alpha0.5", "beta4.0_alpha0.5", "mappo"]
    assert mod.main(["--config", str(exp), "--out", str(tmp_path / "g"), "--dry-run"]) == 0
    assert not any(x.startswith("CUDA_VISIBLE_DEVICES") for x in capsys.readouterr().out.splitlines())
    # training seeds: every cell and baseline once per seed, each with its seed
    exp.write_text("base: small_cpu.yaml\nbeta: [2.0]\nalpha: [0.5]\nseeds: [0, 3]\nbaselines:\n  mappo: {eta1: 0.0}\n")
    assert mod.main(["--config", str(exp), "--out", str(tmp_path / "g"), "--dry-run"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if " train " in x]
    assert [x.split("--out ")[1].split()[0].rsplit("/", 1)[1] for x in lines] == [
        "beta2.0_alpha0.5_s0", "beta2.0_alpha0.5_s3", "mappo_s0", "mappo_s3"]
    assert [x.rsplit("--set seed=", 1)[1].split()[0] for x in lines] == ["0", "3", "0", "3"]
    # a baseline trained from scratch: the empty starting policy stays an empty string
    exp.write_text("base: small_cpu.yaml\noverrides: {init_policy: shipped_v1}\nbeta: [2.0]\nalpha: [0.5]\n"
                   "baselines:\n  mappo: {init_policy: ''}\n")
    plan = dict(mod.plan(yaml.safe_load(exp.read_text()), []))
    cfg = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml", overrides=plan["mappo"])
    assert cfg.init_policy == "" and load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml",
                                                 overrides=plan["beta2.0_alpha0.5"]).init_policy == "shipped_v1"


def test_report_parts_fill_one_cache_that_the_last_pass_reads(tmp_path, capsys):
    from tg_gpudrive.learn.train import Trainer

    mod = _script("run_experiments")
    exp = tmp_path / "grid.yaml"
    exp.write_text("base: small_cpu.yaml\noverrides: {updates: 2}\nbeta: [2.0]\nalpha: [0.25, 0.75]\n"
                   "report: {scenes: 2, seeds: [0, 1], br_iters: 1, br_window: 1, br_patience: 1, br_min_iters: 1, "
                   "br_copies: 2, br_rounds: 1, br_seeds: [0], device: cpu, progress: false}\n")
    base = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    out = tmp_path / "grid"
    for alpha in (0.25, 0.75):  # trained here, as the grid's own train processes would
        run = out / f"beta2.0_alpha{alpha}"
        cfg = dataclasses.replace(base, num_worlds=2, num_scenes=2, rollout_steps=8, epochs=1, minibatches=1, hidden=16,
                                  quantiles=4, updates=2, checkpoint_every=2, alpha=alpha, out_dir=str(run))
        Trainer(cfg, run, progress=False).train()
    cache = out / "report" / "cache"
    assert mod.main(["--config", str(exp), "--out", str(out), "--report-part", "1/2"]) == 0
    assert sorted(f.name for f in cache.glob("*.pkl")) == ["beta2.0_alpha0.75.pkl"]  # the second run, no baselines
    assert mod.main(["--config", str(exp), "--out", str(out), "--report-part", "0/2"]) == 0
    done = {f.name: f.stat().st_mtime_ns for f in cache.glob("*.pkl")}
    assert {"beta2.0_alpha0.25.pkl", "log_replay.pkl", "world_model.pkl"} <= set(done)
    capsys.readouterr()
    assert mod.main(["--config", str(exp), "--out", str(out), "--report-only"]) == 0
    assert {f.name: f.stat().st_mtime_ns for f in cache.glob("*.pkl")} == done  # all read back
    labels = {r["label"] for r in json.loads((out / "report" / "summary.json").read_text())["results"]}
    assert {"log replay", "beta2.0_alpha0.25", "beta2.0_alpha0.75"} <= labels
    md = (out / "report" / "report.md").read_text()
    assert "| alpha | beta 4 | 0.25 -> 0.75 |" in md and "| paired |" in md  # both runs played the same episodes
    # a cache written before the figures kept their episodes' keys: they are rebuilt from its rollouts
    old = cache / "beta2.0_alpha0.25.pkl"
    hit = pickle.loads(old.read_bytes())
    del hit["value"][0]["figures"]["episode_key"]
    old.write_bytes(pickle.dumps(hit))
    (out / "report" / "report.md").unlink()
    assert mod.main(["--config", str(exp), "--out", str(out), "--report-only"]) == 0
    assert (out / "report" / "report.md").read_text() == md
    with pytest.raises(SystemExit):
        mod.main(["--config", str(exp), "--out", str(out), "--report-part", "2/2"])


def test_run_experiments_leaves_the_distance_keeping_reward_to_the_knobs():
    """real_mix.yaml charges closing in (env.reward.ttc); a grid over beta and alpha on it must not, unless it
    says so, or the charge holds the drivers apart whatever the knobs ask."""
    mod = _script("run_experiments")
    base = REPO_CONFIGS / "train" / "real_mix.yaml"
    assert load_config(TrainConfig, base).env.reward.ttc < 0  # the premise: the base charges it
    exp = {"base": "real_mix.yaml", "beta": [2.0, 6.0], "alpha": [0.5], "baselines": {"mappo": {"eta1": 0.0}}}
    for name, sets in mod.plan(exp, []):
        assert load_config(TrainConfig, base, overrides=sets).env.reward.ttc == 0.0, name
    exp["overrides"] = {"env.reward.ttc": -0.1}  # named by the grid: kept
    assert {load_config(TrainConfig, base, overrides=sets).env.reward.ttc for _, sets in mod.plan(exp, [])} == {-0.1}
    # the repository's real-scene grids, resolved as run_experiments resolves them
    for grid in ("grid_horizon_real.yaml", "grid_approach_real.yaml"):
        exp = yaml.safe_load((REPO_CONFIGS / "experiments" / grid).read_text())
        cfgs = [load_config(TrainConfig, base, overrides=sets) for _, sets in mod.plan(exp, [])]
        assert cfgs and all(c.env.reward.ttc == 0.0 for c in cfgs), grid
    assert {c.env.cost_shape for c in cfgs} == {"approach"}


@pytest.mark.parametrize("grid", sorted((REPO_CONFIGS / "experiments").glob("*.yaml")), ids=lambda p: p.name)
def test_every_experiment_grid_resolves_before_it_trains(grid):
    """Every run a shipped grid plans loads as a training config that is the cell it is named for, and the grid's
    report keys are the report's: a misspelt key fails here, not on the GPU or after the grid has trained."""
    mod = _script("run_experiments")
    exp = yaml.safe_load(grid.read_text())
    base = REPO_CONFIGS / "train" / exp["base"]
    runs = mod.plan(exp, [])
    cells = {(float(b), float(a)) for b in exp["beta"] for a in exp["alpha"]}
    assert len(runs) == (len(cells) + len(exp.get("baselines") or {})) * len(exp.get("seeds") or [None])
    for name, sets in runs:
        cfg = load_config(TrainConfig, base, overrides=sets)
        if name.startswith("beta"):
            assert name.split("_s")[0] == f"beta{cfg.env.beta}_alpha{cfg.alpha}", name
            cells.discard((cfg.env.beta, cfg.alpha))
    assert not cells  # every cell planned
    mod.report_options(exp)


def test_flexibility_table_averages_the_last_updates(tmp_path):
    mod = _script("run_experiments")
    run = tmp_path / "beta2.0_alpha0.5"
    run.mkdir()
    cols = ["update", *mod.FLEX_COLUMNS]
    lines = [",".join(cols)] + [",".join([str(u)] + [str(u * (i + 1)) for i in range(len(mod.FLEX_COLUMNS))])
                                for u in range(1, 8)]
    (run / "metrics.csv").write_text("\n".join(lines) + "\n")
    rows = mod.flexibility(tmp_path, [("beta2.0_alpha0.5", ["env.beta=2.0", "alpha=0.5"]), ("missing", [])], tail=5)
    assert len(rows) == 1 and rows[0]["beta"] == "2.0" and rows[0]["updates"] == 7
    assert rows[0]["lambda"] == pytest.approx((3 + 4 + 5 + 6 + 7) / 5)  # updates 3..7, lambda = update
    assert rows[0]["cvar"] == pytest.approx(2 * 5.0)
    assert "| beta2.0_alpha0.5 | 2.0 | 0.5 | 7 | 5.000 |" in (tmp_path / "flexibility.md").read_text()
    # a baseline names no cell: its beta / alpha come from the run's own config.json
    base = tmp_path / "mappo"
    base.mkdir()
    (base / "metrics.csv").write_text("\n".join(lines) + "\n")
    (base / "config.json").write_text(json.dumps({"alpha": 0.5, "env": {"beta": 4.0}}))
    rows = mod.flexibility(tmp_path, [("mappo", ["eta1=0.0"])], tail=5)
    assert rows[0]["beta"] == "4.0" and rows[0]["alpha"] == "0.5"


def test_flexibility_table_says_from_which_update_a_bar_was_out_of_reach(tmp_path):
    """A run whose CVaR stalls at 3x its budget for the watch's whole window is flagged at the window's last
    update, one whose CVaR comes down to its bar is not, and a plain-MAPPO run (no constraint) never is."""
    from tg_gpudrive.learn.bar_watch import WINDOW

    mod = _script("run_experiments")
    n = WINDOW + 20
    cols = ["update", *mod.FLEX_COLUMNS, "cost_to_go", "cost_budget"]
    for name, cvar, constraint in (("stalled", [3.0] * n, True), ("met", np.linspace(3.0, 1.0, n), True),
                                   ("mappo", [3.0] * n, False)):
        run = tmp_path / name
        run.mkdir()
        rows = [[u + 1, 1.0 + 0.05 * u, c, 5.0, 6.0, 0.1, 0.0, 0.9, c, 1.0] for u, c in enumerate(cvar)]
        (run / "metrics.csv").write_text("\n".join([",".join(cols)] + [",".join(map(str, r)) for r in rows]) + "\n")
        (run / "config.json").write_text(json.dumps({"alpha": 0.875, "env": {"beta": 6.0}, "constraint": constraint,
                                                     "lambda_on": "cvar", "lambda_max": 0.0}))
    got = {r["run"]: r["bar out of reach"] for r in mod.flexibility(tmp_path, [(x, []) for x in
                                                                              ("stalled", "met", "mappo")])}
    assert got == {"stalled": f"from update {WINDOW}", "met": "-", "mappo": "-"}
    assert f"| from update {WINDOW} |" in (tmp_path / "flexibility.md").read_text()


def test_run_experiments_takes_the_training_seeds_from_the_command_line():
    mod = _script("run_experiments")
    exp = {"beta": [2.0], "alpha": [0.5], "seeds": [0, 1, 2]}
    assert [n for n, _ in mod.plan(exp, [])] == [f"beta2.0_alpha0.5_s{s}" for s in (0, 1, 2)]
    runs = mod.plan(exp, ["device=cuda"], [2])
    assert [n for n, _ in runs] == ["beta2.0_alpha0.5_s2"] and runs[0][1][-2:] == ["seed=2", "device=cuda"]


def test_run_experiments_refuses_a_bad_grid_with_one_line_naming_the_file(tmp_path, capsys):
    """A missing grid, a grid without a base, and a base that does not exist: exit 2 before anything trains."""
    mod = _script("run_experiments")
    no_base = tmp_path / "no_base.yaml"
    no_base.write_text("beta: [2]\nalpha: [0.5]\n")
    bad_base = tmp_path / "bad_base.yaml"
    bad_base.write_text("base: no_such_train.yaml\nbeta: [2]\nalpha: [0.5]\n")
    for path, says in ((tmp_path / "missing.yaml", "not found"), (no_base, "'base'"), (bad_base, "no_such_train")):
        with pytest.raises(SystemExit) as e:
            mod.main(["--config", str(path), "--out", str(tmp_path / "runs"), "--dry-run"])
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert e.value.code == 2 and path.name in err and says in err
    assert not (tmp_path / "runs").exists()


def test_worst_scenes_rank_scenes_by_failures_per_agent_episode():
    from types import SimpleNamespace

    from tg_gpudrive.evaluation.report_stats import worst_scenes

    E, A, K = 4, 3, 5
    policy = np.ones((E, A), bool)
    policy[:, 2] = False  # never counted
    col = np.zeros((E, A, K), bool)
    off = np.zeros((E, A, K), bool)
    col[0, 0, 3] = True  # scene 0: 1 of 2 agents (its two episodes: 0 and 2)
    off[1, :, 1] = True  # scene 1: both policy agents off the road in episode 1 (the third agent does not count)
    col[3, 0, 0] = off[3, 0, 4] = True  # scene 1 again: one agent, both events
    gen = SimpleNamespace(policy=policy, collided=col, offroad=off, scene_index=np.array([0, 1, 0, 1]),
                          scenes=[SimpleNamespace(scene_id="a"), SimpleNamespace(scene_id="b")])
    rows = worst_scenes(gen)
    assert [r["scene_id"] for r in rows] == ["b", "a"]
    assert rows[0] == {"scene": 1, "scene_id": "b", "agent_episodes": 4, "collisions": 1, "offroad": 3,
                       "failure_rate": 0.75}
    assert rows[1]["failure_rate"] == 0.25 and worst_scenes(gen, k=1) == rows[:1]


def test_the_grid_scene_is_where_the_knob_moves_the_distance_kept_most():
    """knob_scene: per scene, the mean over policy agent-episodes of each agent's least distance to another
    (over its present steps), the largest beta's cell minus the smallest's, averaged over the alphas; the
    scene with the largest difference, by hand."""
    from types import SimpleNamespace

    from tg_gpudrive.evaluation.report_stats import knob_scene, scene_distances

    scenes = [SimpleNamespace(scene_id=n) for n in "abc"]

    def gen(least):  # least[scene] for both policy agents of one episode per scene; agent 2 not the policy's
        E, A, K = 3, 3, 4
        nearest = np.full((E, A, K), 40.0)
        valid = np.ones((E, A, K), bool)
        for e, d in enumerate(least):
            nearest[e, :2, 1] = d
            nearest[e, :, 3] = 0.5  # the last step is not present: never the least
        valid[:, :, 3] = False
        nearest[:, 2] = 0.1
        return SimpleNamespace(policy=np.array([[True, True, False]] * E), valid=valid, nearest=nearest,
                               scene_index=np.arange(E), scenes=scenes)

    assert scene_distances(gen([3.0, 5.0, 7.0])) == {"a": 3.0, "b": 5.0, "c": 7.0}
    cells = {(2.0, 0.1): gen([3.0, 5.0, 7.0]), (6.0, 0.1): gen([4.0, 8.0, 7.5]),  # +1, +3, +0.5
             (2.0, 0.9): gen([3.0, 5.0, 7.0]), (6.0, 0.9): gen([4.0, 5.0, 7.0]),  # +1, 0, 0
             (4.0, 0.1): gen([0.0, 0.0, 0.0])}  # a middle beta takes no part
    def dists(cells):  # what the report hands knob_scene: each cell's distances per scene
        return {cell: scene_distances(g) for cell, g in cells.items()}

    pick = knob_scene(dists(cells))
    assert pick == ("b", 1.5)  # means over alpha: a 1.0, b 1.5, c 0.25
    cells[(6.0, 0.9)] = gen([6.0, 5.0, 7.0])
    assert knob_scene(dists(cells)) == ("a", 2.0)
    # one beta: the largest alpha's distance minus the smallest's; one cell: no pick
    assert knob_scene(dists({(4.0, 0.9): gen([3.0, 9.0, 7.0]), (4.0, 0.1): gen([3.0, 5.0, 7.0])})) == ("b", 4.0)
    assert knob_scene(dists({(4.0, 0.1): gen([3.0, 9.0, 7.0])})) is None


def test_cce_gap_reports_robust_summaries_beside_the_mean():
    """The median, the 10 % trimmed mean and the agents whose gain's interval lies above 0, by hand on a
    matrix game whose row player gains 1 by deviating and whose column player gains nothing."""
    A = np.array([[3.0, 0.0], [5.0, 1.0]])
    assert ex.trimmed_mean([0, 1, 2, 3, 100, -50, 4, 5, 6, 7], 0.1) == pytest.approx(np.mean([0, 1, 2, 3, 4, 5, 6, 7]))
    assert ex.trimmed_mean([1.0, 2.0], 0.1) == 1.5 and math.isnan(ex.trimmed_mean([], 0.1))
    prof = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]  # row cooperates, column defects
    exact = ex.MatrixGame([A, A.T], prof).exact_gaps()
    assert exact.tolist() == pytest.approx([1.0, 0.0])
    res = ex.cce_gap(lambda s: ex.MatrixGame([A, A.T], prof, batch=512, seed=s), seeds=(0,), lr=0.1,
                     critic_lr=0.1, eval_rounds=2, max_iters=40, min_iters=20)
    gaps = np.asarray(res["gap_per_agent"])
    assert res["median_gap"] == pytest.approx(float(np.median(gaps)))
    assert res["trimmed_mean_gap"] == pytest.approx(float(gaps.mean()))  # two agents: nothing trimmed
    assert res["exploitable_agents"] == 1 and res["exploitable_share"] == 0.5, res["gain_per_agent"]


def test_constrained_game_charges_the_deviator_its_multiplier_times_the_cost():
    """SimGame(cost_weight=lambda per slot): every step's reward of the deviator in slot s is the task
    reward minus lambda_s times the distance cost (which fires on part of the steps at beta 8 m on a merge); the
    expert profile plays the same episodes in both games."""
    scenes = [generate_scene("merge", 0)]
    cfg = EngineConfig(max_agents=16, partner_k=4, road_k=8, beta=8.0)
    masks = control_masks(scenes, cfg, "nearest_conflict", 2, None)
    sim = ex.deviation_sim(scenes, masks, cfg, "cpu", 1)
    lam = torch.arange(1, 17, dtype=torch.float32) / 4  # slot s pays (s + 1) / 4
    task = ex.SimGame(sim, expert_policy).play(None)
    game = ex.SimGame(sim, expert_policy, cost_weight=lam)
    con = game.play(None)
    assert torch.equal(task.mask, con.mask)
    diff = task.reward - con.reward  # (T, N, M)
    w = lam[game.slot].view(1, *game.slot.shape)
    ratio = diff / w
    assert bool(((ratio.abs() < 1e-5) | ((ratio - 1).abs() < 1e-5)).all())  # 0 or lambda_s: the cost is 0/1
    assert bool((ratio[con.mask] > 0.5).any()) and bool((ratio[con.mask] < 0.5).any())
    assert bool((diff[~con.mask] == 0).all())
    with pytest.raises(ValueError, match="cost_weight"):
        ex.SimGame(sim, expert_policy, cost_weight=-1.0)


def test_best_response_to_the_world_model_starts_at_its_distribution():
    """A world-model profile is its own base: the driver keeps the logits it sampled from, and each
    deviator's response corrects them from zero, so it starts at the world model's distribution (not
    at the expert prior's, the base of profiles that show none)."""
    from tg_gpudrive.worldmodel import WorldModelDriver, load_world_model

    scenes = [generate_scene("merge", 0)]
    cfg = EngineConfig(max_agents=16, partner_k=4, road_k=8)
    masks = control_masks(scenes, cfg, "nearest_conflict", 2, None)
    sim = ex.deviation_sim(scenes, masks, cfg, "cpu", 2)
    driver = WorldModelDriver(load_world_model("small_cpu", sim), rows="policy", seed=0, temperature=0.7)
    game = ex.SimGame(sim, driver)
    assert game.policy_base and game.prior is None and ex.SimGame(sim, expert_policy).prior is not None
    ep = game.play(game.make_response(0))
    m = ep.mask
    assert bool(m.any())
    base = ep.inputs["base"]
    want = torch.log_softmax(base, -1).gather(-1, ep.act[..., None])[..., 0]
    np.testing.assert_allclose(ep.logp[m].numpy(), want[m].numpy(), atol=1e-5)
    assert bool((base[m].abs().sum(-1) > 0).all())
    # the driver's logits are the model's, tempered, on the rows it drove (the policy agents) only
    pa = sim.policy_agents
    assert bool((driver.last_out[~pa].abs().sum(-1) == 0).all()) and bool((driver.last_out[pa].abs().sum(-1) > 0).any())


def test_advantage_balance_reads_the_cost_advantage_at_each_alpha():
    """scripts/advantage_balance.py on the shipped policy: at the run's own alpha the weighted cost advantage is
    the run's own (correlation 1, the same std); one alpha against itself flips no sign; a different alpha
    reads the same rows with another tail of the cost critic."""
    mod = _script("advantage_balance")
    own = mod.run_config("shipped", None, 4, "cpu")[0].alpha
    same = mod.balance("shipped", "procedural:all", [own, own], num_worlds=4, rollouts=1, device="cpu")
    assert same["live_rows"] > 0 and same["std_a_r"] > 0
    assert same["sign_flips"] == 0.0 and same["mean_abs_change_over_std"] == 0.0
    assert same["per_alpha"][str(own)]["std_lambda_a_c"] == pytest.approx(same["std_lambda_a_c"])
    other = 0.95 if own < 0.5 else 0.05
    moved = mod.balance("shipped", "procedural:all", [own, other], num_worlds=4, rollouts=1, device="cpu")
    assert moved["live_rows"] == same["live_rows"]  # the same seed drives the same rollout
    assert moved["per_alpha"][str(own)]["corr_with_own"] == pytest.approx(1.0)
    assert moved["per_alpha"][str(other)]["std_lambda_a_c"] != pytest.approx(same["std_lambda_a_c"])
    # the critic's tail: CVaR is non-decreasing in alpha, and an alpha against itself gives 1
    assert same["tail_ratio"] == pytest.approx(1.0)
    assert (moved["tail_ratio"] > 1.0) == (other > own) and moved["tail_ratio"] != pytest.approx(1.0)
    # the lean of each part on speed: the acceleration grid read by hand (7 bins over +-6 m/s^2), and the other
    # rule's reading of the same rollouts changes the cost's part alone
    cfg = mod.run_config("shipped", None, 4, "cpu")[0]
    k = cfg.env.curvature_bins
    act = torch.tensor([[[0, k - 1, 3 * k, 3 * k + 2, 6 * k + k // 2]]])
    assert mod.accelerations(cfg, act).tolist() == [[[-6.0, -6.0, 0.0, 0.0, 6.0]]]
    assert -1.0 <= same["cost_lean"] <= 1.0 and same["cost_lean"] != 0.0
    assert same["per_alpha"][str(own)]["cost_lean"] == pytest.approx(same["cost_lean"])  # its own alpha: the run's
    assert moved["per_alpha"][str(other)]["cost_lean"] != pytest.approx(same["cost_lean"])  # another: another lean
    # where actions lead in the critic's tail: nothing beyond one alpha's own reading; a real tail at two
    assert same["tail_step_lean"] == 0.0 and -1.0 <= moved["tail_step_lean"] <= 1.0 and moved["tail_step_lean"] != 0.0
    assert same["cost_advantage"] == cfg.cost_advantage
    rule = "tail" if cfg.cost_advantage == "gae" else "gae"
    read = mod.balance("shipped", "procedural:all", [own, own], num_worlds=4, rollouts=1, device="cpu", rule=rule)
    assert read["cost_advantage"] == rule and read["reward_lean"] == pytest.approx(same["reward_lean"])
    assert read["cost_lean"] != pytest.approx(same["cost_lean"])


def test_heldout_eval_pools_a_cells_training_seeds():
    """Runs trained alike but for the seed pool into one row per mode, weighted by agent-episodes (hand-computed);
    a run of another recipe, or alone in its recipe, is not pooled."""
    mod = _script("heldout_eval")
    base = load_config(TrainConfig, REPO_CONFIGS / "train" / "small_cpu.yaml")
    seeds = [dataclasses.replace(base, seed=s, out_dir=f"runs/b2_s{s}") for s in (0, 1)]
    other = dataclasses.replace(base, seed=0, lr=base.lr * 2)
    assert mod.recipe_key(seeds[0]) == mod.recipe_key(seeds[1]) != mod.recipe_key(other)
    recipes = {"g/b2_s0": mod.recipe_key(seeds[0]), "g/b2_s1": mod.recipe_key(seeds[1]), "g/lr2_s0": mod.recipe_key(other)}

    def row(run, mode, n, goal, col, off):
        return {"run": run, "mode": mode, "episodes": n, "goal_rate": goal, "collision_rate": col, "offroad_rate": off}

    rows = [row("g/b2_s0", "ignore", 100, 1.0, 0.0, 0.0), row("g/b2_s1", "ignore", 300, 0.8, 0.1, 0.02),
            row("g/b2_s0", "stop", 100, 0.5, 0.5, 0.0), row("g/b2_s1", "stop", 100, 0.7, 0.1, 0.1),
            row("g/lr2_s0", "ignore", 50, 0.2, 0.2, 0.2)]
    pooled = mod.pooled_rows(rows, recipes)
    assert [(p["cell"], p["mode"], p["runs"], p["episodes"]) for p in pooled] == [("b2", "ignore", 2, 400),
                                                                                ("b2", "stop", 2, 200)]
    assert pooled[0]["goal_rate"] == pytest.approx(0.85) and pooled[0]["collision_rate"] == pytest.approx(0.075)
    assert pooled[0]["offroad_rate"] == pytest.approx(0.015)
    assert pooled[1]["goal_rate"] == pytest.approx(0.6) and pooled[1]["offroad_rate"] == pytest.approx(0.05)
    assert mod.pooled_rows(rows[-1:], recipes) == []
    # another recipe's runs of the same name (an ablation's folder): each cell also names its folder
    third = mod.recipe_key(dataclasses.replace(base, lr=base.lr * 3))
    recipes.update({"h/b2_s0": third, "h/b2_s1": third})
    rows += [row("h/b2_s0", "ignore", 10, 0.0, 0.0, 0.0), row("h/b2_s1", "ignore", 10, 1.0, 0.0, 0.0)]
    assert [(p["cell"], p["mode"], p["episodes"]) for p in mod.pooled_rows(rows, recipes)] == [
        ("g/b2", "ignore", 400), ("g/b2", "stop", 200), ("h/b2", "ignore", 20)]
