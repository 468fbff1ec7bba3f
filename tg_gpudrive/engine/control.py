"""Who drives which agent: the one module that decides the policy, background and integrated masks.

    policy       the learner's (or the env user's) agents; "controlled" means these everywhere
    background   moved from the action buffers too, but by a background model (reactive traffic),
                 never counted as the policy's
    integrated   policy | background: the agents the engine moves from the action buffers
    the rest     replay their logs

Which agents count (the rule of GPUDrive and PufferDrive, applied identically to every policy, the
expert replay included): an agent is *eligible* when it is a vehicle present at init_step, at
least `goal_radius` from its goal there, not marked `mark_as_expert` by its source file, and its
log is feasible (`data.log_audit`: the logged box neither overlaps another agent's, nor crosses a
road edge, nor jumps, over its scoring window). With `replay_infeasible` (the default) marked and
log-infeasible agents replay their logs and are counted apart (`exclusions`), never in a policy's
rates; rates count each agent's first episode only (the rollouts' `episodes_per_world`).
The modes (tg_gpudrive.enums.ControlMode):

    engine default (EngineConfig.control), over the agents that get slots:
        none              nobody
        vehicles          the eligible vehicles
        all_agents        every agent present at init_step and away from its goal (marked and
                          log-infeasible agents still excluded)
    selection for a run (TrainConfig.control, --control), over the scene's agents:
        vehicles          the eligible vehicles (the engine default)
        nearest_conflict  the k eligible vehicles nearest the scene's conflict point
                          (metadata["conflict_point"] of procedural scenes; else the SDC, else the
                          centroid of the agents at init_step)
        ids               the agents whose source track ids are listed

Masks are NumPy bool arrays over a scene's agents (N,) or over the slotted agents `idx`; the
Model builder, the envs and the rollouts pass them on and must not recompute them. This
module must not touch the engine's arrays.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.log_audit import infeasible_mask, marked_expert
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import ENGINE_CONTROL, SELECT_CONTROL, AgentType, ControlMode


def init_index(scene: Scene, cfg: EngineConfig) -> int:
    """The log step control starts from (init_steps, clipped to the scene's log)."""
    return min(cfg.init_steps, scene.num_steps - 1)


def conflict_point(scene: Scene, init: int) -> np.ndarray:
    cp = scene.metadata.get("conflict_point")
    if cp is not None:
        return np.asarray(cp, np.float32).reshape(2)
    if scene.is_sdc.any():
        return scene.log_pos[np.argmax(scene.is_sdc), init]
    v = scene.log_valid[:, init]
    return scene.log_pos[v, init].mean(0) if v.any() else np.zeros(2, np.float32)


def _present_and_at_goal(scene: Scene, cfg: EngineConfig, idx) -> tuple[np.ndarray, np.ndarray]:
    init = init_index(scene, cfg)
    present = scene.log_valid[idx, init].copy()
    at_goal = np.linalg.norm(scene.log_pos[idx, init] - scene.goal[idx], axis=1) < cfg.goal_radius
    return present, at_goal


def exclusions(scene: Scene, cfg: EngineConfig) -> dict[str, np.ndarray]:
    """(N,) bool masks of the agents the rule keeps from the policy although present and away from
    their goal: "mark_as_expert" (marked by the source file) and "log_infeasible" (`data.log_audit`,
    not marked). Both empty without `cfg.replay_infeasible`."""
    if not cfg.replay_infeasible:
        return {"mark_as_expert": np.zeros(scene.num_agents, bool), "log_infeasible": np.zeros(scene.num_agents, bool)}
    marked = marked_expert(scene)
    infeasible = infeasible_mask(scene, init_index(scene, cfg), cfg.goal_radius) & ~marked
    return {"mark_as_expert": marked, "log_infeasible": infeasible}


def excluded(scene: Scene, cfg: EngineConfig) -> np.ndarray:
    """(N,) bool: marked or log-infeasible (`exclusions`)."""
    ex = exclusions(scene, cfg)
    return ex["mark_as_expert"] | ex["log_infeasible"]


def eligible(scene: Scene, cfg: EngineConfig) -> np.ndarray:
    """(N,) bool: the vehicles present at init_step, away from their goal and not excluded by the rule."""
    present, at_goal = _present_and_at_goal(scene, cfg, slice(None))
    return present & (scene.agent_type == AgentType.VEHICLE) & ~at_goal & ~excluded(scene, cfg)


def default_controlled(scene: Scene, idx: np.ndarray, cfg: EngineConfig,
                       mode: ControlMode | str | None = None) -> tuple[np.ndarray, int]:
    """The engine's default policy agents among the slotted agents `idx`, as a mask over `idx`, and
    how many of them were skipped for starting within goal_radius of their goal. `mode` (one of
    none, vehicles, all_agents) replaces cfg.control."""
    mode = ControlMode.parse(cfg.control if mode is None else mode, "control", ENGINE_CONTROL)
    if mode == ControlMode.NONE:
        return np.zeros(len(idx), bool), 0
    ok, at_goal = _present_and_at_goal(scene, cfg, idx)
    if mode == ControlMode.VEHICLES:
        ok &= scene.agent_type[idx] == AgentType.VEHICLE
    return ok & ~at_goal & ~excluded(scene, cfg)[idx], int((ok & at_goal).sum())


def default_mask(scene: Scene, cfg: EngineConfig, mode: ControlMode | str | None = None) -> np.ndarray:
    """(N,) bool over the scene's agents: `default_controlled` of the agents that get slots."""
    idx = select_slots(scene, cfg.max_agents, cfg.init_steps)
    ctrl, _ = default_controlled(scene, idx, cfg, mode)
    mask = np.zeros(scene.num_agents, bool)
    mask[idx[ctrl]] = True
    return mask


def control_mask(scene: Scene, cfg: EngineConfig, mode: ControlMode | str = ControlMode.VEHICLES, k: int = 5,
                 ids: Sequence[int] | None = None) -> np.ndarray:
    """(N,) bool over the scene's agents: the policy's agents of selection `mode`
    (vehicles, nearest_conflict or ids; see the module docstring)."""
    mode = ControlMode.parse(mode, "control", SELECT_CONTROL)
    ok = eligible(scene, cfg)
    if mode == ControlMode.VEHICLES:
        return ok
    if mode == ControlMode.IDS:
        wanted = set(int(i) for i in (ids or []))
        missing = wanted - set(scene.agent_id.tolist())
        if missing:
            raise ValueError(f"scene {scene.scene_id}: control ids {sorted(missing)} are not in the scene")
        return np.isin(scene.agent_id, list(wanted))
    init = init_index(scene, cfg)
    d = np.linalg.norm(scene.log_pos[:, init] - conflict_point(scene, init), axis=1)
    d = np.where(ok, d, np.inf)
    mask = np.zeros(scene.num_agents, bool)
    mask[np.argsort(d, kind="stable")[:k]] = True
    return mask & ok


def control_masks(scenes: Sequence[Scene], cfg: EngineConfig, mode: ControlMode | str = ControlMode.VEHICLES,
                  k: int = 5, ids: Sequence[int] | None = None) -> list[np.ndarray]:
    return [control_mask(s, cfg, mode, k, ids) for s in scenes]


def background_masks(scenes: Sequence[Scene], cfg: EngineConfig,
                     controlled: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
    """Per scene, (N,) bool: the eligible vehicles the policy does not drive, for a background
    model. With `controlled` None the policy's agents are the engine default, which the Model
    builder takes out itself (`slot_masks`)."""
    out = []
    for w, scene in enumerate(scenes):
        m = eligible(scene, cfg)
        if controlled is not None:
            m &= ~np.asarray(controlled[w], bool)
        out.append(m)
    return out


def slot_masks(scene: Scene, idx: np.ndarray, cfg: EngineConfig, controlled: np.ndarray | None = None,
               background: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """(policy, background, skipped_at_goal) over the slotted agents `idx`: the given (N,) masks, or
    the engine default for the policy and nobody for the background. An agent is never both."""
    if controlled is not None:
        policy, skipped = np.asarray(controlled, bool)[idx], 0
    else:
        policy, skipped = default_controlled(scene, idx, cfg)
    bg = np.zeros(len(idx), bool) if background is None else np.asarray(background, bool)[idx] & ~policy
    return policy, bg, skipped


def relevance_order(scene: Scene, init_step: int) -> np.ndarray:
    """The scene's agents valid at some step, most relevant first: the SDC, objects of interest, agents
    valid at `init_step`, vehicles, then nearest to the SDC (or the scene centre)."""
    init = min(init_step, scene.num_steps - 1)
    valid_any = scene.log_valid.any(axis=1)
    centre = scene.log_pos[scene.is_sdc, init].mean(0) if scene.is_sdc.any() else np.zeros(2, np.float32)
    dist = np.linalg.norm(scene.log_pos[:, init] - centre, axis=1)
    dist = np.where(scene.log_valid[:, init], dist, 1e9)
    keys = (dist, ~(scene.agent_type == AgentType.VEHICLE), ~scene.log_valid[:, init], ~scene.is_interest,
            ~scene.is_sdc)
    order = np.lexsort(keys)
    return order[valid_any[order]]


def select_slots(scene: Scene, max_agents: int, init_step: int) -> np.ndarray:
    """Indices of the agents that get one of the `max_agents` slots (sorted), the most relevant kept
    (`relevance_order`). Commands size max_agents to hold every agent (`engine.model.sized_for`)."""
    return np.sort(relevance_order(scene, init_step)[:max_agents])


def cap_controlled(scene: Scene, mask: np.ndarray, cap: int, init_step: int) -> tuple[np.ndarray, int]:
    """(N,) `mask` keeping at most `cap` of its agents, the most relevant (`relevance_order`), and how many
    it left to replay their logs: how training bounds the policy's agents per world without dropping any."""
    mask = np.asarray(mask, bool)
    if mask.sum() <= cap:
        return mask, 0
    order = relevance_order(scene, init_step)
    keep = np.zeros_like(mask)
    keep[order[mask[order]][:cap]] = True
    return keep, int(mask.sum()) - cap


DRIVER_ROWS = ("background", "controlled", "policy")  # which rows a driver of vehicles (world model, IDM) writes


def driver_rows(sim, rows: str):
    """(W, A) bool: the present agents a driver of `rows` writes actions for: the background ones, every
    integrated one ("controlled", e.g. to drive a whole scene closed loop) or the policy's."""
    if rows == "background":
        sel = sim.background != 0
    elif rows == "controlled":
        sel = sim.integrated != 0
    elif rows == "policy":
        sel = sim.policy_agents
    else:
        raise ValueError(f"rows: expected one of {', '.join(DRIVER_ROWS)}, got {rows!r}")
    return sel & (sim.present != 0)
