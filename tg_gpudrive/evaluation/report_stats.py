"""The numbers a scenario-quality report derives from recorded episodes and training curves.

    measure(label, gen, logged, top)   fidelity, diversity and risk of one policy's episodes
    episode_figures(gen, risk)         one value per agent-episode of each figure the flexibility claims name
    group_cells(results)               the CCE-MAPPO runs grouped by (beta, alpha), their training seeds together
    flexibility_directions(cells)      Spearman's rho of each figure with beta and with alpha, with intervals
    knob_effects(cells)                each figure's change between a knob's extreme cells, with intervals
    gap_headroom(cells)                how much min gap beta, or alpha at a beta, can buy at most
    gap_against_mappo(results)         each CCE-MAPPO policy's CCE-gap against plain MAPPO's, agent by agent
    worst_scenes(gen)                  the scenes where the policy's agents fail most
    knob_scene(dists)                  the scene where beta (or alpha) moves the distance kept most
    tail_means(rows, keys)             training figures averaged over the last updates
    gap_curve(start, kept, last, u)    the CCE-gap over a run's training

No rollouts, no files, no pictures: report.py runs the policies, report_figures.py draws,
report_markdown.py writes the tables. `fmt` is how the report prints a number, here because the
flexibility rows carry their interval as text.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from tg_gpudrive.evaluation import diversity as div
from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.stats import as_runs, effect_ci, paired_difference, spearman_ci

WORST_SCENES = 4  # scenes drawn in worst_scenes.png


def fmt(v, nd=3) -> str:
    """A table cell's number: `nd` significant digits, integers as they are, "-" for None."""
    if v is None:
        return "-"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    return "nan" if math.isnan(v) else f"{v:.{nd}g}" if abs(v) < 1e4 else f"{v:.3e}"


def worst_scenes(gen, k: int = WORST_SCENES) -> list[dict]:
    """The `k` scenes where the policy's agents fail most (a collision or leaving the road, per
    agent-episode), most failures first: scene index and id, agent-episodes, collisions, off-road."""
    pol = np.asarray(gen.policy, bool)
    col = np.asarray(gen.collided, bool).any(-1) & pol
    off = np.asarray(gen.offroad, bool).any(-1) & pol
    by: dict[int, list[int]] = {}
    for e, i in enumerate(np.asarray(gen.scene_index)):
        t = by.setdefault(int(i), [0, 0, 0, 0])
        t[0] += int(pol[e].sum())
        t[1] += int(col[e].sum())
        t[2] += int(off[e].sum())
        t[3] += int((col[e] | off[e]).sum())
    rows = [{"scene": i, "scene_id": gen.scenes[i].scene_id, "agent_episodes": n, "collisions": c, "offroad": o,
             "failure_rate": f / n} for i, (n, c, o, f) in by.items() if n and f]
    return sorted(rows, key=lambda r: (-r["failure_rate"], -r["agent_episodes"], r["scene"]))[:k]


def scene_distances(gen) -> dict[str, float]:
    """Per scene id: the mean, over the policy's agent-episodes of every rollout seed, of each agent's least
    centre distance to another agent (`nearest`, over its present steps)."""
    pol = np.asarray(gen.policy, bool) & np.asarray(gen.valid, bool).any(-1)
    least = np.where(gen.valid, gen.nearest, np.inf).min(-1)  # (E, A)
    sums: dict[str, list[float]] = {}
    for e, i in enumerate(np.asarray(gen.scene_index)):
        t = sums.setdefault(gen.scenes[int(i)].scene_id, [0.0, 0])
        t[0] += float(least[e][pol[e]].sum())
        t[1] += int(pol[e].sum())
    return {k: a / n for k, (a, n) in sums.items() if n}


def knob_scene(cells: dict[tuple[float, float], dict[str, float]]) -> tuple[str, float] | None:
    """The scene (id) where the knob moves the distance kept most, and by how much (m): per scene, the mean
    least distance of the largest beta's cell minus the smallest beta's, averaged over the alphas both have;
    with a single beta, the largest alpha's minus the smallest alpha's (the paper's direction: a larger beta,
    or a larger alpha, the more risk-averse, keeps more distance). `cells` maps (beta, alpha) to its
    `scene_distances`. None with fewer than two cells, or no scene that the extreme cells share."""
    betas = sorted({b for b, _ in cells})
    alphas = sorted({a for _, a in cells})
    if len(betas) > 1:
        pairs = [((betas[-1], a), (betas[0], a)) for a in alphas if (betas[0], a) in cells and (betas[-1], a) in cells]
    else:
        pairs = [((betas[0], alphas[-1]), (betas[0], alphas[0]))] if len(alphas) > 1 else []
    diffs: dict[str, list[float]] = {}
    for hi, lo in pairs:
        d_hi, d_lo = cells[hi], cells[lo]
        for k in d_hi.keys() & d_lo.keys():
            diffs.setdefault(k, []).append(d_hi[k] - d_lo[k])
    full = {k: float(np.mean(v)) for k, v in diffs.items() if len(v) == len(pairs)}
    if not full:
        return None
    best = max(sorted(full), key=lambda k: full[k])
    return best, full[best]


