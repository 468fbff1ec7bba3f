"""Checkpoint files shared by the CCE-MAPPO trainer, the world model and the CLIs.

`save_atomic` writes beside the target and renames, so a run killed mid-write
leaves the previous checkpoint whole; `load_checkpoint` accepts a file, a run
directory (its checkpoint.pt) or the name "shipped" (the policy packaged at
tg_gpudrive/policies/shipped.pt) and names the command-line option in its error.
`policy_engine_config` gives a policy checkpoint's engine config with slots for
every agent of the scenes it is evaluated or rendered on.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from tg_gpudrive.config import EngineConfig, TrainConfig

log = logging.getLogger(__name__)

SHIPPED = "shipped"  # the name that stands for the packaged policy
SHIPPED_POLICY = Path(__file__).resolve().parent / "policies" / "shipped.pt"


def save_atomic(obj, path: str | Path) -> Path:
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)
    return path


def checkpoint_path(path: str | Path, option: str = "--resume") -> Path:
    """`path` itself, `path/checkpoint.pt` for a run directory, or SHIPPED_POLICY for the name "shipped"
    (a local file or directory of that name: ./shipped); FileNotFoundError naming `option`."""
    if isinstance(path, str) and path == SHIPPED:
        if not SHIPPED_POLICY.is_file():
            raise FileNotFoundError(f"{option} {SHIPPED}: the packaged policy {SHIPPED_POLICY} is missing "
                                    "(this install ships none); give a checkpoint file or run directory")
        return SHIPPED_POLICY
    path = Path(path)
    path = path / "checkpoint.pt" if path.is_dir() else path
    if not path.exists():
        raise FileNotFoundError(f"{option}: no checkpoint at {path}")
    return path


def load_checkpoint(path: str | Path, option: str = "--resume", map_location="cpu") -> dict:
    return torch.load(checkpoint_path(path, option), map_location=map_location, weights_only=False)


def policy_engine_config(cfg: TrainConfig, scenes) -> EngineConfig:
    """The engine config of a policy trained with `cfg` (a TrainConfig), sized for `scenes`.

    max_agents = max(cfg.env.max_agents, the most agents any scene needs (engine.agents_needed)), so
    evaluating or rendering on denser scenes than the training ones drops no agent: the actor is per
    agent (heads = 1, the slot index unused) and works at any slot count. A checkpoint with per-slot
    heads (heads > 1) keeps its max_agents, with a warning that agents beyond it are dropped."""
    from tg_gpudrive.engine import agents_needed

    env = cfg.env
    need = max((agents_needed(s) for s in scenes), default=0)
    if need <= env.max_agents:
        return env
    if cfg.heads > 1:
        log.warning("the policy has per-slot heads (heads=%d): keeping its max_agents=%d; agents beyond it "
                    "are dropped (scenes need up to %d slots)", cfg.heads, env.max_agents, need)
        return env
    return dataclasses.replace(env, max_agents=need)
