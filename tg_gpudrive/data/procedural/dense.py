"""Dense scenes of WOMD size for engine benchmarks: `procedural:dense`.

A real WOMD scene holds up to 128 objects and a map of 10-40 k road points sampled every 0.5 m;
one procedural scene holds 2-32 vehicles and 2-7 k points every 1 m. A dense scene lays several
procedural scenes (drawn from all six types, with doubled traffic density) side by side on one
map, without overlap, until it holds the drawn number of agents (64-128), and resamples every
road polyline evenly so that the map holds the drawn number of road points (20-40 k). Each tile
keeps the invariants of its procedural scene (no overlapping boxes, goals on lanes, kinematic
logs); tiles are separated by `gap` metres, so nothing crosses from one tile into another.

It exists to measure the engine on WOMD-sized worlds without the dataset; it is not a scenario
type of the paper and is not in `procedural:all`.
"""

from __future__ import annotations

import math

import numpy as np

from tg_gpudrive.data.procedural.generator import SCENARIO_TYPES, ProceduralParams, generate_scene
from tg_gpudrive.scene import Scene

DENSE_AGENTS = (64, 128)  # agents per scene, drawn uniformly (inclusive)
DENSE_ROAD_POINTS = (20_000, 40_000)  # road points per scene, drawn uniformly (inclusive)
TILE_PARAMS = ProceduralParams(density=2.0, max_vehicles=32)
MAX_TILES = 24


