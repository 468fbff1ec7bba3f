"""Vehicle dynamics: invertible kinematic bicycle, delta-local, and their inverses.

The bicycle is Waymax's invertible model with action (acceleration a [m/s^2],
curvature kappa [1/m]) and state (x, y, yaw, velocity); over one step dt

    x'   = x + vx dt + 0.5 a cos(yaw) dt^2
    y'   = y + vy dt + 0.5 a sin(yaw) dt^2
    yaw' = yaw + kappa (|v| dt + 0.5 a dt^2)
    |v'| = |v| + a dt,          v' = |v'| (cos yaw', sin yaw')

and the inverse recovers (a, kappa) from two consecutive states. Delta-local
moves the agent by (dx, dy, dyaw) given in its own frame.

This module also replays logs for the agents that are not integrated: one kernel moves
every agent slot one step, whoever drives it. It must not touch collision,
road or reward state beyond clearing the per-step event flags it owns.
"""

from __future__ import annotations

import warp as wp

from tg_gpudrive.kernels.kinds import DYNAMICS_BICYCLE, DYNAMICS_DELTA_LOCAL

# a speed below which curvature is undefined: the inverse reports kappa = 0
_MIN_ARC = wp.constant(1.0e-3)


@wp.func
def wrap_angle(a: float):
    return wp.atan2(wp.sin(a), wp.cos(a))


@wp.func
def bicycle_forward(pos: wp.vec2, yaw: float, vel: wp.vec2, accel: float, kappa: float, dt: float):
    """One step of the bicycle; returns (pos', yaw', vel', speed')."""
    c = wp.cos(yaw)
    s = wp.sin(yaw)
    speed = wp.length(vel)
    new_pos = pos + vel * dt + wp.vec2(c, s) * (0.5 * accel * dt * dt)
    new_yaw = wrap_angle(yaw + kappa * (speed * dt + 0.5 * accel * dt * dt))
    new_speed = wp.max(speed + accel * dt, 0.0)
    new_vel = wp.vec2(wp.cos(new_yaw), wp.sin(new_yaw)) * new_speed
    return new_pos, new_yaw, new_vel, new_speed


@wp.func
def bicycle_inverse(yaw: float, vel: wp.vec2, next_yaw: float, next_vel: wp.vec2, dt: float,
                    max_accel: float, max_kappa: float):
    """(a, kappa) that take (yaw, vel) to (next_yaw, |next_vel|), clipped to the action box."""
    speed = wp.length(vel)
    accel = wp.clamp((wp.length(next_vel) - speed) / dt, -max_accel, max_accel)
    arc = speed * dt + 0.5 * accel * dt * dt
    kappa = float(0.0)
    if wp.abs(arc) > _MIN_ARC:
        kappa = wp.clamp(wrap_angle(next_yaw - yaw) / arc, -max_kappa, max_kappa)
    return accel, kappa


@wp.func
def delta_local_forward(pos: wp.vec2, yaw: float, delta: wp.vec3, dt: float):
    c = wp.cos(yaw)
    s = wp.sin(yaw)
    step = wp.vec2(c * delta[0] - s * delta[1], s * delta[0] + c * delta[1])
    new_yaw = wrap_angle(yaw + delta[2])
    vel = step / dt
    return pos + step, new_yaw, vel, wp.length(vel)


@wp.func
def delta_local_inverse(pos: wp.vec2, yaw: float, next_pos: wp.vec2, next_yaw: float):
    d = next_pos - pos
    c = wp.cos(yaw)
    s = wp.sin(yaw)
    return wp.vec3(c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(next_yaw - yaw))


@wp.func
def nearest_bin(v: float, lo: float, hi: float, n: int):
    if n <= 1:
        return 0
    x = (v - lo) / (hi - lo) * float(n - 1)
    return wp.clamp(int(wp.round(x)), 0, n - 1)


@wp.func
def bin_value(i: int, lo: float, hi: float, n: int):
    if n <= 1:
        return 0.5 * (lo + hi)
    return lo + (hi - lo) * float(i) / float(n - 1)


