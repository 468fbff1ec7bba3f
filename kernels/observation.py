"""Observations of each integrated agent (policy or background), in its own frame (x forward, y left).

One flat float32 row per agent slot: ego features, then `partner_k` partner
rows, then `road_k` road rows; each partner/road row starts with a 0/1 mask.
Partners are the nearest present agents within `partner_radius` and the view
cone (`view_cos`, the cosine of half its angle; -1 sees all around), nearest
first; road rows are the nearest road segments (by midpoint) within
`road_radius` and the cone, nearest first, found through the static road grid and a
bounded max-heap, so the work per agent grows with the road density around
it, not with the map size.

Layout constants below are the single source of truth for the observation's
shape: engine/model.py (obs_dim), engine/simulator.py (the views), agents/networks.py
and the world model (worldmodel/model.py, worldmodel/data.py) import them.
"""

from __future__ import annotations

import warp as wp


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


@wp.func
def in_view(d: wp.vec2, c: float, s: float, view_cos: float):
    """Whether offset d (world frame) lies in the cone of half-angle acos(view_cos) around heading (c, s)."""
    if view_cos <= -1.0:
        return True
    return c * d[0] + s * d[1] >= view_cos * wp.length(d)


# one kernel on purpose: splitting it would add launches and global-memory round trips per step
@wp.kernel
def ego_partner_obs_kernel(
    agents_per_world: int,
    partner_k: int,
    partner_radius: float,
    view_cos: float,
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
        if d2 >= r2 or not in_view(d, c, s, view_cos):
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


# Element k of slot i's road heap lives at i * slot_mul + k * k_mul. On the GPU the heaps are strided
# across slots (slot_mul 1, k_mul = slots), so the 32 threads of a warp touching the same heap
# position touch one cache line; on the CPU, where one thread runs a slot's search alone, each heap
# is contiguous (slot_mul road_k, k_mul 1).
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
def heap_sift_down(hd: wp.array(dtype=float), hj: wp.array(dtype=wp.int32), b: int, ks: int, start: int,
                   n: int):
    """Restore the max-heap property below position `start` of the heap of n elements at b, step ks."""
    k = start
    dk = hd[b + k * ks]
    while True:
        l = 2 * k + 1
        if l >= n:
            break
        m = l
        dm = hd[b + l * ks]
        if l + 1 < n:
            dr = hd[b + (l + 1) * ks]
            if dr > dm:
                m = l + 1
                dm = dr
        if dm <= dk:
            break
        heap_swap(hd, hj, b + k * ks, b + m * ks)
        k = m
    return 0


@wp.func
def heapify(hd: wp.array(dtype=float), hj: wp.array(dtype=wp.int32), b: int, ks: int, n: int):
    """Turn the first n elements at b, step ks, into a max-heap (bottom-up, O(n))."""
    s = n / 2 - 1
    while s >= 0:
        heap_sift_down(hd, hj, b, ks, s, n)
        s = s - 1
    return 0


@wp.func
def rect_dist2(p: wp.vec2, lo: wp.vec2, size: float):
    """Squared distance from p to the square [lo, lo + size]^2."""
    dx = wp.max(wp.max(lo[0] - p[0], p[0] - (lo[0] + size)), 0.0)
    dy = wp.max(wp.max(lo[1] - p[1], p[1] - (lo[1] + size)), 0.0)
    return dx * dx + dy * dy


# one kernel on purpose: splitting it would add launches and global-memory round trips per step
@wp.kernel
def road_select_kernel(
    agents_per_world: int,
    road_k: int,
    road_radius: float,
    view_cos: float,
    sort_here: int,  # 1: leave the candidates sorted (CPU); 0: road_rows_kernel ranks them (GPU)
    slot_mul: int,  # heap layout: element k of slot i at i * slot_mul + k * k_mul
    k_mul: int,
    # model
    integrated: wp.array(dtype=wp.int32),
    seg_mid: wp.array(dtype=wp.vec2),
    grid_origin: wp.array(dtype=wp.vec2),
    grid_nx: wp.array(dtype=wp.int32),
    grid_ny: wp.array(dtype=wp.int32),
    grid_cell_offset: wp.array(dtype=wp.int32),
    cell_start: wp.array(dtype=wp.int32),
    cell_size: float,
    # state
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    # out: the road_k nearest segment midpoints within road_radius and the view cone (sorted when sort_here)
    heap_d: wp.array(dtype=float),  # (road_k * slots,) m^2
    heap_j: wp.array(dtype=wp.int32),
    road_n: wp.array(dtype=wp.int32),
):
    """Nearest road segments of one agent by midpoint distance. Segments are binned in the grid by
    midpoint, so a cell can hold a midpoint within the radius only if the cell itself is that close.
    Cells are visited in square rings around the agent's cell; ring q lies at least
    (q - 1) * cell + (the agent's distance to its own cell's border) away, so once road_k
    candidates are held and a ring starts beyond the farthest of them, no later cell can improve
    the set and the search stops. The first road_k candidates are appended as they come and
    heapified once (the rings bring them roughly nearest first, the worst order for pushes);
    the heap's root (the farthest held) stays in a register."""
    i = wp.tid()
    road_n[i] = 0
    if integrated[i] == 0:
        return
    w = i / agents_per_world
    nx = grid_nx[w]
    ny = grid_ny[w]
    if nx == 0:
        return
    b = i * slot_mul
    p = pos[i]
    hc = wp.cos(yaw[i])
    hs = wp.sin(yaw[i])
    n = int(0)
    r2 = road_radius * road_radius
    bound = r2  # candidates must lie strictly closer than this (the root once road_k are held)
    o = grid_origin[w]
    fx = (p[0] - o[0]) / cell_size
    fy = (p[1] - o[1]) / cell_size
    cx = int(wp.floor(fx))
    cy = int(wp.floor(fy))
    ux = (fx - float(cx)) * cell_size
    uy = (fy - float(cy)) * cell_size
    border = wp.min(wp.min(ux, cell_size - ux), wp.min(uy, cell_size - uy))
    # rings beyond the radius cannot hold a midpoint closer than it
    q_max = int(road_radius / cell_size) + 2
    # an agent outside the grid: skip the empty rings between it and the grid
    q0 = wp.max(wp.max(wp.max(-cx - 1, cx - nx), wp.max(-cy - 1, cy - ny)), 0)
    for q in range(q0, q_max + 1):
        if q > 0:
            lb = float(q - 1) * cell_size + border
            if lb > 0.0 and lb * lb >= bound:
                break
        m = wp.max(8 * q, 1)
        for t in range(m):
            gx = cx
            gy = cy
            if q > 0:
                side = t / (2 * q)
                j = t - side * 2 * q
                if side == 0:
                    gx = cx - q + j
                    gy = cy - q
                elif side == 1:
                    gx = cx + q
                    gy = cy - q + j
                elif side == 2:
                    gx = cx + q - j
                    gy = cy + q
                else:
                    gx = cx - q
                    gy = cy + q - j
            if gx < 0 or gx >= nx or gy < 0 or gy >= ny:
                continue
            lo = wp.vec2(o[0] + float(gx) * cell_size, o[1] + float(gy) * cell_size)
            if rect_dist2(p, lo, cell_size) >= bound:
                continue
            g = grid_cell_offset[w] + gy * nx + gx
            for k in range(cell_start[g], cell_start[g + 1]):
                mid = seg_mid[k] - p
                d2 = wp.dot(mid, mid)
                if d2 >= bound or not in_view(mid, hc, hs, view_cos):
                    continue
                if n < road_k:
                    heap_d[b + n * k_mul] = d2
                    heap_j[b + n * k_mul] = k
                    n = n + 1
                    if n == road_k:
                        heapify(heap_d, heap_j, b, k_mul, n)
                        bound = heap_d[b]
                else:
                    heap_d[b] = d2
                    heap_j[b] = k
                    heap_sift_down(heap_d, heap_j, b, k_mul, 0, n)
                    bound = heap_d[b]
    if sort_here != 0:
        # heap sort: ascending distance, so road row k is candidate k
        if n < road_k:
            heapify(heap_d, heap_j, b, k_mul, n)
        e = n
        while e > 1:
            e = e - 1
            heap_swap(heap_d, heap_j, b, b + e * k_mul)
            heap_sift_down(heap_d, heap_j, b, k_mul, 0, e)
    road_n[i] = n


@wp.kernel
def road_rows_kernel(
    road_k: int,
    road_col: int,  # first column of the road block
    ranked: int,  # 1: rank the candidates here; 0: road_select_kernel sorted them
    slot_mul: int,  # heap layout, as in road_select_kernel
    k_mul: int,
    integrated: wp.array(dtype=wp.int32),
    seg_a: wp.array(dtype=wp.vec2),
    seg_b: wp.array(dtype=wp.vec2),
    seg_mid: wp.array(dtype=wp.vec2),
    seg_type: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    heap_d: wp.array(dtype=float),
    heap_j: wp.array(dtype=wp.int32),
    road_n: wp.array(dtype=wp.int32),
    obs_out: wp.array2d(dtype=float),
):
    """Candidate k of agent i goes to road row `rank`, so the rows come out nearest first; rows
    from road_n on are zeroed. Ranked (GPU): rank = how many of the agent's candidates are nearer
    (ties by position), road_k independent counts in parallel instead of one thread's serial heap
    sort, and the threads of a warp read the same heap entries (a broadcast). On the CPU, where
    threads run one after another, the O(road_k^2) counts cost more than the heap sort that
    road_select_kernel does there instead (rank = k)."""
    tid = wp.tid()
    i = tid / road_k
    k = tid - i * road_k
    if integrated[i] == 0:
        return
    b = i * slot_mul
    n = road_n[i]
    if k >= n:
        col = road_col + k * ROAD_DIM
        for f in range(ROAD_DIM):
            obs_out[i, col + f] = 0.0
        return
    rank = k
    if ranked != 0:
        dk = heap_d[b + k * k_mul]
        rank = int(0)
        for j in range(n):
            dj = heap_d[b + j * k_mul]
            if dj < dk or (dj == dk and j < k):
                rank += 1
    col = road_col + rank * ROAD_DIM
    c = wp.cos(yaw[i])
    s = wp.sin(yaw[i])
    sg = heap_j[b + k * k_mul]
    d = seg_b[sg] - seg_a[sg]
    seg_len = wp.length(d)
    dir = to_local(d, c, s)
    if seg_len > 0.0:
        dir = dir / seg_len
    else:
        dir = wp.vec2(1.0, 0.0)
    m = to_local(seg_mid[sg] - pos[i], c, s)
    obs_out[i, col + 0] = 1.0
    obs_out[i, col + 1] = m[0]
    obs_out[i, col + 2] = m[1]
    obs_out[i, col + 3] = dir[0]
    obs_out[i, col + 4] = dir[1]
    obs_out[i, col + 5] = seg_len
    obs_out[i, col + 6] = float(seg_type[sg])


def launch_observations(model, state, control) -> None:
    n, dev = model.num_slots, model.device
    wp.launch(ego_partner_obs_kernel, dim=n, device=dev,
              inputs=[model.max_agents, model.partner_k, model.partner_radius, model.view_cos, model.obs_dim, model.dt,
                      model.integrated, model.length, model.width, model.agent_type, model.goal,
                      model.last_step, state.world_step, state.world_done, state.pos, state.yaw, state.vel, state.speed,
                      state.present, state.agent_done, state.ep_collided, state.ep_offroad,
                      state.lane_dist, state.edge_dist, state.part_d, state.part_j],
              outputs=[state.obs, state.active])
    if model.road_k > 0:
        # GPU: heaps strided across slots (coalesced) and ranked in parallel; CPU: contiguous, heap-sorted
        ranked = int(model.parallel_road_rows)
        layout = [1, n] if ranked else [model.road_k, 1]
        wp.launch(road_select_kernel, dim=n, device=dev,
                  inputs=[model.max_agents, model.road_k, model.road_radius, model.view_cos, 1 - ranked, *layout,
                          model.integrated, model.seg_mid, model.grid_origin, model.grid_nx, model.grid_ny,
                          model.grid_cell_offset, model.cell_start, model.road_cell_size, state.pos, state.yaw],
                  outputs=[state.heap_d, state.heap_j, state.road_n])
        wp.launch(road_rows_kernel, dim=n * model.road_k, device=dev,
                  inputs=[model.road_k, EGO_DIM + model.partner_k * PARTNER_DIM, ranked, *layout, model.integrated, model.seg_a,
                          model.seg_b, model.seg_mid, model.seg_type, state.pos, state.yaw, state.heap_d, state.heap_j,
                          state.road_n],
                  outputs=[state.obs])
