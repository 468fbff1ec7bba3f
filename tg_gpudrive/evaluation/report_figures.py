"""The report's pictures, each drawn from numbers the report has gathered (no rollouts here).

    plot_grid           grid.png: the paper's beta x alpha figure, one frame per CCE-MAPPO cell
    plot_multipliers    multipliers.png: lambda, CVaR and cost during training, per run (a colour per cell)
    plot_gaps           cce_gap.png: each agent's CCE-gap per policy, with the mean and its interval
    plot_gap_curves     cce_gap_curve.png: the CCE-gap over each run's training
    plot_worst_scenes   worst_scenes.png: the last frames of the scenes where a policy fails most

Each plot_* function saves `path` and returns its Figure; every picture stays within MAX_FIG_W x
MAX_FIG_H at any number of runs. matplotlib (the render extra) is imported only when one is drawn.
"""

from __future__ import annotations

import textwrap
from collections import Counter
from pathlib import Path

import numpy as np


# bounds of the report's pictures (inches at 100 dpi): they stay readable and bounded at any number of runs
MAX_FIG_W, MAX_FIG_H = 26.0, 20.0
GRID_MIN_SIDE = 6.0  # in: the grid's cells together span at least this (one run: one 6-inch cell)
GRID_LEGEND_IN = 0.6  # in below the grid's cells for the legend of what the frames draw


def _fig():
    """A blank Figure on the Agg canvas (no window, no pyplot state)."""
    # matplotlib (the render extra) only when a picture is drawn, so the report's numbers do not need it
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _wrapped(text: str, width_in: float, fontsize: float) -> str:
    """`text` wrapped to lines that fit `width_in` inches at `fontsize` points (about 0.55 em a character)."""
    return "\n".join(textwrap.wrap(text, max(12, int(width_in * 72 / (0.55 * fontsize)))))


def _short(label: str, n: int = 26) -> str:
    """`label` cut to `n` characters, keeping its start and end (run names differ at the end)."""
    return label if len(label) <= n else label[: n - 10] + "…" + label[-9:]


