"""Classify every collision and off-road event of the expert replay on real scenes, and give its rates
with and without the control rule's exclusions (data.log_audit).

    python scripts/replay_events.py --scenes ~/.cache/tg_gpudrive/womd_dev [--device cpu]

The classes: `tg_gpudrive/evaluation/log_events.py`. It prints the table of classes (markdown) and the rates of the expert replay per collision mode, with
the rule's exclusions and without them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections import Counter

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.evaluation.log_events import classify, first_events
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout


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
