"""Who is controlled: the policy drives these agents, the rest replay their logs.

    vehicles          every vehicle valid at init_step and not already at its goal (engine default)
    nearest_conflict  the k such vehicles nearest the scene's conflict point
                      (metadata["conflict_point"] of procedural scenes; else the SDC, else the
                      centroid of the agents at init_step)
    ids               the agents whose source track ids are listed
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.scene import Scene
from tg_gpudrive.types import AgentType

CONTROL_MODES = ("vehicles", "nearest_conflict", "ids")


def conflict_point(scene: Scene, init: int) -> np.ndarray:
    cp = scene.metadata.get("conflict_point")
    if cp is not None:
        return np.asarray(cp, np.float32).reshape(2)
    if scene.is_sdc.any():
        return scene.log_pos[np.argmax(scene.is_sdc), init]
    v = scene.log_valid[:, init]
    return scene.log_pos[v, init].mean(0) if v.any() else np.zeros(2, np.float32)


def eligible(scene: Scene, cfg: EngineConfig) -> np.ndarray:
    init = min(cfg.init_steps, scene.num_steps - 1)
    ok = scene.log_valid[:, init] & (scene.agent_type == AgentType.VEHICLE)
    far = np.linalg.norm(scene.log_pos[:, init] - scene.goal, axis=1) >= cfg.goal_radius
    return ok & far


def control_mask(scene: Scene, cfg: EngineConfig, mode: str = "vehicles", k: int = 5,
                 ids: list[int] | None = None) -> np.ndarray:
    """(N,) bool over the scene's agents."""
    if mode not in CONTROL_MODES:
        raise ValueError(f"control: expected one of {', '.join(CONTROL_MODES)}, got {mode!r}")
    ok = eligible(scene, cfg)
    if mode == "vehicles":
        return ok
    if mode == "ids":
        wanted = set(int(i) for i in (ids or []))
        missing = wanted - set(scene.agent_id.tolist())
        if missing:
            raise ValueError(f"scene {scene.scene_id}: control ids {sorted(missing)} are not in the scene")
        return np.isin(scene.agent_id, list(wanted))
    init = min(cfg.init_steps, scene.num_steps - 1)
    d = np.linalg.norm(scene.log_pos[:, init] - conflict_point(scene, init), axis=1)
    d = np.where(ok, d, np.inf)
    mask = np.zeros(scene.num_agents, bool)
    mask[np.argsort(d, kind="stable")[:k]] = True
    return mask & ok


def control_masks(scenes: list[Scene], cfg: EngineConfig, mode: str = "vehicles", k: int = 5,
                  ids: list[int] | None = None) -> list[np.ndarray]:
    return [control_mask(s, cfg, mode, k, ids) for s in scenes]