@wp.func
def tracking_target(pos: wp.vec2, yaw: float, vel: wp.vec2, pos1: wp.vec2, yaw1: float, vel1: wp.vec2,
                    pos2: wp.vec2, has2: int, dt: float, gain_long: float, gain_lat: float):
    """Yaw and speed to aim for at t+1 so the simulated agent follows the logged path.

    Matching only the logged yaw and speed (Waymax's plain inverse) lets position
    errors integrate; here the speed target also closes the along-track error
    and the yaw target turns towards the logged position at t+2."""
    h = wp.vec2(wp.cos(yaw), wp.sin(yaw))
    # along-track error left after a step that matches the logged speed change
    e_long = wp.dot(pos1 - (pos + vel * dt), h) - 0.5 * (wp.length(vel1) - wp.length(vel)) * dt
    speed_t = wp.max(wp.length(vel1) + gain_long * e_long / dt, 0.0)
    yaw_t = yaw1
    if has2 != 0:
        speed = wp.length(vel)
        p1 = pos + h * (0.5 * (speed + speed_t) * dt)
        d = pos2 - p1
        if wp.length(d) > 0.5:
            yaw_t = yaw1 + gain_lat * wrap_angle(wp.atan2(d[1], d[0]) - yaw1)
    return yaw_t, wp.vec2(speed_t, 0.0)


@wp.func
def track_log(i: int, t: int, pos: wp.vec2, yaw: float, vel: wp.vec2, log_pos: wp.array2d(dtype=wp.vec2),
              log_yaw: wp.array2d(dtype=float), log_vel: wp.array2d(dtype=wp.vec2),
              log_valid: wp.array2d(dtype=wp.int32), dt: float, gain_long: float, gain_lat: float):
    """`tracking_target` of log row i towards its log at t + 1, aiming at t + 2 where that is valid."""
    has2 = int(0)
    pos2 = log_pos[i, t + 1]
    if t + 2 < log_pos.shape[1]:
        if log_valid[i, t + 2] != 0:
            has2 = 1
            pos2 = log_pos[i, t + 2]
    return tracking_target(pos, yaw, vel, log_pos[i, t + 1], log_yaw[i, t + 1], log_vel[i, t + 1], pos2, has2, dt,
                           gain_long, gain_lat)


