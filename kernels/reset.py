"""Collision-mode response, episode bookkeeping and auto-reset.

Order within a step: `respond_kernel` (per agent) applies the collision mode
and accumulates episode outcomes; `finish_world_kernel` (per world) advances
the step counter and decides whether the episode ended; `reset_agents_kernel`
(per agent) copies the finished episode's outcomes to the `final_*` arrays and
restores the scene's state at `init_step`. `reset()` runs the last kernel with
`force=1`.

Collision modes (tg_gpudrive.enums.CollisionMode): IGNORE counts the event
and keeps driving; STOP freezes the agent and ends its episode; REMOVE takes
it out of the scene (and of later collision checks) and ends its episode.
The same response applies to off-road events. Goal behaviour
(tg_gpudrive.enums.GoalBehaviour): CONTINUE counts the goal, STOP and REMOVE also
end the episode (default: remove, as GPUDrive does for agents at their goal).
"""

from __future__ import annotations

import warp as wp

from tg_gpudrive.kernels.kinds import COLLISION_IGNORE, COLLISION_REMOVE, GOAL_CONTINUE, GOAL_REMOVE

BIG_DISTANCE = wp.constant(1.0e6)


@wp.kernel
def respond_kernel(
    collision_mode: int,
    goal_behaviour: int,
    alive: wp.array(dtype=wp.int32),
    collided: wp.array(dtype=wp.int32),
    offroad: wp.array(dtype=wp.int32),
    goal_event: wp.array(dtype=wp.int32),
    reward: wp.array(dtype=float),
    cost: wp.array(dtype=float),
    nearest: wp.array(dtype=float),
    # state in/out
    agent_done: wp.array(dtype=wp.int32),
    removed: wp.array(dtype=wp.int32),
    ep_collided: wp.array(dtype=wp.int32),
    ep_offroad: wp.array(dtype=wp.int32),
    ep_goal: wp.array(dtype=wp.int32),
    ep_return: wp.array(dtype=float),
    ep_cost: wp.array(dtype=float),
    ep_min_dist: wp.array(dtype=float),
    ep_steps: wp.array(dtype=wp.int32),
    # out
    terminated_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    terminated_out[i] = 0
    if alive[i] == 0:
        return
    ep_steps[i] = ep_steps[i] + 1
    ep_return[i] = ep_return[i] + reward[i]
    ep_cost[i] = ep_cost[i] + cost[i]
    ep_min_dist[i] = wp.min(ep_min_dist[i], nearest[i])
    if collided[i] != 0:
        ep_collided[i] = 1
    if offroad[i] != 0:
        ep_offroad[i] = 1
    term = int(0)
    rem = int(0)
    if goal_event[i] != 0:
        ep_goal[i] = 1
        if goal_behaviour != GOAL_CONTINUE:
            term = 1
            if goal_behaviour == GOAL_REMOVE:
                rem = 1
    if (collided[i] != 0 or offroad[i] != 0) and collision_mode != COLLISION_IGNORE:
        term = 1
        if collision_mode == COLLISION_REMOVE:
            rem = 1
    if term != 0:
        agent_done[i] = 1
        terminated_out[i] = 1
    if rem != 0:
        removed[i] = 1


@wp.kernel
def finish_world_kernel(
    agents_per_world: int,
    init_step: int,
    integrated: wp.array(dtype=wp.int32),
    background: wp.array(dtype=wp.int32),
    last_step: wp.array(dtype=wp.int32),  # (world,)
    agent_done: wp.array(dtype=wp.int32),
    auto_reset: int,
    world_step: wp.array(dtype=wp.int32),  # (world,) in/out
    world_done: wp.array(dtype=wp.int32),  # (world,) in/out: episode over, waiting for reset()
    world_ended_out: wp.array(dtype=wp.int32),  # (world,) episode ended this step
    world_reset_out: wp.array(dtype=wp.int32),  # (world,) ... and the world was reset
    world_truncated_out: wp.array(dtype=wp.int32),  # (world,) ... by the time limit
    episode_count: wp.array(dtype=wp.int32),  # (world,) in/out
):
    w = wp.tid()
    if world_done[w] != 0:
        world_ended_out[w] = 0
        world_reset_out[w] = 0
        world_truncated_out[w] = 0
        return
    t = world_step[w] + 1
    # the episode ends early once the policy's agents are all done; background-driven agents
    # do not hold it open (they decide only in a world that has no policy agent)
    n_ctrl = int(0)
    n_done = int(0)
    n_pol = int(0)
    n_pol_done = int(0)
    for a in range(agents_per_world):
        i = w * agents_per_world + a
        if integrated[i] != 0:
            n_ctrl += 1
            if agent_done[i] != 0:
                n_done += 1
            if background[i] == 0:
                n_pol += 1
                if agent_done[i] != 0:
                    n_pol_done += 1
    trunc = int(0)
    if t >= last_step[w]:
        trunc = 1
    end = trunc
    if n_pol > 0:
        if n_pol_done == n_pol:
            end = 1
    elif n_ctrl > 0 and n_done == n_ctrl:
        end = 1
    world_ended_out[w] = end
    world_reset_out[w] = end * auto_reset
    world_truncated_out[w] = trunc
    if end != 0:
        episode_count[w] = episode_count[w] + 1
    if end != 0 and auto_reset != 0:
        world_step[w] = init_step
    else:
        world_step[w] = t
        if end != 0:
            world_done[w] = 1


# one kernel on purpose: splitting it would add launches and global-memory round trips per reset
@wp.kernel
def reset_agents_kernel(
    agents_per_world: int,
    init_step: int,
    force: int,
    slot_valid: wp.array(dtype=wp.int32),
    log_row: wp.array(dtype=wp.int32),  # (world * agent,) the slot's row of the log arrays
    log_pos: wp.array2d(dtype=wp.vec2),  # (plan * agent, step)
    log_yaw: wp.array2d(dtype=float),
    log_vel: wp.array2d(dtype=wp.vec2),
    log_valid: wp.array2d(dtype=wp.int32),
    goal: wp.array(dtype=wp.vec2),
    world_ended: wp.array(dtype=wp.int32),
    world_reset: wp.array(dtype=wp.int32),
    world_truncated: wp.array(dtype=wp.int32),
    alive: wp.array(dtype=wp.int32),
    terminated: wp.array(dtype=wp.int32),
    # state in/out
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    vel: wp.array(dtype=wp.vec2),
    speed: wp.array(dtype=float),
    present: wp.array(dtype=wp.int32),
    agent_done: wp.array(dtype=wp.int32),
    removed: wp.array(dtype=wp.int32),
    goal_dist: wp.array(dtype=float),
    cost_depth: wp.array(dtype=float),
    ep_collided: wp.array(dtype=wp.int32),
    ep_offroad: wp.array(dtype=wp.int32),
    ep_goal: wp.array(dtype=wp.int32),
    ep_return: wp.array(dtype=float),
    ep_cost: wp.array(dtype=float),
    ep_min_dist: wp.array(dtype=float),
    ep_steps: wp.array(dtype=wp.int32),
    # out: outcomes of the episode that just ended (valid where world_reset)
    truncated_out: wp.array(dtype=wp.int32),
    final_goal: wp.array(dtype=wp.int32),
    final_collided: wp.array(dtype=wp.int32),
    final_offroad: wp.array(dtype=wp.int32),
    final_return: wp.array(dtype=float),
    final_cost: wp.array(dtype=float),
    final_min_dist: wp.array(dtype=float),
    final_steps: wp.array(dtype=wp.int32),
):
    """force: 0 = after a step (copy outcomes where the episode ended, reset where
    world_reset), 1 = reset every world, 2 = reset the worlds flagged in world_reset."""
    i = wp.tid()
    w = i / agents_per_world
    truncated_out[i] = 0
    if force == 0 and world_ended[w] != 0:
        if alive[i] != 0 and terminated[i] == 0 and world_truncated[w] != 0:
            truncated_out[i] = 1
        final_goal[i] = ep_goal[i]
        final_collided[i] = ep_collided[i]
        final_offroad[i] = ep_offroad[i]
        final_return[i] = ep_return[i]
        final_cost[i] = ep_cost[i]
        final_min_dist[i] = ep_min_dist[i]
        final_steps[i] = ep_steps[i]
    if force != 1 and world_reset[w] == 0:
        return
    agent_done[i] = 0
    removed[i] = 0
    ep_collided[i] = 0
    ep_offroad[i] = 0
    ep_goal[i] = 0
    ep_return[i] = 0.0
    ep_cost[i] = 0.0
    ep_min_dist[i] = BIG_DISTANCE
    ep_steps[i] = 0
    r = log_row[i]
    if slot_valid[i] != 0 and log_valid[r, init_step] != 0:
        pos[i] = log_pos[r, init_step]
        yaw[i] = log_yaw[r, init_step]
        vel[i] = log_vel[r, init_step]
        speed[i] = wp.length(log_vel[r, init_step])
        present[i] = 1
    else:
        pos[i] = wp.vec2(0.0, 0.0)
        yaw[i] = 0.0
        vel[i] = wp.vec2(0.0, 0.0)
        speed[i] = 0.0
        present[i] = 0
    goal_dist[i] = wp.length(goal[i] - pos[i])
    cost_depth[i] = -1.0


def _reset_agents(model, state, force: int) -> None:
    wp.launch(reset_agents_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.max_agents, model.init_step, force, model.slot_valid, model.log_row, model.log_pos,
                      model.log_yaw, model.log_vel, model.log_valid, model.goal,
                      state.world_ended, state.world_reset, state.world_truncated, state.alive, state.terminated,
                      state.pos, state.yaw, state.vel, state.speed, state.present, state.agent_done,
                      state.removed, state.goal_dist, state.cost_depth, state.ep_collided, state.ep_offroad,
                      state.ep_goal, state.ep_return, state.ep_cost, state.ep_min_dist, state.ep_steps],
              outputs=[state.truncated, state.final_goal, state.final_collided, state.final_offroad,
                       state.final_return, state.final_cost, state.final_min_dist, state.final_steps])


