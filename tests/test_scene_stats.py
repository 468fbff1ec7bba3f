"""Scene-set statistics against hand-computed values, and the W1 distance against its definition."""

from __future__ import annotations

import numpy as np
import pytest

from tg_gpudrive.evaluation.scene_stats import gap_table, scene_features, set_features, w1
from tg_gpudrive.scene import make_scene
from tg_gpudrive.enums import AgentType, RoadType

T = 41


def street():
    """A car at 10 m/s along a 3.5 m lane bordered by edges, a parked car and a pedestrian."""
    t = np.arange(T) * 0.1
    pos = np.zeros((3, T, 2))
    pos[0, :, 0] = 10 * t
    pos[1] = [30.0, 3.0]  # parked
    pos[2, :, 0], pos[2, :, 1] = 5.0, -4 + 0.5 * t  # walking
    yaw = np.zeros((3, T))
    roads = [(RoadType.LANE, [[-20, 0], [80, 0]]), (RoadType.ROAD_EDGE, [[-20, 1.75], [80, 1.75]]),
             (RoadType.ROAD_EDGE, [[-20, -1.75], [80, -1.75]])]
    return make_scene(pos, yaw, roads=roads, agent_type=np.array([1, 1, 2]))


def test_features_of_a_hand_made_street():
    f = scene_features(street())
    np.testing.assert_allclose(f["speed"], 10.0, atol=1e-3)  # the driving car from init_step on
    np.testing.assert_allclose(f["accel"], 0.0, atol=1e-2)
    np.testing.assert_allclose(f["curvature"], 0.0, atol=1e-6)
    np.testing.assert_allclose(f["goal_distance"], [30.0], atol=1e-3)  # from x = 10 at step 10 to x = 40
    np.testing.assert_allclose(f["route_length"], [30.0], atol=1e-3)
    np.testing.assert_allclose(f["vehicle_length"], [4.5])  # the driving car's (make_scene's default)
    assert f["agents"][0] == 3 and f["pedestrians"][0] == 1 and f["cyclists"][0] == 0
    assert f["pedestrians_on_lanes"][0] == 0  # it walks from 4 to 2 m beside the lane centre
    assert f["controlled"][0] == 1  # the parked car starts at its goal
    assert f["parked_share"][0] == pytest.approx(0.5)
    np.testing.assert_allclose(f["lane_width"], 3.5, atol=1e-6)
    assert f["lanes"][0] == 1
    np.testing.assert_allclose(f["lateral_shift"], [0.0], atol=1e-6)  # straight down its lane
    assert len(f["closing_speed"]) == 0  # the parked car stands 3 m to the side: nobody ahead in the lane
    # within 50 m of the car's init position (10, 0): both edges from x = -20 (their start) to 60, 2 x 80 m,
    # over a disc of pi 50^2 m^2 (sampled on a 5 m grid: a few per cent)
    assert f["edge_density"][0] == pytest.approx(160 / (np.pi * 2500 / 1e4), rel=0.05)


def test_a_pedestrian_crossing_the_lane_counts_on_the_lanes():
    """The street's pedestrian walks on across the lane: at 0.5 m/s from y = -4 it comes within 1.75 m of
    the centre line after 4.5 s; a log of 4 s keeps it out, one of 6 s lets it in, and its speed there is
    counted over the steps from y = -1.75 to the log's end at y = -1 (1.5 s, 14 whole steps inside)."""
    for steps, want in ((41, 0), (61, 1)):
        t = np.arange(steps) * 0.1
        pos = np.zeros((1, steps, 2))
        pos[0, :, 0], pos[0, :, 1] = 5.0, -4 + 0.5 * t
        sc = make_scene(pos, np.zeros((1, steps)), roads=[(RoadType.LANE, [[-20, 0], [80, 0]])],
                        agent_type=np.array([2]))
        f = scene_features(sc)
        assert f["pedestrians_on_lanes"][0] == want
        assert len(f["pedestrian_lane_speed"]) == 14 * want
        np.testing.assert_allclose(f["pedestrian_lane_speed"], 0.5, atol=1e-4)


def test_closing_speed_of_a_fast_car_behind_a_slow_one():
    """A car at 12 m/s 25 m behind one at 3 m/s in its lane closes at 9 m/s from init_step (t = 1 s, gap
    16 m) until it passes through the slow car (t = 2.78 s): one sample per step, 9 m/s each. From then
    on the slow car has the fast one ahead, pulling away: -9 m/s to the end of the log. A car in the next
    lane (3.5 m to the side) is outside the corridor."""
    t = np.arange(T) * 0.1
    pos = np.zeros((3, T, 2))
    pos[0, :, 0] = 12 * t
    pos[1, :, 0] = 25 + 3 * t
    pos[2, :, 0], pos[2, :, 1] = 10 + 3 * t, 3.5
    f = scene_features(make_scene(pos, np.zeros((3, T)), roads=[(RoadType.LANE, [[-20, 0], [150, 0]])]))
    closing = [k for k in range(10, T) if 0 < 25 - 9 * t[k] < 30]
    opening = [k for k in range(10, T) if 0 < 9 * t[k] - 25 < 30]
    got = np.sort(f["closing_speed"])
    assert (len(closing), len(opening)) == (18, 13) and len(got) == 31
    np.testing.assert_allclose(got[:13], -9.0, atol=1e-3)
    np.testing.assert_allclose(got[13:], 9.0, atol=1e-3)


