"""report.md holds the findings only: its length does not grow with the agents and scenes a report
evaluates, no per-agent row ever lands in it, and those rows are in per_agent.csv and per_scene.csv
beside it. Drawn from synthetic results shaped as report.py gathers them: no training or rollout."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.report_markdown import (PER_AGENT_COLUMNS, PER_SCENE_COLUMNS, write_csv_tables,
                                                    write_markdown)

TYPES = ("merge", "t_junction", "roundabout")
MAX_LINES = 300  # report.md of a large grid stays a few hundred lines


def csv_rows(path: Path, columns) -> list[dict]:
    """The rows of a report CSV file, after checking its header is `columns`."""
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert tuple(reader.fieldnames) == tuple(columns), path
    return rows


def per_agent_lines(md: str, agents: list[dict]) -> list[str]:
    """The lines of report.md that hold a row of per_agent.csv: a table row naming one of its agents."""
    ids = {a["agent"] for a in agents}
    return [ln for ln in md.splitlines() if ln.startswith("|") and any(c.strip() in ids for c in ln.split("|"))]


def _gap(rng, agents: int) -> dict:
    """A CCE-gap result as exploitability.cce_gap returns it, two seeds."""
    types = [TYPES[a % len(TYPES)] for a in range(agents)]
    gap = rng.random(agents)
    return {"agents": [f"procedural/{types[a]}/{90000 + a // 4}/{a % 4}" for a in range(agents)], "types": types,
            "gap_per_agent": gap.tolist(), "gain_per_agent": (gap - 0.1).tolist(),
            "gain_ci95_per_agent": [0.05] * agents, "j_pi_per_agent": [1.0] * agents,
            "j_br_per_agent": (1.0 + gap).tolist(), "mean_gap": float(gap.mean()), "ci95": 0.02, "ci95_seeds": 0.03,
            "mean_gain": float(gap.mean() - 0.1), "mean_iters": 20.0,
            "per_type": {t: {"agents": types.count(t), "mean_gap": 0.5, "ci95": 0.1, "mean_gain": 0.4} for t in TYPES},
            "iters": [[20] * agents, [25] * agents], "plateaued": [[True] * agents, [False] * agents]}


def _result(rng, label: str, kind: str | None, agents: int, top: int, beta: float, alpha: float) -> dict:
    """One policy's result dict as report.py keeps it (kind None: a baseline)."""
    feature = {"hellinger": 0.1, "kl": 0.2, "w1": 0.3, "likelihood": 0.4, "mean_logged": 5.0, "mean_generated": 5.5}
    res = {"label": label, "fidelity": {"realism_ours": 0.05, "per_feature": {n: dict(feature) for n in fid.FEATURES}},
           "diversity": {"mean": 0.4, "per_type": {t: 0.4 for t in TYPES}},
           "risk": {"collision_rate": 0.01, **{k: 0.0 for k in rk.CONTACT_KEYS}},
           "critical": [{"label": label, "scene_id": f"procedural/merge/{90000 + k}", "scenario_type": "merge",
                         "seed": k % 2, "collisions": top - k, "min_ttc_s": 0.5, "min_gap_m": 1.0, "hard_brakes": 1,
                         "file": f"scenarios/{label}/{k}.json"} for k in range(top)],
           "cce_gap": _gap(rng, agents), "gap_curve": [], "figures": {}}
    if kind:
        res.update(kind=kind, beta=beta, alpha=alpha,
                   train_tail={"lambda": 0.1, "mean_min_distance": 4.0, "mean_speed": 6.0, "cost": 0.2})
    return res


def _meta(labels: list[str]) -> dict:
    """The settings of a report (report._meta's shape)."""
    return {"runs": labels, "scenes": 8, "seeds": [0, 1], "eval_scenes": "held out", "cce_gap": True,
            "worst_scenes": None, "br_seeds": [0, 1],
            "best_response": {"max_iters": 100, "tol": 0.01, "window": 5, "patience": 10, "min_iters": 20,
                              "copies": 16, "scenes": 8, "lr": 3e-3, "eval_rounds": 2, "gamma": "the run's"}}


def _write(out: Path, agents: int, top: int) -> list[dict]:
    """report.md and its CSV files of two baselines, a 3 x 3 grid and a MAPPO run, each policy with `agents`
    agents."""
    rng = np.random.default_rng(agents)
    results = [_result(rng, name, None, agents, top, 0, 0) for name in ("expert (inverse dynamics)", "world model")]
    results += [_result(rng, f"beta{b}_alpha{a}", "CCE-MAPPO", agents, top, b, a)
                for b in (2.0, 4.0, 6.0) for a in (0.125, 0.5, 0.875)]
    results += [_result(rng, "mappo_s0", "MAPPO", agents, top, 0, 0)]
    out.mkdir(parents=True, exist_ok=True)
    write_markdown(out, results, _meta([r["label"] for r in results if r.get("kind")]))
    write_csv_tables(out, results)
    return results


