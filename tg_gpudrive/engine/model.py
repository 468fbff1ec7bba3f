"""Model / State / Control of the batched engine, and the builder from Scenes.

W worlds x A agent slots; slot i = w * A + a in every flat array. T logged
steps (the longest scene; shorter scenes are padded invalid). S road
segments over the batch's distinct scenes: worlds that hold the same Scene object share its
segments and grid cells (kernels reach a world's segments only through its grid).

Model (fixed while a batch of scenes is loaded; every kernel scalar is copied
here from the EngineConfig once, so launchers read the Model, never the config):

    field               shape           dtype   unit / meaning
    slot_valid          (W*A,)          int32   slot holds an agent
    integrated          (W*A,)          int32   moved from the action buffers (policy + background), else log replay
    background          (W*A,)          int32   integrated, but driven by a background model (reactive
                                                traffic), not the policy; outcomes count for the policy only
    agent_type          (W*A,)          int32   AgentType
    length, width       (W*A,)          f32     m
    goal                (W*A,)          vec2    m
    log_row             (W*A,)          int32   row of the slot in the log and expert arrays below, which hold
                                                one row per agent slot of a distinct slot plan (P plans: worlds
                                                that share a scene and masks share rows; P = W when all differ)
    log_pos             (P*A, T)        vec2    m
    log_yaw             (P*A, T)        f32     rad
    log_vel             (P*A, T)        vec2    m/s
    log_valid           (P*A, T)        int32
    expert_action       (P*A, T)        vec3    action taking step t to t+1 (a, kappa, 0) or (dx, dy, dyaw)
    expert_index        (P*A, T)        int32   nearest grid index of it, -1 when there is no expert action
    expert_track        (P*A, T)        vec2    m, positions the expert actions produce from init_step
    last_step           (W,)            int32   last logged step of the world's scene
    collision_cell_size (W,)            f32     m, agent broad-phase cell, >= the largest box diagonal and >= beta
    nearest_cap         (W,)            f32     m, cap of State.nearest (and so of ep_min_dist, mean_min_distance):
                                                the broad phase sees one cell around an agent, so this is the
                                                cell size; the cost (nearest < beta) is exact as it is >= beta
    seg_a, seg_b        (S,)            vec2    m, road segment end points; a world's segments are stored
                                                in the order of its grid cells, so a cell's are contiguous
    seg_mid             (S,)            vec2    m, their midpoints (the road observation's distance)
    seg_type            (S,)            int32   RoadType
    grid_origin         (W,)            vec2    m, road grid corner
    grid_nx, grid_ny    (W,)            int32   road grid size in cells
    grid_cell_offset    (W,)            int32   first cell of world w
    cell_start          (C+1,)          int32   segments [cell_start[g], cell_start[g+1]) lie in cell g;
                                                C cells over the distinct scenes
    reward_weights      (NUM_TERMS,)    f32     weights of REWARD_TERMS

    scalar              meaning
    dt, init_step       s per step; log step episodes start from
    dynamics, discrete  Dynamics value; 1 for grid-index actions
    collision_mode      CollisionMode value
    goal_behaviour      GoalBehaviour value
    auto_reset          1: a world resets inside the step its episode ends
    max_accel, max_curvature, accel_bins, curvature_bins, delta_max     the action box and grid
    goal_radius, beta, cost_shape, cost_players, cost_collision, speed_limit, lane_cap  reward and cost parameters
    cost_horizon        s, the cost's distance is the least over this look-ahead (0: now)
    ttc_on, ttc_horizon 1: the reward weights the ttc term, so ttc_kernel runs; its horizon (s)
    partner_k, partner_radius, road_k, road_radius, obs_dim             observation layout
    view_cos            cos of half the view cone (EngineConfig.view_angle): partners and road
                        points outside it are not observed; -1 sees all around
    road_query_radius, road_cell_size, seg_pad, collision_cells         road queries and broad phases
    parallel_road_rows  road heaps strided across slots and rows ordered by parallel ranks (True on
                        CUDA), or contiguous heaps heap-sorted by each agent's thread (kernels/observation.py)

State: see `State` (its shape table is built from the field declarations, which also
make the Simulator's torch views). Control: action (W*A,) vec3 (continuous),
action_index (W*A,) int32 (discrete).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import logging
import time
from typing import Generic, TypeVar

import numpy as np
import warp as wp

from tg_gpudrive.config import COST_PARTNERS, COST_SHAPES, EngineConfig
from tg_gpudrive.data.log_audit import candidates
from tg_gpudrive.engine.control import exclusions, init_index, select_slots, slot_masks
from tg_gpudrive.engine.roads import build_road_tables
from tg_gpudrive.kernels.dynamics import launch_expert_actions
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.kernels.reward import NUM_TERMS, REWARD_TERMS
from tg_gpudrive.scene import Scene, SceneError
from tg_gpudrive.enums import ActionSpace

log = logging.getLogger("tg_gpudrive")


def obs_dim(cfg: EngineConfig) -> int:
    return EGO_DIM + cfg.partner_k * PARTNER_DIM + cfg.road_k * ROAD_DIM


@dataclasses.dataclass
class BuildReport:
    """What the builder dropped or changed, per world, so nothing is lost silently."""

    truncated_agents: list[int]  # agents beyond max_agents, per world
    controlled: list[int]  # the policy's agents per world (background-driven ones not counted)
    skipped_at_goal: list[int]  # vehicles not controlled because they start within goal_radius
    segments: list[int]  # road segments per world after splitting
    marked_expert: list[int] = dataclasses.field(default_factory=list)  # candidates replayed: mark_as_expert
    log_infeasible: list[int] = dataclasses.field(default_factory=list)  # candidates replayed: infeasible log

    @property
    def total_truncated(self) -> int:
        return int(sum(self.truncated_agents))


def agents_needed(scene: Scene) -> int:
    """Slots `scene` needs to keep every agent: those valid at some step (the ones `select_slots` keeps)."""
    return int(scene.log_valid.any(axis=1).sum())


def sized_for(cfg: EngineConfig, scenes) -> EngineConfig:
    """`cfg` with max_agents raised to the most agents any of `scenes` needs (`agents_needed`), so a
    batch of them drops no agent; unchanged when it already holds them all."""
    need = max((agents_needed(s) for s in scenes), default=0)
    return cfg if need <= cfg.max_agents else dataclasses.replace(cfg, max_agents=need)


# --------------------------------------------------------------------- slots
@dataclasses.dataclass
class SlotPlan:
    """Which agents of a scene fill a world's slots and who drives them, for one scene and its control
    masks; the Model builds one per distinct (scene, masks) pair of a batch."""

    scene: Scene
    idx: np.ndarray  # (n,) scene agent of each slot: the policy's first, then background, then replayed
    policy: np.ndarray  # (n,) bool
    background: np.ndarray  # (n,) bool
    skipped_at_goal: int
    dropped: int  # agents beyond max_agents
    cell: float  # m, collision broad-phase cell
    marked: int = 0  # vehicles the control rule would drive but the source marks mark_as_expert: replayed
    infeasible: int = 0  # the same for log-infeasible agents (data.log_audit): replayed

    @classmethod
    def build(cls, scene: Scene, cfg: EngineConfig, controlled: np.ndarray | None,
              background: np.ndarray | None) -> SlotPlan:
        idx = select_slots(scene, cfg.max_agents, cfg.init_steps)
        dropped = agents_needed(scene) - len(idx)
        policy, bg, skipped = slot_masks(scene, idx, cfg, controlled, background)
        # policy agents take the first slots (a learner views obs[:, :max_controlled]), then the
        # background-driven ones, then the replayed ones
        order = np.lexsort((bg, ~(policy | bg)))
        idx, policy, bg = idx[order], policy[order], bg[order]
        diag = np.sqrt(scene.length[idx] ** 2 + scene.width[idx] ** 2).max() if len(idx) else 1.0
        cell = float(np.float32(max(float(diag), cfg.beta, 1.0) * 1.001))
        # the collision pass visits the 3 x 3 cells around an agent, so it finds every partner
        # within one cell size and reports `nearest` capped there (nearest_cap); the cost
        # (nearest < beta) is exact only while no partner within beta can be missed
        assert cell >= cfg.beta, "broad-phase cell smaller than beta: the distance cost would miss partners"
        ex = exclusions(scene, cfg)
        cand = candidates(scene, init_index(scene, cfg), cfg.goal_radius)[idx]
        return cls(scene, idx, policy, bg, skipped, dropped, cell, int((ex["mark_as_expert"][idx] & cand).sum()),
                   int((ex["log_infeasible"][idx] & cand).sum()))


def _plan_arrays(plan_list: list[SlotPlan], A: int, T: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Host arrays of the distinct slot plans, (G, A, ...) each, named as the Model's fields (worlds index
    them by world_plan), and the scene agent of each plan slot (G, A) (-1: empty)."""
    G = len(plan_list)
    g = {
        "slot_valid": np.zeros((G, A), np.int32), "integrated": np.zeros((G, A), np.int32),
        "background": np.zeros((G, A), np.int32),
        "agent_type": np.zeros((G, A), np.int32), "length": np.ones((G, A), np.float32),
        "width": np.ones((G, A), np.float32), "goal": np.zeros((G, A, 2), np.float32),
        "log_pos": np.zeros((G, A, T, 2), np.float32), "log_yaw": np.zeros((G, A, T), np.float32),
        "log_vel": np.zeros((G, A, T, 2), np.float32), "log_valid": np.zeros((G, A, T), np.int32),
    }
    plan_agent = np.full((G, A), -1, np.int64)
    for k, p in enumerate(plan_list):
        sc, idx = p.scene, p.idx
        n, t = len(idx), sc.num_steps
        plan_agent[k, :n] = idx
        g["slot_valid"][k, :n] = 1
        g["integrated"][k, :n] = p.policy | p.background
        g["background"][k, :n] = p.background
        g["agent_type"][k, :n] = sc.agent_type[idx]
        g["length"][k, :n] = sc.length[idx]
        g["width"][k, :n] = sc.width[idx]
        g["goal"][k, :n] = sc.goal[idx]
        g["log_pos"][k, :n, :t] = sc.log_pos[idx]
        g["log_yaw"][k, :n, :t] = sc.log_yaw[idx]
        g["log_vel"][k, :n, :t] = sc.log_vel[idx]
        g["log_valid"][k, :n, :t] = sc.log_valid[idx]
    return g, plan_agent


