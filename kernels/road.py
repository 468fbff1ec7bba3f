"""Road queries: off-road, distance to road edges and to lane centerlines.

Road polylines are stored as flat segments (`seg_a`, `seg_b`, `seg_type`) and
indexed by a static per-world uniform grid built once per Model (CSR:
`grid_cell_offset[w]` is the world's first cell, `cell_start`/`cell_items`
list the segments whose midpoint lies in a cell). Segments are split by the
builder to at most `max_segment_length`, so a query pads its box by half that.

Off-road: the agent's box crosses a road-edge segment (a box edge properly
intersects it, or one of its end points lies strictly inside the box); that is
the moment a corner gets across the curb. WOMD road edges are not
consistently oriented (one of our two sample scenes has vehicles on both sides
of its edges in equal shares), so no side-of-edge sign is used.
"""

from __future__ import annotations

import warp as wp

from tg_gpudrive.kernels.collision import box_axes
from tg_gpudrive.kernels.kinds import ROAD_EDGE, ROAD_LANE


@wp.func
def cross2(a: wp.vec2, b: wp.vec2):
    return a[0] * b[1] - a[1] * b[0]


@wp.func
def point_segment_distance(p: wp.vec2, a: wp.vec2, b: wp.vec2):
    ab = b - a
    den = wp.dot(ab, ab)
    t = float(0.0)
    if den > 0.0:
        t = wp.clamp(wp.dot(p - a, ab) / den, 0.0, 1.0)
    return wp.length(p - (a + ab * t))


@wp.func
def segments_cross(p1: wp.vec2, p2: wp.vec2, q1: wp.vec2, q2: wp.vec2):
    """Proper intersection (touching end points or collinear overlap do not count)."""
    d1 = cross2(q2 - q1, p1 - q1)
    d2 = cross2(q2 - q1, p2 - q1)
    d3 = cross2(p2 - p1, q1 - p1)
    d4 = cross2(p2 - p1, q2 - p1)
    return (d1 * d2 < 0.0) and (d3 * d4 < 0.0)


@wp.func
def point_in_box(p: wp.vec2, c: wp.vec2, yaw: float, length: float, width: float):
    u, v = box_axes(yaw)
    d = p - c
    return wp.abs(wp.dot(d, u)) < 0.5 * length and wp.abs(wp.dot(d, v)) < 0.5 * width


@wp.func
def box_crosses_segment(c: wp.vec2, yaw: float, length: float, width: float, a: wp.vec2, b: wp.vec2):
    u, v = box_axes(yaw)
    hu = u * (0.5 * length)
    hv = v * (0.5 * width)
    c0 = c + hu + hv
    c1 = c - hu + hv
    c2 = c - hu - hv
    c3 = c + hu - hv
    if segments_cross(c0, c1, a, b) or segments_cross(c1, c2, a, b):
        return True
    if segments_cross(c2, c3, a, b) or segments_cross(c3, c0, a, b):
        return True
    return point_in_box(a, c, yaw, length, width) or point_in_box(b, c, yaw, length, width)


@wp.func
def cell_range(lo: float, hi: float, origin: float, cell: float, n: int):
    i0 = wp.clamp(int(wp.floor((lo - origin) / cell)), 0, n - 1)
    i1 = wp.clamp(int(wp.floor((hi - origin) / cell)), 0, n - 1)
    return i0, i1


@wp.kernel
def road_query_kernel(
    agents_per_world: int,
    # model: road segments and their grid
    seg_a: wp.array(dtype=wp.vec2),
    seg_b: wp.array(dtype=wp.vec2),
    seg_type: wp.array(dtype=wp.int32),
    grid_origin: wp.array(dtype=wp.vec2),  # (world,) m
    grid_nx: wp.array(dtype=wp.int32),
    grid_ny: wp.array(dtype=wp.int32),
    grid_cell_offset: wp.array(dtype=wp.int32),  # (world,)
    cell_start: wp.array(dtype=wp.int32),  # (cells + 1,) segments of cell g: [cell_start[g], cell_start[g + 1])
    cell_size: float,
    seg_pad: float,  # m, half the longest segment
    search_radius: float,  # m, cap of the reported distances
    length: wp.array(dtype=float),
    width: wp.array(dtype=float),
    # state
    pos: wp.array(dtype=wp.vec2),
    yaw: wp.array(dtype=float),
    present: wp.array(dtype=wp.int32),
    world_mask: wp.array(dtype=wp.int32),  # (world,) with only_masked: query only these worlds
    only_masked: int,
    # out
    offroad_out: wp.array(dtype=wp.int32),  # box crosses a road edge this step
    edge_dist_out: wp.array(dtype=float),  # m, centre to nearest road edge (<= search_radius)
    lane_dist_out: wp.array(dtype=float),  # m, centre to nearest lane centerline (<= search_radius)
):
    i = wp.tid()
    w = i / agents_per_world
    if only_masked != 0 and world_mask[w] == 0:
        return
    if only_masked == 0:
        offroad_out[i] = 0  # refreshing a reset world keeps the terminal step's event flags
    edge_dist_out[i] = search_radius
    lane_dist_out[i] = search_radius
    if present[i] == 0:
        return
    p = pos[i]
    half_diag = 0.5 * wp.sqrt(length[i] * length[i] + width[i] * width[i])
    r = wp.max(search_radius, half_diag) + seg_pad
    cs = cell_size
    o = grid_origin[w]
    nx = grid_nx[w]
    ny = grid_ny[w]
    if nx == 0:
        return
    x0, x1 = cell_range(p[0] - r, p[0] + r, o[0], cs, nx)
    y0, y1 = cell_range(p[1] - r, p[1] + r, o[1], cs, ny)
    edge_d = search_radius
    lane_d = search_radius
    off = int(0)
    for gy in range(y0, y1 + 1):
        for gx in range(x0, x1 + 1):
            g = grid_cell_offset[w] + gy * nx + gx
            for k in range(cell_start[g], cell_start[g + 1]):
                t = seg_type[k]
                if t == ROAD_EDGE:
                    d = point_segment_distance(p, seg_a[k], seg_b[k])
                    edge_d = wp.min(edge_d, d)
                    if off == 0 and d < half_diag:
                        if box_crosses_segment(p, yaw[i], length[i], width[i], seg_a[k], seg_b[k]):
                            off = 1
                elif t == ROAD_LANE:
                    lane_d = wp.min(lane_d, point_segment_distance(p, seg_a[k], seg_b[k]))
    if only_masked == 0:
        offroad_out[i] = off
    edge_dist_out[i] = edge_d
    lane_dist_out[i] = lane_d


