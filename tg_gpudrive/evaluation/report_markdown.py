"""report.md and the CSV tables beside it, written from the results report.py gathered.

    write_markdown(out, results, meta)   report.md: the findings, one row per policy, cell, feature or
                                         training point, and the pictures
    write_csv_tables(out, results)       per_agent.csv (PER_AGENT_COLUMNS): every agent's CCE-gap of every
                                         policy; per_scene.csv (PER_SCENE_COLUMNS): every exported critical
                                         scenario of every run

report.md names the two CSV files and never holds their rows, so it stays a few hundred lines however
many agents and scenes a report evaluates. The CSV files carry the numbers unrounded; summary.json
holds every number of both.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.report_stats import (FLEX_CLAIMS, TYPE_FIGURES, effect_verdicts, flexibility_directions,
                                                 fmt, gap_against_mappo, gap_headroom, group_cells, knob_effects,
                                                 knob_effects_by_type, played_alike)
from tg_gpudrive.learn import bar_watch

PER_AGENT_CSV, PER_SCENE_CSV = "per_agent.csv", "per_scene.csv"
PER_AGENT_COLUMNS = ("policy", "agent", "scenario_type", "gap", "gain", "gain_ci95", "j_pi", "j_br",
                     "ppo_iterations", "plateaued")
PER_SCENE_COLUMNS = ("run", "scene", "scenario_type", "seed", "colliding_agents", "min_ttc_s", "min_gap_m",
                     "hard_brakes", "exported")


# ------------------------------------------------------------------ cells
def _table(header: list[str], rows: list[list]) -> str:
    """A markdown table; cells that are not text go through `fmt`."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def _pm(mean, half) -> str:
    """"mean ± half" as a table cell."""
    return f"{fmt(mean)} ± {fmt(half)}"


def _br_text(meta: dict) -> str:
    """The best-response settings in one sentence, for the report's opening paragraph."""
    b = meta["best_response"]
    return (f"a PPO best response per agent (others frozen) on the first {b.get('scenes', 'all')} evaluation "
            f"scenes, {b['copies']} episodes per agent and iteration, "
            f"until its discounted return (gamma: {b['gamma']}) plateaus (no new best {b['window']}-iteration "
            f"moving mean by {b['tol']:g} x max(1, |best|) for {b['patience']} iterations, at least "
            f"{b['min_iters']}; cap {b['max_iters']}), "
            f"seeds {meta['br_seeds']}")


def _types(per_policy: list[dict]) -> list[str]:
    """The scenario types named by any policy, in the order they first appear."""
    return list(dict.fromkeys(t for d in per_policy for t in d))


# ------------------------------------------------------------------ sections
def _opening(meta: dict) -> list[str]:
    """Title, what was evaluated and how, and the grid picture."""
    return ["# Scenario-quality report\n",
            f"Runs: {', '.join(meta['runs'])}. Evaluation: {meta['scenes']} scenes per run ({meta['eval_scenes']}), "
            f"rollout seeds {meta['seeds']}; CCE-gap: "
            f"{_br_text(meta) if meta.get('cce_gap', True) else 'not computed (--no-cce-gap)'}. "
            "Definitions and binning: `tg_gpudrive/evaluation/` module docstrings (fidelity bins: speed 0.5 m/s on "
            "[0, 30], accel 0.25 m/s^2 on [-8, 8], nearest 0.5 m on [0, 50], curvature 0.005 1/m on [-0.3, 0.3]; "
            f"KL smoothing eps {fid.KL_EPS:g}; TTC: {rk.TTC_DISCS} discs of radius width/2 per agent, constant "
            f"velocity, horizon {rk.TTC_HORIZON:g} s; hard brake: accel < {rk.HARD_BRAKE:g} m/s^2). "
            f"Per-agent CCE-gaps: [{PER_AGENT_CSV}]({PER_AGENT_CSV}); every exported critical scenario: "
            f"[{PER_SCENE_CSV}]({PER_SCENE_CSV}).\n",
            "**realism (ours)** is a Waymo-Sim-Agents-*style* likelihood score computed by this project, "
            "not the official challenge metric.\n",
            "![grid](grid.png)\n",
            *([f"grid.png shows scene {meta['grid_scene']}, one episode of each cell's first training seed: on the "
               f"left its whole paths; on the right {meta.get('grid_zoom') or 'every cell at one shared moment'}. "
               "That moment is the step and policy car at which, in the most pressing cell (least beta, then least "
               "alpha), a policy car came nearest another ahead of or behind it in its lane after its first step (not "
               "the logged start, nor a car abreast in the next lane, which are the same in every cell) and while "
               "that car is on the road in every cell where it can be, and each "
               "zoom's title is its cell's own distance from that car to its nearest in its lane then; where no car "
               "came near another in its lane, each zoom is its cell's own closest approach. At each picture's "
               "bottom right, the mean over that run's episodes of its cars' least distance to another on this "
               "scene.\n"] if meta.get("grid_scene") else [])]


