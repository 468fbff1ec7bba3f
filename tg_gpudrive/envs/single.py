"""`TGSingleAgentEnv`: one controlled vehicle in one scene as an ordinary gymnasium.Env.

The other agents replay their logs, or are driven by `other_policy` (a
``policy(sim)`` callable writing the simulator's action buffers, as in
tg_gpudrive.agents.builtin, or one of "expert", "constant", "random"), or, with
``background="world_model"``, the other eligible vehicles are driven by the
learned world model, reacting to the controlled one. Observations
are numpy float32 rows of the engine's layout (kernels/observation.py);
the env does not auto-reset: after terminated or truncated, step() raises
until reset() is called, and the obs returned with the end is the true
terminal observation.

The env runs its world with ``auto_reset=False`` whatever the config says
(`EpisodeWorld`, shared with the PettingZoo env): when the episode ends the
engine freezes the world instead of resetting it, so the obs, reward and
flags of the final step are the terminal ones and reset() starts the next
episode.

This module must not change engine semantics: actions reach the engine
unchanged, the state is the one a bare `Simulator` with the same controlled
agents reaches.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import gymnasium
import numpy as np
import torch

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.engine import control
from tg_gpudrive.engine.model import obs_dim
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.envs.vector import (
    ConfigLike,
    OverridesLike,
    make_config,
    render_world,
    scene_source,
    single_action_space,
    single_observation_space,
)
from tg_gpudrive.agents.builtin import background_masks, builtin_policy, check_background, make_background_driver
from tg_gpudrive.scene import Scene
from tg_gpudrive.enums import ControlMode


class EpisodeWorld:
    """One engine world that waits for reset() when its episode ends (``auto_reset=False``).

    `controlled` is a bool mask over the scene's agents; `background` ("log" or
    "world_model", with `background_model`) says who drives the other eligible
    vehicles (tg_gpudrive.agents.builtin). Attributes: `sim` (the Simulator), `cfg` (its
    config), `slots` (the policy's slots, background ones excluded), `slot_agent`
    (scene agent index of each slot, -1 for none).
    """

    def __init__(self, scene: Scene, cfg: EngineConfig, device: str, controlled: np.ndarray,
                 background: str = "log", background_model=None, seed: int = 0):
        self.scene = scene
        self.cfg = dataclasses.replace(cfg, auto_reset=False)
        ctrl = [np.asarray(controlled, bool)]
        bg = background_masks([scene], self.cfg, background, ctrl)
        self.sim = sim = Simulator([scene], self.cfg, device, ctrl, bg)
        self.driver = make_background_driver(sim, background, background_model, seed)
        self.slot_agent = sim.model.slot_agent[0]
        self.slots = np.nonzero(sim.policy_agents[0].cpu().numpy())[0]
        self.ended = False

    @property
    def step_now(self) -> int:
        """The log step the world is at."""
        return int(self.sim.world_step[0])

    def reset(self) -> None:
        self.sim.reset()
        self.ended = False

    def step(self) -> None:
        """One engine step; `ended` tells whether the world's episode is over (it is then frozen)."""
        if self.ended:
            raise RuntimeError("EpisodeWorld: the world's episode ended; reset() first")
        if self.driver is not None:  # after every other writer of the action buffers
            self.driver(self.sim)
        self.sim.step()
        self.ended = bool(self.sim.world_ended[0])

    def obs(self, slot: int) -> np.ndarray:
        return self.sim.obs[0, slot].detach().to("cpu", copy=True).numpy()

    def step_info(self, slot: int) -> dict:
        s = self.sim
        return {"cost": float(s.cost[0, slot]),
                "reward_terms": {n: float(v) for n, v in zip(s.reward_term_names, s.reward_terms[0, slot].tolist())}}

    def outcomes(self, slot: int) -> dict:
        """The episode's outcomes so far for `slot`, keyed final_* like the vector env's."""
        s = self.sim
        return {"final_goal": bool(s.ep_goal[0, slot]), "final_collided": bool(s.ep_collided[0, slot]),
                "final_offroad": bool(s.ep_offroad[0, slot]), "final_return": float(s.ep_return[0, slot]),
                "final_cost": float(s.ep_cost[0, slot]), "final_steps": int(s.ep_steps[0, slot])}


def check_action(action, space: gymnasium.spaces.Space, who: str):
    """A validated action: an int for Discrete, a float32 array for Box; ValueError naming `who` otherwise."""
    if isinstance(space, gymnasium.spaces.Discrete):
        a = action.detach().cpu().numpy() if isinstance(action, torch.Tensor) else np.asarray(action)
        if a.shape not in ((), (1,)) or a.dtype.kind not in "iu":
            raise ValueError(f"{who}: expected one integer action in [0, {space.n}) (Discrete({space.n})), "
                             f"got {a.dtype} of shape {a.shape}")
        v = int(a.reshape(()))
        if not 0 <= v < space.n:
            raise ValueError(f"{who}: discrete action {v} outside [0, {space.n})")
        return v
    a = action.detach().cpu().numpy() if isinstance(action, torch.Tensor) else np.asarray(action)
    if a.shape != space.shape or a.dtype.kind != "f":
        raise ValueError(f"{who}: expected a float array of shape {space.shape} (Box low={space.low.tolist()}, "
                         f"high={space.high.tolist()}), got {a.dtype} of shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{who}: action contains NaN or inf: {a.tolist()}")
    return a.astype(np.float32)


def write_action(sim: Simulator, slot: int, value, discrete: bool) -> None:
    if discrete:
        sim.actions_index[0, slot] = value
    else:
        sim.actions[0, slot, : len(value)] = torch.as_tensor(value, device=sim.actions.device)


def resolve_policy(policy, seed: int, device: str) -> Callable[[Simulator], None] | None:
    if policy is None or callable(policy):
        return policy
    return builtin_policy(str(policy), seed, device)


class TGSingleAgentEnv(gymnasium.Env):
    """One vehicle of one scene under the user's control.

    Args:
        scenes: Scene, list of Scenes, SceneSource or spec string ("procedural:merge", a .json, ...).
        scene_index: which scene of `scenes` (reset(options={"scene_index": k}) switches).
        agent: the scene's agent index to control (default: the SDC when it can be controlled,
            else the first vehicle the engine would control).
        config / overrides / continuous: as for TGVectorEnv (`continuous=True`: Box actions).
        device: engine device: "auto" (default: cuda:0 when CUDA is usable, else cpu), "cpu", "cuda"
            or "cuda:N" ("cpu" is usually fastest for a single scene).
        seed: offset of procedural scene seeds; also seeds a "random" `other_policy`.
        other_policy: None (others replay the log), a `policy(sim)` callable, or "expert",
            "constant", "random"; the others it drives are those `config.control` selects.
        background: "log" (default) or "world_model": the world model drives the other eligible
            vehicles (not with `other_policy`).
        background_model: world-model checkpoint for "world_model" (None: the shipped model).
        render_mode: None or "rgb_array" (tg_gpudrive.render).

    Reward is the engine's weighted sum; `info` holds "cost", "reward_terms"
    (name -> float), "scene_id", "agent_index", "agent_slot", and on the last
    step of an episode "final_goal", "final_collided", "final_offroad",
    "final_return", "final_cost", "final_steps".
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scenes="procedural:all", scene_index: int = 0, agent: int | None = None,
                 config: ConfigLike = None, overrides: OverridesLike = None, continuous: bool | None = None,
                 device: str = "auto", seed: int = 0, other_policy=None, render_mode: str | None = None,
                 background: str = "log", background_model=None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        if check_background(background) != "log" and other_policy is not None:
            raise ValueError(f"background: {background!r} and other_policy both drive the other vehicles; "
                             "give one of them")
        self.background, self.background_model, self.seed = background, background_model, seed
        self.render_mode = render_mode
        self.cfg = make_config(config, overrides, continuous)
        self.source = scene_source(scenes, seed)
        self.device = resolve_device(device)  # "auto" -> cpu / cuda:0, before anything is built
        self.other_policy = resolve_policy(other_policy, seed, self.device)
        self.observation_space = single_observation_space(obs_dim(self.cfg))
        self.action_space = single_action_space(self.cfg)
        self.discrete = self.cfg.discrete
        self._build(int(scene_index), agent)

    def _build(self, scene_index: int, agent: int | None) -> None:
        scene = self.source.get(scene_index)
        a = choose_agent(scene, self.cfg, agent)
        if self.other_policy is None:
            mask = np.zeros(scene.num_agents, bool)
        else:  # the others `other_policy` drives: the engine default
            mask = control.default_mask(scene, self.cfg)
        mask[a] = True
        self.world = EpisodeWorld(scene, self.cfg, self.device, mask, self.background, self.background_model,
                                  self.seed)
        self.sim = self.world.sim
        self.scene, self.scene_index, self.agent_index = scene, scene_index, a
        self.agent_slot = int(np.nonzero(self.world.slot_agent == a)[0][0])
        self._done: str | None = None
        self._started = False

    # ---------------------------------------------------------------- the API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"scene_index", "agent"}
        if unknown:
            raise ValueError(f"reset options: unknown keys {sorted(unknown)} (known: scene_index, agent)")
        k = int(options.get("scene_index", self.scene_index))
        if k != self.scene_index or options.get("agent", self.agent_index) != self.agent_index:
            self._build(k, options.get("agent"))
        self.world.reset()
        self._done, self._started = None, True
        return self.world.obs(self.agent_slot), self._info()

    def step(self, action):
        if not self._started:
            raise RuntimeError("TGSingleAgentEnv: call reset() before step()")
        if self._done is not None:
            raise ValueError(f"action for finished agent {self.agent_index} (slot {self.agent_slot}): its episode "
                             f"ended ({self._done}); call reset() before stepping again")
        a = check_action(action, self.action_space, "action")
        sim, slot = self.sim, self.agent_slot
        if self.other_policy is not None:
            self.other_policy(sim)
        write_action(sim, slot, a, self.discrete)
        self.world.step()
        terminated = bool(sim.terminated[0, slot])
        truncated = bool(sim.truncated[0, slot])
        obs = self.world.obs(slot)
        reward = float(sim.reward[0, slot])
        info = self._info()
        info.update(self.world.step_info(slot))
        if terminated or truncated:
            self._done = "terminated" if terminated else "truncated at the time limit"
            info.update(self.world.outcomes(slot))
        return obs, reward, terminated, truncated, info

    def _info(self) -> dict:
        return {"scene_id": self.scene.scene_id, "agent_index": self.agent_index, "agent_slot": self.agent_slot}

    def render(self):
        if self.render_mode is None:
            return None
        return render_world(self.sim, 0)

    def close(self):
        self.world = self.sim = None


def choose_agent(scene: Scene, cfg: EngineConfig, agent: int | None) -> int:
    """The scene agent index to control: `agent` checked, or the SDC / first default-controlled vehicle."""
    idx = control.select_slots(scene, cfg.max_agents, cfg.init_steps)
    init = control.init_index(scene, cfg)
    if agent is not None:
        agent = int(agent)
        if not 0 <= agent < scene.num_agents:
            raise ValueError(f"agent {agent}: scene {scene.scene_id} has agents 0..{scene.num_agents - 1}")
        if agent not in idx:
            raise ValueError(f"agent {agent} of scene {scene.scene_id} gets no slot (max_agents="
                             f"{cfg.max_agents} keeps the most relevant ones)")
        if not scene.log_valid[agent, init]:
            raise ValueError(f"agent {agent} of scene {scene.scene_id} is not present at init_steps={cfg.init_steps}")
        return agent
    ctrl, _ = control.default_controlled(scene, idx, cfg,
                                         ControlMode.VEHICLES if cfg.control == ControlMode.NONE else cfg.control)
    cand = idx[ctrl]
    if len(cand) == 0:
        raise ValueError(f"scene {scene.scene_id}: no vehicle can be controlled (none is present at "
                         f"init_steps={cfg.init_steps} away from its goal); pass agent=")
    sdc = cand[scene.is_sdc[cand]]
    return int(sdc[0] if len(sdc) else cand[0])
