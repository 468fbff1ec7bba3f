"""What drives a vehicle: a built-in or a trained policy put into worlds, decided in one place.

    opened = open_policy("shipped", scenes, "cpu", collision_mode="stop")
    out = run_rollout(opened.sim, opened.policy, opened.sim.episode_length, background=opened.background)

`open_policy` is the one recipe every command and script uses for "a policy in worlds": the engine
config (a checkpoint's own, sized so every agent of the scenes has a slot, with the evaluation
overrides it allows; a built-in policy's given config, sized likewise), who the policy drives (the
control rule: an explicit `control`, else the checkpoint's training control, else every eligible
vehicle), the background rows and their driver, then the policy itself.
"""

from tg_gpudrive.agents.worlds import BUILTIN, Opened, open_policy, trained_sim

__all__ = ["BUILTIN", "Opened", "open_policy", "trained_sim"]
