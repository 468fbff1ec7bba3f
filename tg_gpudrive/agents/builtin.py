"""Built-in policies and background drivers: what drives a vehicle without a trained network.

A policy is a callable `policy(sim) -> None` that writes the action buffers of the simulator in place
(`sim.actions_index` or `sim.actions`): `expert_policy` (the logs' inverse-dynamics actions),
`constant_policy` (no acceleration, no steering), `make_random_policy`.

Who drives the vehicles the policy does not (`BACKGROUNDS`):

    log          they replay their logs (the engine's default)
    world_model  the learned world model drives them reactively
    idm          each follows its own logged path and timing and brakes for whoever
                 is on that path (agents/idm.py: reactive log replay)

Reactive ones are marked background in the Simulator (`background_masks`) and
`make_background_driver` writes their actions after the policy and before every
`sim.step()`.

A background driver is itself a `policy(sim)` that writes only the background
rows, so it must run after the policy (policies may write every row).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from tg_gpudrive.agents.idm import IDMDriver
from tg_gpudrive.config import BACKGROUNDS
from tg_gpudrive.engine import control
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.worldmodel.prior import WorldModelDriver, load_shipped, load_world_model

Policy = Callable[[Simulator], None]
BUILTIN = ("expert", "constant", "random")  # the names `builtin_policy` knows


def expert_policy(sim: Simulator) -> None:
    sim.use_expert_actions()


def constant_policy(sim: Simulator) -> None:
    """Zero acceleration, zero curvature (or no motion for delta-local)."""
    cfg = sim.cfg
    if cfg.discrete:
        sim.actions_index.fill_(cfg.noop_index)
    else:
        sim.actions.zero_()


def make_random_policy(seed: int, device: str) -> Policy:
    gen = torch.Generator(device=device).manual_seed(seed)

    def random_policy(sim: Simulator) -> None:
        cfg = sim.cfg
        if cfg.discrete:
            sim.actions_index.copy_(torch.randint(0, sim.num_actions, sim.actions_index.shape, generator=gen,
                                                  device=sim.actions_index.device, dtype=torch.int32))
        else:
            hi = torch.zeros(sim.actions.shape[-1])  # the columns past act_dim stay 0
            hi[:cfg.act_dim] = torch.tensor(cfg.act_high)
            hi = hi.to(sim.actions.device)
            u = torch.rand(sim.actions.shape, generator=gen, device=sim.actions.device)
            sim.actions.copy_((2 * u - 1) * hi)

    return random_policy


def builtin_policy(name: str, seed: int, device: str) -> Policy:
    if name == "expert":
        return expert_policy
    if name == "constant":
        return constant_policy
    if name == "random":
        return make_random_policy(seed, device)
    raise ValueError(f"policy: expected expert, random or constant, got {name!r}")


def check_background(background: str, option: str = "background") -> str:
    if background not in BACKGROUNDS:
        raise ValueError(f"{option}: expected one of {', '.join(BACKGROUNDS)}, got {background!r}")
    return background


def background_masks(scenes: Sequence, cfg, background: str = "log",
                     controlled: Sequence[np.ndarray] | None = None) -> list[np.ndarray] | None:
    """The Simulator's `background` argument: None for log replay; for a reactive background
    `engine.control.background_masks` (the eligible vehicles the policy does not drive)."""
    if check_background(background) == "log":
        return None
    return control.background_masks(scenes, cfg, controlled)


def make_background_driver(sim: Simulator, background: str = "log", model: str | Path | None = None,
                           seed: int = 0, option: str = "background_model") -> Policy | None:
    """None for log replay; an `IDMDriver` of the background rows for idm; else a `WorldModelDriver` of
    them, with the checkpoint `model` (a world-model .pt, a train-world-model run directory or a packaged
    name) or the shipped model. The model's action space must match the simulator's (the loader raises
    ValueError otherwise; the shipped model is discrete)."""
    if check_background(background) != "world_model" and model is not None:
        raise ValueError(f"{option}: only used with background world_model, got background {background}")
    if background == "log":
        return None
    if background == "idm":
        return IDMDriver(rows="background")
    if model is None:
        wm = load_shipped(sim)
    else:
        try:
            wm = load_world_model(model, sim)
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{option}: {e}") from None
    return WorldModelDriver(wm, rows="background", seed=seed)