# one kernel on purpose: splitting it would add launches and global-memory round trips per logged step
@wp.kernel
def expert_actions_kernel(
    # model
    log_pos: wp.array2d(dtype=wp.vec2),  # (agent, step) m
    log_yaw: wp.array2d(dtype=float),
    log_vel: wp.array2d(dtype=wp.vec2),
    log_valid: wp.array2d(dtype=wp.int32),
    init_step: int,
    dt: float,
    dynamics: int,
    max_accel: float,
    max_kappa: float,
    discrete: int,
    n_accel: int,
    n_kappa: int,
    gain_long: float,
    gain_lat: float,
    # out
    action_out: wp.array2d(dtype=wp.vec3),  # (agent, step) action taking step -> step + 1
    index_out: wp.array2d(dtype=wp.int32),  # (agent, step) nearest grid index; -1: no expert action
    track_pos_out: wp.array2d(dtype=wp.vec2),  # (agent, step) state the expert actions produce
):
    """Closed-loop inverse dynamics: from `init_step` on, the action at step t
    takes the *simulated* state (not the log) to the log at t + 1, so clipping
    and grid quantisation are corrected at every step instead of accumulating.
    Before `init_step` the log itself is inverted (those steps are warm-up)."""
    i = wp.tid()
    T = log_pos.shape[1]
    pos = log_pos[i, 0]
    yaw = log_yaw[i, 0]
    vel = log_vel[i, 0]
    active = int(0)
    for t in range(T):
        if t <= init_step or active == 0:
            # warm-up or not yet seen: snap to the log
            if log_valid[i, t] != 0:
                pos = log_pos[i, t]
                yaw = log_yaw[i, t]
                vel = log_vel[i, t]
                active = 1
        track_pos_out[i, t] = pos
        if t == T - 1:
            action_out[i, t] = wp.vec3(0.0, 0.0, 0.0)
            index_out[i, t] = -1
            continue
        if active == 0:
            action_out[i, t] = wp.vec3(0.0, 0.0, 0.0)
            index_out[i, t] = -1
            continue
        if log_valid[i, t + 1] == 0:
            # a gap in the log (or its end): coast with the no-op action, as the engine will,
            # and let the tracker close the distance once the log resumes
            action_out[i, t] = wp.vec3(0.0, 0.0, 0.0)
            index_out[i, t] = nearest_bin(0.0, -max_accel, max_accel, n_accel) * n_kappa + nearest_bin(
                0.0, -max_kappa, max_kappa, n_kappa)
            if dynamics == DYNAMICS_DELTA_LOCAL:
                index_out[i, t] = 0
            if t >= init_step:
                if dynamics == DYNAMICS_BICYCLE:
                    pos, yaw, vel, speed = bicycle_forward(pos, yaw, vel, 0.0, 0.0, dt)
                else:
                    pos, yaw, vel, speed = delta_local_forward(pos, yaw, wp.vec3(0.0, 0.0, 0.0), dt)
            continue
        if dynamics == DYNAMICS_BICYCLE:
            yaw_t = log_yaw[i, t + 1]
            vel_t = log_vel[i, t + 1]
            if t >= init_step:
                yaw_t, vel_t = track_log(i, t, pos, yaw, vel, log_pos, log_yaw, log_vel, log_valid, dt, gain_long,
                                         gain_lat)
            a, k = bicycle_inverse(yaw, vel, yaw_t, vel_t, dt, max_accel, max_kappa)
            ia = nearest_bin(a, -max_accel, max_accel, n_accel)
            ik = nearest_bin(k, -max_kappa, max_kappa, n_kappa)
            idx = ia * n_kappa + ik
            if discrete != 0:
                a = bin_value(ia, -max_accel, max_accel, n_accel)
                k = bin_value(ik, -max_kappa, max_kappa, n_kappa)
            action_out[i, t] = wp.vec3(a, k, 0.0)
            index_out[i, t] = idx
            if t >= init_step:
                pos, yaw, vel, speed = bicycle_forward(pos, yaw, vel, a, k, dt)
        else:
            d = delta_local_inverse(pos, yaw, log_pos[i, t + 1], log_yaw[i, t + 1])
            action_out[i, t] = d
            index_out[i, t] = 0  # defined (delta-local has no grid)
            if t >= init_step:
                pos, yaw, vel, speed = delta_local_forward(pos, yaw, d, dt)


@wp.func
def finite_or_zero(u: wp.vec3, bad_actions: wp.array(dtype=wp.int32)):
    """u itself, or the zero action (counted in bad_actions) if any entry is NaN or infinite."""
    if wp.isfinite(u[0]) and wp.isfinite(u[1]) and wp.isfinite(u[2]):
        return u
    wp.atomic_add(bad_actions, 0, 1)
    return wp.vec3(0.0, 0.0, 0.0)


