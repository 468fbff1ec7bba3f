"""Classify every collision and off-road event of the expert replay on real scenes, and give its rates
with and without the control rule's exclusions (data.log_audit).

    python scripts/replay_events.py --scenes ~/.cache/tg_gpudrive/womd_dev [--device cpu]

Every agent the policy would drive (the rule without its exclusions) is driven by the expert (the
closed-loop tracker of its log) for one episode; its first collision and its first off-road event are
classified by what the log itself shows (data.log_audit's reasons for that agent), by the other
agent's type for collisions, and else by how far the replay was from the log at that step:

    log overlaps another agent at the first step / later, log leaves the road, log jumps, log needs
    reversing or sideways motion   -> the log (replayed and counted apart under the rule)
    with a pedestrian or cyclist   -> the other agent is not a vehicle
    replay > 0.5 m off the log     -> tracking (our controller or dynamics)
    replay within 0.5 m of the log -> geometry (boxes or edges that graze where the log does not)

It prints the table of classes (markdown) and the rates of the expert replay per collision mode, with
the rule's exclusions and without them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections import Counter

import numpy as np

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.log_audit import boxes_overlap, infeasible_reasons
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.rollout import expert_policy, run_rollout
from tg_gpudrive.types import AgentType

LOG_CLASSES = {"overlap": "log overlaps another agent", "offroad": "log leaves the road",
               "jump": "log jumps (tracking error in the data)", "kinematics": "log reverses or moves sideways"}


def first_events(scenes, cfg, device):
    """[(world, scene agent, kind, step, metres off the log, partner type or None)] of the expert replay."""
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


def classify(scene, agent, kind, step, off, partner, init, radius):
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
    return "tracking (replay > 0.5 m off the log)" if off > 0.5 else "geometry (replay within 0.5 m of the log)"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", required=True)
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    src = resolve_scenes(args.scenes)
    scenes = [src.get(i) for i in range(len(src))]
    base = sized_for(EngineConfig(), scenes)
    for name, rule in (("without the rule's exclusions", False), ("under the rule", True)):
        cfg = dataclasses.replace(base, replay_infeasible=rule)
        events = first_events(scenes, cfg, args.device)
        table = Counter((classify(scenes[w], i, kind, t, off, partner, cfg.init_steps, cfg.goal_radius), kind)
                        for w, i, kind, t, off, partner in events)
        print(f"\n### Expert replay {name}: first events by class ({len(events)} events)\n")
        print("| class | collisions | off-road |\n|---|---:|---:|")
        for c in sorted({c for c, _ in table}):
            print(f"| {c} | {table[(c, 'collision')]} | {table[(c, 'offroad')]} |")
        for mode in ("ignore", "stop", "remove"):
            sim = Simulator(scenes, dataclasses.replace(cfg, collision_mode=mode), args.device)
            r = run_rollout(sim, expert_policy, sim.episode_length, episodes_per_world=1)
            print(json.dumps({"rule": rule, "mode": mode, **{k: r[k] for k in ("agent_episodes", "goal_rate",
                  "collision_rate", "offroad_rate", "score_rate")}, **{k: v for k, v in sim.report().items()
                  if k.startswith("agents_")}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
