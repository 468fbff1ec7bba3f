"""Gymnasium and PettingZoo front ends of the engine, and their gymnasium ids.

    import tg_gpudrive.envs  # registers the ids below
    env = gymnasium.make("tg_gpudrive/SingleAgent-v0", scenes="procedural:merge")
    vec = gymnasium.make_vec("tg_gpudrive/Vector-v0", num_envs=1024, scenes="procedural:all", device="auto")

(or ``gymnasium.make("tg_gpudrive.envs:tg_gpudrive/SingleAgent-v0", ...)``, which imports this module.)

    id                                      class / entry point                 actions
    tg_gpudrive/SingleAgent-v0              single.TGSingleAgentEnv             Discrete(accel x curvature grid)
    tg_gpudrive/SingleAgentContinuous-v0    single.TGSingleAgentEnv             Box (accel, curvature)
    tg_gpudrive/Vector-v0                   vector.make_vector_env (make_vec)   MultiDiscrete over rows
    tg_gpudrive/VectorContinuous-v0         vector.make_vector_env (make_vec)   Box (rows, 2)

In the vector envs an env is one agent slot (a row): make_vec's `num_envs`
(a multiple of max_agents, 64 by default) is the env's own `num_envs`, here
16 worlds x 64 slots; `num_worlds=` asks for worlds instead. The PettingZoo env (parallel.TGParallelEnv) has
no gymnasium id. Every env
takes ``device=``: "auto" (the default: cuda:0 when CUDA is usable, else
cpu), "cpu", "cuda" or "cuda:N"; asking for CUDA without one is a ValueError.
"""

from __future__ import annotations

import gymnasium

from tg_gpudrive.envs.parallel import TGParallelEnv
from tg_gpudrive.envs.single import TGSingleAgentEnv
from tg_gpudrive.envs.vector import TGVectorEnv, make_vector_env

__all__ = ["TGParallelEnv", "TGSingleAgentEnv", "TGVectorEnv", "make_vector_env"]

_IDS = {
    "tg_gpudrive/SingleAgent-v0": dict(entry_point="tg_gpudrive.envs.single:TGSingleAgentEnv"),
    "tg_gpudrive/SingleAgentContinuous-v0": dict(entry_point="tg_gpudrive.envs.single:TGSingleAgentEnv",
                                                 kwargs={"continuous": True}),
    "tg_gpudrive/Vector-v0": dict(vector_entry_point="tg_gpudrive.envs.vector:make_vector_env"),
    "tg_gpudrive/VectorContinuous-v0": dict(vector_entry_point="tg_gpudrive.envs.vector:make_vector_env",
                                            kwargs={"continuous": True}),
}

for _id, _spec in _IDS.items():
    if _id not in gymnasium.registry:
        gymnasium.register(id=_id, **_spec)