def _comparison_section(results: list[dict]) -> list[str]:
    """One row per policy: realism, divergences, CCE-gap, diversity and risk."""
    rows = []
    for r in results:
        f = r["fidelity"]["per_feature"]
        g = r.get("cce_gap")
        rows.append([r["label"], r.get("kind", "baseline"), r.get("acting", "-"), r["fidelity"]["realism_ours"],
                     np.nanmean([v["hellinger"] for v in f.values()]), np.nanmean([v["kl"] for v in f.values()]),
                     _pm(g["mean_gap"], g["ci95"]) if g else "-", r["diversity"]["mean"],
                     r["risk"].get("collision_rate"), r["risk"].get("near_miss_rate"),
                     r["risk"].get("mean_min_ttc_s"), r["risk"].get("mean_min_gap_m"),
                     r["risk"].get("hard_brakes_per_agent")])
    return ["## Comparison against baselines\n",
            _table(["policy", "kind", "acts at", "realism (ours)", "Hellinger (mean)", "KL (mean)",
                    "CCE-gap ± 95% CI (agents)", "diversity [m]", "collision rate", f"TTC < {rk.TTC_CRITICAL:g} s rate", "mean min TTC [s]",
                    "mean min gap [m]", "hard brakes / agent"], rows)]


def _collides_section(results: list[dict]) -> list[str]:
    """One row per policy: its collisions by partner and by contact."""
    keys = ["collision_rate", "collision_with_policy_rate", "collision_with_other_rate", *rk.CONTACT_KEYS]
    return ["\n### Who collides\n\nEach policy agent's first collision, by its partner (the nearest other car "
            "then: driven by the policy, or another one: a replayed log, which does not react) and by the contact "
            "in the agent's frame (hit from behind, ran into a car ahead, crossing / side / head-on); rates per "
            "policy agent-episode (`tg_gpudrive/evaluation/risk.py`).\n\n",
            _table(["policy", "collision rate", "with a policy car", "with a non-policy car",
                    *(f"contact: {c}" for c in rk.CONTACTS)],
                   [[r["label"], *(r["risk"].get(k, "-") for k in keys)] for r in results])]


def _closest_section(results: list[dict]) -> list[str]:
    """One row per policy: where its agents' closest approaches were (the partner's place, parked or a policy car).
    Nothing when no policy carries these shares (a cache evaluated before the report had them)."""
    keys = [*rk.PLACE_KEYS, "closest_parked_share", "closest_policy_share"]
    if not any(keys[0] in r["risk"] for r in results):
        return []
    return ["\n### Where the closest approach is\n\nEach policy agent's closest step (its min gap), the nearest other "
            f"agent then: beside it (centre more than {rk.ABREAST_OFFSET:g} m to the side: the next lane, the kerb, "
            "crossing traffic), ahead or behind; parked (never faster than "
            f"{rk.PARKED_SPEED:g} m/s) or driven by the policy. Shares of the agent-episodes. A distance knob can "
            "widen a gap ahead or behind by speed; one beside the agent it widens only by leaving the lane or "
            "waiting.\n\n",
            _table(["policy", *(f"closest: {p}" for p in rk.PLACES), "a parked partner", "a policy partner"],
                   [[r["label"], *(r["risk"].get(k, "-") for k in keys)] for r in results])]


def stepped_on(tail: dict):
    """What a run's multipliers were stepped on over its last updates: the `constraint` column (the critic's CVaR
    or mean, or the sampled cost rate), or the critic's CVaR for runs logged before that column; "-" without."""
    value = tail.get("constraint", float("nan"))
    return tail.get("cvar", "-") if value != value else value


