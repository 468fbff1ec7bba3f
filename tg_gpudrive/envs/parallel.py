"""`TGParallelEnv`: every controlled vehicle of one scene as a PettingZoo ParallelEnv agent.

Agents are named ``agent_<slot>`` after their engine slot; `possible_agents`
are the scene's controlled slots (`config.control`, or an explicit
`controlled` mask), all live after reset. The other eligible vehicles replay
their logs, or with ``background="world_model"`` are driven by the learned
world model (never agents of the env). An agent leaves `env.agents` on the
step the engine terminates it, which follows the config: a goal ends it unless
``goal_behaviour="continue"``; a collision or off-road ends it in the "stop"
and "remove" collision modes and never in "ignore" (the event is then only
counted, in the reward terms and obs flags). At the scene's last step every
remaining agent is truncated. Stopped agents stay in the scene, frozen;
removed ones leave it. Observations, rewards and flags are numpy / Python
values per agent, returned for the agents that acted in the step (those that
just finished included, with their true terminal obs: the world never
auto-resets: it runs with ``auto_reset=False``).

Actions: a dict with one action for every agent in `env.agents`; an action
for an agent that already left is a ValueError ("action for finished agent"),
as is a missing or unknown agent, or a wrong shape or dtype.

Many scenes at once: this env runs one scene, stepping one engine world and
copying per-agent rows to the host, which suits tests, evaluation and
PettingZoo tooling. For training over many scenes use the torch-native
`TGVectorEnv` (tg_gpudrive/envs/vector.py): one row per agent slot of W
worlds, agents of all worlds stepped together on the device, with
``info["active"]`` as the live-agent mask (rows whose agents are done stay in
the batch, masked, until their world resets).
"""

from __future__ import annotations

import gymnasium
import numpy as np
from pettingzoo import ParallelEnv

from tg_gpudrive.engine import control
from tg_gpudrive.engine.model import obs_dim
from tg_gpudrive.engine.simulator import resolve_device
from tg_gpudrive.envs.single import EpisodeWorld, check_action, write_action
from tg_gpudrive.envs.vector import (
    ConfigLike,
    OverridesLike,
    make_config,
    render_world,
    scene_source,
    single_action_space,
    single_observation_space,
)
from tg_gpudrive.agents.builtin import check_background


class TGParallelEnv(ParallelEnv):
    """Args: as `TGSingleAgentEnv` (scenes, scene_index, config, overrides, continuous, device, seed,
    render_mode), plus `controlled`: an optional bool mask over the scene's agents choosing the agents
    (default: those `config.control` selects), and `background` / `background_model`: who drives the
    other eligible vehicles, "log" (default) or "world_model" (None: the shipped model)."""

    metadata = {"name": "tg_gpudrive_parallel_v0", "render_modes": ["rgb_array"], "render_fps": 10,
                "is_parallelizable": True}

    def __init__(self, scenes="procedural:all", scene_index: int = 0, config: ConfigLike = None,
                 overrides: OverridesLike = None, continuous: bool | None = None, device: str = "auto",
                 seed: int = 0, controlled: np.ndarray | None = None, render_mode: str | None = None,
                 background: str = "log", background_model=None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        check_background(background)
        device = resolve_device(device)  # a CUDA request without CUDA fails here, before the scene loads
        self.render_mode = render_mode
        self.cfg = make_config(config, overrides, continuous)
        self.discrete = self.cfg.discrete
        self.scene = scene = scene_source(scenes, seed).get(int(scene_index))
        controlled = control.default_mask(scene, self.cfg) if controlled is None else np.asarray(controlled, bool)
        if controlled.shape != (scene.num_agents,):
            raise ValueError(f"controlled: expected a bool mask of shape ({scene.num_agents},), "
                             f"got {controlled.shape}")
        self.world = EpisodeWorld(scene, self.cfg, device, controlled, background, background_model, seed)
        self.sim = self.world.sim
        if len(self.world.slots) == 0:
            raise ValueError(f"scene {scene.scene_id}: no agent is controlled (config.control="
                             f"{str(self.cfg.control)!r}); nothing to act")
        self.possible_agents = [f"agent_{s}" for s in self.world.slots]
        self._slot = {name: int(s) for name, s in zip(self.possible_agents, self.world.slots)}
        self._obs_space = single_observation_space(obs_dim(self.cfg))
        self._act_spaces = {name: single_action_space(self.cfg) for name in self.possible_agents}
        self.agents: list[str] = []
        self._finished: dict[str, str] = {}

    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        return self._obs_space

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        return self._act_spaces[agent]

    def agent_slot(self, agent: str) -> int:
        return self._slot[agent]

    # ---------------------------------------------------------------- the API
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            for i, space in enumerate(self._act_spaces.values()):
                space.seed(seed + i)
        self.world.reset()
        self.agents = list(self.possible_agents)
        self._finished = {}
        obs_all = self.sim.obs[0].detach().to("cpu", copy=True).numpy()
        return {a: obs_all[self._slot[a]] for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions: dict):
        if not isinstance(actions, dict):
            raise ValueError(f"actions: expected a dict agent -> action, got {type(actions).__name__}")
        for name in actions:
            if name not in self._slot:
                raise ValueError(f"action for unknown agent {name!r} (possible agents: "
                                 f"{', '.join(self.possible_agents)})")
            if name not in self.agents:
                why = self._finished.get(name, "the episode has not been reset")
                raise ValueError(f"action for finished agent {name!r}: it left env.agents ({why}); "
                                 "agents that are done take no actions")
        if not self.agents:
            raise ValueError("step() with no live agent: every agent finished (or reset() was not called); "
                             "call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: missing for live agents {missing}")
        sim = self.sim
        checked = {name: check_action(a, self._act_spaces[name], f"action of {name!r}") for name, a in actions.items()}
        for name, a in checked.items():
            write_action(sim, self._slot[name], a, self.discrete)
        self.world.step()
        # one host copy per quantity; each agent's obs is a row of this step's own array
        obs_all = sim.obs[0].detach().to("cpu", copy=True).numpy()
        term, trunc = sim.terminated[0].tolist(), sim.truncated[0].tolist()
        reward, cost, terms_all = sim.reward[0].tolist(), sim.cost[0].tolist(), sim.reward_terms[0].tolist()
        names = sim.reward_term_names
        acted = self.agents
        obs, rew, terms, truncs, infos = {}, {}, {}, {}, {}
        for name in acted:
            s = self._slot[name]
            obs[name] = obs_all[s]
            rew[name] = reward[s]
            terms[name] = bool(term[s])
            truncs[name] = bool(trunc[s])
            infos[name] = {"cost": cost[s], "reward_terms": dict(zip(names, terms_all[s]))}
            if terms[name] or truncs[name]:
                infos[name].update(self.world.outcomes(s))
                self._finished[name] = (f"terminated at log step {self.world.step_now}" if terms[name]
                                        else "truncated at the time limit")
        self.agents = [a for a in acted if not (terms[a] or truncs[a])]
        return obs, rew, terms, truncs, infos

    def render(self):
        if self.render_mode is None:
            return None
        return render_world(self.sim, 0)

    def close(self):
        pass
