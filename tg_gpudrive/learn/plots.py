"""Training curves as a PNG (metrics.csv -> curves.png); the rates panel shows the windowed rates of
`learn.quality`, as the progress bar does."""

from __future__ import annotations

import csv
from pathlib import Path

from tg_gpudrive.learn.quality import RATE_KEYS, RATE_WINDOW, windowed_rates

PANELS = (
    (f"rates (episode-weighted, last {RATE_WINDOW} updates)", RATE_KEYS),
    ("reward terms (per agent-step)", None),  # every reward/* column
    ("cost and risk", ("cost", "cvar", "cost_budget")),
    ("Lagrange multiplier", ("lambda",)),
    ("KL terms", ("kl/prior", "kl/prev")),
    ("entropy", ("entropy",)),
    ("losses", ("loss/policy", "loss/value", "loss/cost_quantile")),
    ("throughput (agent steps/s)", ("agent_steps_per_s",)),
)


def plot_curves(csv_path: str | Path, out: str | Path) -> Path:
    # matplotlib is an optional extra, and pyplot (with its backend switch) only once a plot is drawn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(Path(csv_path).open()))
    if not rows:
        raise ValueError(f"{csv_path}: no rows to plot")
    x = [float(r["agent_steps"]) for r in rows]
    fig, axes = plt.subplots(2, 4, figsize=(18, 8))
    windowed = [windowed_rates(rows[:i + 1]) for i in range(len(rows))]
    for ax, (title, keys) in zip(axes.flat, PANELS):
        keys = keys or tuple(k for k in rows[0] if k.startswith("reward/"))
        for k in keys:
            if keys is RATE_KEYS:
                ax.plot(x, [w[k] if w else float("nan") for w in windowed], label=k)
                ax.set_ylim(-0.02, 1.02)
            elif k in rows[0]:
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