def _flexibility_section(results: list[dict], logged_hist: dict | None) -> list[str]:
    """The report's beta x alpha section: the runs' training and evaluation means, and (three cells or
    more) the direction of every figure with each knob, and its change between each knob's extreme
    cells; a cell's training seeds are resampled with its episodes. Nothing without CCE-MAPPO cells."""
    cce = sorted((r for r in results if r.get("kind") == "CCE-MAPPO"),
                 key=lambda r: (r["beta"], r["alpha"], r.get("seed", 0)))
    if not cce:
        return []
    rules = sorted({r["constraint"] for r in cce if r.get("constraint")})
    rule = f" Each cell's multipliers were stepped on {'; '.join(rules)}." if rules else ""
    out = ["\n## Flexibility: beta x alpha\n\nTraining: mean of the last 5 updates. Evaluation: the "
           "rollouts above. Paper's direction: larger beta (tighter) -> larger lambda and gaps; lower "
           f"alpha (less risk-averse) -> faster, smaller gaps.{rule}\n\n"]
    rows = [[r["beta"], r["alpha"], r.get("seed", "-"), r["train_tail"]["lambda"],
             stepped_on(r["train_tail"]), r["train_tail"].get("cost_budget", "-"),
             r["train_tail"]["mean_min_distance"], r["train_tail"]["mean_speed"], r["train_tail"]["cost"],
             r["risk"].get("mean_min_gap_m"), r["fidelity"]["per_feature"].get("speed", {}).get("mean_generated"),
             r["risk"].get("collision_rate"),
             bar_watch.label(r.get("bar_out_of_reach"))] for r in cce]
    out.append(_table(["beta [m]", "alpha", "training seed", "lambda (train)", "stepped on (train)",
                       "budget (train)", "min distance (train) [m]", "speed (train) [m/s]", "cost (train)",
                       "min gap (eval) [m]", "speed (eval) [m/s]", "collision rate (eval)",
                       "bar out of reach (train)"], rows))
    if not all("figures" in r for r in cce):
        return out
    cells = group_cells(cce)
    seeds = min(c["runs"] for c in cells)
    noise = ("training seeds and evaluation noise: each resample draws a cell's runs with replacement, then "
             "each drawn run's agent-episodes" if seeds > 1 else
             "evaluation noise only (one training seed per cell): each resample draws every cell's agent-episodes")
    if played_alike(cells):
        noise += (f"; the cells played the same {len(cells[0]['figures']['episode_key'][0])} agent-episodes "
                  "(scenes, agents, rollout seeds), so a resample draws one set of them for every run of every "
                  "cell (**paired**): which episodes were drawn is one noise for all cells, as in a paired test")
    if len(cells) >= 3:
        out.append(f"\nDirection of each figure with each knob over the {len(cells)} cells ({seeds}+ training "
                   f"seeds each): Spearman's rho of the knob with the cells' means, 95 % bootstrap interval over "
                   f"{noise}. **holds**: the interval lies on the paper's "
                   "side of 0; **reversed**: on the other side; **not shown**: it contains 0. Samples: agent-episodes; "
                   "for the CCE-gap the deviation game's agents; the Hellinger distance is of each cell's pooled "
                   "histograms, its resamples reweight the agent-episodes' histograms.\n\n")
        out.append(_table(["figure", "knob", "paper's sign", "rho", "95 % interval", "verdict",
                           "samples per cell (min)"], flexibility_directions(cells, logged=logged_hist)))
    effects = knob_effects(cells)
    if effects:
        out.append(f"\nEffect sizes: each claimed figure at a knob's lowest and highest cell, the other knob held; "
                   f"the difference (high - low) and the ratio (high / low) with 95 % bootstrap intervals over "
                   f"{noise}. **holds**: the difference's interval lies on the paper's side of 0.\n\n")
        out.append(_table(["figure", "knob", "held", "knob low -> high", "at low", "at high", "difference [95 %]",
                           "ratio [95 %]", "paper's sign", "verdict", "episodes resampled"], effects))
        out.append("\nVerdicts of the effect sizes per knob: how many of the rows above move the paper's way with an "
                   "interval clear of 0, and which go the other way.\n\n")
        out.append(_table(["knob", "rows", "holds", "reversed", "not shown", "reversed rows"],
                          effect_verdicts(effects)))
    by_type = knob_effects_by_type(cells)
    if by_type:
        names = [FLEX_CLAIMS[k][0] for k in TYPE_FIGURES]
        out.append(f"\nEffect sizes per scenario type: the table above on each type's agent-episodes alone, for "
                   f"{', '.join(names)}: min gap's difference high - low and the rates' ratio high / low, each with "
                   f"its 95 % interval (as above) and its verdict.\n\n")
        out.append(_table(["scenario type", "knob", "held", "knob low -> high", "agent-episodes a run", *names],
                          by_type))
    headroom = gap_headroom(cells)
    if headroom:
        out.append("\nHow much min gap a knob can buy: the ceiling is the change if every agent of the low cell "
                   "kept at least beta wherever its first state (the log's, which no policy moves) allows: the "
                   "high beta for beta, the held beta for alpha. The cost charges nothing beyond beta, so a change "
                   "above the ceiling needs agents to keep more distance than beta asks, and at a beta that only "
                   "cars in contact come within, alpha has nothing to buy.\n\n")
        out.append(_table(["held", "knob low -> high", "min gap at low [m]", "at high [m]", "change [m]",
                           "ceiling [m]", "share of the ceiling"], headroom))
    return out


