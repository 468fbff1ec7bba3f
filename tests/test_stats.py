"""Spearman's rho with ties against hand-computed values, and its bootstrap interval on made cases."""

from __future__ import annotations

import numpy as np
import pytest

from tg_gpudrive.evaluation.stats import average_ranks, effect_ci, spearman, spearman_ci


def test_average_ranks_share_ties():
    np.testing.assert_array_equal(average_ranks([3.0, 1.0, 2.0, 2.0]), [4.0, 1.0, 2.5, 2.5])


def test_spearman_by_hand():
    # no ties: d = (0, 1, 1, 0), rho = 1 - 6 * 2 / (4 * 15) = 0.8
    assert spearman([1, 2, 3, 4], [1, 3, 2, 4]) == pytest.approx(0.8)
    # ties in y: ranks (2, 1, 3.5, 3.5, 5); centred products sum to 8.5, norms 10 and 9.5
    assert spearman([1, 2, 3, 4, 5], [2, 1, 4, 4, 5]) == pytest.approx(8.5 / np.sqrt(95.0))
    assert spearman([1, 2, 3], [3, 2, 1]) == pytest.approx(-1.0)
    assert np.isnan(spearman([1, 2, 3], [5, 5, 5]))  # a constant figure has no order


def test_interval_of_a_monotone_grid_excludes_zero():
    """Five cells whose figure rises with the knob by far more than the episodes' spread."""
    rng = np.random.default_rng(0)
    knob = [2.0, 3.0, 4.0, 5.0, 6.0]
    cells = [rng.normal(m, 0.5, 400) for m in (1.0, 2.0, 3.0, 4.0, 5.0)]
    r = spearman_ci(knob, cells, n_boot=500, seed=1)
    assert r.rho == pytest.approx(1.0) and r.lo == pytest.approx(1.0) and r.hi == pytest.approx(1.0)
    assert r.verdict(+1) == "holds" and r.verdict(-1) == "reversed"
    # the same cells against a decreasing knob
    assert spearman_ci(knob[::-1], cells, n_boot=500, seed=1).verdict(-1) == "holds"


def test_interval_of_noise_contains_zero_and_is_seeded():
    """Cells drawn from one distribution: whatever rho the means give, the interval spans 0."""
    rng = np.random.default_rng(3)
    cells = [rng.normal(0.0, 1.0, 60) for _ in range(5)]
    r = spearman_ci([1, 2, 3, 4, 5], cells, n_boot=1000, seed=2)
    assert r.lo < 0.0 < r.hi
    assert r.verdict(+1) == "not shown"
    assert spearman_ci([1, 2, 3, 4, 5], cells, n_boot=1000, seed=2) == r


def test_a_statistic_of_summed_rows_is_resampled_like_a_mean():
    """With `statistic`, each cell's figure comes from its rows' sum: a share of one column (a ratio of
    sums, like a histogram distance) rising with the knob holds; with the share as the statistic of
    one-hot rows it is the mean of 0/1 values, so rho equals the plain call's; noise spans 0."""
    rng = np.random.default_rng(0)
    knob = [2.0, 3.0, 4.0, 5.0, 6.0]
    share = lambda sums: sums[..., 0] / sums.sum(-1)
    onehot = [np.eye(2)[(rng.random(500) > p).astype(int)] for p in (0.1, 0.3, 0.5, 0.7, 0.9)]
    r = spearman_ci(knob, onehot, n_boot=500, seed=1, statistic=share)
    assert r.rho == pytest.approx(1.0) and r.lo == pytest.approx(1.0) and r.verdict(+1) == "holds"
    plain = spearman_ci(knob, [c[:, 0] for c in onehot], n_boot=500, seed=1)
    assert plain.rho == pytest.approx(r.rho)
    noise = [np.eye(2)[(rng.random(80) > 0.5).astype(int)] for _ in knob]
    r = spearman_ci(knob, noise, n_boot=1000, seed=2, statistic=share)
    assert r.lo < 0.0 < r.hi and r == spearman_ci(knob, noise, n_boot=1000, seed=2, statistic=share)
    with pytest.raises(ValueError, match="beta=3"):  # rows, not 1-D values, when a statistic reads them
        spearman_ci([2, 3], [np.ones((4, 2)), np.ones(4)], statistic=share, labels=["beta=2", "beta=3"])