def test_report_md_holds_no_per_agent_rows_and_stays_short(tmp_path):
    small = (_write(tmp_path / "small", agents=8, top=1), (tmp_path / "small" / "report.md").read_text())
    results = _write(tmp_path / "large", agents=400, top=10)
    md = (tmp_path / "large" / "report.md").read_text()
    # as many lines at 400 agents and 10 scenarios a run as at 8 and 1: nothing in it is per agent or scene
    assert len(md.splitlines()) == len(small[1].splitlines()) <= MAX_LINES
    agents = csv_rows(tmp_path / "large" / "per_agent.csv", PER_AGENT_COLUMNS)
    assert len(agents) == 12 * 400 and not per_agent_lines(md, agents)
    assert agents[0]["policy"] == "expert (inverse dynamics)" and agents[0]["ppo_iterations"] == "20;25"
    assert agents[0]["plateaued"] == "1;0" and float(agents[0]["gap"]) == results[0]["cce_gap"]["gap_per_agent"][0]
    scenes = csv_rows(tmp_path / "large" / "per_scene.csv", PER_SCENE_COLUMNS)
    assert len(scenes) == 10 * 10 and {s["run"] for s in scenes} == {r["label"] for r in results if r.get("kind")}
    assert "](per_agent.csv)" in md and "](per_scene.csv)" in md
    # the summary tables stay: one row per policy, per beta x alpha cell, per scenario type column
    for text in ("## Comparison against baselines", "## Flexibility: beta x alpha", "## CCE-gap per scenario type",
                 "| beta6.0_alpha0.875 | CCE-MAPPO", "| roundabout |", "## CCE-gap against plain MAPPO",
                 "| beta2.0_alpha0.125 | merge | 134 | 1 |"):
        assert text in md, text


def test_the_flexibility_section_names_each_cells_constraint_rule(tmp_path):
    """The rule the cells' multipliers followed, in words from each run's config, and each cell's CVaR and
    budget at the end of training beside lambda."""
    import dataclasses

    from tg_gpudrive.config import TrainConfig
    from tg_gpudrive.evaluation.report import constraint_rule

    cfg = TrainConfig(alpha=0.875, lambda_on="cvar", cost_limit_mode="start", cost_limit=0.5)
    assert constraint_rule(cfg) == "CVaR 0.875 of the cost-to-go against 0.5 x the starting policy's mean"
    assert (constraint_rule(dataclasses.replace(cfg, lambda_on="mean", cost_limit_mode="logs", cost_limit=1.0))
            == "the mean of the cost-to-go against 1 x the logs' mean")
    assert (constraint_rule(dataclasses.replace(cfg, cost_limit_mode="absolute", cost_limit=0.0))
            == "CVaR 0.875 of the cost-to-go against 0")
    assert (constraint_rule(dataclasses.replace(cfg, lambda_on="sampled", cost_limit_beta=2.0))
            == "the sampled cost rate / (1 - gamma) against 0.5 x the starting policy's mean at beta 2")
    assert (constraint_rule(dataclasses.replace(cfg, lambda_on="sampled_cvar", cost_limit_mode="logs"))
            == "CVaR 0.875 over the vehicles of their sampled cost rate / (1 - gamma) against 0.5 x the logs' mean")
    assert (constraint_rule(dataclasses.replace(cfg, cost_limit_beta=2.0))
            == "CVaR 0.875 of the cost-to-go against 0.5 x the starting policy's mean at beta 2")
    assert constraint_rule(dataclasses.replace(cfg, constraint=False)) == "no constraint"
    rng = np.random.default_rng(0)
    cells = [_result(rng, f"beta{b}_alpha{a}", "CCE-MAPPO", 4, 1, b, a) for b in (2.0, 6.0) for a in (0.125, 0.875)]
    for c in cells:
        c["constraint"] = constraint_rule(dataclasses.replace(cfg, alpha=c["alpha"]))
        c["train_tail"].update(cvar=0.25, cost_budget=0.125)
    write_markdown(tmp_path, cells, _meta([c["label"] for c in cells]))
    md = (tmp_path / "report.md").read_text()
    assert ("stepped on CVaR 0.125 of the cost-to-go against 0.5 x the starting policy's mean; CVaR 0.875 of the "
            "cost-to-go against 0.5 x the starting policy's mean." in md)
    assert "| 2 | 0.125 | - | 0.1 | 0.25 | 0.125 | 4 |" in md


def test_the_per_agent_check_finds_a_per_agent_row(tmp_path):
    """The check above is not vacuous: a per-agent table in report.md is caught."""
    _write(tmp_path, agents=4, top=1)
    agents = csv_rows(tmp_path / "per_agent.csv", PER_AGENT_COLUMNS)
    md = (tmp_path / "report.md").read_text() + f"\n| world model | {agents[0]['agent']} | merge | 0.1 |\n"
    assert per_agent_lines(md, agents)


def test_the_flexibility_table_shows_what_lambda_was_stepped_on():
    """The training column beside the budget is the logged `constraint` (in the budget's units whatever
    lambda_on), and the critic's CVaR for runs logged before that column."""
    from tg_gpudrive.evaluation.report_markdown import stepped_on

    assert stepped_on({"cvar": 0.4, "constraint": 0.07}) == 0.07
    assert stepped_on({"cvar": 0.4, "constraint": float("nan")}) == 0.4
    assert stepped_on({"cvar": 0.4}) == 0.4
    assert stepped_on({}) == "-"