def _fidelity_section(results: list[dict]) -> list[str]:
    """One row per policy and feature: the divergences of its histogram from the logs'."""
    rows = [[r["label"], name, v["hellinger"], v["kl"], v["w1"], v["likelihood"], v.get("mean_logged"),
             v.get("mean_generated")] for r in results for name, v in r["fidelity"]["per_feature"].items()]
    return ["\n## Fidelity per feature (logged vs generated)\n\n![fidelity](fidelity.png)\n\n",
            _table(["policy", "feature", "Hellinger", "KL(log || gen)", "W1", "likelihood", "mean logged",
                    "mean generated"], rows),
            "\n## Multipliers during training\n\n![multipliers](multipliers.png)\n"]


def _gap_agent_section() -> list[str]:
    """The CCE-gap picture and what per_agent.csv's columns mean (its rows stay in the CSV)."""
    return ["\n## CCE-gap per agent\n\n![cce_gap](cce_gap.png)\n\n",
            "gain = J(BR) - J(pi), each agent's discounted return on fresh rollouts with its PPO best response "
            "against everyone else frozen at the policy, and with the policy itself; gap = max(0, gain) (the agent "
            "could keep pi). Means over the best-response seeds; the gain's 95 % interval is the evaluation's "
            "(1.96 standard errors of the fresh episodes). One row per policy and agent: "
            f"[{PER_AGENT_CSV}]({PER_AGENT_CSV}), columns {', '.join(PER_AGENT_COLUMNS)} (ppo_iterations: PPO "
            "iterations to the plateau per seed, `;`-separated; plateaued 0: stopped at the cap).\n"]


def _gap_type_section(gapped: list[tuple[str, dict]]) -> list[str]:
    """One row per policy: the CCE-gap over all its agents and over each scenario type's."""
    types = _types([g["per_type"] for _, g in gapped])
    rows = []
    for label, g in gapped:
        cells = [f"{_pm(v['mean_gap'], v['ci95'])} ({v['agents']})" if v else "-"
                 for v in (g["per_type"].get(t) for t in types)]
        share = f"{g['exploitable_agents']} ({g['exploitable_share']:.0%})" if "exploitable_agents" in g else "-"
        rows.append([label, len(g["agents"]), _pm(g["mean_gap"], g["ci95"]), fmt(g.get("median_gap")),
                     fmt(g.get("trimmed_mean_gap")), share, g["mean_gain"], fmt(g["ci95_seeds"]),
                     g["mean_iters"], *cells])
    return ["\n## CCE-gap per scenario type\n\nMean gap over the agents of each scenario type with its "
            "Student-t 95 % interval over those agents (each agent's gap averaged over the seeds), the number of "
            "those agents in parentheses; all: every agent, with the interval over seeds of the mean over agents "
            "beside it, the median and the 10 % trimmed mean of the agents' gaps, and the count (share) of agents "
            "whose gain's 95 % interval lies above 0 (significantly exploitable). Rows marked (constrained game) "
            "play TrafficGamer's objective: the deviator pays its slot's final multiplier lambda_i times the "
            "distance cost each step, as the run's own agents did; the other rows play the task reward alone. "
            "The mean raw gain of each type: summary.json (cce_gap.per_type).\n\n",
            _table(["policy", "agents", "CCE-gap ± 95% CI (agents)", "median gap", "trimmed mean gap",
                    "significantly exploitable", "mean raw gain", "95% CI (seeds)", "mean PPO iterations", *types],
                   rows)]


