"""`open_policy`: a built-in or trained policy in worlds of given scenes (see the package docstring)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from tg_gpudrive.checkpoint import (checkpoint_path, evaluation_engine, load_checkpoint, policy_engine_config,
                                    usable_checkpoint)
from tg_gpudrive.config import EngineConfig, TrainConfig, from_dict
from tg_gpudrive.engine.control import control_masks
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.policy import load_policy
from tg_gpudrive.agents.builtin import BUILTIN, Policy, background_masks, builtin_policy, make_background_driver


@dataclass
class Opened:
    """A policy in worlds: the Simulator, the policy (`policy(sim)` writes its agents' actions), the
    background driver (None: log replay), the policy's agents per scene, and for a trained policy its
    checkpoint, training config, the temperature it acts at and its safety guard's horizon in s (0: none; both None
    for a built-in)."""

    sim: Simulator
    policy: Policy
    background: Policy | None
    masks: list | None
    checkpoint: Path | None = None
    trained: TrainConfig | None = None
    temperature: float | None = None
    guard_s: float | None = None

    def act(self, sim: Simulator) -> None:
        """One step's actions: the policy's agents', then the background's (what `sim.step()` needs next)."""
        self.policy(sim)
        if self.background is not None:
            self.background(sim)


def _masks(scenes, env: EngineConfig, control, control_k, trained: TrainConfig | None):
    """Who the policy drives, decided once: `control` if given, else the run's training control (with
    its k and ids), else None (the engine's default: every eligible vehicle)."""
    if control is None and trained is None:
        return None
    mode = control or trained.control
    k = control_k if control_k is not None else (trained.control_k if trained else 5)
    ids = trained.control_ids if trained is not None else None
    return control_masks(scenes, env, mode, k, ids)


def trained_sim(trained: TrainConfig, scenes: Sequence, device: str, *, overrides: Sequence[str] = (),
                path=None, collision_mode=None, control=None, control_k=None, background: str = "log",
                auto_reset: bool = True) -> tuple[Simulator, list | None]:
    """The worlds of a policy trained with `trained` on `scenes`: its engine config with a slot for every
    agent, the evaluation `overrides` it allows (`checkpoint.evaluation_engine`), the collision mode,
    its agents (`control`, else its training control), the background rows. Returns (sim, masks)."""
    env = evaluation_engine(policy_engine_config(trained, scenes), list(overrides), path)
    return _build(scenes, env, device, collision_mode, auto_reset, _masks(scenes, env, control, control_k, trained),
                  background)


def _build(scenes, env, device, collision_mode, auto_reset, masks, background):
    if collision_mode:
        env = dataclasses.replace(env, collision_mode=collision_mode)
    if not auto_reset:  # keep an episode's final state (a rendered last frame)
        env = dataclasses.replace(env, auto_reset=False)
    return Simulator(scenes, env, device, masks, background_masks(scenes, env, background, masks)), masks


def check_specs(specs: Sequence[str], option: str) -> None:
    """Fail at once, before any scene is built, when a spec of `specs` is neither a built-in policy nor a
    checkpoint (file, run directory or packaged name): FileNotFoundError naming `option` and the spec."""
    for spec in specs:
        if spec not in BUILTIN:
            checkpoint_path(spec, option)


def open_policy(spec: str, scenes: Sequence, device: str, *, engine: EngineConfig | None = None,
                overrides: Sequence[str] = (), collision_mode=None, control=None, control_k=None,
                background: str = "log", background_model=None, seed: int = 0, temperature: float | None = None,
                guard_s: float | None = None, auto_reset: bool = True, option: str = "--checkpoint") -> Opened:
    """`spec` (expert, constant, random, or a checkpoint file, run directory or packaged name such as
    "shipped") in worlds of `scenes`. A built-in policy runs in `engine` (default: EngineConfig()), sized
    for the scenes; a trained one in its own engine (`trained_sim`; `overrides` are --set keys, checked
    against what its network fixes). `seed` seeds the built-in random policy and the world-model
    background; `temperature` is a trained policy's acting temperature (None: its checkpoint's;
    policy.actor_policy) and `guard_s` its safety guard's horizon (None: its checkpoint's; policy.load_policy);
    `option` names the flag in errors."""
    if spec in BUILTIN:
        env = sized_for(engine or EngineConfig(), scenes)
        sim, masks = _build(scenes, env, device, collision_mode, auto_reset,
                            _masks(scenes, env, control, control_k, None), background)
        policy, path, trained = builtin_policy(spec, seed, sim.device), None, None
    else:
        path = usable_checkpoint(spec, option)  # a damaged checkpoint.pt: the previous one, with a warning
        trained = from_dict(TrainConfig, load_checkpoint(path, option)["config"], str(path))
        sim, masks = trained_sim(trained, scenes, device, overrides=overrides, path=path,
                                 collision_mode=collision_mode, control=control, control_k=control_k,
                                 background=background, auto_reset=auto_reset)
        policy = load_policy(path, sim, temperature, guard_s)
    driver = make_background_driver(sim, background, background_model, seed, "--background-model")
    guard = getattr(policy, "guard", None)
    return Opened(sim, policy, driver, masks, path, trained, getattr(policy, "temperature", None),
                  None if trained is None else (guard.horizon if guard is not None else 0.0))