def launch_respond_and_finish(model, state, control) -> None:
    """Collision-mode and goal response, episode bookkeeping, then auto-reset of the worlds whose episode ended."""
    wp.launch(respond_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.collision_mode, model.goal_behaviour, state.alive, state.collided, state.offroad,
                      state.goal_event, state.reward, state.cost, state.nearest, state.agent_done,
                      state.removed, state.ep_collided, state.ep_offroad, state.ep_goal, state.ep_return,
                      state.ep_cost, state.ep_min_dist, state.ep_steps],
              outputs=[state.terminated])
    wp.launch(finish_world_kernel, dim=model.num_worlds, device=model.device,
              inputs=[model.max_agents, model.init_step, model.integrated, model.background, model.last_step,
                      state.agent_done, model.auto_reset, state.world_step, state.world_done],
              outputs=[state.world_ended, state.world_reset, state.world_truncated, state.episode_count])
    _reset_agents(model, state, force=0)


@wp.kernel
def mark_worlds_kernel(init_step: int, mask: wp.array(dtype=wp.int32), world_step: wp.array(dtype=wp.int32),
                       world_done: wp.array(dtype=wp.int32), world_reset_out: wp.array(dtype=wp.int32)):
    w = wp.tid()
    world_reset_out[w] = mask[w]
    if mask[w] != 0:
        world_step[w] = init_step
        world_done[w] = 0


def launch_force_reset(model, state, control, mask=None) -> None:
    """Reset every world, or those where `mask` (W,) int32 is non-zero (outcomes are not copied)."""
    if mask is None:
        state.world_step.fill_(model.init_step)
        state.world_done.zero_()
        _reset_agents(model, state, force=1)
    else:
        wp.launch(mark_worlds_kernel, dim=model.num_worlds, device=model.device,
                  inputs=[model.init_step, mask, state.world_step, state.world_done], outputs=[state.world_reset])
        _reset_agents(model, state, force=2)