# --------------------------------------------------------------------- model
class Model:
    """Fixed arrays and scalars of a batch of scenes (see the module docstring for fields).

    Work that depends only on a scene is done once per distinct scene of the batch (the same
    Scene object in many worlds, as when a few scenes are cycled over thousands of worlds): slot
    selection, logs and expert actions once per distinct (scene, masks) pair, road grids once per
    scene, which the worlds then share (their slots reach the logs through `log_row`).
    `build_seconds` holds the build's phases: host (slot plans, per-world tables), roads (segments
    and grids of the distinct scenes, batched on the device: engine/roads.py), upload, expert
    (expert actions of the distinct plans)."""

    def __init__(self, scenes: list[Scene], cfg: EngineConfig, device: str,
                 controlled: list[np.ndarray] | None = None, background: list[np.ndarray] | None = None):
        """`controlled` / `background`: per scene, (N,) bool masks of the policy's and the
        background model's agents (tg_gpudrive.engine.control); None: the engine default / nobody."""
        if not scenes:
            raise ValueError("Model needs at least one scene")
        t0 = time.perf_counter()
        self.cfg, self.device = cfg, device
        W, A = len(scenes), cfg.max_agents
        T = max(s.num_steps for s in scenes)
        if T <= cfg.init_steps + 1:
            raise SceneError(scenes[0].scene_id, "log", f"{T} steps leave nothing after init_steps={cfg.init_steps}")
        self.num_worlds, self.max_agents, self.num_steps = W, A, T
        self.num_slots = W * A
        self.dt = float(scenes[0].dt)
        self.scenes = scenes
        self._copy_scalars(cfg)
        self.parallel_road_rows = wp.get_device(device).is_cuda  # the same rows either way
        plan_list, road_scenes, world_road, report = self._plan_worlds(controlled, background)
        G = len(plan_list)
        seconds = {"host": time.perf_counter() - t0}
        t0 = time.perf_counter()
        roads_t = build_road_tables(road_scenes, cfg, device)  # on the device, all distinct scenes at once
        report.segments.extend(roads_t.segments[world_road].tolist())
        seconds["roads"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.report = report
        self.max_controlled = max(report.controlled)
        g, plan_agent = _plan_arrays(plan_list, A, T)
        self._plan_host = g
        self.slot_agent = plan_agent[self.world_plan]  # (W, A) scene agent index of each slot, -1: empty
        cell = np.array([p.cell for p in plan_list], np.float32)[self.world_plan]
        last_step = np.array([s.num_steps - 1 for s in scenes], np.int32)
        n_seg = int(roads_t.segments.sum())
        self.seg_pad = float(0.5 * roads_t.max_len) + 1e-3 if n_seg else 0.0
        grid = {"grid_origin": roads_t.origin[world_road], "grid_nx": roads_t.nx.astype(np.int32)[world_road],
                "grid_ny": roads_t.ny.astype(np.int32)[world_road],
                "grid_cell_offset": roads_t.cell_offset.astype(np.int32)[world_road]}
        seconds["host"] += time.perf_counter() - t0

        t0 = time.perf_counter()
        self._upload(g, G, cell, last_step, grid, roads_t)
        wp.synchronize_device(device)
        seconds["upload"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        self.expert_action = wp.zeros((G * A, T), dtype=wp.vec3, device=device)
        self.expert_index = wp.zeros((G * A, T), dtype=wp.int32, device=device)
        self.expert_track = wp.zeros((G * A, T), dtype=wp.vec2, device=device)
        launch_expert_actions(self)
        wp.synchronize_device(device)
        seconds["expert"] = time.perf_counter() - t0
        self.build_seconds = seconds

    def _plan_worlds(self, controlled: list[np.ndarray] | None, background: list[np.ndarray] | None
                     ) -> tuple[list[SlotPlan], list[Scene], np.ndarray, BuildReport]:
        """The slot plan of every world, built once per distinct (scene, masks) pair (`world_plan` indexes
        them), and the distinct scenes whose road grids the worlds share: (the distinct plans, the distinct
        scenes, the road grid of each world, the build report without its segments)."""
        scenes, cfg, A = self.scenes, self.cfg, self.max_agents
        plans: dict[tuple, int] = {}  # (scene id, mask bytes) -> distinct slot plan
        roads: dict[int, int] = {}  # scene id -> distinct road grid (`scenes` keeps every id alive)
        plan_list: list[SlotPlan] = []
        road_scenes: list[Scene] = []  # the distinct scenes, in order of first use
        self.world_plan = np.zeros(len(scenes), np.int64)  # distinct slot plan of each world
        world_road = np.zeros(len(scenes), np.int64)
        report = BuildReport([], [], [], [])
        for w, sc in enumerate(scenes):
            if abs(sc.dt - self.dt) > 1e-9:
                raise SceneError(sc.scene_id, "dt", f"all scenes of a batch need one dt; {sc.dt} != {self.dt}")
            ctrl = None if controlled is None else np.asarray(controlled[w], bool)
            bg = None if background is None else np.asarray(background[w], bool)
            key = (id(sc), None if ctrl is None else ctrl.tobytes(), None if bg is None else bg.tobytes())
            if key not in plans:
                plans[key] = len(plan_list)
                plan_list.append(SlotPlan.build(sc, cfg, ctrl, bg))
            plan = plan_list[plans[key]]
            self.world_plan[w] = plans[key]
            if plan.dropped > 0:
                log.info("scene %s: %d agents beyond max_agents=%d were dropped (least relevant first)",
                         sc.scene_id, plan.dropped, A)
            report.truncated_agents.append(max(plan.dropped, 0))
            report.controlled.append(int(plan.policy.sum()))
            report.skipped_at_goal.append(plan.skipped_at_goal)
            report.marked_expert.append(plan.marked)
            report.log_infeasible.append(plan.infeasible)
            if id(sc) not in roads:
                roads[id(sc)] = len(road_scenes)
                road_scenes.append(sc)
            world_road[w] = roads[id(sc)]
        return plan_list, road_scenes, world_road, report

    def _upload(self, g: dict[str, np.ndarray], G: int, cell: np.ndarray, last_step: np.ndarray,
                grid: dict[str, np.ndarray], roads_t) -> None:
        """The Model's device arrays: per-slot ones gathered from the `G` distinct plans' host arrays `g`,
        the logs one row per plan slot, the road tables as views of `roads_t`'s tensors."""
        W, A, T, dev = self.num_worlds, self.max_agents, self.num_steps, self.device

        def flat(name, dtype):
            x = g[name][self.world_plan]
            return wp.array(x.reshape(W * A, *x.shape[2:]), dtype=dtype, device=dev)

        self.slot_valid = flat("slot_valid", wp.int32)
        self.integrated = flat("integrated", wp.int32)
        self.background = flat("background", wp.int32)
        self.agent_type = flat("agent_type", wp.int32)
        self.length = flat("length", float)
        self.width = flat("width", float)
        self.goal = flat("goal", wp.vec2)
        self.num_plans = G
        log_row = self.world_plan[:, None] * A + np.arange(A)
        self.log_row = wp.array(log_row.reshape(-1).astype(np.int32), dtype=wp.int32, device=dev)
        self.log_pos = wp.array(g["log_pos"].reshape(G * A, T, 2), dtype=wp.vec2, device=dev)
        self.log_yaw = wp.array(g["log_yaw"].reshape(G * A, T), dtype=float, device=dev)
        self.log_vel = wp.array(g["log_vel"].reshape(G * A, T, 2), dtype=wp.vec2, device=dev)
        self.log_valid = wp.array(g["log_valid"].reshape(G * A, T), dtype=wp.int32, device=dev)
        self.last_step = wp.array(last_step, dtype=wp.int32, device=dev)
        self.collision_cell_size = wp.array(cell, dtype=float, device=dev)
        self.nearest_cap = self.collision_cell_size  # one array: the cap is the cell size (see above)
        self._road_tensors = roads_t  # the Warp arrays below are views of its tensors
        self.seg_a = wp.from_torch(roads_t.seg_a, dtype=wp.vec2)
        self.seg_b = wp.from_torch(roads_t.seg_b, dtype=wp.vec2)
        self.seg_mid = wp.from_torch(roads_t.seg_mid, dtype=wp.vec2)
        self.seg_type = wp.from_torch(roads_t.seg_type, dtype=wp.int32)
        self.grid_origin = wp.array(grid["grid_origin"], dtype=wp.vec2, device=dev)
        self.grid_nx = wp.array(grid["grid_nx"], dtype=wp.int32, device=dev)
        self.grid_ny = wp.array(grid["grid_ny"], dtype=wp.int32, device=dev)
        self.grid_cell_offset = wp.array(grid["grid_cell_offset"], dtype=wp.int32, device=dev)
        self.cell_start = wp.from_torch(roads_t.cell_start, dtype=wp.int32)
        r = self.cfg.reward
        self.reward_weights = wp.array(np.array([getattr(r, k) for k in REWARD_TERMS], np.float32),
                                       dtype=float, device=dev)

    @functools.cached_property
    def host(self) -> dict[str, np.ndarray]:
        """The per-slot and log arrays on the host, (W, A, ...) each, named as the Model's fields
        (gathered from the distinct slot plans on first use)."""
        return {k: v[self.world_plan] for k, v in self._plan_host.items()}

    def _copy_scalars(self, cfg: EngineConfig) -> None:
        """The kernel scalars, as the types the kernels take (modes as their integer values)."""
        self.init_step = int(cfg.init_steps)
        self.dynamics = int(cfg.dynamics)
        self.discrete = int(cfg.action_space == ActionSpace.DISCRETE)
        self.collision_mode = int(cfg.collision_mode)
        self.goal_behaviour = int(cfg.goal_behaviour)
        self.auto_reset = int(cfg.auto_reset)
        self.max_accel, self.max_curvature = float(cfg.max_accel), float(cfg.max_curvature)
        self.accel_bins, self.curvature_bins = int(cfg.accel_bins), int(cfg.curvature_bins)
        self.delta_max = wp.vec3(*cfg.delta_max)
        self.goal_radius, self.beta = float(cfg.goal_radius), float(cfg.beta)
        self.cost_shape = COST_SHAPES.index(cfg.cost_shape)
        self.cost_players = COST_PARTNERS.index(cfg.cost_partners)
        self.cost_horizon, self.cost_collision = float(cfg.cost_horizon), float(cfg.cost_collision)
        self.speed_limit, self.lane_cap = float(cfg.reward.speed_limit), float(cfg.reward.lane_cap)
        self.ttc_on, self.ttc_horizon = int(cfg.reward.ttc != 0.0), float(cfg.reward.ttc_horizon)
        self.partner_k, self.partner_radius = int(cfg.partner_k), float(cfg.partner_radius)
        self.road_k, self.road_radius = int(cfg.road_k), float(cfg.road_radius)
        self.view_cos = float(np.cos(np.radians(cfg.view_angle) / 2))  # cos of half the view cone
        self.obs_dim = obs_dim(cfg)
        self.road_query_radius = float(cfg.road_query_radius)
        self.road_cell_size = float(cfg.road_cell_size)
        self.collision_cells = int(cfg.collision_cells)


# --------------------------------------------------------------------- state
class Dims(enum.Enum):
    """Shape kinds of the State arrays: the flat shape they are allocated with and the
    (W, A, ...) / (W,) shape of their torch views (vector dtypes add a last axis)."""

    SLOT = "(W*A,)"
    WORLD = "(W,)"
    TERMS = "(W*A, NUM_TERMS)"
    OBS = "(W*A, obs_dim)"
    COUNTER = "(1,)"
    CELLS = "(W*collision_cells,)"  # broad-phase scratch, not viewed
    PARTNERS = "(W*A*partner_k,)"  # observation scratch, not viewed
    ROADS = "(road_k*W*A,)"  # observation scratch, not viewed; layout: Model.parallel_road_rows

    def alloc_shape(self, m: Model) -> tuple[int, ...]:
        n, W = m.num_slots, m.num_worlds
        return {Dims.SLOT: (n,), Dims.WORLD: (W,), Dims.TERMS: (n, NUM_TERMS), Dims.OBS: (n, m.obs_dim),
                Dims.COUNTER: (1,), Dims.CELLS: (W * m.collision_cells,),
                Dims.PARTNERS: (max(n * m.partner_k, 1),), Dims.ROADS: (max(n * m.road_k, 1),)}[self]

    def view_shape(self, m: Model) -> tuple[int, ...]:
        W, A = m.num_worlds, m.max_agents
        return {Dims.SLOT: (W, A), Dims.WORLD: (W,), Dims.TERMS: (W, A, NUM_TERMS), Dims.OBS: (W, A, m.obs_dim),
                Dims.COUNTER: (1,)}[self]


def view_shape(f: dataclasses.Field, m: Model) -> tuple[int, ...]:
    """Shape of the torch view of State field `f`: its `Dims.view_shape`, plus the vector length."""
    return (*f.metadata["dims"].view_shape(m), *((f.metadata["dtype"]._length_,) if f.metadata["dtype"] in
                                                 (wp.vec2, wp.vec3) else ()))


def array_field(dims: Dims, dtype, meaning: str):
    """A State field: its shape kind, Warp dtype and meaning (unit first), declared once."""
    return dataclasses.field(metadata={"dims": dims, "dtype": dtype, "meaning": meaning})


_DTYPE_NAMES = {wp.int32: "int32", wp.float32: "f32", wp.vec2: "vec2", wp.vec3: "vec3"}


def shape_table(cls) -> str:
    """The column-aligned field table of a State-like dataclass: name, shape, dtype, meaning."""
    rows = [(f.name, f.metadata["dims"].value, _DTYPE_NAMES[f.metadata["dtype"]], f.metadata["meaning"])
            for f in dataclasses.fields(cls)]
    rows.insert(0, ("field", "shape", "dtype", "unit / meaning"))
    w0, w1, w2 = (max(len(r[k]) for r in rows) for k in range(3))
    return "\n".join(f"    {a:<{w0}}  {b:<{w1}}  {c:<{w2}}  {d}" for a, b, c, d in rows)


ArrayT = TypeVar("ArrayT")

SLOT, WORLD = Dims.SLOT, Dims.WORLD


@dataclasses.dataclass(eq=False, repr=False)
class StepState(Generic[ArrayT]):
    """The per-step arrays a learner reads: in `State` Warp arrays (flat), in the `Simulator`
    torch views of them shaped (W, A, ...) or (W,) (`Dims.view_shape`). Declared once here."""

    # kinematics
    pos: ArrayT = array_field(SLOT, wp.vec2, "m, box centre")
    yaw: ArrayT = array_field(SLOT, wp.float32, "rad")
    vel: ArrayT = array_field(SLOT, wp.vec2, "m/s")
    speed: ArrayT = array_field(SLOT, wp.float32, "m/s, |vel|")
    applied_action: ArrayT = array_field(SLOT, wp.vec3, "the action the last step applied, decoded and clipped")
    # worlds
    world_step: ArrayT = array_field(WORLD, wp.int32, "log step the world is at")
    world_ended: ArrayT = array_field(WORLD, wp.int32, "0/1, the world's episode ended in the last step")
    world_reset: ArrayT = array_field(WORLD, wp.int32, "0/1, ... and the world was reset to init_step")
    world_done: ArrayT = array_field(WORLD, wp.int32, "0/1, episode over, frozen until reset() (auto_reset off)")
    world_truncated: ArrayT = array_field(WORLD, wp.int32, "0/1, the episode ended at the time limit")
    episode_count: ArrayT = array_field(WORLD, wp.int32, "episodes the world finished since the build")
    bad_actions: ArrayT = array_field(Dims.COUNTER, wp.int32, "unusable actions met by the steps since the build")
    # agent flags, this step
    present: ArrayT = array_field(SLOT, wp.int32, "0/1, in the scene")
    alive: ArrayT = array_field(SLOT, wp.int32, "0/1, integrated and acted in this step")
    active: ArrayT = array_field(SLOT, wp.int32, "0/1, integrated and acts in the next step (the action mask)")
    agent_done: ArrayT = array_field(SLOT, wp.int32, "0/1, the agent's episode is over: frozen or removed")
    removed: ArrayT = array_field(SLOT, wp.int32, "0/1, taken out of the scene")
    collided: ArrayT = array_field(SLOT, wp.int32, "0/1, its box overlaps another present agent's")
    offroad: ArrayT = array_field(SLOT, wp.int32, "0/1, its box crosses a road edge")
    goal_event: ArrayT = array_field(SLOT, wp.int32, "0/1, it reached its goal (on the road)")
    terminated: ArrayT = array_field(SLOT, wp.int32, "0/1, its episode ended (goal, collision, off-road per mode)")
    truncated: ArrayT = array_field(SLOT, wp.int32, "0/1, its episode ended at the time limit")
    # distances
    goal_dist: ArrayT = array_field(SLOT, wp.float32, "m, centre to goal")
    edge_dist: ArrayT = array_field(SLOT, wp.float32, "m, centre to the nearest road edge, <= road_query_radius")
    lane_dist: ArrayT = array_field(SLOT, wp.float32, "m, centre to the nearest lane, <= road_query_radius")
    nearest: ArrayT = array_field(SLOT, wp.float32, "m, centre to the nearest present agent, <= Model.nearest_cap")
    cost_dist: ArrayT = array_field(SLOT, wp.float32, "m, the same to the nearest agent the cost counts (cost_partners), "
                                                     "least over cost_horizon")
    ttc: ArrayT = array_field(SLOT, wp.float32, "s, time to collision with an agent ahead, <= ttc_horizon (when weighted)")
    # reward and cost
    reward: ArrayT = array_field(SLOT, wp.float32, "weighted sum of the reward terms")
    reward_terms: ArrayT = array_field(Dims.TERMS, wp.float32, "the named terms (kernels/reward.py), unweighted")
    cost: ArrayT = array_field(SLOT, wp.float32, "in [0, 1], a present agent is nearer than beta (cost_shape)")
    cost_depth: ArrayT = array_field(SLOT, wp.float32, "in [0, 1], (beta - d) / beta of its last step (cost_shape "
                                                      "approach); -1 before its episode's first step")
    # the running episode
    ep_goal: ArrayT = array_field(SLOT, wp.int32, "0/1, reached its goal")
    ep_collided: ArrayT = array_field(SLOT, wp.int32, "0/1, collided")
    ep_offroad: ArrayT = array_field(SLOT, wp.int32, "0/1, went off the road")
    ep_return: ArrayT = array_field(SLOT, wp.float32, "sum of reward")
    ep_cost: ArrayT = array_field(SLOT, wp.float32, "sum of cost")
    ep_min_dist: ArrayT = array_field(SLOT, wp.float32, "m, least `nearest` (capped)")
    ep_steps: ArrayT = array_field(SLOT, wp.int32, "steps acted")
    # the last finished episode (valid where world_ended)
    final_goal: ArrayT = array_field(SLOT, wp.int32, "0/1, ep_goal at the end")
    final_collided: ArrayT = array_field(SLOT, wp.int32, "0/1, ep_collided at the end")
    final_offroad: ArrayT = array_field(SLOT, wp.int32, "0/1, ep_offroad at the end")
    final_return: ArrayT = array_field(SLOT, wp.float32, "ep_return at the end")
    final_cost: ArrayT = array_field(SLOT, wp.float32, "ep_cost at the end")
    final_min_dist: ArrayT = array_field(SLOT, wp.float32, "m, ep_min_dist at the end")
    final_steps: ArrayT = array_field(SLOT, wp.int32, "ep_steps at the end")
    # observation
    obs: ArrayT = array_field(Dims.OBS, wp.float32, "ego, partner and road blocks (kernels/observation.py)")


@dataclasses.dataclass(eq=False, repr=False)
class State(StepState[wp.array]):
    """Per-step arrays of the engine (Warp, flat), the scratch of its broad phases included:

    {table}
    """

    # scratch of the broad phases, rewritten every step
    agent_cell: wp.array = array_field(SLOT, wp.int32, "hashed collision cell, -1 when absent")
    grid_count: wp.array = array_field(Dims.CELLS, wp.int32, "agents per collision cell")
    grid_start: wp.array = array_field(Dims.CELLS, wp.int32, "first agent of each cell")
    grid_fill: wp.array = array_field(Dims.CELLS, wp.int32, "end of each cell after the scatter")
    grid_items: wp.array = array_field(SLOT, wp.int32, "agents sorted by cell (order from atomics)")
    part_d: wp.array = array_field(Dims.PARTNERS, wp.float32, "m^2, nearest partners, sorted")
    part_j: wp.array = array_field(Dims.PARTNERS, wp.int32, "their slots")
    heap_d: wp.array = array_field(Dims.ROADS, wp.float32, "m^2, nearest road segments: a max-heap, then sorted")
    heap_j: wp.array = array_field(Dims.ROADS, wp.int32, "their segment indices")
    road_n: wp.array = array_field(SLOT, wp.int32, "road rows found (<= road_k)")

    @classmethod
    def allocate(cls, model: Model) -> State:
        """Zeroed arrays of every field on the model's device."""
        return cls(**{f.name: wp.zeros(f.metadata["dims"].alloc_shape(model), dtype=f.metadata["dtype"],
                                       device=model.device) for f in dataclasses.fields(cls)})


State.__doc__ = State.__doc__.format(table=shape_table(State).strip())


class Control:
    """Per-step inputs: the action buffers the policy (and a background driver) writes."""

    def __init__(self, model: Model):
        self.action = wp.zeros(model.num_slots, dtype=wp.vec3, device=model.device)  # continuous, (W*A,)
        self.action_index = wp.zeros(model.num_slots, dtype=wp.int32, device=model.device)  # grid index, (W*A,)