def road_grid_inputs(model) -> list:
    return [model.seg_a, model.seg_b, model.seg_type, model.grid_origin, model.grid_nx, model.grid_ny,
            model.grid_cell_offset, model.cell_start, model.road_cell_size, model.seg_pad]


def launch_road_query(model, state, control, only_reset_worlds: bool = False) -> None:
    """Off-road, edge and lane distances; `only_reset_worlds` refreshes the worlds that just reset."""
    wp.launch(road_query_kernel, dim=model.num_slots, device=model.device,
              inputs=[model.max_agents, *road_grid_inputs(model), model.road_query_radius, model.length,
                      model.width, state.pos, state.yaw, state.present, state.world_reset,
                      int(only_reset_worlds)],
              outputs=[state.offroad, state.edge_dist, state.lane_dist])


@wp.func
def point_segment_distance64(p: wp.vec2, a: wp.vec2, b: wp.vec2):
    """point_segment_distance in float64: RDP's farthest point is picked as the NumPy reference does."""
    pd = wp.vec2d(wp.float64(p[0]), wp.float64(p[1]))
    ad = wp.vec2d(wp.float64(a[0]), wp.float64(a[1]))
    ab = wp.vec2d(wp.float64(b[0]), wp.float64(b[1])) - ad
    den = wp.dot(ab, ab)
    t = wp.float64(0.0)
    if den > wp.float64(0.0):
        t = wp.clamp(wp.dot(pd - ad, ab) / den, wp.float64(0.0), wp.float64(1.0))
    return wp.length(pd - (ad + ab * t))


@wp.kernel
def simplify_kernel(
    pts: wp.array(dtype=wp.vec2),
    start: wp.array(dtype=wp.int32),  # (polylines,) first point
    count: wp.array(dtype=wp.int32),  # points
    polygon: wp.array(dtype=wp.int32),  # 1: a closed shape (crosswalk, speed bump, driveway)
    tolerance: wp.float64,
    stack: wp.array(dtype=wp.int32),  # scratch, 2 per point: a polyline's pending spans live in its own rows
    keep_out: wp.array(dtype=wp.int32),  # (points,) 1: the point stays
):
    """Ramer-Douglas-Peucker, one thread per polyline (the iterative form of
    tg_gpudrive.data.simplify.rdp_mask): every dropped point lies within `tolerance` of the kept
    polyline, endpoints stay, and a polygon keeps at least three corners (its widest one when
    thinner than the tolerance)."""
    r = wp.tid()
    a = start[r]
    n = count[r]
    if n <= 2:
        for k in range(n):
            keep_out[a + k] = 1
        return
    keep_out[a] = 1
    keep_out[a + n - 1] = 1
    for k in range(1, n - 1):
        keep_out[a + k] = 0
    kept = int(2)
    # spans pending, stored as (i, j) pairs at stack[2a + 2t], stack[2a + 2t + 1]
    stack[2 * a] = 0
    stack[2 * a + 1] = n - 1
    top = int(1)
    while top > 0:
        top -= 1
        i = stack[2 * a + 2 * top]
        j = stack[2 * a + 2 * top + 1]
        if j - i >= 2:
            best = wp.float64(-1.0)
            m = int(-1)
            for k in range(i + 1, j):
                d = point_segment_distance64(pts[a + k], pts[a + i], pts[a + j])
                if d > best:
                    best = d
                    m = k
            if best > tolerance:
                keep_out[a + m] = 1
                kept += 1
                stack[2 * a + 2 * top] = i
                stack[2 * a + 2 * top + 1] = m
                stack[2 * a + 2 * top + 2] = m
                stack[2 * a + 2 * top + 3] = j
                top += 2
    if polygon[r] != 0 and kept < 3:
        best = wp.float64(-1.0)
        m = int(1)
        for k in range(1, n - 1):
            d = point_segment_distance64(pts[a + k], pts[a], pts[a + n - 1])
            if d > best:
                best = d
                m = k
        keep_out[a + m] = 1


def launch_simplify(pts: wp.array, start: wp.array, count: wp.array, polygon: wp.array, tolerance: float,
                    stack: wp.array, keep: wp.array, device) -> None:
    """The RDP keep mask (`keep`, int32 per point) of the polylines [start, start + count) of `pts`;
    `stack`: int32 scratch of 2 per point."""
    wp.launch(simplify_kernel, dim=len(start), device=device,
              inputs=[pts, start, count, polygon, wp.float64(tolerance), stack], outputs=[keep])
