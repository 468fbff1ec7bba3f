"""Model / State / Control of the batched engine, and the builder from Scenes.

W worlds x A agent slots; slot i = w * A + a in every flat array. T logged
steps (the longest scene; shorter scenes are padded invalid). S road
segments over all worlds (CSR by world).

Model (fixed while a batch of scenes is loaded):

    field               shape           dtype   unit / meaning
    slot_valid          (W*A,)          int32   slot holds an agent
    controlled          (W*A,)          int32   integrated from the action buffers (else log replay)
    background          (W*A,)          int32   controlled, but driven by a background model (reactive
                                                traffic), not the policy; outcomes count for the policy only
    agent_type          (W*A,)          int32   AgentType
    length, width       (W*A,)          f32     m
    goal                (W*A,)          vec2    m
    log_pos             (W*A, T)        vec2    m
    log_yaw             (W*A, T)        f32     rad
    log_vel             (W*A, T)        vec2    m/s
    log_valid           (W*A, T)        int32
    expert_action       (W*A, T)        vec3    action taking step t to t+1 (a, kappa, 0) or (dx, dy, dyaw)
    expert_index        (W*A, T)        int32   nearest grid index of it, -1 when there is no expert action
    expert_track        (W*A, T)        vec2    m, positions the expert actions produce from init_step
    last_step           (W,)            int32   last logged step of the world's scene
    collision_cell_size (W,)            f32     m, agent broad-phase cell
    seg_a, seg_b        (S,)            vec2    m, road segment end points
    seg_type            (S,)            int32   RoadType
    world_seg_offset    (W+1,)          int64   (host) segments of world w
    grid_origin         (W,)            vec2    m, road grid corner
    grid_nx, grid_ny    (W,)            int32   road grid size in cells
    grid_cell_offset    (W,)            int32   first cell of world w
    cell_start          (C+1,)          int32   CSR of segments per cell
    cell_items          (S,)            int32   segment index

State (changes every step): pos/vel (W*A,) vec2, yaw/speed (W*A,) f32,
step (W,) int32, world_ended / world_reset / world_done (W,) int32, flags present/alive/active/agent_done/removed/collided/
offroad/goal_event/terminated/truncated (W*A,) int32, episode accumulators
ep_* and the outcomes of the last finished episode final_* (W*A,), world_reset
and world_truncated (W,), reward (W*A,), reward_terms (W*A, NUM_TERMS),
cost (W*A,), obs (W*A, obs_dim), and the scratch of the broad phases.

Control: action (W*A,) vec3 (continuous), action_index (W*A,) int32 (discrete).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import warp as wp

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.kernels.reward import NUM_TERMS, REWARD_TERMS
from tg_gpudrive.scene import Scene, SceneError
from tg_gpudrive.types import AgentType, CollisionMode, parse_enum

log = logging.getLogger("tg_gpudrive")

GOAL_BEHAVIOURS = {"continue": 0, "stop": 1, "remove": 2}


def obs_dim(cfg: EngineConfig) -> int:
    return EGO_DIM + cfg.partner_k * PARTNER_DIM + cfg.road_k * ROAD_DIM


@dataclasses.dataclass
class BuildReport:
    """What the builder dropped or changed, per world, so nothing is lost silently."""

    truncated_agents: list[int]  # agents beyond max_agents, per world
    controlled: list[int]  # policy-controlled agents per world (background-driven ones not counted)
    skipped_at_goal: list[int]  # vehicles not controlled because they start within goal_radius
    segments: list[int]  # road segments per world after splitting

    @property
    def total_truncated(self) -> int:
        return int(sum(self.truncated_agents))


# ------------------------------------------------------------------ selection
def agents_needed(scene: Scene) -> int:
    """Slots `scene` needs to keep every agent: those valid at some step (the ones `select_slots` keeps)."""
    return int(scene.log_valid.any(axis=1).sum())


def select_slots(scene: Scene, max_agents: int, init_step: int) -> np.ndarray:
    """Indices of the agents that get slots, most relevant first.

    Order: the SDC, objects of interest, agents valid at `init_step`,
    vehicles, then nearest to the SDC (or the scene centre)."""
    init = min(init_step, scene.num_steps - 1)
    valid_any = scene.log_valid.any(axis=1)
    centre = scene.log_pos[scene.is_sdc, init].mean(0) if scene.is_sdc.any() else np.zeros(2, np.float32)
    dist = np.linalg.norm(scene.log_pos[:, init] - centre, axis=1)
    dist = np.where(scene.log_valid[:, init], dist, 1e9)
    keys = (dist, ~(scene.agent_type == AgentType.VEHICLE), ~scene.log_valid[:, init], ~scene.is_interest,
            ~scene.is_sdc)
    order = np.lexsort(keys)
    order = order[valid_any[order]]
    return np.sort(order[:max_agents])


def default_controlled(scene: Scene, idx: np.ndarray, cfg: EngineConfig) -> tuple[np.ndarray, int]:
    """Controlled mask over the selected agents and the count skipped for starting at their goal."""
    if cfg.control == "none":
        return np.zeros(len(idx), bool), 0
    init = min(cfg.init_steps, scene.num_steps - 1)
    ok = scene.log_valid[idx, init].copy()
    if cfg.control == "vehicles":
        ok &= scene.agent_type[idx] == AgentType.VEHICLE
    at_goal = np.linalg.norm(scene.log_pos[idx, init] - scene.goal[idx], axis=1) < cfg.goal_radius
    return ok & ~at_goal, int((ok & at_goal).sum())


# --------------------------------------------------------------------- roads
def scene_segments(scene: Scene, max_len: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Road polylines as segments of at most `max_len` metres: (a (S,2), b (S,2), type (S,))."""
    pts, off = scene.road_points, scene.road_offsets
    if scene.num_polylines == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32), np.zeros(0, np.int32)
    counts = np.diff(off)
    # a segment between consecutive points of the same polyline; single points become degenerate segments
    starts = np.arange(len(pts) - 1)
    same = np.searchsorted(off, starts, side="right") == np.searchsorted(off, starts + 1, side="right")
    a, b = pts[starts[same]], pts[starts[same] + 1]
    types = scene.road_type[np.searchsorted(off, starts[same], side="right") - 1]
    single = np.nonzero(counts == 1)[0]
    a = np.concatenate([a, pts[off[single]]])
    b = np.concatenate([b, pts[off[single]]])
    types = np.concatenate([types, scene.road_type[single]]).astype(np.int32)
    seg_len = np.linalg.norm(b - a, axis=1)
    pieces = np.maximum(1, np.ceil(seg_len / max_len).astype(np.int64))
    rep = np.repeat(np.arange(len(a)), pieces)
    k = np.arange(len(rep)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    f0 = (k / pieces[rep])[:, None].astype(np.float32)
    f1 = ((k + 1) / pieces[rep])[:, None].astype(np.float32)
    d = (b - a)[rep]
    return (a[rep] + f0 * d).astype(np.float32), (a[rep] + f1 * d).astype(np.float32), types[rep]


def build_road_grid(mid: np.ndarray, cell: float) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
    """Uniform grid over segment midpoints: origin, nx, ny, cell_start (nx*ny+1), items (S)."""
    if len(mid) == 0:
        return np.zeros(2, np.float32), 0, 0, np.zeros(1, np.int32), np.zeros(0, np.int32)
    lo = mid.min(0) - 1e-3
    hi = mid.max(0)
    nx, ny = (np.floor((hi - lo) / cell).astype(np.int64) + 1).tolist()
    if nx * ny > 4_000_000:
        raise SceneError("roads", "geometry", f"road extent {hi - lo} m needs {nx * ny} grid cells; "
                         "raise road_cell_size")
    ix = np.clip(np.floor((mid[:, 0] - lo[0]) / cell).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor((mid[:, 1] - lo[1]) / cell).astype(np.int64), 0, ny - 1)
    cid = iy * nx + ix
    items = np.argsort(cid, kind="stable").astype(np.int32)
    start = np.zeros(nx * ny + 1, np.int64)
    np.add.at(start, cid + 1, 1)
    return lo.astype(np.float32), nx, ny, np.cumsum(start).astype(np.int32), items


# --------------------------------------------------------------------- model
class Model:
    """Fixed arrays of a batch of scenes (see the module docstring for fields)."""

    def __init__(self, scenes: list[Scene], cfg: EngineConfig, device: str,
                 controlled: list[np.ndarray] | None = None, background: list[np.ndarray] | None = None):
        if not scenes:
            raise ValueError("Model needs at least one scene")
        self.cfg, self.device = cfg, device
        W, A = len(scenes), cfg.max_agents
        T = max(s.num_steps for s in scenes)
        if T <= cfg.init_steps + 1:
            raise SceneError(scenes[0].scene_id, "log", f"{T} steps leave nothing after init_steps={cfg.init_steps}")
        self.num_worlds, self.max_agents, self.num_steps = W, A, T
        self.num_slots = W * A
        self.dt = float(scenes[0].dt)
        self.init_step = cfg.init_steps
        self.dynamics = 0 if cfg.dynamics == "bicycle" else 1
        self.discrete = int(cfg.action_space == "discrete")
        self.collision_mode = int(parse_enum(CollisionMode, cfg.collision_mode, "collision_mode"))
        self.goal_behaviour = GOAL_BEHAVIOURS[cfg.goal_behaviour]
        self.collision_cells = cfg.collision_cells
        self.auto_reset = int(cfg.auto_reset)
        self.obs_dim = obs_dim(cfg)
        self.road_cell_size = float(cfg.road_cell_size)
        self.scenes = scenes

        h = {  # host arrays, (W, A, ...)
            "slot_valid": np.zeros((W, A), np.int32), "controlled": np.zeros((W, A), np.int32),
            "background": np.zeros((W, A), np.int32),
            "agent_type": np.zeros((W, A), np.int32), "length": np.ones((W, A), np.float32),
            "width": np.ones((W, A), np.float32), "goal": np.zeros((W, A, 2), np.float32),
            "log_pos": np.zeros((W, A, T, 2), np.float32), "log_yaw": np.zeros((W, A, T), np.float32),
            "log_vel": np.zeros((W, A, T, 2), np.float32), "log_valid": np.zeros((W, A, T), np.int32),
        }
        self.slot_agent = np.full((W, A), -1, np.int64)  # scene agent index of each slot
        last_step = np.zeros(W, np.int32)
        cell = np.zeros(W, np.float32)
        report = BuildReport([], [], [], [])
        seg_a, seg_b, seg_t, seg_off = [], [], [], [0]
        grid_origin = np.zeros((W, 2), np.float32)
        grid_nx, grid_ny, grid_off = np.zeros(W, np.int32), np.zeros(W, np.int32), np.zeros(W, np.int32)
        cell_start, cell_items, n_cells, n_seg = [], [], 0, 0
        for w, sc in enumerate(scenes):
            if abs(sc.dt - self.dt) > 1e-9:
                raise SceneError(sc.scene_id, "dt", f"all scenes of a batch need one dt; {sc.dt} != {self.dt}")
            idx = select_slots(sc, A, cfg.init_steps)
            dropped = agents_needed(sc) - len(idx)
            if dropped > 0:
                log.info("scene %s: %d agents beyond max_agents=%d were dropped (least relevant first)",
                         sc.scene_id, dropped, A)
            report.truncated_agents.append(max(dropped, 0))
            n, t = len(idx), sc.num_steps
            if controlled is not None:
                ctrl = np.asarray(controlled[w], bool)[idx]
                skipped = 0
            else:
                ctrl, skipped = default_controlled(sc, idx, cfg)
            bg = np.zeros(len(idx), bool) if background is None else np.asarray(background[w], bool)[idx] & ~ctrl
            # policy agents take the first slots (a learner views obs[:, :max_controlled]), then the
            # background-driven ones, then the replayed ones
            order = np.lexsort((bg, ~(ctrl | bg)))
            idx, ctrl, bg = idx[order], ctrl[order], bg[order]
            report.controlled.append(int(ctrl.sum()))
            report.skipped_at_goal.append(skipped)
            self.slot_agent[w, :n] = idx
            h["slot_valid"][w, :n] = 1
            h["controlled"][w, :n] = ctrl | bg
            h["background"][w, :n] = bg
            h["agent_type"][w, :n] = sc.agent_type[idx]
            h["length"][w, :n] = sc.length[idx]
            h["width"][w, :n] = sc.width[idx]
            h["goal"][w, :n] = sc.goal[idx]
            h["log_pos"][w, :n, :t] = sc.log_pos[idx]
            h["log_yaw"][w, :n, :t] = sc.log_yaw[idx]
            h["log_vel"][w, :n, :t] = sc.log_vel[idx]
            h["log_valid"][w, :n, :t] = sc.log_valid[idx]
            last_step[w] = t - 1
            diag = np.sqrt(sc.length[idx] ** 2 + sc.width[idx] ** 2).max() if n else 1.0
            cell[w] = max(float(diag), cfg.beta, 1.0) * 1.001

            a, b, ty = scene_segments(sc, cfg.max_segment_length)
            origin, nx, ny, start, items = build_road_grid(0.5 * (a + b), self.road_cell_size)
            seg_a.append(a), seg_b.append(b), seg_t.append(ty)
            grid_origin[w], grid_nx[w], grid_ny[w], grid_off[w] = origin, nx, ny, n_cells
            cell_start.append(start[:-1] + n_seg)
            cell_items.append(items + n_seg)
            n_cells += nx * ny
            n_seg += len(a)
            seg_off.append(n_seg)
            report.segments.append(len(a))
        cell_start.append(np.array([n_seg], np.int32))
        self.report = report
        self.max_controlled = max(report.controlled)
        self.world_seg_offset = np.asarray(seg_off, np.int64)
        all_a = np.concatenate(seg_a) if n_seg else np.zeros((1, 2), np.float32)
        all_b = np.concatenate(seg_b) if n_seg else np.zeros((1, 2), np.float32)
        seg_len = np.linalg.norm(all_b - all_a, axis=1)
        self.seg_pad = float(0.5 * seg_len.max()) + 1e-3 if n_seg else 0.0
        self.host = h

        dev = device
        def flat(x, dtype):
            return wp.array(x.reshape(W * A, *x.shape[2:]), dtype=dtype, device=dev)

        self.slot_valid = flat(h["slot_valid"], wp.int32)
        self.controlled = flat(h["controlled"], wp.int32)
        self.background = flat(h["background"], wp.int32)
        self.agent_type = flat(h["agent_type"], wp.int32)
        self.length = flat(h["length"], float)
        self.width = flat(h["width"], float)
        self.goal = flat(h["goal"], wp.vec2)
        self.log_pos = wp.array(h["log_pos"].reshape(W * A, T, 2), dtype=wp.vec2, device=dev)
        self.log_yaw = wp.array(h["log_yaw"].reshape(W * A, T), dtype=float, device=dev)
        self.log_vel = wp.array(h["log_vel"].reshape(W * A, T, 2), dtype=wp.vec2, device=dev)
        self.log_valid = wp.array(h["log_valid"].reshape(W * A, T), dtype=wp.int32, device=dev)
        self.last_step = wp.array(last_step, dtype=wp.int32, device=dev)
        self.collision_cell_size = wp.array(cell, dtype=float, device=dev)
        self.seg_a = wp.array(all_a, dtype=wp.vec2, device=dev)
        self.seg_b = wp.array(all_b, dtype=wp.vec2, device=dev)
        self.seg_type = wp.array(np.concatenate(seg_t) if n_seg else np.zeros(1, np.int32), dtype=wp.int32,
                                 device=dev)
        self.grid_origin = wp.array(grid_origin, dtype=wp.vec2, device=dev)
        self.grid_nx = wp.array(grid_nx, dtype=wp.int32, device=dev)
        self.grid_ny = wp.array(grid_ny, dtype=wp.int32, device=dev)
        self.grid_cell_offset = wp.array(grid_off, dtype=wp.int32, device=dev)
        self.cell_start = wp.array(np.concatenate(cell_start).astype(np.int32), dtype=wp.int32, device=dev)
        self.cell_items = wp.array(np.concatenate(cell_items).astype(np.int32) if n_seg else np.zeros(1, np.int32),
                                   dtype=wp.int32, device=dev)
        r = cfg.reward
        self.reward_weights = wp.array(np.array([getattr(r, k) for k in REWARD_TERMS], np.float32),
                                       dtype=float, device=dev)
        self.expert_action = wp.zeros((W * A, T), dtype=wp.vec3, device=dev)
        self.expert_index = wp.zeros((W * A, T), dtype=wp.int32, device=dev)
        self.expert_track = wp.zeros((W * A, T), dtype=wp.vec2, device=dev)

        from tg_gpudrive.kernels.dynamics import launch_expert_actions

        launch_expert_actions(self, cfg)


class State:
    """Per-step arrays (see the engine module docstring)."""

    INT_FIELDS = ("present", "alive", "active", "agent_done", "removed", "collided", "offroad", "goal_event",
                  "terminated", "truncated", "ep_collided", "ep_offroad", "ep_goal", "ep_steps", "final_goal",
                  "final_collided", "final_offroad", "final_steps", "agent_cell")
    FLOAT_FIELDS = ("yaw", "speed", "goal_dist", "edge_dist", "lane_dist", "nearest", "reward", "cost",
                    "ep_return", "ep_cost", "ep_min_dist", "final_return", "final_cost", "final_min_dist")

    def __init__(self, model: Model, cfg: EngineConfig):
        n, W, dev = model.num_slots, model.num_worlds, model.device
        for name in self.INT_FIELDS:
            setattr(self, name, wp.zeros(n, dtype=wp.int32, device=dev))
        for name in self.FLOAT_FIELDS:
            setattr(self, name, wp.zeros(n, dtype=float, device=dev))
        self.pos = wp.zeros(n, dtype=wp.vec2, device=dev)
        self.vel = wp.zeros(n, dtype=wp.vec2, device=dev)
        self.applied_action = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.step = wp.zeros(W, dtype=wp.int32, device=dev)
        self.world_reset = wp.zeros(W, dtype=wp.int32, device=dev)
        self.world_ended = wp.zeros(W, dtype=wp.int32, device=dev)
        self.world_done = wp.zeros(W, dtype=wp.int32, device=dev)
        self.world_truncated = wp.zeros(W, dtype=wp.int32, device=dev)
        self.episode_count = wp.zeros(W, dtype=wp.int32, device=dev)
        self.bad_actions = wp.zeros(1, dtype=wp.int32, device=dev)  # unusable actions met by step_agents, summed
        self.reward_terms = wp.zeros((n, NUM_TERMS), dtype=float, device=dev)
        self.obs = wp.zeros((n, model.obs_dim), dtype=float, device=dev)
        # broad-phase scratch
        g = model.collision_cells
        self.grid_count = wp.zeros(W * g, dtype=wp.int32, device=dev)
        self.grid_start = wp.zeros(W * g, dtype=wp.int32, device=dev)
        self.grid_fill = wp.zeros(W * g, dtype=wp.int32, device=dev)
        self.grid_items = wp.zeros(n, dtype=wp.int32, device=dev)
        self.part_d = wp.zeros(max(n * cfg.partner_k, 1), dtype=float, device=dev)
        self.part_j = wp.zeros(max(n * cfg.partner_k, 1), dtype=wp.int32, device=dev)
        self.heap_d = wp.zeros(max(n * cfg.road_k, 1), dtype=float, device=dev)
        self.heap_j = wp.zeros(max(n * cfg.road_k, 1), dtype=wp.int32, device=dev)


class Control:
    def __init__(self, model: Model):
        self.action = wp.zeros(model.num_slots, dtype=wp.vec3, device=model.device)
        self.action_index = wp.zeros(model.num_slots, dtype=wp.int32, device=model.device)