def test_training_seeds_widen_the_interval_by_their_spread():
    """Runs whose episodes are all alike carry no evaluation noise: the interval of one run per cell
    is a point, while three runs per cell spread it by the seeds alone. Cells 0-2-4 / 10-12-14 by
    run: their means 2 and 12 differ by 10, and a resample of the runs can give any difference
    from 10 - 4 (low runs all 4, high all 10) to 10 + 4."""
    low = [np.full(50, v) for v in (0.0, 2.0, 4.0)]
    high = [np.full(50, v) for v in (10.0, 12.0, 14.0)]
    one = effect_ci(low[1], high[1], n_boot=500, seed=0)
    assert (one.diff, one.diff_lo, one.diff_hi) == (10.0, 10.0, 10.0) and one.ratio == pytest.approx(6.0)
    e = effect_ci(low, high, n_boot=2000, seed=0)
    assert e.low == 2.0 and e.high == 12.0 and e.diff == 10.0
    assert 6.0 <= e.diff_lo < 9.0 and 11.0 < e.diff_hi <= 14.0 and e.verdict(+1) == "holds"
    assert e.ratio == pytest.approx(6.0) and e.ratio_lo < 6.0 < e.ratio_hi
    assert effect_ci(low, high, n_boot=2000, seed=0) == e  # seeded
    # seeds that disagree on the sign: the difference is not shown
    mixed = effect_ci([np.full(20, 0.0)] * 3, [np.full(20, v) for v in (-1.0, 0.5, 2.0)], n_boot=2000, seed=1)
    assert mixed.diff_lo < 0 < mixed.diff_hi and mixed.verdict(+1) == "not shown"
    # the rank correlation's interval takes the runs in the same way: three seeds per cell whose spread
    # overlaps the next cell's leave the order unsure, one run per cell (their means) does not
    knob = [1.0, 2.0, 3.0]
    runs = [[np.full(30, m + d) for d in (-3.0, 0.0, 3.0)] for m in (0.0, 1.0, 2.0)]
    assert spearman_ci(knob, runs, n_boot=1000, seed=0).lo < 0.5
    assert spearman_ci(knob, [r[1] for r in runs], n_boot=1000, seed=0).lo == pytest.approx(1.0)


def test_a_cell_without_episodes_is_an_error_naming_it():
    with pytest.raises(ValueError, match="beta=3"):
        spearman_ci([2, 3], [np.ones(5), np.array([np.nan])], labels=["beta=2", "beta=3"])


