"""Training curves as a PNG (metrics.csv -> curves.png)."""

from __future__ import annotations

import csv
from pathlib import Path

PANELS = (
    ("rates", ("goal_rate", "collision_rate", "offroad_rate")),
    ("reward terms (per agent-step)", None),  # every reward/* column
    ("cost and risk", ("cost", "cvar", "cost_budget")),
    ("Lagrange multiplier", ("lambda",)),
    ("KL terms", ("kl/prior", "kl/prev")),
    ("entropy", ("entropy",)),
    ("losses", ("loss/policy", "loss/value", "loss/cost_quantile")),
    ("throughput (agent steps/s)", ("agent_steps_per_s",)),
)


def plot_curves(csv_path: str | Path, out: str | Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(Path(csv_path).open()))
    if not rows:
        raise ValueError(f"{csv_path}: no rows to plot")
    x = [float(r["agent_steps"]) for r in rows]
    fig, axes = plt.subplots(2, 4, figsize=(18, 8))
    for ax, (title, keys) in zip(axes.flat, PANELS):
        keys = keys or tuple(k for k in rows[0] if k.startswith("reward/"))
        for k in keys:
            if k in rows[0]:
                ax.plot(x, [float(r[k]) if r[k] not in ("", "nan") else float("nan") for r in rows], label=k)
        ax.set_title(title)
        ax.set_xlabel("agent steps")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out
