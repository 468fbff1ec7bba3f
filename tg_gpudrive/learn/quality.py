"""The stopping rule of training: windowed rates and the quality bar.

Per-update rates are noisy and often undefined (no episode ended in that update), so every place a
person reads rates (the progress bar, the rates panel of curves.png, the final line) and the rule that
stops training at quality (`target_*`) use them episode-weighted over the last `RATE_WINDOW` updates
(`windowed_rates`); `time_to_quality` finds the first update of a metrics.csv that meets the bar.
"""

from __future__ import annotations

import math
from typing import Sequence

RATE_WINDOW = 10  # updates
RATE_KEYS = ("goal_rate", "collision_rate", "offroad_rate")


def windowed_rates(rows: Sequence[dict], window: int = RATE_WINDOW) -> dict[str, float] | None:
    """Episode-weighted goal / collision / off-road rates over the last `window` rows (metrics.csv
    rows or the trainer's row dicts, with "episodes" and the per-update rates); None before any
    episode has ended."""
    def num(v) -> float:
        v = float(v) if v not in ("", None) else float("nan")
        return 0.0 if math.isnan(v) else v

    recent = rows[-window:]
    n = sum(num(r["episodes"]) for r in recent)
    if n <= 0:
        return None
    return {k: sum(num(r[k]) * num(r["episodes"]) for r in recent) / n for k in RATE_KEYS}


def meets_quality(rates: dict, goal: float, collision: float, offroad: float) -> bool:
    """goal_rate >= goal with collision_rate <= collision and offroad_rate <= offroad (bounds inclusive):
    the one quality rule of training's stop (`target_*`) and of `time_to_quality`."""
    return rates["goal_rate"] >= goal and rates["collision_rate"] <= collision and rates["offroad_rate"] <= offroad


def time_to_quality(rows: Sequence[dict], goal: float = 0.95, collision: float = 0.05, offroad: float = 0.02,
                    window: int = RATE_WINDOW) -> dict | None:
    """The first metrics.csv row whose windowed rates (the `window` updates up to it) meet the
    quality bar: goal >= `goal` with collision <= `collision` and off-road <= `offroad`. Returns
    that row's update, wall_s (rollouts and updates), elapsed_s (all of training, where logged) and
    rates, or None if training never got there (BENCHMARKS.md's
    time to quality; a full window is required, so a lucky first update does not count)."""
    for i in range(window, len(rows) + 1):
        r = windowed_rates(rows[:i], window)
        if r and meets_quality(r, goal, collision, offroad):
            got = {"update": int(float(rows[i - 1]["update"])), "wall_s": float(rows[i - 1]["wall_s"]), **r}
            if rows[i - 1].get("elapsed_s") not in (None, ""):
                got["elapsed_s"] = float(rows[i - 1]["elapsed_s"])
            return got
    return None