def plot_grid(cells: dict[tuple[float, float], np.ndarray], path: Path, max_rows: int = 8, scene: str = "",
              notes: dict[tuple[float, float], str] | None = None, zoom: str = ""):
    """The paper's beta x alpha figure: one picture per CCE-MAPPO cell (the report's: the whole paths beside a
    zoom on one moment, the report's shared moment, which `zoom` says in the title), beta down the rows, alpha
    across the columns, each cell's line of `notes` at its picture's foot (what it measured on the scene, which a
    picture of metres at a crossing's scale does not show). More than `max_rows` betas wrap into further blocks
    side by side (each block all the alphas); cells shrink (from 2.4 in tall) and labels with them, so the picture
    stays within MAX_FIG_W x MAX_FIG_H; the title wraps to the picture's width."""
    from tg_gpudrive.render.draw import legend_handles  # the render extra, as the cells' frames

    betas = sorted({b for b, _ in cells}) or [0.0]
    alphas = sorted({a for _, a in cells}) or [0.0]
    blocks = [betas[i:i + max_rows] for i in range(0, len(betas), max_rows)]
    nrows, ncols = len(blocks[0]), len(blocks) * len(alphas)
    # a cell's picture may be wider than tall (the whole paths beside the closest approach): `cell` is its height
    aspect = max((im.shape[1] / im.shape[0] for im in cells.values()), default=1.0)
    # a few cells are drawn large (GRID_MIN_SIDE in across the picture), many shrink towards the bounds
    cell = min(max(2.4, GRID_MIN_SIDE / max(nrows, ncols * aspect)),
               (MAX_FIG_W - 0.8 - 0.3 * len(blocks)) / (ncols * aspect), (MAX_FIG_H - 1.2 - GRID_LEGEND_IN) / nrows)
    fs = max(5.0, min(9.0, cell * 72 / (0.6 * 13)))  # "beta = 10.5 m" fits beside a cell
    width = max(4.0, ncols * cell * aspect + 0.3 * len(blocks) + 0.8)
    where = f" on scene {scene}" if scene else ""
    what = (f"left, whole trajectories (a dot each second); right, {zoom or 'the closest approach zoomed in'}"
            if aspect > 1.5 else "whole trajectories (a dot each second)")
    title = _wrapped(f"CCE-MAPPO{where}: beta (distance constraint, rows) x alpha (CVaR level, columns); {what}; "
                     "controlled vehicles blue", width - 0.2, 9)
    head = 0.25 + 0.18 * (title.count("\n") + 1)  # inches above the panels for the title
    height = nrows * cell + 0.4 + head + GRID_LEGEND_IN
    fig = _fig()
    fig.set_size_inches(width, height)
    for k, block in enumerate(blocks):
        for r, b in enumerate(block):
            for c, a in enumerate(alphas):
                ax = fig.add_subplot(nrows, ncols, r * ncols + k * len(alphas) + c + 1)
                ax.set_xticks([])
                ax.set_yticks([])
                if (b, a) in cells:
                    ax.imshow(cells[(b, a)])
                if (b, a) in (notes or {}):  # bottom right: the frame's scale bar holds the bottom left
                    ax.text(0.98, 0.02, notes[(b, a)], transform=ax.transAxes, ha="right", va="bottom",
                            fontsize=max(5.0, fs - 1), bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.6"))
                if r == 0:
                    ax.set_title(f"alpha = {a:g}", fontsize=fs)
                if c == 0:
                    ax.set_ylabel(f"beta = {b:g} m", fontsize=fs)
    if not cells:
        fig.axes[0].text(0.5, 0.5, "no CCE-MAPPO run", ha="center", va="center", fontsize=9)
    fig.suptitle(title, fontsize=9, y=1 - 0.1 / height, va="top")
    handles = legend_handles()
    fig.legend([h for h, _ in handles], [n for _, n in handles], loc="center", ncol=6 if width >= 5.5 else 4,
               fontsize=7, frameon=False, bbox_to_anchor=(0.5, GRID_LEGEND_IN / 2 / height))
    fig.tight_layout(rect=(0, GRID_LEGEND_IN / height, 1, 1 - head / height))
    # rows carry no labels between them, so tight_layout may close the gap below 0: the pictures would overlap
    fig.subplots_adjust(hspace=max(fig.subplotpars.hspace, 0.02))
    fig.savefig(path)
    return fig


def plot_multipliers(curves: dict[str, list[dict]], path: Path, groups: dict[str, str] | None = None):
    """The Lagrange multiplier, the CVaR of the cost-to-go and the cost per agent-step against the
    training update, one line per run in three panels; the legend goes below them in columns (its rows
    grow the picture, up to MAX_FIG_H). `groups` names each run's cell (its training seeds share one):
    when a cell has several runs, its lines share a colour and the legend has one entry per cell."""
    fig = _fig()
    groups = {label: (groups or {}).get(label, label) for label in curves}
    by_cell = len(set(groups.values())) < len(groups)
    line_of = groups if by_cell else {label: label for label in curves}  # a run's colour and legend entry
    runs = Counter(line_of.values())
    colour = {name: k for k, name in enumerate(runs)}
    ncol = 4
    legend_rows = -(-len(runs) // ncol)
    extra = min(0.2 * legend_rows, MAX_FIG_H - 3.4)
    fig.set_size_inches(12, 3.4 + extra)
    styles = ("-", "--", ":", "-.")
    for i, key in enumerate(("lambda", "cvar", "cost")):
        ax = fig.add_subplot(1, 3, i + 1)
        drawn = set()
        for label, rows in curves.items():
            name = line_of[label]
            j = colour[name]
            x = [int(r["update"]) for r in rows if r.get(key) not in (None, "", "nan")]
            y = [float(r[key]) for r in rows if r.get(key) not in (None, "", "nan")]
            legend = None  # a cell's first line carries its entry
            if name not in drawn:
                legend = _short(f"{name} ({runs[name]} runs)" if runs[name] > 1 else name, 40)
            drawn.add(name)
            ax.plot(x, y, marker="." if len(x) < 10 else None, lw=1, label=legend,
                    color=f"C{j % 10}", ls=styles[j // 10 % len(styles)], alpha=0.7 if by_cell else 1.0)
        ax.set_xlabel("update", fontsize=8)
        ax.set_title({"lambda": "Lagrange multiplier lambda", "cvar": "CVaR_alpha of cost-to-go",
                      "cost": "cost per agent-step"}[key], fontsize=9)
        ax.tick_params(labelsize=7)
    bottom = (extra + 0.1) / (3.4 + extra)
    if curves:
        handles, labels = fig.axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7, frameon=False,
                   bbox_to_anchor=(0.5, 0.0))
    fig.tight_layout(rect=(0, bottom, 1, 1))
    fig.savefig(path)
    return fig


def plot_gap_curves(curves: dict[str, list[dict]], path: Path):
    """CCE-gap against the training update, one line per run, with its 95 % interval as a band."""
    fig = _fig()
    fig.set_size_inches(6.0, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    for i, (label, pts) in enumerate(curves.items()):
        u = np.array([p["update"] for p in pts], float)
        m = np.array([p["mean_gap"] for p in pts], float)
        ci = np.nan_to_num(np.array([p["ci95"] if p["ci95"] is not None else np.nan for p in pts], float))
        ax.plot(u, m, marker="o", ms=3, lw=1, color=f"C{i % 10}", label=_short(label))
        ax.fill_between(u, m - ci, m + ci, color=f"C{i % 10}", alpha=0.15, lw=0)
    ax.set_xlabel("training update", fontsize=8)
    ax.set_ylabel("CCE-gap (mean over agents)", fontsize=8)
    ax.tick_params(labelsize=7)
    if curves:
        ax.legend(fontsize=6, loc="upper right")
    else:
        ax.text(0.5, 0.5, "no run kept policies (keep_policy_every)", ha="center", va="center", transform=ax.transAxes)
    fig.suptitle("CCE-gap over training (95 % interval over agents)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    return fig


def plot_gaps(gaps: dict[str, dict], path: Path):
    """CCE-gap per policy: each agent's gap (PPO best response, exploitability.py) a dot, the mean
    over agents with its 95% CI over agents a black bar.
    One column per policy, wrapped into rows of at most `per_row` columns (at most 6 rows; more
    policies make the columns narrower), so the picture stays within MAX_FIG_W x MAX_FIG_H."""
    labels = list(gaps)
    n = max(len(labels), 1)
    per_row = max(12, -(-n // 6))
    rows = -(-n // per_row)
    cols = min(n, per_row)
    width = min(MAX_FIG_W, max(5.0, 0.75 * cols + 1.6))
    height = min(MAX_FIG_H, 3.0 * rows + 0.5)
    fig = _fig()
    fig.set_size_inches(width, height)
    vals = [v for g in gaps.values() for v in g["gap_per_agent"] if np.isfinite(v)]
    hi = max(vals + [g["mean_gap"] + (g.get("ci95") or 0) for g in gaps.values()
                     if np.isfinite(g["mean_gap"] + (g.get("ci95") or 0))] + [1e-6])
    rng = np.random.default_rng(0)
    for r in range(rows):
        ax = fig.add_subplot(rows, 1, r + 1)
        part = labels[r * per_row:(r + 1) * per_row]
        for i, label in enumerate(part):
            g = gaps[label]
            y = np.asarray(g["gap_per_agent"], float)
            ax.scatter(i + rng.uniform(-0.18, 0.18, len(y)), y, s=9, alpha=0.6, color=f"C{(r * per_row + i) % 10}",
                       label="gap of one agent" if r == 0 and i == 0 else None)
            ax.errorbar(i, g["mean_gap"], yerr=g.get("ci95") or 0, fmt="_", ms=14, color="k", capsize=3, lw=1,
                        label="mean over agents, 95% CI over agents" if r == 0 and i == 0 else None)
        ax.set_xlim(-0.6, cols - 0.4)
        ax.set_ylim(-0.05 * hi, 1.1 * hi)
        ax.set_xticks(range(len(part)))
        ax.set_xticklabels([_short(lab) for lab in part], rotation=25, ha="right", fontsize=7)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_ylabel("CCE-gap", fontsize=8)
        if r == 0 and labels:  # above the panel, under the title: it never hides a dot
            ax.legend(fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=2, frameon=False)
    if not labels:
        fig.axes[0].text(0.5, 0.5, "no CCE-gap measured", ha="center", va="center", transform=fig.axes[0].transAxes)
    title = _wrapped("CCE-gap (discounted-return gain of each agent's PPO best response) per policy", width - 0.2, 9)
    head = 0.05 + 0.18 * (title.count("\n") + 1)
    fig.suptitle(title, fontsize=9, y=1 - 0.05 / height, va="top")
    fig.tight_layout(rect=(0, 0, 1, 1 - head / height))
    fig.savefig(path)
    return fig


def plot_worst_scenes(frames: list[np.ndarray], rows: list[dict], label: str, path: Path):
    """The last frames of the worst scenes side by side, each titled with its failures; frames wider than tall
    (the report's: the whole paths beside the closest approach) wrap into rows about 13 inches wide."""
    fig = _fig()
    aspect = max((im.shape[1] / im.shape[0] for im in frames), default=1.0)
    ncols = max(1, min(len(frames), int(13.0 // (3.2 * aspect))))
    nrows = -(-len(frames) // ncols)
    fig.set_size_inches(min(3.2 * aspect * ncols, MAX_FIG_W), min(3.6 * nrows, MAX_FIG_H))
    for k, (img, r) in enumerate(zip(frames, rows)):
        ax = fig.add_subplot(nrows, ncols, k + 1)
        ax.imshow(img)
        ax.set_axis_off()
        ax.set_title(f"{_short(r['scene_id'], 22)}\ncollisions {r['collisions']}, off-road {r['offroad']} "
                     f"of {r['agent_episodes']}", fontsize=8)
    fig.suptitle(f"Worst scenes of {label}", fontsize=10)
    fig.savefig(path)
    return fig