def episode_keys(gen, m: np.ndarray) -> np.ndarray:
    """'scene|rollout seed|scene agent' of each agent-episode of mask `m` (E, A), in the figures' order: two
    runs played the same agent-episodes when their keys are equal."""
    ids = gen.scene_ids
    return np.array([f"{ids[e]}|{gen.seed[e]}|{gen.slot_agent[e, a]}" for e, a in zip(*np.nonzero(m))], dtype=str)


def episode_figures(gen, risk: dict) -> dict[str, np.ndarray]:
    """One value per policy agent-episode of each figure the flexibility claims are about, its `start_gap` (the
    min gap's ceiling), its `episode_key` and its scene's `scenario_type`."""
    m = risk["agents"]  # present at some step, so the mean speed below has a step to average
    speed = np.where(gen.valid, gen.speed, 0.0).sum(-1) / np.maximum(gen.valid.sum(-1), 1)
    types = np.array(gen.scenario_types(), dtype=str)[np.nonzero(m)[0]]
    return {"episode_key": episode_keys(gen, m), "scenario_type": types, "start_gap": risk["start_gap"][m],
            "min_gap": risk["min_gap"][m], "min_gap_ahead": risk["min_gap_ahead"][m],
            "close_time": risk["close_time"][m], "speed": speed[m],
            "ttc_critical": (risk["min_ttc"][m] < rk.TTC_CRITICAL).astype(float),
            "collision": risk["collided"][m].astype(float), "hard_brakes": risk["hard_brakes"][m].astype(float),
            "collision_other": ((risk["contact"] >= 0) & ~risk["partner_policy"])[m].astype(float),
            "from_behind": (risk["contact"] == rk.CONTACTS.index("from behind"))[m].astype(float),
            # rows, not values: the Hellinger figure is a statistic of their sum (flexibility_directions)
            "hellinger": fid.episode_histograms(gen, m).astype(np.float32)}


def measure(label: str, gen, logged, top: int) -> dict:
    """Fidelity, diversity and risk of recorded episodes `gen` against the `logged` ones (no CCE-gap),
    with the `top` most critical scenarios; `figures` holds the per-agent-episode values behind the
    flexibility intervals (left out of summary.json)."""
    risk = rk.episode_risk(gen)
    return {"label": label, "fidelity": fid.compare(logged, gen), "diversity": div.diversity(gen),
            "risk": rk.summarize(gen, risk), "critical": rk.rank_scenarios(gen, risk, top=top), "cce_gap": None,
            "figures": episode_figures(gen, risk)}


# The paper's direction for each figure as the knob grows: beta (the distance constraint: larger is
# tighter) gives larger gaps and safer, less competitive traffic; alpha (the CVaR level: larger is
# more risk-averse) gives lower speeds and larger spacing. 0: the paper states no direction.
FLEX_CLAIMS = {  # figure: (label, sign with beta, sign with alpha)
    "min_gap": ("min gap [m]", +1, +1),
    # what the look-ahead cost charges: the least gap over the next second, where slowing down keeps distance
    "min_gap_ahead": (f"min gap over the next {rk.ANTICIPATION:g} s [m]", +1, +1),
    # the same claim (traffic keeps its distance) over the whole episode, not its closest moment
    "close_time": (f"time within {rk.CLOSE_DISTANCE:g} m [share of steps]", -1, -1),
    "speed": ("mean speed [m/s]", -1, -1),
    "ttc_critical": (f"TTC < {rk.TTC_CRITICAL:g} s rate", -1, -1),
    "collision": ("collision rate", -1, -1),
    "hard_brakes": ("hard brakes / agent", 0, 0),
    "collision_other": ("collision with a non-policy car", 0, 0),  # the replayed logs do not react
    "from_behind": ("hit from behind", 0, 0),
    # per agent (the deviation game's), not per agent-episode
    "cce_gap": ("CCE-gap", 0, 0),
    # of the cell's pooled histograms, not a mean: bootstrapped through fidelity.episode_histograms' rows
    "hellinger": ("Hellinger to the logs (mean of 4 features)", 0, 0),
}