# one kernel on purpose: splitting it would add launches and global-memory round trips per step
@wp.kernel
def step_agents_kernel(
    # model
    agents_per_world: int,
    slot_valid: wp.array(dtype=wp.int32),  # (world * agent,)
    integrated: wp.array(dtype=wp.int32),  # moved by its action (policy or background), else log replay
    log_row: wp.array(dtype=wp.int32),  # (world * agent,) the slot's row of the log arrays
    log_pos: wp.array2d(dtype=wp.vec2),  # (plan * agent, step)
    log_yaw: wp.array2d(dtype=float),
    log_vel: wp.array2d(dtype=wp.vec2),
    log_valid: wp.array2d(dtype=wp.int32),
    dt: float,
    dynamics: int,
    discrete: int,
    max_accel: float,
    max_kappa: float,
    n_accel: int,
    n_kappa: int,
    delta_max: wp.vec3,
    # control
    action: wp.array(dtype=wp.vec3),  # (world * agent,) continuous action
    action_index: wp.array(dtype=wp.int32),  # (world * agent,) discrete grid index
    # state in/out
    world_step: wp.array(dtype=wp.int32),  # (world,) log step the state is at
    world_done: wp.array(dtype=wp.int32),  # (world,) ended without auto-reset: frozen
    agent_done: wp.array(dtype=wp.int32),
    removed: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    vel: wp.array(dtype=wp.vec2),
    speed: wp.array(dtype=float),
    # out
    present_out: wp.array(dtype=wp.int32),
    alive_out: wp.array(dtype=wp.int32),
    applied_out: wp.array(dtype=wp.vec3),  # action actually applied (after decoding/clipping)
    bad_actions: wp.array(dtype=wp.int32),  # (1,) in/out: acting rows with an unusable action, summed
):
    """Advance every slot by one step: integrated agents apply their action,
    the others replay the log at step + 1; done agents stay frozen (stop) or
    absent (remove). An unusable action (a grid index out of range, a non-finite
    continuous value) is counted in `bad_actions`; a grid index is clamped, a
    non-finite value acts as 0 (no acceleration, no turn) instead of a bound."""
    i = wp.tid()
    w = i / agents_per_world
    tn = world_step[w] + 1
    alive_out[i] = 0
    applied_out[i] = wp.vec3(0.0, 0.0, 0.0)
    if world_done[w] != 0:
        return
    if slot_valid[i] == 0 or removed[i] != 0:
        present_out[i] = 0
        return
    if integrated[i] == 0:
        r = log_row[i]
        if log_valid[r, tn] != 0:
            pos[i] = log_pos[r, tn]
            yaw[i] = log_yaw[r, tn]
            vel[i] = log_vel[r, tn]
            speed[i] = wp.length(log_vel[r, tn])
            present_out[i] = 1
        else:
            present_out[i] = 0
        return
    present_out[i] = 1
    if agent_done[i] != 0:
        vel[i] = wp.vec2(0.0, 0.0)
        speed[i] = 0.0
        return
    alive_out[i] = 1
    if dynamics == DYNAMICS_BICYCLE:
        a = float(0.0)
        k = float(0.0)
        if discrete != 0:
            raw = action_index[i]
            if raw < 0 or raw >= n_accel * n_kappa:
                wp.atomic_add(bad_actions, 0, 1)
            idx = wp.clamp(raw, 0, n_accel * n_kappa - 1)
            a = bin_value(idx / n_kappa, -max_accel, max_accel, n_accel)
            k = bin_value(idx % n_kappa, -max_kappa, max_kappa, n_kappa)
        else:
            u = finite_or_zero(action[i], bad_actions)
            a = wp.clamp(u[0], -max_accel, max_accel)
            k = wp.clamp(u[1], -max_kappa, max_kappa)
        p, y, v, s = bicycle_forward(pos[i], yaw[i], vel[i], a, k, dt)
        pos[i] = p
        yaw[i] = y
        vel[i] = v
        speed[i] = s
        applied_out[i] = wp.vec3(a, k, 0.0)
    else:
        u = finite_or_zero(action[i], bad_actions)
        d = wp.vec3(
            wp.clamp(u[0], -delta_max[0], delta_max[0]),
            wp.clamp(u[1], -delta_max[1], delta_max[1]),
            wp.clamp(u[2], -delta_max[2], delta_max[2]),
        )
        p, y, v, s = delta_local_forward(pos[i], yaw[i], d, dt)
        pos[i] = p
        yaw[i] = y
        vel[i] = v
        speed[i] = s
        applied_out[i] = d


# gains of the closed-loop expert (tracking_target); 0, 0 is Waymax's plain inverse
TRACK_GAIN_LONG = 0.3
TRACK_GAIN_LAT = 1.0


def launch_expert_actions(model) -> None:
    """Fill model.expert_action / expert_index / expert_track from the logs (once, by the builder,
    on the rows of the batch's distinct slot plans)."""
    wp.launch(
        expert_actions_kernel,
        dim=model.log_pos.shape[0],
        inputs=[model.log_pos, model.log_yaw, model.log_vel, model.log_valid, model.init_step, model.dt,
                model.dynamics, model.max_accel, model.max_curvature, model.discrete, model.accel_bins,
                model.curvature_bins, TRACK_GAIN_LONG, TRACK_GAIN_LAT],
        outputs=[model.expert_action, model.expert_index, model.expert_track],
        device=model.device,
    )


def launch_step_agents(model, state, control) -> None:
    wp.launch(
        step_agents_kernel,
        dim=model.num_slots,
        inputs=[model.max_agents, model.slot_valid, model.integrated, model.log_row, model.log_pos, model.log_yaw,
                model.log_vel, model.log_valid, model.dt, model.dynamics, model.discrete, model.max_accel,
                model.max_curvature, model.accel_bins, model.curvature_bins, model.delta_max,
                control.action, control.action_index, state.world_step, state.world_done, state.agent_done,
                state.removed, state.pos, state.yaw, state.vel, state.speed],
        outputs=[state.present, state.alive, state.applied_action, state.bad_actions],
        device=model.device,
    )


