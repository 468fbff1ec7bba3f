"""Reward terms and the distance cost, per agent and per step.

Rewards are named, weighted terms (REWARD_TERMS, in this order in the
`terms_out` rows); the total is their weighted sum. Only agents that acted
this step (`alive`) earn anything; every other row is zero.

    goal_progress   m      decrease of the distance to the goal (TrafficGamer's distance term)
    goal_reached    0/1    the agent came within `goal_radius` of its goal this step, on the road:
                           an agent that crossed a road edge earlier in the episode (or does so
                           now) has left the road, and a goal reached off the road is not a goal
                           (for the reward, the episode's goal flag and every goal rate)
    collision       0/1    its box overlaps another present agent's box
    offroad         0/1    its box crosses a road edge
    lane_deviation  m      distance to the nearest lane centerline, capped
    overspeed       m/s    speed above the limit
    ttc             0..1   1 - TTC / ttc_horizon, the time to collision with an agent ahead of its
                           motion (kernels/collision.py `ttc_kernel`): 0 with no conflict within the
                           horizon, 1 in contact; computed only when weighted (else 0)

cost, the constraint signal of CCE-MAPPO, from the centre distance d to the nearest
other present agent the cost counts (`cost_dist` of kernels/collision.py: any agent, or
the policy's own with `cost_partners: players`; with `cost_horizon` > 0 the least such distance over
that look-ahead at constant velocity), shaped by `cost_shape`:
    step      1 when d < beta (TrafficGamer's distance cost)
    hinge     max(beta - d, 0) / beta: how deep the neighbour is inside beta, so a contact
              costs nearly 1 and a pass just inside beta nearly 0
    approach  the hinge's increase since the agent's last step, never below 0: a pass costs the
              depth of its closest approach once, however long it stays inside beta, so a policy
              lowers it by passing wider, not by passing sooner. An episode's first step costs 0:
              its depth is the state the log hands over (`cost_depth` holds the last step's depth,
              -1 after a reset)
The distance is capped at
the world's `nearest_cap` (kernels/collision.py); the cost is exact only because
the Model builder keeps that cap >= beta. A step in contact with another agent (`collided`) costs at least
`cost_collision` (0 by default): the cost's top, whatever beta.
"""

from __future__ import annotations

import warp as wp

REWARD_TERMS = ("goal_progress", "goal_reached", "collision", "offroad", "lane_deviation", "overspeed", "ttc")
NUM_TERMS = len(REWARD_TERMS)


@wp.kernel
def reward_kernel(
    goal_radius: float,
    beta: float,
    cost_shape: int,  # 0: step, 1: hinge, 2: approach (config.COST_SHAPES)
    cost_collision: float,  # the least cost of a step in contact
    speed_limit: float,
    lane_cap: float,
    ttc_on: int,
    ttc_horizon: float,
    weights: wp.array(dtype=float),  # (NUM_TERMS,)
    goal: wp.array(dtype=wp.vec2),
    # state
    alive: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec2),
    speed: wp.array(dtype=float),
    collided: wp.array(dtype=wp.int32),
    offroad: wp.array(dtype=wp.int32),
    lane_dist: wp.array(dtype=float),
    cost_dist: wp.array(dtype=float),
    ttc: wp.array(dtype=float),
    ep_goal: wp.array(dtype=wp.int32),
    ep_offroad: wp.array(dtype=wp.int32),
    goal_dist: wp.array(dtype=float),  # in: distance before the step; out: after
    cost_depth: wp.array(dtype=float),  # in: the hinge depth of the last step (-1: none yet); out: this step's
    # out
    goal_event_out: wp.array(dtype=wp.int32),
    terms_out: wp.array2d(dtype=float),  # (world * agent, NUM_TERMS)
    reward_out: wp.array(dtype=float),
    cost_out: wp.array(dtype=float),
):
    i = wp.tid()
    if alive[i] == 0:
        goal_event_out[i] = 0
        for k in range(NUM_TERMS):
            terms_out[i, k] = 0.0
        reward_out[i] = 0.0
        cost_out[i] = 0.0
        return
    d = wp.length(goal[i] - pos[i])
    ev = int(0)
    if d < goal_radius and ep_goal[i] == 0 and offroad[i] == 0 and ep_offroad[i] == 0:
        ev = 1
    goal_event_out[i] = ev
    t0 = goal_dist[i] - d
    goal_dist[i] = d
    t1 = float(ev)
    t2 = float(collided[i])
    t3 = float(offroad[i])
    t4 = wp.min(lane_dist[i], lane_cap)
    t5 = wp.max(speed[i] - speed_limit, 0.0)
    t6 = float(0.0)
    if ttc_on == 1:
        t6 = 1.0 - ttc[i] / ttc_horizon
    terms_out[i, 0] = t0
    terms_out[i, 1] = t1
    terms_out[i, 2] = t2
    terms_out[i, 3] = t3
    terms_out[i, 4] = t4
    terms_out[i, 5] = t5
    terms_out[i, 6] = t6
    reward_out[i] = (weights[0] * t0 + weights[1] * t1 + weights[2] * t2
                     + weights[3] * t3 + weights[4] * t4 + weights[5] * t5 + weights[6] * t6)
    depth = float(0.0)
    if cost_dist[i] < beta:
        depth = (beta - cost_dist[i]) / beta
    c = depth
    if cost_shape == 0 and depth > 0.0:
        c = 1.0
    if cost_shape == 2:
        c = float(0.0)
        if cost_depth[i] >= 0.0:
            c = wp.max(depth - cost_depth[i], 0.0)
        cost_depth[i] = depth
    if collided[i] != 0:
        c = wp.max(c, cost_collision)
    cost_out[i] = c


def launch_reward(model, state, control) -> None:
    wp.launch(reward_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.goal_radius, model.beta, model.cost_shape, model.cost_collision, model.speed_limit,
                      model.lane_cap, model.ttc_on, model.ttc_horizon, model.reward_weights, model.goal,
                      state.alive, state.pos, state.speed, state.collided, state.offroad, state.lane_dist,
                      state.cost_dist, state.ttc, state.ep_goal, state.ep_offroad, state.goal_dist, state.cost_depth],
              outputs=[state.goal_event, state.reward_terms, state.reward, state.cost])
