"""Observations of each integrated agent (policy or background), in its own frame (x forward, y left).

One flat float32 row per agent slot: ego features, then `partner_k` partner
rows, then `road_k` road rows; each partner/road row starts with a 0/1 mask.
Partners are the nearest present agents within `partner_radius`, nearest
first; road rows are the nearest road segments (by midpoint) within
`road_radius`, nearest first, found through the static road grid and a
bounded max-heap, so the work per agent grows with the road density around
it, not with the map size.

Layout constants below are the single source of truth for the learner and the
envs (tg_gpudrive.obs_layout reads them).
"""

from __future__ import annotations

import warp as wp

from tg_gpudrive.kernels.road import cell_range, road_grid_inputs

# ego: speed, length, width, goal x, goal y, collided (episode), offroad (episode),
#      lane distance, road-edge distance, time left (s)
EGO_DIM = 10
# partner: mask, x, y, cos dyaw, sin dyaw, vx, vy, length, width, type
PARTNER_DIM = 10
# road: mask, x, y, cos dir, sin dir, segment length, type
ROAD_DIM = 7


@wp.func
def to_local(d: wp.vec2, c: float, s: float):
    return wp.vec2(c * d[0] + s * d[1], -s * d[0] + c * d[1])


@wp.kernel
def ego_partner_obs_kernel(
    agents_per_world: int,
    partner_k: int,
    partner_radius: float,
    obs_dim: int,
    dt: float,
    # model
    integrated: wp.array(dtype=wp.int32),  # rows without it get no observation
    length: wp.array(dtype=float),
    width: wp.array(dtype=float),
    agent_type: wp.array(dtype=wp.int32),
    goal: wp.array(dtype=wp.vec2),
    last_step: wp.array(dtype=wp.int32),  # (world,)
    # state
    world_step: wp.array(dtype=wp.int32),  # (world,)
    world_done: wp.array(dtype=wp.int32),  # (world,) ended without auto-reset: nobody acts
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    vel: wp.array(dtype=wp.vec2),
    speed: wp.array(dtype=float),
    present: wp.array(dtype=wp.int32),
    agent_done: wp.array(dtype=wp.int32),
    ep_collided: wp.array(dtype=wp.int32),
    ep_offroad: wp.array(dtype=wp.int32),
    lane_dist: wp.array(dtype=float),
    edge_dist: wp.array(dtype=float),
    # scratch
    part_d: wp.array(dtype=float),  # (world * agent * partner_k,)
    part_j: wp.array(dtype=wp.int32),
    # out
    obs_out: wp.array2d(dtype=float),  # (world * agent, obs_dim)
    active_out: wp.array(dtype=wp.int32),  # integrated and will act next step
):
    i = wp.tid()
    w = i / agents_per_world
    act = int(0)
    if integrated[i] != 0 and present[i] != 0 and agent_done[i] == 0 and world_done[w] == 0:
        act = 1
    active_out[i] = act
    if integrated[i] == 0:
        return
    base = w * agents_per_world
    p = pos[i]
    c = wp.cos(yaw[i])
    s = wp.sin(yaw[i])
    g = to_local(goal[i] - p, c, s)
    obs_out[i, 0] = speed[i]
    obs_out[i, 1] = length[i]
    obs_out[i, 2] = width[i]
    obs_out[i, 3] = g[0]
    obs_out[i, 4] = g[1]
    obs_out[i, 5] = float(ep_collided[i])
    obs_out[i, 6] = float(ep_offroad[i])
    obs_out[i, 7] = lane_dist[i]
    obs_out[i, 8] = edge_dist[i]
    obs_out[i, 9] = float(last_step[w] - world_step[w]) * dt

    # nearest partner_k present agents, kept sorted by distance (insertion)
    sb = i * partner_k
    n = int(0)
    r2 = partner_radius * partner_radius
    for a in range(agents_per_world):
        j = base + a
        if j == i or present[j] == 0:
            continue
        d = pos[j] - p
        d2 = wp.dot(d, d)
        if d2 >= r2:
            continue
        if n == partner_k:
            if d2 >= part_d[sb + n - 1]:
                continue
            n = n - 1
        k = n
        while k > 0 and part_d[sb + k - 1] > d2:
            part_d[sb + k] = part_d[sb + k - 1]
            part_j[sb + k] = part_j[sb + k - 1]
            k = k - 1
        part_d[sb + k] = d2
        part_j[sb + k] = j
        n = n + 1
    col = EGO_DIM
    for k in range(partner_k):
        if k < n:
            j = part_j[sb + k]
            rel = to_local(pos[j] - p, c, s)
            rv = to_local(vel[j] - vel[i], c, s)
            dyaw = yaw[j] - yaw[i]
            obs_out[i, col + 0] = 1.0
            obs_out[i, col + 1] = rel[0]
            obs_out[i, col + 2] = rel[1]
            obs_out[i, col + 3] = wp.cos(dyaw)
            obs_out[i, col + 4] = wp.sin(dyaw)
            obs_out[i, col + 5] = rv[0]
            obs_out[i, col + 6] = rv[1]
            obs_out[i, col + 7] = length[j]
            obs_out[i, col + 8] = width[j]
            obs_out[i, col + 9] = float(agent_type[j])
        else:
            for f in range(PARTNER_DIM):
                obs_out[i, col + f] = 0.0
        col += PARTNER_DIM


@wp.func
def heap_swap(hd: wp.array(dtype=float), hj: wp.array(dtype=wp.int32), x: int, y: int):
    td = hd[x]
    tj = hj[x]
    hd[x] = hd[y]
    hj[x] = hj[y]
    hd[y] = td
    hj[y] = tj
    return 0