def test_flexibility_table_marks_each_claim():
    """Six made cells (beta 2-4 x alpha 0.1, 0.9): gaps grow with beta far beyond the episodes' spread,
    speed grows with alpha (against the paper), the rest is noise."""
    from tg_gpudrive.evaluation.report_stats import flexibility_directions

    rng = np.random.default_rng(5)
    cells = []
    for beta in (2.0, 3.0, 4.0):
        for alpha in (0.1, 0.9):
            n = 300
            cells.append({"label": f"b{beta}a{alpha}", "beta": beta, "alpha": alpha, "figures": {
                "min_gap": rng.normal(2.0 * beta, 0.3, n), "speed": rng.normal(5.0 + 4.0 * alpha, 0.3, n),
                "ttc_critical": (rng.random(n) < 0.2).astype(float), "collision": (rng.random(n) < 0.1).astype(float),
                "hard_brakes": rng.poisson(0.3, n).astype(float)}})
    rows = {(r[0], r[1]): r for r in flexibility_directions(cells, n_boot=400)}
    assert ("CCE-gap", "beta") not in rows and not any(k[0].startswith("Hellinger") for k in rows)  # none given
    # per-agent CCE-gaps rising with beta; histograms drifting from the logs' with alpha: the Hellinger
    # figure is a statistic of each cell's pooled rows, bootstrapped by reweighting them
    from tg_gpudrive.evaluation import fidelity as fid

    widths = [b.num_bins for b in fid.FEATURES.values()]
    logged = {name: np.eye(w)[0] * 100 for name, w in zip(fid.FEATURES, widths)}  # all mass in each first bin
    for c in cells:
        c["figures"]["cce_gap"] = rng.normal(0.1 * c["beta"], 0.01, 240)
        drift = 0.1 if c["alpha"] < 0.5 else 0.6
        c["figures"]["hellinger"] = np.concatenate(
            [np.eye(w)[np.where(rng.random(n) < drift, rng.integers(1, w, n), 0)] for w in widths], axis=1)
    more = {(r[0], r[1]): r for r in flexibility_directions(cells, n_boot=400, logged=logged)}
    assert more[("CCE-gap", "beta")][3] > 0.9 and more[("CCE-gap", "beta")][6] == 240  # ties in beta: < 1
    hel = more[("Hellinger to the logs (mean of 4 features)", "alpha")]
    lo = float(hel[4].strip("[]").split(",")[0])
    assert hel[3] > 0.8 and lo > 0 and hel[2] == "none" and hel[5] == "-" and hel[6] == 300
    assert abs(more[("Hellinger to the logs (mean of 4 features)", "beta")][3]) < 0.5
    assert rows[("min gap [m]", "beta")][5] == "holds"
    assert rows[("mean speed [m/s]", "alpha")][5] == "reversed"
    assert rows[("collision rate", "beta")][5] == "not shown"
    assert rows[("hard brakes / agent", "alpha")][2] == "none" and rows[("hard brakes / agent", "alpha")][5] == "-"
    assert all(r[6] == 300 for r in rows.values())


def test_cells_group_their_training_seeds_and_effects_compare_the_extreme_cells():
    """Two seeds per cell (beta 2, 4, 6 x alpha 0.1, 0.9): min gap grows by 0.5 m per metre of beta with
    seeds 0.1 m apart; the TTC rate halves from beta 2 to beta 6; collisions are noise."""
    from tg_gpudrive.evaluation.report_stats import flexibility_directions, group_cells, knob_effects

    rng = np.random.default_rng(7)
    runs = []
    for beta in (2.0, 4.0, 6.0):
        for alpha in (0.1, 0.9):
            for seed, shift in ((0, -0.05), (1, 0.05)):
                n = 400
                runs.append({"label": f"b{beta}a{alpha}s{seed}", "beta": beta, "alpha": alpha, "seed": seed, "figures": {
                    "min_gap": rng.normal(0.5 * beta + shift, 0.2, n), "speed": rng.normal(7.0, 0.5, n),
                    "ttc_critical": (rng.random(n) < 0.4 / (beta / 2) ** 0.631).astype(float),
                    "collision": (rng.random(n) < 0.03).astype(float)}})
    cells = group_cells(runs)
    assert [(c["beta"], c["alpha"], c["runs"]) for c in cells][:2] == [(2.0, 0.1, 2), (2.0, 0.9, 2)]
    assert len(cells) == 6 and len(cells[0]["figures"]["min_gap"]) == 2
    rows = {(r[0], r[1]): r for r in flexibility_directions(cells, n_boot=300)}
    assert rows[("min gap [m]", "beta")][5] == "holds" and rows[("min gap [m]", "beta")][6] == 800
    eff = {(r[0], r[1], r[2]): r for r in knob_effects(cells, n_boot=300)}
    gap = eff[("min gap [m]", "beta", "alpha 0.1")]
    assert gap[3] == "2 -> 6" and gap[4] == pytest.approx(1.0, abs=0.05) and gap[5] == pytest.approx(3.0, abs=0.05)
    lo, hi = (float(x) for x in gap[6].split("[")[1].strip("]").split(","))
    assert 1.8 < lo < 2.0 < hi < 2.2 and gap[8] == "+" and gap[9] == "holds"
    ttc = eff[("TTC < 1.5 s rate", "beta", "alpha 0.9")]
    assert float(ttc[7].split()[0]) == pytest.approx(0.5, abs=0.12) and ttc[9] == "holds"
    assert eff[("collision rate", "beta", "alpha 0.1")][9] == "not shown"
    assert eff[("min gap [m]", "alpha", "beta 4")][3] == "0.1 -> 0.9"  # alpha's extremes, beta held
    assert not any(k[0] == "hard brakes / agent" for k in eff)  # the paper claims no direction there