def _pull_out(t_start: float, cross_speed: float, cross_at: float, T: int = 101):
    """A car at rest at (0, -10.2) that pulls away north at 5 m/s from `t_start`, and a car driving east along
    y = 0 at `cross_speed` that passes x = 0 at `cross_at` seconds."""
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    pos[0, :, 1] = -10.2 + 5 * np.maximum(t - t_start, 0.0)
    pos[1, :, 0] = cross_speed * (t - cross_at)
    yaw = np.stack([np.full(T, np.pi / 2), np.zeros(T)])
    return make_scene(pos, yaw, roads=[(RoadType.LANE, [[-100, 0], [100, 0]])])


@pytest.mark.parametrize("t_start, cross_speed, cross_at, n, pet", [
    # the mover enters the crosser's path (comes within CONFLICT_M of y = 0) at y = -1.7, t = 3.7 s
    (2.0, 10.0, 3.0, 1, [0.7]),  # the crosser passes x = 0 0.7 s before it
    (2.0, 10.0, 6.5, 1, [2.8]),  # 2.8 s after it
    (2.0, 10.0, 9.5, 0, [5.8]),  # 5.8 s after it: a crossing too far apart in time to conflict
    (2.0, 6.0, 3.0, 0, []),  # crossing traffic slower than FAST_MPS
    (0.0, 10.0, 3.0, 0, []),  # the car is moving at init_step (1 s): not a pull from rest
])
def test_rest_crossings_of_a_car_pulling_out_across_traffic(t_start, cross_speed, cross_at, n, pet):
    f = scene_features(_pull_out(t_start, cross_speed, cross_at))
    assert f["rest_starts"][0] == (0.5 if t_start > 1.0 else 0.0)  # of the two candidates, the mover at rest
    assert f["rest_crossings"][0] == n
    np.testing.assert_allclose(f["rest_crossing_pet"], pet, atol=1e-6)


def test_a_car_merging_from_rest_into_fast_traffic():
    """The mover pulls away at 5 m/s on a 45-degree diagonal from (-10, -10) towards the eastbound lane y = 0
    and turns onto it, as a car merging from a side road. It enters the lane's path (within CONFLICT_M of
    y = 0) at t = 4.3 s, at x = -1.87, 45 degrees from the lane; the car on the lane at 10 m/s is nearest
    that point (x = -1.8 at t = 3.0 s): PET 1.3 s."""
    T = 101
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    s_ = 5 * np.maximum(t - 2.0, 0.0)
    diag = np.minimum(s_, 10 * np.sqrt(2))
    pos[0, :, 0] = -10 + diag / np.sqrt(2) + (s_ - diag)
    pos[0, :, 1] = -10 + diag / np.sqrt(2)
    pos[1, :, 0] = 10 * (t - 3.0) - 1.8
    yaw = np.zeros((2, T))
    yaw[0] = np.where(s_ < 10 * np.sqrt(2), np.pi / 4, 0.0)
    f = scene_features(make_scene(pos, yaw, roads=[(RoadType.LANE, [[-100, 0], [100, 0]])]))
    assert f["rest_crossings"][0] == 1
    np.testing.assert_allclose(f["rest_crossing_pet"], [1.3], atol=1e-6)


def test_a_car_following_the_mover_does_not_cross_it():
    """A fast car that drives north on the mover's own path, behind it, follows; it does not cross."""
    T = 81
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    pos[0, :, 1] = -10 + 5 * np.maximum(t - 2.0, 0.0)
    pos[1, :, 1] = -80 + 9 * t
    yaw = np.full((2, T), np.pi / 2)
    f = scene_features(make_scene(pos, yaw, roads=[(RoadType.LANE, [[0, -100], [0, 100]])]))
    assert f["rest_crossings"][0] == 0 and len(f["rest_crossing_pet"]) == 0


def test_lateral_shift_of_a_lane_change_and_not_of_a_turn():
    """A car that moves one lane (3.5 m) left after init_step ends 3.5 m to the side of its init heading;
    one that turns a corner is not a straight path and gives no sample."""
    t = np.arange(T) * 0.1
    pos = np.zeros((2, T, 2))
    pos[0, :, 0] = 10 * t
    x = np.clip((t - 1.5) / 1.5, 0, 1)
    pos[0, :, 1] = 3.5 * x * x * (3 - 2 * x)
    yaw = np.zeros((2, T))
    pos[1, :, 0] = np.minimum(10 * t, 20.0)  # turns left at x = 20
    pos[1, :, 1] = np.maximum(10 * t - 20.0, 0.0)
    yaw[1] = np.where(10 * t > 20.0, np.pi / 2, 0.0)
    f = scene_features(make_scene(pos, yaw, roads=[(RoadType.LANE, [[-20, 0], [80, 0]])]))
    np.testing.assert_allclose(f["lateral_shift"], [3.5], atol=1e-4)
    assert len(f["goal_distance"]) == 2


def test_w1_is_the_shift_of_a_shifted_sample_and_the_table_ranks_by_distance():
    x = np.random.default_rng(0).normal(size=500)
    assert w1(x, x + 2.0) == pytest.approx(2.0)
    assert w1(x, x) == 0.0
    ref = set_features([street()])
    other = {k: v.copy() for k, v in ref.items()}
    other["speed"] = other["speed"] + 5.0  # only speed moves
    rows = gap_table({**ref, "speed": np.r_[ref["speed"], 9.0]}, {**other, "speed": np.r_[other["speed"], 14.0]})
    assert rows[0].feature == "speed" and rows[0].distance > 1
    assert all(r.distance == 0 or np.isnan(r.distance) for r in rows[1:])