def _gap_mappo_section(results: list[dict]) -> list[str]:
    """The paper's exploitability claim, agent by agent against plain MAPPO (report_stats.gap_against_mappo);
    a line saying what it needs when the report holds no MAPPO run with CCE-gaps."""
    rows = gap_against_mappo(results)
    if not rows:
        return ["\nNo comparison of CCE-gaps against plain MAPPO: it needs a MAPPO run (eta1 0, eta2 inf, no "
                "constraint) among --runs, evaluated on the same scenes.\n"]
    return ["\n## CCE-gap against plain MAPPO\n\nThe paper's claim is that TrafficGamer's equilibrium is less "
            "exploitable than plain MAPPO's. Each agent's gap in the task game under the policy is paired with the "
            "same agent's gap under MAPPO (the mean over the MAPPO runs); difference = policy - MAPPO, mean over "
            "agents with a 95 % bootstrap interval over agents; the verdict says which side of 0 the interval "
            "lies on.\n\n",
            _table(["policy", "scenario type", "agents", "MAPPO runs", "CCE-gap (policy)", "CCE-gap (MAPPO)",
                    "difference [95% CI]", "median difference", "agents more exploitable", "verdict"], rows)]


def _gap_curve_section(results: list[dict]) -> list[str]:
    """One row per run and training point of the CCE-gap over training, or why there is none."""
    curves = [(r["label"], r["gap_curve"]) for r in results if r.get("gap_curve")]
    if not curves:
        return ["\nNo CCE-gap curve over training: it needs a run that started from a policy (`init_policy`; the "
                "starting policy's gap is computed by the report process that also does the baselines, not "
                "with --no-baselines) or kept policies during training (`--set keep_policy_every=N`).\n"]
    return ["\n## CCE-gap over training\n\n![cce_gap_curve](cce_gap_curve.png)\n\nThe same best-response "
            "procedure on the policy the run started from (`init_policy`, update 0), each policy it kept "
            "(`keep_policy_every`) and its final checkpoint.\n\n",
            _table(["run", "update", "CCE-gap ± 95% CI (agents)"],
                   [[label, p["update"], _pm(p["mean_gap"], p["ci95"])] for label, pts in curves for p in pts])]


def _gap_sections(results: list[dict], computed: bool = True) -> list[str]:
    """The CCE-gap sections of report.md: per agent (a pointer to per_agent.csv), per scenario type, over
    training; one line where the report was asked for none (`computed` False: --no-cce-gap)."""
    if not computed:
        return ["\n## CCE-gap\n\nNot computed (--no-cce-gap): this report has rollouts only. The same command "
                "without the flag adds a PPO best response per agent (GPU time).\n"]
    gapped = []
    for r in results:  # the task game, then for CCE-MAPPO runs the constrained one
        gapped += [(r["label"], r["cce_gap"])] if r.get("cce_gap") else []
        gapped += [(f"{r['label']} (constrained game)", r["cce_gap_constrained"])] if r.get("cce_gap_constrained") else []
    return [*_gap_agent_section(), *_gap_type_section(gapped), *_gap_mappo_section(results),
            *_gap_curve_section(results)]


def _diversity_section(results: list[dict]) -> list[str]:
    """One row per policy: its mean pairwise displacement in each scenario type."""
    types = _types([r["diversity"]["per_type"] for r in results])
    rows = [[r["label"], *(r["diversity"]["per_type"].get(t, "-") for t in types)] for r in results]
    return ["\n## Diversity per scenario type [m]\n\nMean pairwise displacement of a scene's episodes, averaged "
            "over the scenes of each type.\n\n", _table(["policy", *types], rows)]


