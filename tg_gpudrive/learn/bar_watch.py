"""Whether the constraint's bar is within the policy's reach. While the constrained cost stays above its
budget the Lagrange multiplier climbs every update (or sits at its cap, `lambda_max`); when the cost has also
stopped coming down, that climb buys a policy the cost outweighs: goals fall and the bar is still not met. The
trainer warns once, with the figures and the ways out: a looser `cost_limit`, or a cap on lambda that keeps
the reward in play."""

from __future__ import annotations

from collections import deque

import numpy as np

from tg_gpudrive.config import TrainConfig

WINDOW = 100  # updates the watch looks back over
MARGIN = 1.5  # constraint / budget above which the bar counts as unmet
STALLED = 0.8  # the window's last tenth of the constraint over its first tenth, at or above which it has stalled


class BarWatch:
    """Feed every update's metrics row to `add`; it returns the warning once, the first time the last
    `window` updates all held the constraint above MARGIN x its budget and its last tenth came down less
    than (1 - STALLED) from its first; None otherwise (and always without a constraint). Rows of the warm-up
    (`update` <= lambda_warmup), whose multipliers were held, are not watched."""

    def __init__(self, cfg: TrainConfig, window: int | None = None):
        self.on, self.cap, self.window = bool(cfg.constraint), float(cfg.lambda_max), window or WINDOW
        self.key = {"cvar": "cvar", "mean": "cost_to_go"}.get(cfg.lambda_on, "constraint")
        self.name = {"cvar": f"CVaR_{cfg.alpha:g} of the cost-to-go", "mean": "mean cost-to-go",
                     "sampled": "sampled cost rate x 1 / (1 - gamma)",
                     "sampled_cvar": f"CVaR_{cfg.alpha:g} over the vehicles of the sampled cost rate x 1 / (1 - gamma)",
                     }[cfg.lambda_on]
        self.warmup = cfg.lambda_warmup
        self.recent: deque[tuple[float, float, float]] = deque(maxlen=self.window)
        self.warned = False

    def add(self, row: dict) -> str | None:
        if not self.on or self.warned or row.get("update", self.warmup + 1) <= self.warmup:
            return None
        self.recent.append((row["lambda"], row[self.key], row["cost_budget"]))
        if len(self.recent) < self.window:
            return None
        lam, con, budget = (np.array(x) for x in zip(*self.recent))
        tenth = max(1, self.window // 10)
        first, last = float(con[:tenth].mean()), float(con[-tenth:].mean())
        if not (con > MARGIN * budget).all() or last < STALLED * first:
            return None
        self.warned = True
        capped = self.cap > 0 and lam[-1] >= self.cap * (1.0 - 1e-6)
        if capped:
            how = (f"sat at its cap lambda_max = {self.cap:g}. It can climb no further, so the bar will not be met; "
                   "a looser cost_limit sets one the policy can reach")
        else:
            how = (f"went {lam[0]:.3g} -> {lam[-1]:.3g}. It climbs for as long as the bar is unmet, until the cost "
                   "outweighs the reward; a looser cost_limit, or a cap on lambda (lambda_max), stops that")
        return (f"the constraint's bar looks out of reach: over the last {self.window} updates the {self.name} "
                f"stayed above {MARGIN:g}x its budget of {budget[-1]:.3g} ({first:.3g} -> {last:.3g}) while lambda "
                + how)


def replay(cfg: TrainConfig, rows: list[dict]) -> int | None:
    """The update at which a finished run's metrics rows (metrics.csv, run under `cfg`) first drew the warning;
    None if they never did, or hold no multiplier."""
    watch = BarWatch(cfg)
    keys = ("update", "lambda", watch.key, "cost_budget")
    for r in rows:
        if any(r.get(k) in (None, "", "nan") for k in keys):
            return None
        if watch.add({k: float(r[k]) for k in keys}):
            return int(float(r["update"]))
    return None


def label(update: int | None) -> str:
    """A run's verdict as the flexibility tables print it: the update the trainer warned at, or "-"."""
    return "-" if update is None else f"from update {update}"
