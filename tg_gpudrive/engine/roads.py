"""Road segments and grids of a batch's distinct scenes, built in one batched pass on the engine's device.

Every scene's polylines become segments of at most `max_segment_length` metres (a single-point
polyline becomes one degenerate segment); each scene gets a uniform grid of `road_cell_size` cells
over its segment midpoints, and the segments of all scenes are stored sorted by (scene, cell), so a
cell's segments are contiguous and a scene's cells follow each other:

    field         shape        meaning
    seg_a, seg_b  (S, 2) f32   m, segment end points, in (scene, cell) order (one zero row when S = 0)
    seg_mid       (S, 2) f32   m, their midpoints
    seg_type      (S,) int32   RoadType
    cell_start    (C + 1,)     int32, segments [cell_start[g], cell_start[g + 1]) lie in cell g
    origin        (n, 2) f32   m, grid corner of each scene; nx, ny (n,) int64 its cells
    cell_offset   (n,) int64   first cell of each scene
    segments      (n,) int64   segments of each scene
    max_len       float        m, the longest segment

The work is torch tensor operations over all scenes at once (the GPU when the engine runs there),
not a Python loop per scene: a batch of 4,096 distinct WOMD-size maps holds over 100 M segments.
The segments equal those of a per-scene NumPy reference (tests/reference.py `scene_segments`), in
the same order within each cell.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
import warp as wp

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.enums import POLYGON_ROAD_TYPES
from tg_gpudrive.kernels.road import launch_simplify
from tg_gpudrive.scene import Scene, SceneError

MAX_GRID_CELLS = 4_000_000  # per scene; a larger road extent needs a larger road_cell_size
CHUNK_POINTS = 20_000_000  # road points built at once (a few GB of work arrays)


@dataclasses.dataclass
class RoadTables:
    seg_a: torch.Tensor
    seg_b: torch.Tensor
    seg_mid: torch.Tensor
    seg_type: torch.Tensor
    cell_start: torch.Tensor
    origin: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    cell_offset: np.ndarray
    segments: np.ndarray
    max_len: float


def build_road_tables(scenes: list[Scene], cfg: EngineConfig, device: str,
                      chunk_points: int = CHUNK_POINTS) -> RoadTables:
    """Segments and grids of `scenes` (distinct scenes, in the order worlds refer to them), built in
    chunks of scenes holding about `chunk_points` road points each, so the work arrays (about 150
    bytes per segment) stay bounded however many scenes a batch holds."""
    chunks, cur, size = [], [], 0
    for sc in scenes:
        if cur and size + len(sc.road_points) > chunk_points:
            chunks.append(cur)
            cur, size = [], 0
        cur.append(sc)
        size += len(sc.road_points)
    chunks.append(cur)
    dev = torch.device(device)
    parts = [_build_chunk(c, cfg, dev) for c in chunks]
    tables = _nonempty(parts[0] if len(parts) == 1 else _concat(parts))
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)  # built on torch's stream; Warp's kernels read the tables on its own
        torch.cuda.empty_cache()  # the work arrays go back to the device, not to torch's cache
    return tables


def _concat(parts: list[RoadTables]) -> RoadTables:
    """The tables of consecutive chunks of scenes as one: segment and cell indices shifted."""
    seg_base = np.cumsum([0] + [int(p.segments.sum()) for p in parts[:-1]])
    cell_base = np.cumsum([0] + [len(p.cell_start) - 1 for p in parts[:-1]])
    return RoadTables(
        seg_a=torch.cat([p.seg_a for p in parts]), seg_b=torch.cat([p.seg_b for p in parts]),
        seg_mid=torch.cat([p.seg_mid for p in parts]), seg_type=torch.cat([p.seg_type for p in parts]),
        cell_start=torch.cat([p.cell_start[:-1] + int(b) for p, b in zip(parts, seg_base)]
                             + [parts[-1].cell_start[-1:] + int(seg_base[-1])]),
        origin=np.concatenate([p.origin for p in parts]), nx=np.concatenate([p.nx for p in parts]),
        ny=np.concatenate([p.ny for p in parts]),
        cell_offset=np.concatenate([p.cell_offset + b for p, b in zip(parts, cell_base)]),
        segments=np.concatenate([p.segments for p in parts]), max_len=max(p.max_len for p in parts))


def _nonempty(t: RoadTables) -> RoadTables:
    """A batch without any road keeps one zero segment, which no grid cell reaches: the kernels'
    segment arrays are never empty. `segments` still counts none."""
    if len(t.seg_a) == 0:
        t.seg_a = t.seg_b = t.seg_mid = t.seg_a.new_zeros((1, 2))
        t.seg_type = t.seg_type.new_zeros(1)
    return t


def _simplified(pts: torch.Tensor, off: torch.Tensor, ptype: torch.Tensor, tolerance: float):
    """The points RDP keeps at `tolerance` (kernels/road.py simplify_kernel) and the polylines' new
    offsets: straight runs of densely sampled roads collapse to their ends, so the `road_k` nearest
    segments an agent observes reach metres ahead instead of a few half-metre pieces around it."""
    if len(pts) == 0:
        return pts, off
    counts = (off[1:] - off[:-1]).to(torch.int32)
    polygon = torch.isin(ptype, torch.tensor([int(t) for t in POLYGON_ROAD_TYPES], device=ptype.device)).to(torch.int32)
    starts = off[:-1].to(torch.int32)
    keep = torch.empty(len(pts), dtype=torch.int32, device=pts.device)
    stack = torch.empty(2 * len(pts), dtype=torch.int32, device=pts.device)
    args = (wp.from_torch(pts.contiguous(), dtype=wp.vec2), wp.from_torch(starts), wp.from_torch(counts),
            wp.from_torch(polygon), tolerance, wp.from_torch(stack), wp.from_torch(keep),
            wp.device_from_torch(pts.device))
    if pts.is_cuda:  # on torch's stream: the inputs are ready and the scratch is freed after the kernel
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(pts.device))):
            launch_simplify(*args)
    else:
        launch_simplify(*args)
    keep = keep.bool()
    before = torch.cat([keep.new_zeros(1, dtype=torch.long), torch.cumsum(keep.long(), 0)])
    return pts[keep], before[off]


def _build_chunk(scenes: list[Scene], cfg: EngineConfig, dev: torch.device) -> RoadTables:
    n = len(scenes)
    # host: the scenes' polylines back to back (one copy of the points); everything else on `dev`
    n_pts = np.array([len(s.road_points) for s in scenes], np.int64)
    n_poly = np.array([s.num_polylines for s in scenes], np.int64)
    pts = torch.from_numpy(np.concatenate([np.asarray(s.road_points, np.float32).reshape(-1, 2) for s in scenes]
                                          + [np.zeros((0, 2), np.float32)])).to(dev)
    pt_base = np.cumsum(n_pts) - n_pts
    off = np.concatenate([np.asarray(s.road_offsets[:-1], np.int64) + b for s, b in zip(scenes, pt_base)]
                         + [[int(n_pts.sum())]])
    off = torch.from_numpy(off).to(dev)
    ptype = torch.from_numpy(np.concatenate([np.asarray(s.road_type, np.int32) for s in scenes]
                                            + [np.zeros(0, np.int32)])).to(dev)
    if cfg.road_simplify > 0:
        pts, off = _simplified(pts, off, ptype, cfg.road_simplify)
    poly_scene = torch.repeat_interleave(torch.arange(n, device=dev), torch.from_numpy(n_poly).to(dev))
    counts = off[1:] - off[:-1]  # points per polyline (>= 1 in a validated scene)

    # segments between consecutive points of one polyline, then single points as degenerate segments
    P = pts.shape[0]
    same = torch.ones(max(P - 1, 0), dtype=torch.bool, device=dev)
    ends = off[1:-1] - 1  # a polyline's last point, followed by the next polyline's first
    same[ends[(ends >= 0) & (ends < P - 1)]] = False
    starts = torch.nonzero(same)[:, 0]
    pair_poly = torch.repeat_interleave(torch.arange(len(counts), device=dev), (counts - 1).clamp(min=0))
    single = torch.nonzero(counts == 1)[:, 0]
    a = torch.cat([pts[starts], pts[off[single]]])
    b = torch.cat([pts[starts + 1], pts[off[single]]])
    poly = torch.cat([pair_poly, single])
    d = b - a
    length = torch.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    pieces = torch.clamp(torch.ceil(length / cfg.max_segment_length).long(), min=1)
    rep = torch.repeat_interleave(torch.arange(len(a), device=dev), pieces)
    k = torch.arange(len(rep), device=dev) - torch.repeat_interleave(torch.cumsum(pieces, 0) - pieces, pieces)
    f0 = (k.double() / pieces[rep].double()).float()[:, None]
    f1 = ((k + 1).double() / pieces[rep].double()).float()[:, None]
    a, d = a[rep], d[rep]
    seg_a, seg_b = a + f0 * d, a + f1 * d
    seg_type, seg_scene = ptype[poly][rep], poly_scene[poly][rep]
    mid = 0.5 * (seg_a + seg_b)
    del a, d, f0, f1, rep, k

    # one grid per scene over its midpoints: corner, size, cell of each segment
    cell = float(cfg.road_cell_size)
    big = torch.finfo(torch.float32).max
    idx2 = seg_scene[:, None].expand(-1, 2)
    lo = torch.full((n, 2), big, device=dev).scatter_reduce(0, idx2, mid, "amin") - 1e-3
    hi = torch.full((n, 2), -big, device=dev).scatter_reduce(0, idx2, mid, "amax")
    segments = torch.bincount(seg_scene, minlength=n)
    has = segments > 0
    size = torch.where(has[:, None], torch.floor((hi - lo) / cell).long() + 1, torch.zeros_like(hi, dtype=torch.long))
    lo = torch.where(has[:, None], lo, torch.zeros_like(lo))
    cells = size[:, 0] * size[:, 1]
    too_big = torch.nonzero(cells > MAX_GRID_CELLS)[:, 0].tolist()
    if too_big:
        s = too_big[0]
        extent = (hi[s] - lo[s]).tolist()
        raise SceneError(scenes[s].scene_id, "roads.geometry", f"road extent {extent} m needs {int(cells[s])} "
                         "grid cells; raise road_cell_size")
    cell_offset = torch.cumsum(cells, 0) - cells
    nx = size[seg_scene, 0]
    ix = torch.minimum(torch.floor((mid[:, 0] - lo[seg_scene, 0]) / cell).long().clamp(min=0), nx - 1)
    iy = torch.minimum(torch.floor((mid[:, 1] - lo[seg_scene, 1]) / cell).long().clamp(min=0),
                       size[seg_scene, 1] - 1)
    key = cell_offset[seg_scene] + iy * nx + ix
    del ix, iy, nx
    key, order = torch.sort(key, stable=True)
    C = int(cells.sum())
    cell_start = torch.zeros(C + 1, dtype=torch.int64, device=dev)
    cell_start[1:] = torch.cumsum(torch.bincount(key, minlength=C), 0)
    del key
    seg_len = torch.linalg.vector_norm(seg_b - seg_a, dim=1)
    return RoadTables(
        seg_a=seg_a[order].contiguous(), seg_b=seg_b[order].contiguous(), seg_mid=mid[order].contiguous(),
        seg_type=seg_type[order].to(torch.int32).contiguous(), cell_start=cell_start.to(torch.int32),
        origin=lo.cpu().numpy().astype(np.float32), nx=size[:, 0].cpu().numpy(), ny=size[:, 1].cpu().numpy(),
        cell_offset=cell_offset.cpu().numpy(), segments=segments.cpu().numpy(),
        max_len=float(seg_len.max()) if len(seg_len) else 0.0)
