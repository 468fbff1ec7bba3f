"""Agent-agent collision between oriented boxes, with a per-world hashed grid.

Broad phase: every present agent is binned into a hashed uniform grid of its
world (cell size >= the largest box diagonal and >= the cost distance beta),
so each agent only meets the agents of its 3 x 3 neighbouring cells and the
cost does not grow as A^2 when scenes are dense. The grid is rebuilt each step
with a counting sort (clear, count, per-world scan, scatter).

Narrow phase: separating axis test on the two boxes (4 axes). Boxes that only
touch (zero-length overlap on some axis) do not collide.

The same neighbour pass also yields the distance to the nearest other present
agent (centre to centre), and the distance the cost reads: to the nearest agent of
any kind, or (`cost_players`) to the nearest one the policy drives, as TrafficGamer's
cost counts only the agents of its game. Agents farther than one cell may sit
outside the 3 x 3 cells visited, so both distances are capped at the world's
`nearest_cap` (the cell size): a capped metric, exact below the cap. The cost
compares it with beta, which is right because the builder keeps the cap >= beta.

Time to collision (`ttc_kernel`, for the reward's `ttc` term): each acting agent against every
present agent of its world that lies ahead of its motion (positive dot product of its velocity with
the offset), both moving on at their current velocity. Boxes are covered by three discs of radius
width/2 along the long axis, the model of evaluation/risk.py's `min_ttc`; the TTC is the first time
any disc pair touches (0 when they already overlap), capped at the horizon. Only agents ahead count,
so a car is charged for closing on a slower one, not for being closed on from behind.

Anticipated cost distance (`anticipate_kernel`, with `cost_horizon` > 0): the cost's distance becomes
the least centre distance to an agent it counts over the next `cost_horizon` seconds, both moving on
at their current velocity (closest approach of two points, now included), so beta is kept ahead of
time: a car closing fast on another pays before the gap is gone. It visits every agent of the world,
so it is exact beyond the broad phase's cells.
"""

from __future__ import annotations

import warp as wp


@wp.func
def box_axes(yaw: float):
    c = wp.cos(yaw)
    s = wp.sin(yaw)
    return wp.vec2(c, s), wp.vec2(-s, c)


@wp.func
def box_half_extent_on(axis: wp.vec2, yaw: float, length: float, width: float):
    """Half length of the box's projection on a unit axis."""
    u, v = box_axes(yaw)
    return 0.5 * length * wp.abs(wp.dot(u, axis)) + 0.5 * width * wp.abs(wp.dot(v, axis))


@wp.func
def separated_on(axis: wp.vec2, d: wp.vec2, yaw_a: float, len_a: float, wid_a: float,
                 yaw_b: float, len_b: float, wid_b: float):
    r = box_half_extent_on(axis, yaw_a, len_a, wid_a) + box_half_extent_on(axis, yaw_b, len_b, wid_b)
    return wp.abs(wp.dot(d, axis)) >= r


@wp.func
def boxes_overlap(pa: wp.vec2, yaw_a: float, len_a: float, wid_a: float,
                  pb: wp.vec2, yaw_b: float, len_b: float, wid_b: float):
    d = pb - pa
    ua, va = box_axes(yaw_a)
    ub, vb = box_axes(yaw_b)
    if separated_on(ua, d, yaw_a, len_a, wid_a, yaw_b, len_b, wid_b):
        return False
    if separated_on(va, d, yaw_a, len_a, wid_a, yaw_b, len_b, wid_b):
        return False
    if separated_on(ub, d, yaw_a, len_a, wid_a, yaw_b, len_b, wid_b):
        return False
    if separated_on(vb, d, yaw_a, len_a, wid_a, yaw_b, len_b, wid_b):
        return False
    return True


@wp.func
def cell_hash(ix: int, iy: int, n_cells: int):
    h = (ix * 73856093) ^ (iy * 19349663)
    h = h % n_cells
    if h < 0:
        h = h + n_cells
    return h


@wp.func
def cell_coord(p: float, cell: float):
    return int(wp.floor(p / cell))


@wp.kernel
def grid_count_kernel(
    agents_per_world: int,
    n_cells: int,
    cell_size: wp.array(dtype=float),  # (world,) m
    pos: wp.array(dtype=wp.vec2),
    present: wp.array(dtype=wp.int32),
    cell_count: wp.array(dtype=wp.int32),  # (world * n_cells,) zeroed before
    agent_cell_out: wp.array(dtype=wp.int32),  # (world * agent,) hashed cell or -1
):
    i = wp.tid()
    w = i / agents_per_world
    if present[i] == 0:
        agent_cell_out[i] = -1
        return
    c = cell_size[w]
    h = cell_hash(cell_coord(pos[i][0], c), cell_coord(pos[i][1], c), n_cells)
    agent_cell_out[i] = h
    wp.atomic_add(cell_count, w * n_cells + h, 1)