def cell_label(beta: float, alpha: float) -> str:
    """How the report names a cell (beta, alpha): its tables' rows and the legend of multipliers.png."""
    return f"beta {beta:g} / alpha {alpha:g}"


def group_cells(results: list[dict]) -> list[dict]:
    """The CCE-MAPPO runs grouped by cell (beta, alpha): one dict per cell with its `runs` (training
    seeds) and, per figure, a list of the runs' per-episode arrays (stats resamples seeds, then
    episodes)."""
    cells: dict[tuple[float, float], dict] = {}
    for r in sorted(results, key=lambda r: (r["beta"], r["alpha"])):
        c = cells.setdefault((r["beta"], r["alpha"]), {"label": cell_label(r["beta"], r["alpha"]),
                                                        "beta": r["beta"], "alpha": r["alpha"], "runs": 0,
                                                        "figures": {}})
        c["runs"] += 1
        for k, v in r["figures"].items():
            c["figures"].setdefault(k, []).append(v)
    return list(cells.values())


def _episodes(x) -> int:
    """Episodes (or agents) behind a cell's figure: one array, or the runs' arrays."""
    return sum(len(v) for v in as_runs(x))


def _run_figures(cell: dict, key: str) -> list:
    """A cell's per-run arrays of figure `key` (a single run's `figures` hold the array itself)."""
    x = cell["figures"].get(key)
    return [] if x is None else as_runs(x)


def played_alike(cells: list[dict]) -> bool:
    """Whether every run of `cells` played the same agent-episodes in the same order (equal `episode_key`s):
    their figures can be compared episode by episode (stats' paired resampling)."""
    keys = [_run_figures(c, "episode_key") for c in cells]
    if any(len(k) != c.get("runs", 1) for k, c in zip(keys, cells)):  # a cache written before the keys existed
        return False
    first = keys[0][0]
    return all(np.array_equal(k, first) for ks in keys for k in ks)


def knob_effects(cells: list[dict], n_boot: int = 2000) -> list[list]:
    """Rows (figure, knob, the other knob's value, knob low -> high, figure at low, at high, difference
    high - low with its 95 % interval, ratio high / low with its interval, paper's sign, verdict, how the
    interval resampled): each claimed figure between the extreme cells of each knob, the other knob held.
    Cells are `group_cells` dicts (or single runs with `figures` arrays); cells that played the same
    agent-episodes are compared episode by episode (`played_alike`)."""
    rows, alike = [], {}  # alike: played_alike of each compared pair, checked once for all figures
    for key, (name, *signs) in FLEX_CLAIMS.items():
        if not any(signs) or any(key not in c["figures"] for c in cells):
            continue
        for knob, other, sign in (("beta", "alpha", signs[0]), ("alpha", "beta", signs[1])):
            for at in sorted({c[other] for c in cells}):
                row = sorted((c for c in cells if c[other] == at), key=lambda c: c[knob])
                if len(row) < 2 or row[0][knob] == row[-1][knob]:
                    continue
                lo_c, hi_c = row[0], row[-1]
                if (knob, at) not in alike:
                    alike[knob, at] = played_alike([lo_c, hi_c])
                paired = alike[knob, at]
                e = effect_ci(lo_c["figures"][key], hi_c["figures"][key], n_boot=n_boot,
                              labels=(lo_c["label"], hi_c["label"]), paired=paired)
                rows.append([name, knob, f"{other} {at:g}", f"{lo_c[knob]:g} -> {hi_c[knob]:g}", e.low, e.high,
                             f"{fmt(e.diff)} [{fmt(e.diff_lo)}, {fmt(e.diff_hi)}]",
                             f"{fmt(e.ratio)} [{fmt(e.ratio_lo)}, {fmt(e.ratio_hi)}]",
                             {1: "+", -1: "-"}[sign], e.verdict(sign), "paired" if paired else "each cell alone"])
    return rows



def effect_verdicts(effects: list[list]) -> list[list]:
    """Rows (knob, rows compared, holds, reversed, not shown, the reversed rows as "figure (held)") counted over
    `knob_effects`' rows: how many of the paper's claims each knob meets with an interval clear of 0."""
    out = []
    for knob in dict.fromkeys(r[1] for r in effects):
        mine = [r for r in effects if r[1] == knob]
        count = {v: sum(r[9] == v for r in mine) for v in ("holds", "reversed", "not shown")}
        out.append([knob, len(mine), count["holds"], count["reversed"], count["not shown"],
                    "; ".join(f"{r[0]} ({r[2]})" for r in mine if r[9] == "reversed") or "-"])
    return out

