"""Diversity: how different the generated episodes of one scene are across rollouts / seeds.

For two episodes a, b of the same scene, their distance is the mean over the
policy's agents and the steps where the agent is present in both of
||pos_a - pos_b|| (metres, an average displacement). A scene's diversity is
the mean over all pairs of its episodes; the set's is the mean over scenes
with at least two episodes (also reported per scenario type). Log replay has
diversity 0 by construction.
"""

from __future__ import annotations

from collections import defaultdict
from itertools import combinations

import numpy as np

from tg_gpudrive.evaluation.episodes import Trajectories


def pair_distance(tr: Trajectories, a: int, b: int) -> float:
    both = tr.valid[a] & tr.valid[b] & (tr.policy[a] & tr.policy[b])[:, None]
    if not both.any():
        return float("nan")
    d = np.linalg.norm(tr.pos[a] - tr.pos[b], axis=-1)
    return float(d[both].mean())


def diversity(tr: Trajectories) -> dict:
    """{"mean": m, "per_scene": {scene_id: m}, "per_type": {type: m}, "pairs": n}."""
    groups: dict[str, list[int]] = defaultdict(list)
    for e, sid in enumerate(tr.scene_ids):
        groups[sid].append(e)
    types = dict(zip(tr.scene_ids, tr.scenario_types()))
    per_scene, pairs = {}, 0
    for sid, eps in groups.items():
        vals = [pair_distance(tr, a, b) for a, b in combinations(eps, 2)]
        vals = [v for v in vals if np.isfinite(v)]
        pairs += len(vals)
        if vals:
            per_scene[sid] = float(np.mean(vals))
    per_type: dict[str, list[float]] = defaultdict(list)
    for sid, v in per_scene.items():
        per_type[types[sid]].append(v)
    return {"mean": float(np.mean(list(per_scene.values()))) if per_scene else float("nan"),
            "per_scene": per_scene, "per_type": {k: float(np.mean(v)) for k, v in per_type.items()},
            "pairs": pairs}