@wp.kernel
def grid_scan_kernel(
    n_cells: int,
    cell_count: wp.array(dtype=wp.int32),
    cell_start_out: wp.array(dtype=wp.int32),  # (world * n_cells,) start within the world's slice
    cell_fill_out: wp.array(dtype=wp.int32),
):
    w = wp.tid()
    run = int(0)
    for g in range(n_cells):
        cell_start_out[w * n_cells + g] = run
        cell_fill_out[w * n_cells + g] = run
        run += cell_count[w * n_cells + g]
        cell_count[w * n_cells + g] = 0  # ready for the next step's count


@wp.kernel
def grid_scatter_kernel(
    agents_per_world: int,
    n_cells: int,
    agent_cell: wp.array(dtype=wp.int32),
    cell_fill: wp.array(dtype=wp.int32),
    cell_items_out: wp.array(dtype=wp.int32),  # (world * agent,) agent index within world
):
    i = wp.tid()
    h = agent_cell[i]
    if h < 0:
        return
    w = i / agents_per_world
    slot = wp.atomic_add(cell_fill, w * n_cells + h, 1)
    cell_items_out[w * agents_per_world + slot] = i - w * agents_per_world


@wp.kernel
def collide_kernel(
    agents_per_world: int,
    n_cells: int,
    cell_size: wp.array(dtype=float),  # (world,) m
    nearest_cap: wp.array(dtype=float),  # (world,) m, reported when no partner is nearer (<= cell_size)
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    length: wp.array(dtype=float),
    width: wp.array(dtype=float),
    present: wp.array(dtype=wp.int32),
    integrated: wp.array(dtype=wp.int32),
    background: wp.array(dtype=wp.int32),
    cost_players: int,  # 1: the cost's distance counts only the policy's agents (integrated, not background)
    agent_cell: wp.array(dtype=wp.int32),
    cell_start: wp.array(dtype=wp.int32),
    cell_fill: wp.array(dtype=wp.int32),  # after scatter: end of each cell
    cell_items: wp.array(dtype=wp.int32),
    # out
    collided_out: wp.array(dtype=wp.int32),  # (world * agent,) boxes overlap this step
    nearest_out: wp.array(dtype=float),  # (world * agent,) m, centre distance to nearest, <= nearest_cap
    cost_dist_out: wp.array(dtype=float),  # (world * agent,) m, the same to the nearest the cost counts
):
    i = wp.tid()
    collided_out[i] = 0
    w = i / agents_per_world
    c = cell_size[w]
    nearest_out[i] = nearest_cap[w]
    cost_dist_out[i] = nearest_cap[w]
    if present[i] == 0:
        return
    base = w * agents_per_world
    p = pos[i]
    cx = cell_coord(p[0], c)
    cy = cell_coord(p[1], c)
    nearest = nearest_cap[w]
    cost_dist = nearest_cap[w]
    hit = int(0)
    for k in range(9):
        h = cell_hash(cx + k / 3 - 1, cy + k % 3 - 1, n_cells)
        # two neighbour cells may hash to one bucket: visit it once (the result would be the
        # same, only slower)
        seen = int(0)
        for e in range(k):
            if cell_hash(cx + e / 3 - 1, cy + e % 3 - 1, n_cells) == h:
                seen = 1
        if seen == 0:
            g = w * n_cells + h
            for s in range(cell_start[g], cell_fill[g]):
                j = base + cell_items[base + s]
                if j == i:
                    continue
                q = pos[j]
                d = wp.length(q - p)
                nearest = wp.min(nearest, d)
                if cost_players == 1:  # else the cost reads `nearest` (set below): no extra loads per pair
                    if integrated[j] != 0 and background[j] == 0:
                        cost_dist = wp.min(cost_dist, d)
                if hit == 0:
                    reach = 0.5 * (wp.sqrt(length[i] * length[i] + width[i] * width[i])
                                   + wp.sqrt(length[j] * length[j] + width[j] * width[j]))
                    if d < reach:
                        if boxes_overlap(p, yaw[i], length[i], width[i], q, yaw[j], length[j], width[j]):
                            hit = 1
    collided_out[i] = hit
    nearest_out[i] = nearest
    if cost_players == 0:
        cost_dist = nearest
    cost_dist_out[i] = cost_dist


@wp.func
def disc_ttc(p: wp.vec2, v: wp.vec2, r: float, horizon: float):
    """Constant-velocity TTC of two discs at relative position p, relative velocity v, radius sum r."""
    c = wp.dot(p, p) - r * r
    if c <= 0.0:
        return 0.0
    a = wp.dot(v, v)
    b = 2.0 * wp.dot(p, v)
    disc = b * b - 4.0 * a * c
    if a <= 1e-12 or disc < 0.0:
        return horizon
    t = (-b - wp.sqrt(disc)) / (2.0 * a)
    if t < 0.0:
        return horizon  # both roots behind: moving apart
    return wp.min(t, horizon)