def _worst_section(meta: dict) -> list[str]:
    """The first run's worst scenes (at most report_stats.WORST_SCENES rows) beside their picture."""
    worst = meta.get("worst_scenes") or {}
    if not worst.get("scenes"):
        return []
    return [f"\n## Worst scenes of {worst['label']}\n\nThe scenes where its agents collided or left the road "
            "most often (per agent-episode), each drawn as its episode ends.\n\n![worst scenes](worst_scenes.png)\n\n",
            _table(["scene", "agent-episodes", "collisions", "off-road", "failure rate"],
                   [[w["scene_id"], w["agent_episodes"], w["collisions"], w["offroad"], w["failure_rate"]]
                    for w in worst["scenes"]])]


def _critical_section(results: list[dict]) -> list[str]:
    """One row per run: its most safety-critical generated scenario (every exported one: per_scene.csv)."""
    rows = [[r["label"], c["scene_id"], c["seed"], c["collisions"], c["min_ttc_s"], c["min_gap_m"], c["hard_brakes"],
             c.get("file", "-")] for r in results if r.get("kind") for c in r["critical"][:1]]
    return ["\n## Most safety-critical generated scenarios\n\nEach run's most critical episode (most colliding "
            "agents, then the lowest TTC, the smallest gap, the most hard brakes); every exported one, as GPUDrive "
            f"JSON under scenarios/: [{PER_SCENE_CSV}]({PER_SCENE_CSV}).\n\n",
            _table(["run", "scene", "seed", "colliding agents", "min TTC [s]", "min gap [m]", "hard brakes",
                    "exported"], rows)]


def write_markdown(out: Path, results: list[dict], meta: dict, logged_hist: dict | None = None) -> None:
    """Write out/report.md: the findings of `results` (one dict per policy, as report.py gathers them)
    under the settings `meta`; `logged_hist` (the logs' histograms) adds the Hellinger direction row."""
    parts = [*_opening(meta), *_comparison_section(results), *_collides_section(results), *_closest_section(results),
             *_flexibility_section(results, logged_hist), *_fidelity_section(results),
             *_gap_sections(results, meta.get("cce_gap", True)), *_diversity_section(results),
             *_worst_section(meta), *_critical_section(results)]
    (out / "report.md").write_text("\n".join(parts))


# ------------------------------------------------------------------ CSV
def _csv_cell(v) -> str:
    """A CSV cell: numbers unrounded, None empty."""
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return str(int(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def per_agent_rows(results: list[dict]) -> list[list]:
    """PER_AGENT_COLUMNS rows: every agent of every policy's deviation game."""
    rows = []
    for r in results:
        g = r.get("cce_gap")
        if not g:
            continue
        iters, plat = np.asarray(g["iters"]).T.tolist(), np.asarray(g["plateaued"]).T.tolist()
        for a, agent in enumerate(g["agents"]):
            rows.append([r["label"], agent, g["types"][a], g["gap_per_agent"][a], g["gain_per_agent"][a],
                         g["gain_ci95_per_agent"][a], g["j_pi_per_agent"][a], g["j_br_per_agent"][a],
                         ";".join(str(int(i)) for i in iters[a]), ";".join(str(int(bool(p))) for p in plat[a])])
    return rows


def per_scene_rows(results: list[dict]) -> list[list]:
    """PER_SCENE_COLUMNS rows: every critical scenario exported for a run (baselines export none)."""
    return [[r["label"], c["scene_id"], c.get("scenario_type", ""), c["seed"], c["collisions"], c["min_ttc_s"],
             c["min_gap_m"], c["hard_brakes"], c.get("file", "")] for r in results if r.get("kind")
            for c in r["critical"]]


def write_csv_tables(out: Path, results: list[dict]) -> None:
    """Write out/per_agent.csv and out/per_scene.csv (a header alone where there are no rows, so no
    earlier report's rows stay beside this one's report.md)."""
    for name, columns, rows in ((PER_AGENT_CSV, PER_AGENT_COLUMNS, per_agent_rows(results)),
                                (PER_SCENE_CSV, PER_SCENE_COLUMNS, per_scene_rows(results))):
        with (out / name).open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(columns)
            w.writerows([[_csv_cell(v) for v in row] for row in rows])
