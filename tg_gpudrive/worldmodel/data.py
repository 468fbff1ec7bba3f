"""Teacher-forced samples for the world model: what `train.py` fits and `metrics.py` scores.

Every scene is driven by its closed-loop inverse-dynamics expert
(`sim.use_expert_actions`) and, at each step, every active controlled vehicle
with an expert action (`sim.log_at("expert_index", step) >= 0`) gives one sample: its
observation row (cut to the model's nearest `max_partners` / `max_roads` rows),
its history window and the expert's grid index, or for
`env.action_space: continuous` the expert's (accel, curvature). The engine is
deterministic, so the same scenes give the same samples (a resumed run
collects the same ones). This module only reads the simulator; it fits nothing.
"""

from __future__ import annotations

import dataclasses

import torch

from tg_gpudrive.config import ConfigError, EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HistoryBuffer
from tg_gpudrive.kernels.observation import EGO_DIM, PARTNER_DIM, ROAD_DIM
from tg_gpudrive.enums import CollisionMode, GoalBehaviour
from tg_gpudrive.worldmodel.model import require_bicycle


def full_horizon_env(env: EngineConfig) -> EngineConfig:
    """`env` for closed-loop roll-outs and their metrics: agents keep driving after their goal and
    through contacts, so every track lasts the whole horizon."""
    return dataclasses.replace(env, goal_behaviour=GoalBehaviour.CONTINUE, collision_mode=CollisionMode.IGNORE)


def truncate_obs(obs: torch.Tensor, k: int, kr: int, kp: int, krr: int) -> torch.Tensor:
    """Observation rows with only the nearest kp partner / krr road rows (layout (kp, krr))."""
    ego = obs[..., :EGO_DIM]
    part = obs[..., EGO_DIM:EGO_DIM + k * PARTNER_DIM][..., :kp * PARTNER_DIM]
    road = obs[..., EGO_DIM + k * PARTNER_DIM:][..., :krr * ROAD_DIM]
    return torch.cat([ego, part, road], dim=-1)


@torch.no_grad()
def collect(scenes, env: EngineConfig, *, history: int, max_partners: int, max_roads: int,
            num_worlds: int = 16, device: str = "cpu") -> dict:
    """Teacher-forced samples of `scenes` (every agent of a scene has a slot, `env.max_agents` raised
    where a scene needs more), on the host: obs (N, D), hist (N, H, 7), target (N,) grid
    indices (discrete) or (N, 2) expert (accel, curvature) (continuous), expert (N, 4) (the logged
    expert action and a validity flag, for the oracle bound), layout (partner_k, road_k) of obs."""
    require_bicycle(env)
    continuous = not env.discrete
    kp, krr = min(env.partner_k, max_partners), min(env.road_k, max_roads)
    out = {"obs": [], "hist": [], "target": [], "expert": []}
    for b in range(0, len(scenes), num_worlds):
        batch = scenes[b:b + num_worlds]
        sim = Simulator(batch, sized_for(env, batch), device)  # every agent gets a slot: none is dropped
        sim.reset()
        hb = HistoryBuffer(history)
        for _ in range(sim.episode_length):
            hb.sync(sim)
            target = sim.log_at("expert_index", sim.world_step)
            rows = (sim.active != 0) & (sim.background == 0) & (target >= 0)
            w, a = rows.nonzero(as_tuple=True)
            out["obs"].append(truncate_obs(sim.obs[w, a], env.partner_k, env.road_k, kp, krr).cpu())
            out["hist"].append(hb.features(sim)[w, a].cpu())
            act = sim.log_at("expert_action", sim.world_step)  # (W, A, 3)
            out["target"].append(act[w, a, :2].cpu() if continuous else target[w, a].long().cpu())
            out["expert"].append(torch.cat([act, (target >= 0).float()[..., None]], -1)[w, a].cpu())
            sim.use_expert_actions()
            sim.step()
    data = {k: torch.cat(v) for k, v in out.items()}
    data["layout"] = (kp, krr)
    return data


def load_scene_split(cfg) -> tuple[list, list]:
    src = resolve_scenes(cfg.scenes, n=cfg.num_scenes + cfg.val_scenes, seed=cfg.seed)
    n = len(src)
    if n <= cfg.val_scenes:
        raise ConfigError(f"scenes {cfg.scenes!r}: {n} scenes, need more than val_scenes={cfg.val_scenes}")
    n_train = min(cfg.num_scenes, n - cfg.val_scenes)
    get = getattr(src, "get_many", None)
    scenes = get(list(range(n_train + cfg.val_scenes))) if get else [src.get(i) for i in range(n)]
    return scenes[:n_train], scenes[n_train:n_train + cfg.val_scenes]
