"""What drives a vehicle: the policy's networks and head, the behaviour priors, and a built-in or
trained policy put into worlds, decided in one place.

Below the world model: `networks.py` (actor, centralised critic), `policy.py` (`PolicyHead` with its
exact KLs, the `BehaviourPrior` interface, building and loading a policy), `prior.py` (the expert
prior). Above it: `worlds.py` (`open_policy`, which uses the world-model background). This package
imports the upper half lazily, so the world model can import the lower half.

    opened = open_policy("shipped", scenes, "cpu", collision_mode="stop")
    out = run_rollout(opened.sim, opened.policy, opened.sim.episode_length, background=opened.background)

`open_policy` is the one recipe every command and script uses for "a policy in worlds": the engine
config (a checkpoint's own, sized so every agent of the scenes has a slot, with the evaluation
overrides it allows; a built-in policy's given config, sized likewise), who the policy drives (the
control rule: an explicit `control`, else the checkpoint's training control, else every eligible
vehicle), the background rows and their driver, then the policy itself.
"""

__all__ = ["BUILTIN", "Opened", "check_specs", "open_policy", "trained_sim"]


def __getattr__(name: str):
    if name in __all__:
        from tg_gpudrive.agents import worlds

        return getattr(worlds, name)
    raise AttributeError(f"module 'tg_gpudrive.agents' has no attribute {name!r}")