@wp.kernel
def ttc_kernel(
    agents_per_world: int,
    horizon: float,  # s, reported when no conflict comes sooner
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    vel: wp.array(dtype=wp.vec2),
    length: wp.array(dtype=float),
    width: wp.array(dtype=float),
    present: wp.array(dtype=wp.int32),
    alive: wp.array(dtype=wp.int32),
    # out
    ttc_out: wp.array(dtype=float),  # (world * agent,) s, <= horizon
):
    i = wp.tid()
    ttc_out[i] = horizon
    vi = vel[i]
    if alive[i] == 0 or wp.dot(vi, vi) < 1e-6:
        return
    w = i / agents_per_world
    base = w * agents_per_world
    p = pos[i]
    hi = wp.vec2(wp.cos(yaw[i]), wp.sin(yaw[i]))
    oi = 0.5 * wp.max(length[i] - width[i], 0.0)
    big_i = 0.5 * wp.sqrt(length[i] * length[i] + width[i] * width[i])
    best = horizon
    for a in range(agents_per_world):
        j = base + a
        if j == i or present[j] == 0:
            continue
        d = pos[j] - p
        if wp.dot(vi, d) <= 0.0:
            continue
        v = vel[j] - vi
        # the bounding circles meet no later than any disc pair inside them: prune on them first
        big = big_i + 0.5 * wp.sqrt(length[j] * length[j] + width[j] * width[j])
        if disc_ttc(d, v, big, horizon) >= best:
            continue
        hj = wp.vec2(wp.cos(yaw[j]), wp.sin(yaw[j]))
        oj = 0.5 * wp.max(length[j] - width[j], 0.0)
        r = 0.5 * (width[i] + width[j])
        for da in range(3):
            ci = hi * (oi * float(da - 1))
            for db in range(3):
                cj = hj * (oj * float(db - 1))
                best = wp.min(best, disc_ttc(d + cj - ci, v, r, horizon))
    ttc_out[i] = best


@wp.kernel
def anticipate_kernel(
    agents_per_world: int,
    horizon: float,  # s
    cost_players: int,  # 1: only the policy's agents count (as collide_kernel's cost distance)
    pos: wp.array(dtype=wp.vec2),
    vel: wp.array(dtype=wp.vec2),
    present: wp.array(dtype=wp.int32),
    alive: wp.array(dtype=wp.int32),
    integrated: wp.array(dtype=wp.int32),
    background: wp.array(dtype=wp.int32),
    # in: the distance now (collide_kernel); out: the least over the horizon
    cost_dist: wp.array(dtype=float),
):
    i = wp.tid()
    if alive[i] == 0:
        return
    w = i / agents_per_world
    base = w * agents_per_world
    p = pos[i]
    best = cost_dist[i]
    for a in range(agents_per_world):
        j = base + a
        if j == i or present[j] == 0:
            continue
        if cost_players == 1 and (integrated[j] == 0 or background[j] != 0):
            continue
        d = pos[j] - p
        v = vel[j] - vel[i]
        vv = wp.dot(v, v)
        t = float(0.0)
        if vv > 1e-12:
            t = wp.clamp(-wp.dot(d, v) / vv, 0.0, horizon)
        best = wp.min(best, wp.length(d + v * t))
    cost_dist[i] = best


def launch_collision(model, state, control) -> None:
    """Broad phase (hashed grid, counting sort) then narrow phase for every slot."""
    n, dev, g = model.num_slots, model.device, model.collision_cells
    wp.launch(grid_count_kernel, dim=n, device=dev,
              inputs=[model.max_agents, g, model.collision_cell_size, state.pos, state.present],
              outputs=[state.grid_count, state.agent_cell])
    wp.launch(grid_scan_kernel, dim=model.num_worlds, device=dev,
              inputs=[g, state.grid_count], outputs=[state.grid_start, state.grid_fill])
    wp.launch(grid_scatter_kernel, dim=n, device=dev,
              inputs=[model.max_agents, g, state.agent_cell, state.grid_fill], outputs=[state.grid_items])
    wp.launch(collide_kernel, dim=n, device=dev,
              inputs=[model.max_agents, g, model.collision_cell_size, model.nearest_cap, state.pos, state.yaw,
                      model.length, model.width, state.present, model.integrated, model.background,
                      model.cost_players, state.agent_cell, state.grid_start, state.grid_fill, state.grid_items],
              outputs=[state.collided, state.nearest, state.cost_dist])
    if model.cost_horizon > 0.0:
        wp.launch(anticipate_kernel, dim=n, device=dev,
                  inputs=[model.max_agents, model.cost_horizon, model.cost_players, state.pos, state.vel, state.present,
                          state.alive, model.integrated, model.background],
                  outputs=[state.cost_dist])


def launch_ttc(model, state, control) -> None:
    """Time to collision of every acting agent; only when the reward weights it (O(A^2) per world)."""
    if not model.ttc_on:
        return
    wp.launch(ttc_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.max_agents, model.ttc_horizon, state.pos, state.yaw, state.vel, model.length, model.width,
                      state.present, state.alive],
              outputs=[state.ttc])
