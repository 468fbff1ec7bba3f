"""Where the expert replay's collisions and off-road events on real scenes come from.

The expert (the closed-loop tracker of each log, `Simulator.use_expert_actions`) drives every agent the
control rule gives a policy for one episode; each agent's first collision and first off-road event is
put in one class, by what its log itself shows (`data.log_audit`'s reasons), by the other agent's type
for collisions, and else by how far the replay was from the log at that step:

    class                                        meaning
    log overlaps another agent (at the first step)   the logged boxes overlap: the data
    log leaves the road                          the logged box crosses a road edge: the data
    log jumps (tracking error in the data)       the track teleports or flips: the data
    log reverses or moves sideways               beyond a forward-only vehicle model: the data
    with a pedestrian or cyclist                 the other agent is not a vehicle
    tracking (replay > 0.5 m off the log)        our controller or dynamics
    geometry (replay within 0.5 m of the log)    boxes or edges that graze where the log's do not

The first four are what the rule replays and counts apart (`replay_infeasible`); the last two are ours
to improve. `scripts/replay_events.py` prints the table for a scene set.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.log_audit import boxes_overlap, infeasible_reasons
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.enums import AgentType

TRACKING_M = 0.5  # m off the log at the event: beyond it the replay, not the log, put the box there

LOG_CLASSES = {"overlap": "log overlaps another agent", "offroad": "log leaves the road",
               "jump": "log jumps (tracking error in the data)", "kinematics": "log reverses or moves sideways"}


def first_events(scenes, cfg: EngineConfig, device: str) -> list[tuple]:
    """[(world, scene agent, kind, step, metres off the log, partner type or None)]: the first collision
    ("collision") and first off-road event ("offroad") of every policy agent under the expert replay;
    step counts from the first controlled step (0), the partner is the other box's AgentType."""
    sim = Simulator(scenes, dataclasses.replace(cfg, auto_reset=False), device)
    sim.reset()
    slot_agent = np.asarray(sim.model.slot_agent)
    policy = sim.policy_agents.cpu().numpy()
    seen: set[tuple[int, int, str]] = set()
    out = []
    for k in range(sim.episode_length):
        sim.use_expert_actions()
        sim.step()
        pos, yaw = sim.pos.cpu().numpy(), sim.yaw.cpu().numpy()
        logp = sim.log_at("log_pos", sim.world_step.clamp(max=sim.model.num_steps - 1)).cpu().numpy()
        alive = sim.alive.cpu().numpy() != 0
        for kind, flags in (("collision", sim.collided), ("offroad", sim.offroad)):
            for w, a in zip(*np.nonzero((flags.cpu().numpy() != 0) & policy)):
                if (w, a, kind) in seen:
                    continue
                seen.add((w, a, kind))
                partner = None
                if kind == "collision":
                    L, Wd = sim.length.cpu().numpy()[w], sim.width.cpu().numpy()[w]
                    hit = boxes_overlap(pos[w, a], yaw[w, a], L[a], Wd[a], pos[w], yaw[w], L, Wd) & alive[w]
                    hit[a] = False
                    types = sim.agent_type.cpu().numpy()[w][hit]
                    partner = int(types.max()) if len(types) else None
                out.append((int(w), int(slot_agent[w, a]), kind, k, float(np.linalg.norm(pos[w, a] - logp[w, a])),
                            partner))
    return out


def classify(scene, agent: int, kind: str, step: int, off: float, partner: int | None, init: int,
             radius: float) -> str:
    """The class (module docstring) of one event of `first_events`."""
    reasons = infeasible_reasons(scene, init, radius).get(agent, [])
    if kind == "collision" and "overlap" in reasons:
        return "log overlaps another agent" + (" at the first step" if step == 0 else "")
    if kind == "offroad" and "offroad" in reasons:
        return LOG_CLASSES["offroad"]
    for r in ("jump", "kinematics", "overlap", "offroad"):
        if r in reasons:
            return LOG_CLASSES[r]
    if kind == "collision" and partner in (int(AgentType.PEDESTRIAN), int(AgentType.CYCLIST)):
        return "with a pedestrian or cyclist"
    return "tracking (replay > 0.5 m off the log)" if off > TRACKING_M else "geometry (replay within 0.5 m of the log)"