def test_effect_verdicts_count_each_knobs_rows_and_name_the_reversed():
    """Three beta rows (two hold, one reversed) and two alpha rows (one holds, one not shown), by hand; the
    knobs keep the order of their first row."""
    from tg_gpudrive.evaluation.report_stats import effect_verdicts

    def row(fig, knob, held, verdict):
        return [fig, knob, held, "2 -> 6", 1.0, 2.0, "1 [0.5, 1.5]", "2 [1.5, 2.5]", "+", verdict, "paired"]

    rows = [row("min gap [m]", "beta", "alpha 0.1", "holds"), row("min gap [m]", "alpha", "beta 2", "holds"),
            row("min gap [m]", "beta", "alpha 0.9", "reversed"), row("collision rate", "beta", "alpha 0.1", "holds"),
            row("collision rate", "alpha", "beta 2", "not shown")]
    assert effect_verdicts(rows) == [["beta", 3, 2, 1, 0, "min gap [m] (alpha 0.9)"], ["alpha", 2, 1, 0, 1, "-"]]
    assert effect_verdicts([]) == []


def test_paired_difference_by_hand():
    """a - b = (1, 2, 3): mean 2, median 2, every unit greater; a constant difference has a zero-width interval;
    unequal samples are an error."""
    from tg_gpudrive.evaluation.stats import paired_difference

    d = paired_difference([1.5, 2.0, 3.5], [0.5, 0.0, 0.5], n_boot=500)
    assert (d.n, d.mean_a, d.mean_b, d.diff, d.median_diff, d.share_a_greater) == (3, pytest.approx(7 / 3),
                                                                                   pytest.approx(1 / 3), 2.0, 2.0, 1.0)
    assert 1.0 <= d.lo < 2.0 < d.hi <= 3.0 and d.verdict(1) == "holds" and d.verdict(-1) == "reversed"
    flat = paired_difference([1.0, 2.0, 3.0], [1.5, 2.5, 3.5], n_boot=200)
    assert flat.lo == flat.hi == pytest.approx(-0.5) and flat.share_a_greater == 0.0
    with pytest.raises(ValueError, match="paired_difference"):
        paired_difference([1.0, 2.0], [1.0])


def test_gap_against_mappo_pairs_agents_and_says_which_side():
    """Two MAPPO runs and three CCE-MAPPO policies over the same six agents (two scenario types): one policy
    more exploitable on every agent, one less, one the same; an agent MAPPO never played is left out."""
    from tg_gpudrive.evaluation.report_stats import gap_against_mappo

    agents = [f"s{i // 3}/agent{i}" for i in range(6)]
    types = ["merge"] * 3 + ["roundabout"] * 3
    base = np.array([0.1, 0.3, 0.2, 0.4, 0.2, 0.1])

    def result(label, kind, gaps, who=agents, kinds=types):
        return {"label": label, "kind": kind,
                "cce_gap": {"agents": list(who), "types": list(kinds), "gap_per_agent": list(gaps)}}

    results = [result("mappo_s0", "MAPPO", base - 0.05), result("mappo_s1", "MAPPO", base + 0.05),
               result("high", "CCE-MAPPO", np.append(base + [0.5, 0.4, 0.6, 0.5, 0.45, 0.55], 9.0),
                      agents + ["s9/agent99"], types + ["merge"]),
               result("low", "CCE-MAPPO", base - [0.1, 0.05, 0.15, 0.2, 0.1, 0.05]),
               result("same", "CCE-MAPPO", base + [0.1, -0.1, 0.05, -0.05, 0.1, -0.1]),
               {"label": "expert", "cce_gap": None}]
    rows = {(r[0], r[1]): r for r in gap_against_mappo(results, n_boot=500)}
    assert set(rows) == {(p, t) for p in ("high", "low", "same") for t in ("all", "merge", "roundabout")}
    high = rows[("high", "all")]
    assert high[2:4] == [6, 2] and high[4] == pytest.approx(base.mean() + 0.5) and high[5] == pytest.approx(base.mean())
    assert high[7] == pytest.approx(0.5) and high[8] == "100%" and high[9] == "more exploitable"
    assert rows[("high", "merge")][2] == 3 and rows[("low", "all")][9] == "less exploitable"
    assert rows[("same", "all")][9] == "not distinguishable" and rows[("same", "all")][8] == "50%"
    assert gap_against_mappo([r for r in results if r.get("kind") != "MAPPO"]) == []