@wp.func
def heap_sift_down(hd: wp.array(dtype=float), hj: wp.array(dtype=wp.int32), b: int, start: int, n: int):
    """Restore the max-heap property below `start` in hd[b : b + n]."""
    k = start
    while True:
        l = 2 * k + 1
        if l >= n:
            break
        m = l
        if l + 1 < n and hd[b + l + 1] > hd[b + l]:
            m = l + 1
        if hd[b + m] <= hd[b + k]:
            break
        heap_swap(hd, hj, b + k, b + m)
        k = m
    return 0


@wp.kernel
def road_obs_kernel(
    agents_per_world: int,
    road_k: int,
    road_radius: float,
    road_col: int,  # first column of the road block
    # model
    integrated: wp.array(dtype=wp.int32),
    seg_a: wp.array(dtype=wp.vec2),
    seg_b: wp.array(dtype=wp.vec2),
    seg_type: wp.array(dtype=wp.int32),
    grid_origin: wp.array(dtype=wp.vec2),
    grid_nx: wp.array(dtype=wp.int32),
    grid_ny: wp.array(dtype=wp.int32),
    grid_cell_offset: wp.array(dtype=wp.int32),
    cell_start: wp.array(dtype=wp.int32),
    cell_items: wp.array(dtype=wp.int32),
    cell_size: float,
    seg_pad: float,
    # state
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    # scratch
    heap_d: wp.array(dtype=float),  # (world * agent * road_k,)
    heap_j: wp.array(dtype=wp.int32),
    # out
    obs_out: wp.array2d(dtype=float),
):
    i = wp.tid()
    if integrated[i] == 0:
        return
    w = i / agents_per_world
    p = pos[i]
    b = i * road_k
    n = int(0)
    nx = grid_nx[w]
    ny = grid_ny[w]
    r2 = road_radius * road_radius
    if nx > 0:
        o = grid_origin[w]
        r = road_radius + seg_pad
        x0, x1 = cell_range(p[0] - r, p[0] + r, o[0], cell_size, nx)
        y0, y1 = cell_range(p[1] - r, p[1] + r, o[1], cell_size, ny)
        for gy in range(y0, y1 + 1):
            for gx in range(x0, x1 + 1):
                g = grid_cell_offset[w] + gy * nx + gx
                for si in range(cell_start[g], cell_start[g + 1]):
                    k = cell_items[si]
                    m = 0.5 * (seg_a[k] + seg_b[k]) - p
                    d2 = wp.dot(m, m)
                    if d2 >= r2:
                        continue
                    if n < road_k:
                        # push and sift up
                        hc = n
                        heap_d[b + hc] = d2
                        heap_j[b + hc] = k
                        while hc > 0:
                            par = (hc - 1) / 2
                            if heap_d[b + par] >= heap_d[b + hc]:
                                break
                            heap_swap(heap_d, heap_j, b + par, b + hc)
                            hc = par
                        n = n + 1
                    elif d2 < heap_d[b]:
                        heap_d[b] = d2
                        heap_j[b] = k
                        heap_sift_down(heap_d, heap_j, b, 0, n)
    # heap sort: ascending distance, so row 0 is the nearest segment
    e = n
    while e > 1:
        e = e - 1
        heap_swap(heap_d, heap_j, b, b + e)
        heap_sift_down(heap_d, heap_j, b, 0, e)
    c = wp.cos(yaw[i])
    s = wp.sin(yaw[i])
    col = road_col
    for k in range(road_k):
        if k < n:
            sg = heap_j[b + k]
            d = seg_b[sg] - seg_a[sg]
            seg_len = wp.length(d)
            dir = to_local(d, c, s)
            if seg_len > 0.0:
                dir = dir / seg_len
            else:
                dir = wp.vec2(1.0, 0.0)
            m = to_local(0.5 * (seg_a[sg] + seg_b[sg]) - p, c, s)
            obs_out[i, col + 0] = 1.0
            obs_out[i, col + 1] = m[0]
            obs_out[i, col + 2] = m[1]
            obs_out[i, col + 3] = dir[0]
            obs_out[i, col + 4] = dir[1]
            obs_out[i, col + 5] = seg_len
            obs_out[i, col + 6] = float(seg_type[sg])
        else:
            for f in range(ROAD_DIM):
                obs_out[i, col + f] = 0.0
        col += ROAD_DIM


def launch_observations(model, state, control) -> None:
    n, dev = model.num_slots, model.device
    wp.launch(ego_partner_obs_kernel, dim=n, device=dev,
              inputs=[model.max_agents, model.partner_k, model.partner_radius, model.obs_dim, model.dt,
                      model.integrated, model.length, model.width, model.agent_type, model.goal,
                      model.last_step, state.world_step, state.world_done, state.pos, state.yaw, state.vel, state.speed,
                      state.present, state.agent_done, state.ep_collided, state.ep_offroad,
                      state.lane_dist, state.edge_dist, state.part_d, state.part_j],
              outputs=[state.obs, state.active])
    if model.road_k > 0:
        wp.launch(road_obs_kernel, dim=n, device=dev,
                  inputs=[model.max_agents, model.road_k, model.road_radius, EGO_DIM + model.partner_k * PARTNER_DIM,
                          model.integrated, *road_grid_inputs(model), state.pos, state.yaw,
                          state.heap_d, state.heap_j],
                  outputs=[state.obs])
