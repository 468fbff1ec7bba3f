"""The report's pictures (grid.png, cce_gap.png, multipliers.png) stay bounded and unclipped at any
number of runs: drawn from synthetic runs, no training or rollout."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")
from PIL import Image  # noqa: E402

from tg_gpudrive.evaluation.report_figures import plot_gaps, plot_grid, plot_multipliers  # noqa: E402

MAX_W, MAX_H = 3000, 2200  # pixels


def _fake_runs(n: int, agents: int = 12, wide: int = 1):
    rng = np.random.default_rng(n)
    betas, alphas = (2.0, 4.0, 6.0, 8.0, 10.0), (0.25, 0.5, 0.75, 0.9)
    keys = [(betas[i % 5] + 10 * (i // 20), alphas[i // 5 % 4]) for i in range(n)]
    cells = {k: rng.integers(0, 255, (64, 64 * wide, 3), dtype=np.uint8) for k in keys}
    labels = ["expert (inverse dynamics)", "behaviour prior"] + [f"beta{b:g}_alpha{a:g}_a_long_run_name" for b, a in keys]
    gaps = {lab: {"agents": [f"s{j // 2}/a{j % 2}" for j in range(agents)],
                  "gap_per_agent": rng.random(agents).tolist(), "mean_gap": 0.5, "ci95": 0.1} for lab in labels}
    curves = {lab: [{"update": u, "lambda": rng.random(), "cvar": rng.random(), "cost": rng.random()}
                    for u in range(1, 20)] for lab in labels[2:]}
    return cells, gaps, curves


def _inside(fig, artist) -> bool:
    """The artist's drawn box lies within the figure (nothing clipped at an edge)."""
    renderer = fig.canvas.get_renderer()
    box, page = artist.get_window_extent(renderer), fig.bbox
    return box.x0 >= page.x0 - 1 and box.y0 >= page.y0 - 1 and box.x1 <= page.x1 + 1 and box.y1 <= page.y1 + 1


def _apart(fig) -> bool:
    """No two of the figure's axes overlap (by more than half a pixel)."""
    renderer = fig.canvas.get_renderer()
    boxes = [ax.get_window_extent(renderer) for ax in fig.axes]
    return all(min(a.x1, b.x1) - max(a.x0, b.x0) <= 0.5 or min(a.y1, b.y1) - max(a.y0, b.y0) <= 0.5
               for k, a in enumerate(boxes) for b in boxes[k + 1:])


@pytest.mark.parametrize("wide", [1, 2], ids=["square", "paths-and-closest-approach"])
@pytest.mark.parametrize("runs", [1, 20, 200])
def test_report_pictures_stay_bounded_and_unclipped(tmp_path, runs, wide):
    """`wide` 2: each cell's picture is two frames side by side, as the report draws them."""
    cells, gaps, curves = _fake_runs(runs, wide=wide)
    figs = {"grid": plot_grid(cells, tmp_path / "grid.png"),
            "cce_gap": plot_gaps(gaps, tmp_path / "cce_gap.png"),
            "multipliers": plot_multipliers(curves, tmp_path / "multipliers.png")}
    for name, fig in figs.items():
        w, h = Image.open(tmp_path / f"{name}.png").size
        assert 300 <= w <= MAX_W and 250 <= h <= MAX_H, (name, runs, w, h)
        if fig._suptitle is not None:
            assert _inside(fig, fig._suptitle), (name, runs)
        for ax in fig.axes:
            assert _inside(fig, ax.title), (name, runs)
    assert _apart(figs["grid"]), (runs, wide)
    # the grid carries the legend of what its frames draw, inside the picture
    assert figs["grid"].legends and _inside(figs["grid"], figs["grid"].legends[0])
    # one run: one large cell (at least 6 inches at 100 dpi), not a thumbnail
    if runs == 1:
        assert Image.open(tmp_path / "grid.png").size[0] >= 600
    # cce_gap: one column per policy, wrapped into rows rather than one ever wider strip
    ticks = [t.get_text() for ax in figs["cce_gap"].axes for t in ax.get_xticklabels()]
    assert len(ticks) == len(gaps)


@pytest.mark.parametrize("wide", [1, 2], ids=["square", "paths-and-closest-approach"])
def test_grid_writes_each_cells_note_under_its_picture(tmp_path, wide):
    """The knobs' extreme cells, two by two as a grid report draws them (`wide` 2: its two frames side by side);
    the pictures do not overlap, so no note is hidden under the next row."""
    rng = np.random.default_rng(0)
    cells = {(b, a): rng.integers(0, 255, (640, 640 * wide, 3), dtype=np.uint8) for b in (2.0, 6.0)
             for a in (0.125, 0.875)}
    notes = {cell: f"mean least distance here {i + 3.5:.1f} m" for i, cell in enumerate(sorted(cells))}
    fig = plot_grid(cells, tmp_path / "grid.png", notes=notes)
    renderer = fig.canvas.get_renderer()
    drawn = {}
    for ax in fig.axes:
        for t in ax.texts:  # each note inside its own cell's picture, so it covers no other cell
            drawn[t.get_text()] = ax
            box, own = t.get_window_extent(renderer), ax.get_window_extent(renderer)
            assert own.x0 <= box.x0 and box.x1 <= own.x1 and own.y0 <= box.y0 and box.y1 <= own.y1, t.get_text()
    assert sorted(drawn) == sorted(notes.values()) and _apart(fig)
    assert not any(ax.texts for ax in plot_grid(cells, tmp_path / "bare.png").axes)
    # the title says what the right-hand zooms show (the report's shared moment), beside the whole paths only
    zoom = "every cell at 3.3 s, zoomed in on car 0"
    title = " ".join(plot_grid(cells, tmp_path / "zoom.png", zoom=zoom)._suptitle.get_text().split())
    assert (f"right, {zoom}" in title) == (wide == 2)


def test_report_pictures_without_runs(tmp_path):
    plot_grid({}, tmp_path / "grid.png")
    plot_gaps({}, tmp_path / "cce_gap.png")
    plot_multipliers({}, tmp_path / "multipliers.png")
    for name in ("grid", "cce_gap", "multipliers"):
        assert (tmp_path / f"{name}.png").stat().st_size > 0


def test_multipliers_colour_a_cells_training_seeds_alike(tmp_path):
    """Two cells of three training seeds each: every seed's line in its cell's colour, one legend entry a cell
    naming its runs; without cells (or one run a cell) each run keeps its own colour and entry."""
    rng = np.random.default_rng(0)
    cell_of = {f"beta{b}_alpha0.5_s{s}": f"beta {b} / alpha 0.5" for b in (2, 6) for s in range(3)}
    curves = {lab: [{"update": u, "lambda": rng.random(), "cvar": rng.random(), "cost": rng.random()}
                    for u in range(1, 20)] for lab in cell_of}
    fig = plot_multipliers(curves, tmp_path / "multipliers.png", cell_of)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["beta 2 / alpha 0.5 (3 runs)",
                                                                 "beta 6 / alpha 0.5 (3 runs)"]
    for ax in fig.axes:
        colours = [line.get_color() for line in ax.get_lines()]
        assert len(colours) == 6 and len(set(colours[:3])) == 1 and len(set(colours[3:])) == 1
        assert colours[0] != colours[3]
    for groups in (None, {lab: lab for lab in cell_of}):
        fig = plot_multipliers(curves, tmp_path / "own.png", groups)
        assert [t.get_text() for t in fig.legends[0].get_texts()] == list(cell_of)
        assert len({line.get_color() for line in fig.axes[0].get_lines()}) == 6