def _alike_cells(rng, shift: float, n: int = 300):
    """Three runs of one cell on n shared episodes whose values spread 0-20 (the scene sets them), each run a
    little off (its training seed), moved by `shift`."""
    base = np.random.default_rng(3).uniform(0.0, 20.0, n)
    return [base + shift + seed + rng.normal(0.0, 0.1, n) for seed in (-0.02, 0.0, 0.02)]


def test_paired_cells_resample_their_shared_episodes_once():
    """Two cells that played the same 300 episodes, 0.2 apart on every one of them: resampled each alone, the
    episodes' own spread (0-20) hides the 0.2; paired, the interval holds 0.2 and excludes 0. Runs of other
    lengths cannot be paired; an episode without a finite value in one run leaves every run."""
    rng = np.random.default_rng(0)
    low, high = _alike_cells(rng, 0.0), _alike_cells(rng, 0.2)
    alone = effect_ci(low, high, n_boot=2000, seed=0)
    paired = effect_ci(low, high, n_boot=2000, seed=0, paired=True)
    assert alone.diff == paired.diff and alone.diff_lo < 0.0 < alone.diff_hi
    assert 0.0 < paired.diff_lo < 0.2 < paired.diff_hi < 0.4 and paired.verdict(1) == "holds"
    assert spearman_ci([2, 6], [low, high], n_boot=500, paired=True).lo == 1.0  # every resample ranks them alike
    assert spearman_ci([2, 6], [low, high], n_boot=500).lo == -1.0
    with pytest.raises(ValueError, match="beta 2.*beta 6"):
        effect_ci(low, [h[:-1] for h in high], paired=True, labels=("beta 2", "beta 6"))
    holed = [r.copy() for r in high]
    holed[1][0] = np.inf
    dropped = effect_ci(low, holed, n_boot=100, paired=True)
    assert dropped.low == pytest.approx(np.mean([r[1:].mean() for r in low]))
    with pytest.raises(ValueError, match="paired"):
        spearman_ci([2, 6], [np.ones((4, 2))] * 2, statistic=lambda s: s[..., 0], paired=True)