# the per-type table's figures (distance, near miss, crash), each read as the difference or the ratio high / low
TYPE_FIGURES = {"min_gap": "difference", "ttc_critical": "ratio", "collision": "ratio"}


def knob_effects_by_type(cells: list[dict], n_boot: int = 2000, min_episodes: int = 30) -> list[list]:
    """Rows (scenario type, knob, held, knob low -> high, agent-episodes a run, then per TYPE_FIGURES figure its
    difference or ratio with its 95 % interval, and its verdict) of `knob_effects` on each scenario type's
    agent-episodes alone: where a knob acts and where it does not. Only with two types or more, each with at least
    `min_episodes` agent-episodes in every run; nothing for cells evaluated before the figures kept their types."""
    runs = [r for c in cells for r in _run_figures(c, "scenario_type")]
    if len(runs) < sum(c.get("runs", 1) for c in cells):
        return []
    types = sorted(t for t in set(np.concatenate(runs)) if all((r == t).sum() >= min_episodes for r in runs))
    if len(types) < 2:
        return []
    rows, lead_key = [], next(iter(TYPE_FIGURES))  # one row per (type, knob, held): keyed on the first figure
    for t in types:
        sub = [{**c, "figures": {k: [f[kind == t] for f, kind in zip(_run_figures(c, k), of_type)]
                                 for k in (*TYPE_FIGURES, "episode_key")}}
               for c in cells for of_type in [_run_figures(c, "scenario_type")]]
        # knob_effects' rows: figure, knob, held, low -> high, at low, at high, difference, ratio, sign, verdict, ...
        effects = {(r[0], r[1], r[2]): r for r in knob_effects(sub, n_boot)}
        for (name, knob, held), lead in effects.items():
            if name != FLEX_CLAIMS[lead_key][0]:
                continue
            row = [t, knob, held, lead[3], min(len(f) for c in sub for f in c["figures"][lead_key])]
            for key, read in TYPE_FIGURES.items():
                e = effects[(FLEX_CLAIMS[key][0], knob, held)]
                if read == "difference":
                    text = e[6]
                elif e[4] > 0:
                    text = "x" + e[7]
                else:  # none at the low cell: a ratio says nothing, the difference does
                    text = e[6] + " (none at low)"
                row.append(f"{text} {e[9]}")
            rows.append(row)
    return rows


# m: a min gap ceiling below this (a beta only cars in contact come within) leaves no share of it to print
SHARE_FLOOR = 0.01


def gap_headroom(cells: list[dict]) -> list[list]:
    """Rows (knob held, knob low -> high, min gap at low, at high, the change, the ceiling, the share of it the
    cells reach) of how much min gap a knob can buy. A cost whose distance threshold is beta charges nothing
    beyond it, and no policy moves the state the log hands over, so the most a cell can add to the low cell's
    min gaps is every agent keeping at least beta wherever its first state allows: the mean of max(min gap,
    min(beta, start gap)) less the low cell's mean min gap. For beta (alpha held) that beta is the high cell's;
    for alpha (beta held) it is the held beta, the threshold both cells' costs share, so a beta that only
    contacts reach leaves alpha nothing to buy (no share printed below SHARE_FLOOR). Nothing for cells without
    start gaps (evaluated before the figure existed)."""
    rows = []
    for knob, held in (("beta", "alpha"), ("alpha", "beta")):
        for at in sorted({c[held] for c in cells}):
            row = sorted((c for c in cells if c[held] == at), key=lambda c: c[knob])
            lo_c, hi_c = row[0], row[-1]
            if len(row) < 2 or lo_c[knob] == hi_c[knob] or not _run_figures(lo_c, "start_gap"):
                continue
            beta = hi_c["beta"]
            low, ceiling = [], []
            for gap, start in zip(_run_figures(lo_c, "min_gap"), _run_figures(lo_c, "start_gap")):
                ok = np.isfinite(gap)
                low.append(gap[ok].mean())
                ceiling.append(np.maximum(gap[ok], np.minimum(beta, start[ok])).mean() - gap[ok].mean())
            high = [g[np.isfinite(g)].mean() for g in _run_figures(hi_c, "min_gap")]
            change, most = float(np.mean(high) - np.mean(low)), float(np.mean(ceiling))
            rows.append([f"{held} {at:g}", f"{knob} {lo_c[knob]:g} -> {hi_c[knob]:g}", float(np.mean(low)),
                         float(np.mean(high)), change, most, change / most if most > SHARE_FLOOR else float("nan")])
    return rows