@wp.kernel
def corrective_expert_kernel(
    agents_per_world: int,
    world_step: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    vel: wp.array(dtype=wp.vec2),
    log_row: wp.array(dtype=wp.int32),  # (world * agent,) the slot's row of the log arrays
    log_pos: wp.array2d(dtype=wp.vec2),  # (plan * agent, step)
    log_yaw: wp.array2d(dtype=float),
    log_vel: wp.array2d(dtype=wp.vec2),
    log_valid: wp.array2d(dtype=wp.int32),
    dt: float,
    dynamics: int,
    max_accel: float,
    max_kappa: float,
    n_accel: int,
    n_kappa: int,
    gain_long: float,
    gain_lat: float,
    action_out: wp.array(dtype=wp.vec3),
    index_out: wp.array(dtype=wp.int32),
):
    """The expert's action from the agent's *current* state: the tracking controller of
    `expert_actions_kernel` aimed at the log at t + 1 and t + 2, wherever the agent has
    drifted to. Continuous action (a, kappa, 0) or (dx, dy, dyaw); the nearest grid index
    (-1: the log has no next state)."""
    i = wp.tid()
    t = world_step[i / agents_per_world]
    r = log_row[i]
    T = log_pos.shape[1]
    if t + 1 >= T or log_valid[r, t + 1] == 0:
        action_out[i] = wp.vec3(0.0, 0.0, 0.0)
        index_out[i] = -1
        return
    if dynamics == DYNAMICS_BICYCLE:
        yaw_t, vel_t = track_log(r, t, pos[i], yaw[i], vel[i], log_pos, log_yaw, log_vel, log_valid, dt, gain_long,
                                 gain_lat)
        a, k = bicycle_inverse(yaw[i], vel[i], yaw_t, vel_t, dt, max_accel, max_kappa)
        action_out[i] = wp.vec3(a, k, 0.0)
        index_out[i] = nearest_bin(a, -max_accel, max_accel, n_accel) * n_kappa + nearest_bin(
            k, -max_kappa, max_kappa, n_kappa)
    else:
        action_out[i] = delta_local_inverse(pos[i], yaw[i], log_pos[r, t + 1], log_yaw[r, t + 1])
        index_out[i] = 0


def launch_corrective_expert(model, state, control, action_out, index_out) -> None:
    """The tracking expert's action from every slot's current state into `action_out` (W*A,) vec3 and
    its grid index into `index_out` (W*A,) int32; the control buffers are not touched."""
    wp.launch(corrective_expert_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.max_agents, state.world_step, state.pos, state.yaw, state.vel, model.log_row, model.log_pos,
                      model.log_yaw, model.log_vel, model.log_valid, model.dt, model.dynamics, model.max_accel,
                      model.max_curvature, model.accel_bins, model.curvature_bins, TRACK_GAIN_LONG,
                      TRACK_GAIN_LAT],
              outputs=[action_out, index_out])


@wp.kernel
def expert_to_control_kernel(
    agents_per_world: int,
    world_step: wp.array(dtype=wp.int32),
    log_row: wp.array(dtype=wp.int32),  # (world * agent,) the slot's row of the expert arrays
    expert_action: wp.array2d(dtype=wp.vec3),  # (plan * agent, step)
    expert_index: wp.array2d(dtype=wp.int32),
    action_out: wp.array(dtype=wp.vec3),
    index_out: wp.array(dtype=wp.int32),
):
    """Write the expert action of the current step into the control buffers."""
    i = wp.tid()
    t = world_step[i / agents_per_world]
    r = log_row[i]
    action_out[i] = expert_action[r, t]
    index_out[i] = wp.max(expert_index[r, t], 0)


def launch_expert_to_control(model, state, control) -> None:
    wp.launch(expert_to_control_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.max_agents, state.world_step, model.log_row, model.expert_action, model.expert_index],
              outputs=[control.action, control.action_index])