def test_knob_effects_pair_cells_that_played_the_same_episodes_and_gap_headroom_by_hand():
    """Cells whose runs carry equal episode keys are compared episode by episode; a run with other keys (or
    none: a cache from before the keys) makes the pair each cell alone. The headroom: agents at 1, 3 and 8 m
    with first states 10, 4 and 9 m away, beta 6: max(gap, min(6, start)) = 6, 4, 8, +2 m over the mean gap of
    4, of which a high cell at 5 m reaches 1 m: half."""
    from tg_gpudrive.evaluation.report_stats import gap_headroom, group_cells, knob_effects, played_alike

    keys = np.array(["s|0|1", "s|0|2", "s|0|3"])

    def run(beta, seed, gap, key=keys):
        return {"label": f"b{beta}s{seed}", "beta": beta, "alpha": 0.5, "seed": seed, "figures": {
            "episode_key": key, "start_gap": np.array([10.0, 4.0, 9.0]), "min_gap": np.asarray(gap, float),
            "speed": np.asarray(gap, float)}}
    cells = group_cells([run(2.0, 0, [1.0, 3.0, 8.0]), run(2.0, 1, [1.0, 3.0, 8.0]),
                         run(6.0, 0, [2.0, 4.0, 9.0]), run(6.0, 1, [2.0, 4.0, 9.0])])
    assert played_alike(cells)
    gap = next(r for r in knob_effects(cells, n_boot=200) if r[0] == "min gap [m]")
    assert gap[6] == "1 [1, 1]" and gap[9] == "holds" and gap[10] == "paired"
    other = group_cells([run(2.0, 0, [1.0, 3.0, 8.0]), run(6.0, 0, [2.0, 4.0, 9.0], keys[::-1])])
    assert not played_alike(other) and knob_effects(other, n_boot=200)[0][10] == "each cell alone"
    old = group_cells([run(2.0, 0, [1.0, 3.0, 8.0]), run(6.0, 0, [2.0, 4.0, 9.0])])
    del old[0]["figures"]["episode_key"]
    assert not played_alike(old)
    [row] = gap_headroom(group_cells([run(2.0, 0, [1.0, 3.0, 8.0]), run(6.0, 0, [5.0, 5.0, 5.0])]))
    assert row[:2] == ["alpha 0.5", "beta 2 -> 6"] and row[2:5] == [4.0, 5.0, 1.0]
    assert row[5:] == [2.0, 0.5]
    # alpha at a held beta 2 can lift only the agent at 1 m, to 2 m: a ceiling of 1/3 m, reached in full
    lo, hi = run(2.0, 0, [1.0, 3.0, 8.0]), run(2.0, 0, [2.0, 3.0, 8.0])
    lo["alpha"], hi["alpha"] = 0.1, 0.9
    [row] = gap_headroom(group_cells([lo, hi]))
    assert row[:2] == ["beta 2", "alpha 0.1 -> 0.9"] and row[2:4] == [4.0, pytest.approx(13 / 3)]
    assert row[5] == pytest.approx(1 / 3) and row[6] == pytest.approx(1.0)
    # a beta the agents come within by millimetres leaves a ceiling too small to take a share of
    lo["figures"]["min_gap"] = np.array([1.99, 3.0, 8.0])
    [row] = gap_headroom(group_cells([lo, hi]))
    assert row[5] == pytest.approx(0.01 / 3) and np.isnan(row[6])


def test_effects_per_scenario_type_say_where_a_knob_acts():
    """Two training seeds a cell (beta 2, 6 x alpha 0.1, 0.9) over the same agent-episodes of two scenario types:
    on merges beta widens the min gap by 1 m and halves near misses, on roundabouts it moves nothing; a third
    type with too few agent-episodes gets no row, and cells without types give no table."""
    from tg_gpudrive.evaluation.report_stats import group_cells, knob_effects_by_type

    rng = np.random.default_rng(3)
    kinds = np.array(["merge"] * 300 + ["roundabout"] * 300 + ["t_junction"] * 10)
    keys = np.array([f"scene{i}|0|1" for i in range(len(kinds))])
    merge = kinds == "merge"
    runs = []
    for beta in (2.0, 6.0):
        for alpha in (0.1, 0.9):
            for seed in (0, 1):
                acts = merge * (beta == 6.0)
                runs.append({"label": f"b{beta}a{alpha}s{seed}", "beta": beta, "alpha": alpha, "seed": seed,
                             "figures": {"episode_key": keys, "scenario_type": kinds,
                                         "min_gap": rng.normal(5.0 + acts, 0.3, len(kinds)),
                                         "ttc_critical": (rng.random(len(kinds)) < 0.4 / (1 + acts)).astype(float),
                                         "collision": np.zeros(len(kinds))}})
    rows = {(r[0], r[1], r[2]): r for r in knob_effects_by_type(group_cells(runs), n_boot=300)}
    assert {t for t, _, _ in rows} == {"merge", "roundabout"}
    on_merge, elsewhere = rows[("merge", "beta", "alpha 0.1")], rows[("roundabout", "beta", "alpha 0.1")]
    assert on_merge[3] == "2 -> 6" and on_merge[4] == 300
    assert float(on_merge[5].split()[0]) == pytest.approx(1.0, abs=0.1) and on_merge[5].endswith("holds")
    assert on_merge[6].endswith("holds")
    assert float(on_merge[6][1:].split()[0]) == pytest.approx(0.5, abs=0.12)
    assert elsewhere[5].endswith("not shown") and elsewhere[6].endswith("not shown")
    assert on_merge[7] == "0 [0, 0] (none at low) not shown"  # no collisions anywhere: no ratio to read
    for r in runs:
        del r["figures"]["scenario_type"]
    assert knob_effects_by_type(group_cells(runs)) == []