def gap_against_mappo(results: list[dict], n_boot: int = 2000) -> list[list]:
    """Rows (policy, scenario type, agents, MAPPO runs, CCE-gap of the policy, of MAPPO, difference with its
    95 % interval, median difference, share of agents more exploitable under the policy, verdict) of the
    paper's claim that TrafficGamer's equilibrium is less exploitable than plain MAPPO's, in the task game
    both profiles can play. Each agent's gap under a CCE-MAPPO policy is paired with its gap under MAPPO,
    averaged over the MAPPO runs (training seeds) that hold the agent, so the interval resamples agents
    of the same scenes; a row for all agents, then one per scenario type. No rows without a MAPPO run
    with CCE-gaps."""
    mappo = [r["cce_gap"] for r in results if r.get("kind") == "MAPPO" and r.get("cce_gap")]
    if not mappo:
        return []
    per_agent: dict[str, list[float]] = {}
    for g in mappo:
        for agent, gap in zip(g["agents"], g["gap_per_agent"]):
            per_agent.setdefault(agent, []).append(gap)
    rows = []
    for r in results:
        g = r.get("cce_gap")
        if r.get("kind") != "CCE-MAPPO" or not g:
            continue
        shared = [(agent, t, gap) for agent, t, gap in zip(g["agents"], g["types"], g["gap_per_agent"])
                  if agent in per_agent]
        types = sorted({t for _, t, _ in shared})  # per-type rows only where there are several types
        groups = [("all", shared)] + ([(t, [x for x in shared if x[1] == t]) for t in types]
                                      if len(types) > 1 else [])
        for label, members in groups:
            if not members:
                continue
            d = paired_difference([gap for _, _, gap in members],
                                  [float(np.mean(per_agent[agent])) for agent, _, _ in members], n_boot=n_boot)
            verdict = {"holds": "more exploitable", "reversed": "less exploitable"}.get(d.verdict(1),
                                                                                      "not distinguishable")
            rows.append([r["label"], label, d.n, len(mappo), d.mean_a, d.mean_b,
                         f"{fmt(d.diff)} [{fmt(d.lo)}, {fmt(d.hi)}]", d.median_diff, f"{d.share_a_greater:.0%}",
                         verdict])
    return rows


def flexibility_directions(cells: list[dict], n_boot: int = 2000, logged: dict | None = None) -> list[list]:
    """Rows (figure, knob, paper's sign, rho, 95 % interval, verdict, samples per cell) of the Spearman
    correlation of each figure with beta and with alpha over the CCE-MAPPO cells; the Hellinger row
    needs the `logged` histograms (fidelity.histograms of the logs the cells were compared with)."""
    rows, alike = [], played_alike(cells)
    for key, (name, *signs) in FLEX_CLAIMS.items():
        # a cache written before the figure existed, or a report without CCE-gaps
        if any(key not in c["figures"] for c in cells) or key == "hellinger" and logged is None:
            continue
        samples = [c["figures"][key] for c in cells]
        stat = (lambda sums: fid.hellinger_of_sums(logged, sums)) if key == "hellinger" else None
        paired = stat is None and alike
        for knob, sign in zip(("beta", "alpha"), signs):
            values = [c[knob] for c in cells]
            if len(set(values)) < 2:
                continue
            r = spearman_ci(values, samples, n_boot=n_boot, labels=[c["label"] for c in cells], statistic=stat,
                            paired=paired)
            verdict = r.verdict(sign) if sign else "-"
            rows.append([name, knob, {1: "+", -1: "-", 0: "none"}[sign], r.rho, f"[{fmt(r.lo)}, {fmt(r.hi)}]",
                         verdict, min(_episodes(x) for x in samples)])
    return rows


def tail_means(rows: list[dict], keys: Sequence[str], tail: int = 5) -> dict:
    """Mean of each key over the last `tail` training updates (NaN when absent)."""
    out = {}
    for k in keys:
        vals = [float(r[k]) for r in rows[-tail:] if r.get(k) not in (None, "", "nan")]
        out[k] = sum(vals) / len(vals) if vals else math.nan
    return out


def gap_curve(start: dict | None, kept: list[dict], last: dict | None, last_update: int | None) -> list[dict]:
    """The CCE-gap over a run's training: `start` (the gap of the policy it started from) at update 0,
    the kept policies' points (report.kept_gaps) and the final checkpoint's gap `last` at `last_update`;
    empty with fewer than two points."""
    points = [] if start is None else [{"update": 0, "mean_gap": start["mean_gap"], "ci95": start["ci95"]}]
    points += kept
    if points and last and last_update is not None and last_update > points[-1]["update"]:
        points.append({"update": last_update, "mean_gap": last["mean_gap"], "ci95": last["ci95"]})
    return points if len(points) > 1 else []