def resample_polylines(points: np.ndarray, offsets: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Every polyline re-sampled at (about) `spacing` metres along its length, end points kept:
    a polyline of length L gets max(2, ceil(L / spacing) + 1) evenly spaced points; a single-point
    polyline stays one point. Returns (points (P', 2), offsets (R + 1,))."""
    out, new_off = [], [0]
    for r in range(len(offsets) - 1):
        p = points[offsets[r]:offsets[r + 1]].astype(np.float64)
        if len(p) < 2:
            out.append(p)
            new_off.append(new_off[-1] + len(p))
            continue
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        n = max(2, math.ceil(s[-1] / spacing) + 1)
        t = np.linspace(0.0, s[-1], n)
        q = np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)
        out.append(q)
        new_off.append(new_off[-1] + n)
    return np.concatenate(out).astype(np.float32), np.asarray(new_off, np.int64)


def _polyline_lengths(points: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points.astype(np.float64), axis=0), axis=1)
    same = np.ones(len(seg), bool)
    same[offsets[1:-1] - 1] = False  # segments joining two polylines
    cum = np.concatenate([[0.0], np.cumsum(np.where(same, seg, 0.0))])
    return cum[offsets[1:] - 1] - cum[offsets[:-1]]


def _draw_tiles(rng: np.random.Generator, n_agents: int) -> tuple[list[Scene], list[str], list[int]]:
    """Procedural scenes of random types and seeds, drawn until they hold at least `n_agents` agents:
    (tiles, their types, their seeds)."""
    tiles: list[Scene] = []
    kinds, seeds = [], []
    total = 0
    while total < n_agents:
        if len(tiles) == MAX_TILES:
            raise ValueError(f"dense_scene: {MAX_TILES} tiles hold only {total} agents, fewer than {n_agents}")
        kind = SCENARIO_TYPES[int(rng.integers(len(SCENARIO_TYPES)))]
        kinds.append(kind)
        seeds.append(int(rng.integers(2**31 - 1)))
        tile = generate_scene(kind, seeds[-1], TILE_PARAMS)
        tiles.append(tile)
        total += tile.num_agents
    T = max(t.num_steps for t in tiles)
    if any(t.num_steps != T or t.dt != tiles[0].dt for t in tiles):
        raise ValueError("dense_scene: tiles differ in steps or dt")
    return tiles, kinds, seeds


def _tile_shifts(tiles: list[Scene], gap: float) -> list[np.ndarray]:
    """The offset of each tile that lays the tiles on a square grid, each road bounding box centred in its
    cell, cells `gap` metres wider than the largest box."""
    lo = np.array([t.road_points.min(0) for t in tiles])
    hi = np.array([t.road_points.max(0) for t in tiles])
    pitch = float((hi - lo).max()) + gap
    cols = math.ceil(math.sqrt(len(tiles)))
    return [np.array([(i % cols) * pitch, (i // cols) * pitch], np.float32) - 0.5 * (lo[i] + hi[i])
            for i in range(len(tiles))]


def _agent_fields(tiles: list[Scene], shift: list[np.ndarray], n_agents: int) -> dict[str, np.ndarray]:
    """The agent fields of the dense scene: every tile whole, the last one cut to reach exactly `n_agents`;
    positions and goals shifted with their tile, ids renumbered, one logging vehicle (the first tile's)."""
    keep = []
    left = n_agents
    for t in tiles:
        keep.append(min(t.num_agents, left))
        left -= keep[-1]

    def agents_of(name: str, offset: bool = False) -> np.ndarray:
        parts = []
        for t, k, d in zip(tiles, keep, shift):
            x = getattr(t, name)[:k]
            parts.append(x + d if offset else x)
        return np.concatenate(parts)

    log_valid = agents_of("log_valid")
    log_pos = np.where(log_valid[..., None], agents_of("log_pos", offset=True), 0.0).astype(np.float32)
    is_sdc = agents_of("is_sdc")
    if is_sdc.sum() > 1:  # one logging vehicle per scene, as in WOMD: the first tile's
        is_sdc[np.nonzero(is_sdc)[0][1:]] = False
    return dict(log_pos=log_pos, log_yaw=agents_of("log_yaw"), log_vel=agents_of("log_vel"), log_valid=log_valid,
                length=agents_of("length"), width=agents_of("width"), height=agents_of("height"),
                agent_type=agents_of("agent_type"), agent_id=np.arange(n_agents, dtype=np.int64),
                goal=agents_of("goal", offset=True), is_sdc=is_sdc, is_interest=agents_of("is_interest"))


def _road_fields(tiles: list[Scene], shift: list[np.ndarray], n_points: int) -> tuple[dict[str, np.ndarray], float]:
    """The road fields of the dense scene: the tiles' polylines back to back, ids and lane edges renumbered,
    resampled evenly so that the map holds about `n_points` points. Returns (fields, the spacing in m)."""
    pts, offs, types, ids, edges = [], [0], [], [], []
    n_poly = 0
    for t, d in zip(tiles, shift):
        pts.append(t.road_points + d)
        offs.extend((t.road_offsets[1:] + offs[-1]).tolist())
        types.append(t.road_type)
        ids.append(np.arange(t.num_polylines, dtype=np.int64) + n_poly)
        edges.append(t.lane_edges + n_poly)
        n_poly += t.num_polylines
    points, offsets = np.concatenate(pts), np.asarray(offs, np.int64)
    lengths = _polyline_lengths(points, offsets)
    multi = np.diff(offsets) >= 2
    # each polyline of length L gets ceil(L / s) + 1 points: solve sum(L / s + 1) = n_points for s
    budget = n_points - int((~multi).sum()) - 1.5 * int(multi.sum())
    spacing = float(lengths[multi].sum()) / max(budget, 1.0)
    points, offsets = resample_polylines(points, offsets, max(spacing, 0.05))
    return dict(road_points=points, road_offsets=offsets, road_type=np.concatenate(types),
                road_id=np.concatenate(ids), lane_edges=np.concatenate(edges).astype(np.int32)), spacing


def dense_scene(seed: int, agents: int | None = None, road_points: int | None = None, gap: float = 30.0) -> Scene:
    """One dense scene from `seed`; `agents` / `road_points` fix the sizes (else drawn from
    DENSE_AGENTS / DENSE_ROAD_POINTS)."""
    rng = np.random.default_rng([seed, 0xD5])
    n_agents = int(agents if agents is not None else rng.integers(DENSE_AGENTS[0], DENSE_AGENTS[1] + 1))
    n_points = int(road_points if road_points is not None else rng.integers(DENSE_ROAD_POINTS[0],
                                                                           DENSE_ROAD_POINTS[1] + 1))
    if not 1 <= n_agents <= 1024 or n_points < 2:
        raise ValueError(f"dense_scene: agents must be 1..1024 and road_points >= 2, got {n_agents}, {n_points}")
    tiles, kinds, seeds = _draw_tiles(rng, n_agents)
    shift = _tile_shifts(tiles, gap)
    roads, spacing = _road_fields(tiles, shift, n_points)
    cp = tiles[0].metadata.get("conflict_point")
    scene = Scene(
        scene_id=f"dense-{seed}", **_agent_fields(tiles, shift, n_agents), **roads, dt=tiles[0].dt,
        metadata={"scenario_type": "dense", "source": "procedural:dense", "tile_types": kinds, "tile_seeds": seeds,
                  "road_spacing_m": spacing,
                  **({"conflict_point": (np.asarray(cp, np.float32) + shift[0]).tolist()} if cp is not None else {})},
    )
    return scene.validate(scene.scene_id)
