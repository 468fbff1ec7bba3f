"""`tg-gpudrive report`: the scenario-quality report of one or more training runs.

    report_main(["runs/grid/beta4.0_alpha0.5", ...], "report/")

For every run directory (holding checkpoint.pt, config.json, metrics.csv as
`learn.train.Trainer` writes them) the run's policy drives the first
`scenes` scenes of its own scene source (same control selection), once per
rollout seed, with a slot for every agent of those scenes
(checkpoint.policy_engine_config); the logs of those worlds are the reference.
A run may also be a checkpoint file, or `shipped` (the packaged policy,
tg_gpudrive/policies/shipped.pt): config from the checkpoint, no training
curves. Baselines on the first run's scenes: log replay (the engine replaying
every agent's log, recorded like a policy: the floor of the divergences; no
CCE-gap, nobody drives), the closed-loop inverse-dynamics expert in the run's
action space, the behaviour prior alone (actions sampled from the expert
prior, agents/prior.py, discrete action spaces) and the world model alone (the
first run's magnet, `prior_model`, default the shipped model, sampling every
policy agent's action: the paper's baseline beside plain MAPPO; continuous runs
need a continuous `prior_model`). A
run counts as plain MAPPO when its config switches the magnet, the proximal
term and the constraint off
(eta1 = 0, eta2 = inf, constraint = false; see
configs/experiments/grid.yaml), else as CCE-MAPPO.

Writes into `out`:

    report.md           tables: comparison against baselines, fidelity per feature, CCE-gap per
                        agent and per scenario type (PPO best responses trained to a plateau on
                        the first --br-scenes evaluation scenes, exploitability.py; --br-* flags),
                        diversity per scenario type, most critical scenarios
    grid.png            the paper's beta x alpha figure: one scene (--grid-scene) per CCE-MAPPO cell,
                        beta down the rows, alpha across, whole trajectories drawn
    frames/<run>.gif    with --grid-gifs: that scene's episode per cell
    multipliers.png     lambda and CVaR of the cost during training, per run (metrics.csv)
    fidelity.png        histograms of speed, accel, nearest distance, curvature: logs vs generated
    cce_gap.png         CCE-gap per agent, per run (not with --no-cce-gap)
    cce_gap_curve.png   the CCE-gap over each run's training: its starting policy (init_policy, update 0;
                        computed once when runs share it), the policies it kept (keep_policy_every > 0)
                        and its final checkpoint, by the same best-response procedure at every point
    summary.json        every number of the tables
    scenarios/<run>/    the most critical generated scenarios as GPUDrive JSON (risk in metadata)
    frames/<run>.png    the top-down pictures of the grid
    worst_scenes.png    the first run's scenes with the most collisions and off-road events per agent-episode,
                        drawn as their episodes end (frames/worst_<k>.png)
    cache/<label>.pkl   each policy's rollouts and figures, CCE-gap included, keyed by its checkpoint
                        files and the options: a report that was stopped goes on where it stopped, and
                        several processes (one per GPU, each with some of the runs and --no-baselines
                        but one) fill the cache that a last report over all the runs reads
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import pickle
import sys
import textwrap
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm import tqdm

from tg_gpudrive.agents import trained_sim
from tg_gpudrive.checkpoint import checkpoint_path, kept_policies, load_checkpoint
from tg_gpudrive.cli_help import HelpFormatter
from tg_gpudrive.config import TrainConfig, from_dict
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.evaluation import diversity as div
from tg_gpudrive.evaluation import exploitability as ex
from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.export import export_episodes
from tg_gpudrive.evaluation.episodes import logged_episodes, record_rollouts, replay_episodes
from tg_gpudrive.evaluation.stats import spearman_ci
from tg_gpudrive.agents.prior import ExpertPrior
from tg_gpudrive.agents.policy import load_actor, load_policy
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.worldmodel.prior import WorldModelDriver, load_world_model

FILES = ("report.md", "grid.png", "multipliers.png", "fidelity.png", "cce_gap.png", "worst_scenes.png", "summary.json")


@dataclasses.dataclass
class ReportOptions:
    scenes: int = 4  # evaluation scenes per run (worlds)
    # held-out evaluation scenes: the run's scene spec (or `eval_scenes`) with procedural seeds from
    # `scene_seed` on, never trained on (a run trains on seeds seed .. seed + num_scenes - 1; `evaluate`'s
    # held-out seed is the same 90000); None: the run's own seed, i.e. its training scenes. File and store
    # specs have no seed: name held-out files with `eval_scenes`.
    scene_seed: int | None = 90000
    eval_scenes: str | None = None
    cce_gap: bool = True  # the CCE-gaps (PPO best responses: the report's GPU time); False: rollouts only
    seeds: tuple[int, ...] = (0, 1)  # rollout seeds (diversity needs >= 2)
    # CCE-gap (exploitability.py): a PPO best response per agent, trained until its return plateaus
    br_iters: int = 100  # cap on the PPO iterations of one best response
    br_seeds: tuple[int, ...] = (0, 1)
    br_lr: float = 3e-3
    br_rounds: int = 2  # fresh evaluation batches of J_pi and of J_br
    br_tol: float = 0.01  # plateau: no new best moving mean by tol * max(1, |best|) ...
    br_window: int = 5  # ... of this many iterations ...
    br_patience: int = 10  # ... for this many iterations ...
    br_min_iters: int = 20  # ... and never before this many
    br_copies: int | None = None  # episodes per agent and PPO iteration; None: 16 on a GPU, 4 on the CPU
    # the first br_scenes evaluation scenes play the deviation game (None: all of them); scene sources
    # cycle over the scenario types, so a multiple of their number keeps the types balanced
    br_scenes: int | None = None
    br_gamma: float | None = None  # discount of the returns; None: the run's gamma (baselines: the first run's)
    top: int = 3  # critical scenarios exported per run
    device: str | None = "auto"  # auto (cuda when one is visible, else cpu) | cpu | cuda:N; None: the run's config
    frame_size: int = 320
    grid_scene: int = 0  # which evaluation scene (0 .. scenes-1) the beta x alpha figure shows
    grid_gifs: bool = False  # also write frames/<run>.gif, the whole episode of that scene, per cell
    progress: bool = True  # a tqdm bar over the policies evaluated (stderr)
    # log replay, expert, behaviour prior and world model on the first run's scenes, and the CCE-gap of
    # the policy the runs started from (init_policy): what report parts share
    baselines: bool = True


# ------------------------------------------------------------------ helpers
def _run_config(run: Path):
    path = run / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{run}: no config.json (not a training run directory?)")
    return from_dict(TrainConfig, json.loads(path.read_text()), str(path))


def _run_files(run: Path):
    """(TrainConfig, checkpoint path) of a run: a run directory (config.json, checkpoint.pt), a checkpoint
    file or "shipped", the packaged policy (checkpoint.checkpoint_path; the config from the checkpoint)."""
    if run.is_dir():
        ckpt = run / "checkpoint.pt"
        if not ckpt.exists():
            raise FileNotFoundError(f"{run}: no checkpoint.pt")
        return _run_config(run), ckpt
    ckpt = checkpoint_path(str(run), "--runs")
    return from_dict(TrainConfig, load_checkpoint(ckpt, "--runs")["config"], str(ckpt)), ckpt


def run_kind(cfg) -> str:
    plain = cfg.eta1 == 0 and math.isinf(cfg.eta2) and (not cfg.constraint or (cfg.lambda_lr == 0 and cfg.lambda_init < 1e-3))
    return "MAPPO" if plain else "CCE-MAPPO"


def _eval_spec(cfg, opts: ReportOptions) -> tuple[str, int, bool]:
    """(scene spec, seed, procedural) of the evaluation scenes of a run trained with `cfg`."""
    spec = opts.eval_scenes or cfg.scenes
    return spec, cfg.seed if opts.scene_seed is None else opts.scene_seed, spec.startswith("procedural:")


def _scenes(cfg, n: int, opts: ReportOptions) -> list:
    """The first `n` evaluation scenes (ReportOptions.scene_seed / eval_scenes) of a run trained with `cfg`."""
    spec, seed, procedural = _eval_spec(cfg, opts)
    if opts.scene_seed is not None and spec == cfg.scenes and procedural \
            and seed < cfg.seed + cfg.num_scenes and cfg.seed < seed + n:
        raise ValueError(f"scene_seed {seed}: procedural seeds {seed} .. {seed + n - 1} overlap the run's training "
                         f"scenes (seeds {cfg.seed} .. {cfg.seed + cfg.num_scenes - 1})")
    src = resolve_scenes(spec, n=n if opts.scene_seed is not None else cfg.num_scenes, seed=seed)
    return [src.get(i) for i in range(min(n, len(src)))]


def eval_scenes_text(cfg, opts: ReportOptions) -> str:
    """Which scenes `_scenes` evaluates, and whether they are held out, for the report's readers."""
    spec, _, procedural = _eval_spec(cfg, opts)
    if opts.eval_scenes:
        return f"{spec}" + (f" from seed {opts.scene_seed}" if procedural and opts.scene_seed is not None else "")
    if procedural and opts.scene_seed is not None:
        return f"held out: {spec}, procedural seeds from {opts.scene_seed} (training: from {cfg.seed})"
    why = "--scene-seed -1" if procedural else "file and store specs have no seed: name held-out ones with --eval-scenes"
    return f"{spec}: the runs' training scenes, not held out ({why})"


def prior_policy(sim):
    """Sample every slot's action from the expert prior (agents/prior.py): "the behaviour prior alone"."""
    prior = ExpertPrior(sim)

    def policy(sim_):
        logits = prior.distribution(prior.context(sim_, sim_.max_agents))
        a = torch.distributions.Categorical(logits=logits).sample()
        sim_.actions_index.copy_(a.to(torch.int32))

    return policy


def world_model_policy(cfg: TrainConfig, sim) -> WorldModelDriver:
    """The world model alone driving every policy agent (sampled, as the magnet is a distribution):
    the run's `prior_model`, or the shipped model when it names none."""
    return WorldModelDriver(load_world_model(cfg.prior_model or "shipped", sim), rows="policy", seed=0)


def _last_frame(cfg, scene, mask, ckpt, device, size: int, path: Path, gif: bool = False) -> np.ndarray:
    """Last frame of the scene's episode under the run's policy, with every agent's whole trajectory
    (engine without auto-reset, so the final state is still there to draw), saved to `path`; with
    `gif` also the whole episode beside it (`path` with .gif)."""
    # drawing needs the render extra (matplotlib, Pillow): imported when a report draws, so that the
    # report's parser and its numbers do not need it
    from PIL import Image

    from tg_gpudrive.render import render_episode

    sim = Simulator([scene], dataclasses.replace(cfg.env, auto_reset=False), device, controlled=[mask])
    path.parent.mkdir(parents=True, exist_ok=True)
    # the view fits the controlled cars' paths: the interaction the knobs change, not the whole map; the
    # same seed makes the GIF the picture's episode
    kw = dict(world=0, size=(size, size), legend=False, fit="controlled", seed=0)
    render_episode(sim, load_policy(ckpt, sim), out=path, **kw)
    if gif:
        render_episode(sim, load_policy(ckpt, sim), out=path.with_suffix(".gif"), **kw)
    return np.asarray(Image.open(path).convert("RGB"))


WORST_SCENES = 4  # scenes drawn in worst_scenes.png


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


def plot_worst_scenes(frames: list[np.ndarray], rows: list[dict], label: str, path: Path) -> None:
    """The last frames of the worst scenes side by side, each titled with its failures."""
    fig = _fig()
    fig.set_size_inches(min(3.2 * len(frames), MAX_FIG_W), 3.6)
    for k, (img, r) in enumerate(zip(frames, rows)):
        ax = fig.add_subplot(1, len(frames), k + 1)
        ax.imshow(img)
        ax.set_axis_off()
        ax.set_title(f"{_short(r['scene_id'], 22)}\ncollisions {r['collisions']}, off-road {r['offroad']} "
                     f"of {r['agent_episodes']}", fontsize=8)
    fig.suptitle(f"Worst scenes of {label}", fontsize=10)
    fig.savefig(path)


def _br_copies(opts: ReportOptions, device: str) -> int:
    """Episodes per agent and PPO iteration: --br-copies, else 16 on a GPU and 4 on the CPU (where a
    report is a try of the pipeline: 4 x the agents' worlds already cost seconds per iteration)."""
    if opts.br_copies is not None:
        return opts.br_copies
    return 4 if device == "cpu" else 16


def br_config(opts: ReportOptions, gamma: float) -> ex.BRConfig:
    """The best-response settings of the report (`gamma`: the run's unless --br-gamma)."""
    return ex.BRConfig(gamma=opts.br_gamma if opts.br_gamma is not None else gamma, lr=opts.br_lr,
                       max_iters=opts.br_iters, tol=opts.br_tol, window=opts.br_window, patience=opts.br_patience,
                       min_iters=opts.br_min_iters, eval_rounds=opts.br_rounds)


def episode_figures(gen, risk: dict) -> dict[str, np.ndarray]:
    """One value per policy agent-episode of each figure the flexibility claims are about."""
    m = risk["agents"]  # present at some step, so the mean speed below has a step to average
    speed = np.where(gen.valid, gen.speed, 0.0).sum(-1) / np.maximum(gen.valid.sum(-1), 1)
    return {"min_gap": risk["min_gap"][m], "speed": speed[m],
            "ttc_critical": (risk["min_ttc"][m] < rk.TTC_CRITICAL).astype(float),
            "collision": risk["collided"][m].astype(float), "hard_brakes": risk["hard_brakes"][m].astype(float),
            "collision_other": ((risk["contact"] >= 0) & ~risk["partner_policy"])[m].astype(float),
            "from_behind": (risk["contact"] == rk.CONTACTS.index("from behind"))[m].astype(float),
            # rows, not values: the Hellinger figure is a statistic of their sum (flexibility_directions)
            "hellinger": fid.episode_histograms(gen, m).astype(np.float32)}


def _measure(label, gen, logged, opts) -> dict:
    """Fidelity, diversity and risk of recorded episodes `gen` (no CCE-gap); `figures` holds the
    per-agent-episode values behind the flexibility intervals (left out of summary.json)."""
    risk = rk.episode_risk(gen)
    return {"label": label, "fidelity": fid.compare(logged, gen), "diversity": div.diversity(gen),
            "risk": rk.summarize(gen, risk), "critical": rk.rank_scenarios(gen, risk, top=opts.top), "cce_gap": None,
            "figures": episode_figures(gen, risk)}


# The paper's direction for each figure as the knob grows: beta (the distance constraint: larger is
# tighter) gives larger gaps and safer, less competitive traffic; alpha (the CVaR level: larger is
# more risk-averse) gives lower speeds and larger spacing. 0: the paper states no direction.
FLEX_CLAIMS = {  # figure: (label, sign with beta, sign with alpha)
    "min_gap": ("min gap [m]", +1, +1),
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


def flexibility_directions(cells: list[dict], n_boot: int = 2000, logged: dict | None = None) -> list[list]:
    """Rows (figure, knob, paper's sign, rho, 95 % interval, verdict, samples per cell) of the Spearman
    correlation of each figure with beta and with alpha over the CCE-MAPPO cells; the Hellinger row
    needs the `logged` histograms (fidelity.histograms of the logs the cells were compared with)."""
    rows = []
    for key, (name, *signs) in FLEX_CLAIMS.items():
        # a cache written before the figure existed, or a report without CCE-gaps
        if any(key not in c["figures"] for c in cells) or key == "hellinger" and logged is None:
            continue
        samples = [c["figures"][key] for c in cells]
        stat = (lambda sums: fid.hellinger_of_sums(logged, sums)) if key == "hellinger" else None
        for knob, sign in zip(("beta", "alpha"), signs):
            values = [c[knob] for c in cells]
            if len(set(values)) < 2:
                continue
            r = spearman_ci(values, samples, n_boot=n_boot, labels=[c["label"] for c in cells], statistic=stat)
            verdict = r.verdict(sign) if sign else "-"
            rows.append([name, knob, {1: "+", -1: "-", 0: "none"}[sign], r.rho, f"[{_fmt(r.lo)}, {_fmt(r.hi)}]",
                         verdict, min(len(x) for x in samples)])
    return rows


def _evaluate(label, sim, policy, logged, opts, gap_game, bar, gamma: float) -> tuple[dict, object]:
    """Rollouts, fidelity, diversity and risk of one policy, then its CCE-gap (PPO best responses,
    discount `gamma` unless --br-gamma); advances `bar` by one."""
    bar.set_postfix_str(f"{label}: rollouts")
    gen = record_rollouts(sim, policy, opts.seeds, label=label)
    res = _measure(label, gen, logged, opts)
    if opts.cce_gap:
        bar.set_postfix_str(f"{label}: CCE-gap ({len(opts.br_seeds)} seeds, PPO best responses to a plateau, "
                            f"<= {opts.br_iters} iterations)")
        res["cce_gap"] = ex.cce_gap(gap_game, seeds=opts.br_seeds, config=br_config(opts, gamma))
        res["figures"]["cce_gap"] = np.asarray(res["cce_gap"]["gap_per_agent"], np.float64)
    bar.update(1)
    return res, gen


def _cache_key(label: str, files: Sequence[Path], opts: ReportOptions) -> str:
    """What a policy's evaluation depends on: its label, the checkpoint files' contents (so a run
    directory copied to another machine keeps its cache) and every option but the progress bar, the
    baselines switch and the grid picture's (drawn anew on every pass)."""
    h = hashlib.sha256(label.encode())
    for f in files:
        h.update(Path(f).read_bytes())
    o = {k: v for k, v in dataclasses.asdict(opts).items()
         if k not in ("progress", "baselines", "grid_scene", "grid_gifs", "frame_size")}
    h.update(json.dumps(o, default=str, sort_keys=True).encode())
    return h.hexdigest()


def _cached(out: Path, label: str, files: Sequence[Path], opts: ReportOptions, compute, bar):
    """`compute()` (a policy's (result, rollouts)), or what cache/<label>.pkl holds under the same
    `_cache_key` (advancing `bar`, if any, by the one step compute would have); stored atomically after
    computing."""
    key = _cache_key(label, files, opts)
    path = out / "cache" / (label.replace("/", "_").replace(" ", "_") + ".pkl")
    if path.exists():
        try:
            with path.open("rb") as f:
                hit = pickle.load(f)
        except Exception:  # a cache from another version or a torn file: evaluate again
            hit = None
        if isinstance(hit, dict) and hit.get("key") == key:
            if bar is not None:
                bar.set_postfix_str(f"{label}: from {path.parent.name}/")
                bar.update(1)
            return hit["value"]
    value = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        pickle.dump({"key": key, "value": value}, f, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return value


def _read_metrics(run: Path) -> list[dict]:
    path = run / "metrics.csv"
    return list(csv.DictReader(path.open())) if path.exists() else []


def _tail_means(rows: list[dict], keys: Sequence[str], tail: int = 5) -> dict:
    """Mean of each key over the last `tail` training updates (NaN when absent)."""
    out = {}
    for k in keys:
        vals = [float(r[k]) for r in rows[-tail:] if r.get(k) not in (None, "", "nan")]
        out[k] = sum(vals) / len(vals) if vals else math.nan
    return out


def _fig():
    # matplotlib (the render extra) only when a figure is drawn, as in _last_frame
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(dpi=100)
    FigureCanvasAgg(fig)
    return fig


# ---------------------------------------------------------------- figures
# bounds of the report's pictures (inches at 100 dpi): they stay readable and bounded at any number of runs;
# each plot_* function saves `path` and returns its Figure
MAX_FIG_W, MAX_FIG_H = 26.0, 20.0
GRID_MIN_SIDE = 6.0  # in: the grid's cells together span at least this (one run: one 6-inch cell)
GRID_LEGEND_IN = 0.6  # in below the grid's cells for the legend of what the frames draw


def _wrapped(text: str, width_in: float, fontsize: float) -> str:
    """`text` wrapped to lines that fit `width_in` inches at `fontsize` points (about 0.55 em a character)."""
    return "\n".join(textwrap.wrap(text, max(12, int(width_in * 72 / (0.55 * fontsize)))))


def _short(label: str, n: int = 26) -> str:
    return label if len(label) <= n else label[: n - 10] + "…" + label[-9:]


def plot_grid(cells: dict[tuple[float, float], np.ndarray], path: Path, max_rows: int = 8, scene: str = ""):
    """The paper's beta x alpha figure: one picture per CCE-MAPPO cell, beta down the rows, alpha
    across the columns. More than `max_rows` betas wrap into further blocks side by side (each block
    all the alphas); cells shrink (from 2.4 in) and labels with them, so the picture stays within
    MAX_FIG_W x MAX_FIG_H; the title wraps to the picture's width."""
    from tg_gpudrive.render.draw import legend_handles  # the render extra, as the cells' frames

    betas = sorted({b for b, _ in cells}) or [0.0]
    alphas = sorted({a for _, a in cells}) or [0.0]
    blocks = [betas[i:i + max_rows] for i in range(0, len(betas), max_rows)]
    nrows, ncols = len(blocks[0]), len(blocks) * len(alphas)
    # a few cells are drawn large (GRID_MIN_SIDE in across the picture), many shrink towards the bounds
    cell = min(max(2.4, GRID_MIN_SIDE / max(nrows, ncols)), (MAX_FIG_W - 0.8 - 0.3 * len(blocks)) / ncols,
               (MAX_FIG_H - 1.2 - GRID_LEGEND_IN) / nrows)
    fs = max(5.0, min(9.0, cell * 72 / (0.6 * 13)))  # "beta = 10.5 m" fits beside a cell
    width = max(4.0, ncols * cell + 0.3 * len(blocks) + 0.8)
    where = f" on scene {scene}" if scene else ""
    title = _wrapped(f"CCE-MAPPO{where}: beta (distance constraint, rows) x alpha (CVaR level, columns); whole "
                     "trajectories, controlled vehicles blue", width - 0.2, 9)
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
    fig.savefig(path)
    return fig


def plot_multipliers(curves: dict[str, list[dict]], path: Path):
    """Three panels; the legend goes below them in columns (its rows grow the picture, up to MAX_FIG_H)."""
    fig = _fig()
    ncol = 4
    legend_rows = -(-len(curves) // ncol)
    extra = min(0.2 * legend_rows, MAX_FIG_H - 3.4)
    fig.set_size_inches(12, 3.4 + extra)
    styles = ("-", "--", ":", "-.")
    for i, key in enumerate(("lambda", "cvar", "cost")):
        ax = fig.add_subplot(1, 3, i + 1)
        for j, (label, rows) in enumerate(curves.items()):
            x = [int(r["update"]) for r in rows if r.get(key) not in (None, "", "nan")]
            y = [float(r[key]) for r in rows if r.get(key) not in (None, "", "nan")]
            ax.plot(x, y, marker="." if len(x) < 10 else None, lw=1, label=_short(label, 40),
                    color=f"C{j % 10}", ls=styles[j // 10 % len(styles)])
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


def policy_gap(ckpt: Path, gsim, opts: ReportOptions, gamma: float) -> dict:
    """The CCE-gap of the policy in checkpoint `ckpt` on the deviation game of `gsim`."""
    actor = load_actor(ckpt, gsim)[0]  # once, shared by the seeds
    return ex.cce_gap(lambda s: ex.SimGame(gsim, actor=actor), seeds=opts.br_seeds, config=br_config(opts, gamma))


def kept_gaps(kept: list[tuple[int, Path]], gsim, opts: ReportOptions, gamma: float,
              last_update: int | None) -> list[dict]:
    """The CCE-gap of every policy a run kept during training (checkpoint.kept_policies) but the one of
    its final update (`last_update`: the final checkpoint's policy, evaluated as the run itself):
    [{update, mean_gap, ci95}], oldest first."""
    points = []
    for update, f in kept:
        if update != last_update:
            g = policy_gap(f, gsim, opts, gamma)
            points.append({"update": update, "mean_gap": g["mean_gap"], "ci95": g["ci95"]})
    return points


def gap_curve(start: dict | None, kept: list[dict], last: dict | None, last_update: int | None) -> list[dict]:
    """The CCE-gap over a run's training: `start` (the gap of the policy it started from) at update 0,
    the kept policies' points (`kept_gaps`) and the final checkpoint's gap `last` at `last_update`;
    empty with fewer than two points."""
    points = [] if start is None else [{"update": 0, "mean_gap": start["mean_gap"], "ci95": start["ci95"]}]
    points += kept
    if points and last and last_update is not None and last_update > points[-1]["update"]:
        points.append({"update": last_update, "mean_gap": last["mean_gap"], "ci95": last["ci95"]})
    return points if len(points) > 1 else []


def start_gap(run: Path, cfg: TrainConfig, gsim, opts: ReportOptions, out: Path, bar) -> dict | None:
    """The CCE-gap of the policy run `run` started from (its `init_policy`; None without one) on the
    run's deviation game `gsim`, cached under the starting checkpoint and a label that hashes what
    defines the game (its scenes, who is controlled, engine and discount, not the run's own knobs), so
    runs that share both compute it once."""
    if not cfg.init_policy:
        return None
    init = checkpoint_path(cfg.init_policy, f"{run}/config.json: init_policy")
    env = {k: v for k, v in dataclasses.asdict(cfg.env).items() if k != "beta"}  # beta shapes the cost only
    game = json.dumps({"scenes": [s.scene_id for s in gsim.model.scenes], "control": cfg.control,
                       "control_k": cfg.control_k, "control_ids": cfg.control_ids, "gamma": cfg.gamma, "env": env},
                      default=str, sort_keys=True)
    label = f"start {hashlib.sha256((str(init) + game).encode()).hexdigest()[:12]}"
    if bar is not None:
        bar.set_postfix_str(f"{run.name}: CCE-gap of its starting policy ({cfg.init_policy})")
    return _cached(out, label, [init], opts, lambda: policy_gap(init, gsim, opts, cfg.gamma), None)


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


# ------------------------------------------------------------------ tables
def _fmt(v, nd=3) -> str:
    if v is None:
        return "-"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    v = float(v)
    return "nan" if math.isnan(v) else f"{v:.{nd}g}" if abs(v) < 1e4 else f"{v:.3e}"


def _table(header: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(c if isinstance(c, str) else _fmt(c) for c in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def _pm(mean, half) -> str:
    return f"{_fmt(mean)} ± {_fmt(half)}"


def _br_text(meta: dict) -> str:
    b = meta["best_response"]
    return (f"a PPO best response per agent (others frozen) on the first {b.get('scenes', 'all')} evaluation "
            f"scenes, {b['copies']} episodes per agent and iteration, "
            f"until its discounted return (gamma: {b['gamma']}) plateaus (no new best {b['window']}-iteration "
            f"moving mean by {b['tol']:g} x max(1, |best|) for {b['patience']} iterations, at least "
            f"{b['min_iters']}; cap {b['max_iters']}), "
            f"seeds {meta['br_seeds']}")


def _gap_sections(results: list[dict], computed: bool = True) -> list[str]:
    """The CCE-gap sections of report.md: per agent, per scenario type, PPO iterations; one line where the
    report was asked for none (`computed` False: --no-cce-gap)."""
    if not computed:
        return ["\n## CCE-gap\n\nNot computed (--no-cce-gap): this report has rollouts only. The same command "
                "without the flag adds a PPO best response per agent (GPU time).\n"]
    gapped = [(r["label"], r["cce_gap"]) for r in results if r.get("cce_gap")]
    L = ["\n## CCE-gap per agent\n\n![cce_gap](cce_gap.png)\n\n",
         "gain = J(BR) - J(pi), each agent's discounted return on fresh rollouts with its PPO best response "
         "against everyone else frozen at the policy, and with the policy itself; gap = max(0, gain) (the agent "
         "could keep pi). Means over the best-response seeds; the gain's 95 % interval is the evaluation's "
         "(1.96 standard errors of the fresh episodes); iterations: PPO iterations to the plateau per seed "
         "(* = stopped at the cap).\n\n"]
    rows = []
    for label, g in gapped:
        n = len(g["agents"])
        iters, plat = np.asarray(g["iters"]).T.tolist(), np.asarray(g["plateaued"]).T.tolist()
        for a in range(n):
            its = ", ".join(f"{i}{'' if p else '*'}" for i, p in zip(iters[a], plat[a]))
            rows.append([label, g["agents"][a], g["types"][a], g["gap_per_agent"][a],
                         _pm(g["gain_per_agent"][a], g["gain_ci95_per_agent"][a]), g["j_pi_per_agent"][a], g["j_br_per_agent"][a], its])
    L.append(_table(["policy", "agent", "scenario type", "gap", "raw gain ± 95% CI", "J(pi)", "J(BR)",
                     "PPO iterations"], rows))
    L.append("\n## CCE-gap per scenario type\n\nMean gap over the agents of that scenario type with its "
             "Student-t 95 % interval over those agents (each agent's gap averaged over the seeds); "
             "all: every agent, and the interval over seeds of the mean over agents beside it.\n\n")
    rows = []
    for label, g in gapped:
        n = len(g["agents"])
        rows.append([label, "all", n, _pm(g["mean_gap"], g["ci95"]), g["mean_gain"], _fmt(g["ci95_seeds"]),
                     g["mean_iters"]])
        for t, v in g["per_type"].items():
            rows.append([label, t, v["agents"], _pm(v["mean_gap"], v["ci95"]), v["mean_gain"], "-", "-"])
    L.append(_table(["policy", "scenario type", "agents", "CCE-gap ± 95% CI (agents)", "mean raw gain",
                     "95% CI (seeds)", "mean PPO iterations"], rows))
    curves = [(r["label"], r["gap_curve"]) for r in results if r.get("gap_curve")]
    if curves:
        L.append("\n## CCE-gap over training\n\n![cce_gap_curve](cce_gap_curve.png)\n\nThe same best-response "
                 "procedure on the policy the run started from (`init_policy`, update 0), each policy it kept "
                 "(`keep_policy_every`) and its final checkpoint.\n\n")
        L.append(_table(["run", "update", "CCE-gap ± 95% CI (agents)"],
                        [[label, p["update"], _pm(p["mean_gap"], p["ci95"])] for label, pts in curves for p in pts]))
    else:
        L.append("\nNo CCE-gap curve over training: it needs a run that started from a policy (`init_policy`; the "
                 "starting policy's gap is computed by the report process that also does the baselines, not "
                 "with --no-baselines) or kept policies during training (`--set keep_policy_every=N`).\n")
    return L


def _flexibility_section(results: list[dict], logged_hist: dict | None) -> list[str]:
    """The report's beta x alpha section: the cells' training and evaluation means, and (three cells or
    more) the direction of every figure with each knob; nothing without CCE-MAPPO cells."""
    out: list[str] = []
    cce = sorted((r for r in results if r.get("kind") == "CCE-MAPPO"), key=lambda r: (r["beta"], r["alpha"]))
    if cce:
        out.append("\n## Flexibility: beta x alpha\n\nTraining: mean of the last 5 updates. Evaluation: the "
                   "rollouts above. Paper's direction: larger beta (tighter) -> larger lambda and gaps; lower "
                   "alpha (less risk-averse) -> faster, smaller gaps.\n\n")
        rows = [[r["beta"], r["alpha"], r["train_tail"]["lambda"], r["train_tail"]["mean_min_distance"],
                 r["train_tail"]["mean_speed"], r["train_tail"]["cost"], r["risk"].get("mean_min_gap_m"),
                 r["fidelity"]["per_feature"].get("speed", {}).get("mean_generated"),
                 r["risk"].get("collision_rate")] for r in cce]
        out.append(_table(["beta [m]", "alpha", "lambda (train)", "min distance (train) [m]", "speed (train) [m/s]",
                           "cost (train)", "min gap (eval) [m]", "speed (eval) [m/s]", "collision rate (eval)"],
                          rows))
        if len(cce) >= 3 and all("figures" in r for r in cce):
            out.append("\nDirection of each figure with each knob over the cells: Spearman's rho of the knob with "
                       "the cells' means, 95 % bootstrap interval from resampling every cell's agent-episodes "
                       "(evaluation noise only, not training seeds). **holds**: the interval lies on the paper's "
                       "side of 0; **reversed**: on the other side; **not shown**: it contains 0. Samples: agent-episodes; "
                       "for the CCE-gap the deviation game's agents; the Hellinger distance is of each cell's pooled "
                       "histograms, its resamples reweight the agent-episodes' histograms.\n\n")
            out.append(_table(["figure", "knob", "paper's sign", "rho", "95 % interval", "verdict",
                               "samples per cell (min)"], flexibility_directions(cce, logged=logged_hist)))
    return out


def write_markdown(out: Path, results: list[dict], meta: dict, logged_hist: dict | None = None) -> None:
    L = ["# Scenario-quality report\n",
         f"Runs: {', '.join(meta['runs'])}. Evaluation: {meta['scenes']} scenes per run ({meta['eval_scenes']}), "
         f"rollout seeds {meta['seeds']}; CCE-gap: "
         f"{_br_text(meta) if meta.get('cce_gap', True) else 'not computed (--no-cce-gap)'}. "
         "Definitions and binning: `tg_gpudrive/evaluation/` module docstrings (fidelity bins: speed 0.5 m/s on "
         "[0, 30], accel 0.25 m/s^2 on [-8, 8], nearest 0.5 m on [0, 50], curvature 0.005 1/m on [-0.3, 0.3]; "
         f"KL smoothing eps {fid.KL_EPS:g}; TTC: {rk.TTC_DISCS} discs of radius width/2 per agent, constant "
         f"velocity, horizon {rk.TTC_HORIZON:g} s; hard brake: accel < {rk.HARD_BRAKE:g} m/s^2).\n",
         "**realism (ours)** is a Waymo-Sim-Agents-*style* likelihood score computed by this project, "
         "not the official challenge metric.\n",
         "![grid](grid.png)\n", "## Comparison against baselines\n"]
    rows = []
    for r in results:
        f = r["fidelity"]["per_feature"]
        g = r.get("cce_gap")
        rows.append([r["label"], r.get("kind", "baseline"), r["fidelity"]["realism_ours"],
                     np.nanmean([v["hellinger"] for v in f.values()]), np.nanmean([v["kl"] for v in f.values()]),
                     _pm(g["mean_gap"], g["ci95"]) if g else "-", r["diversity"]["mean"],
                     r["risk"].get("collision_rate"), r["risk"].get("near_miss_rate"),
                     r["risk"].get("mean_min_ttc_s"), r["risk"].get("mean_min_gap_m"),
                     r["risk"].get("hard_brakes_per_agent")])
    L.append(_table(["policy", "kind", "realism (ours)", "Hellinger (mean)", "KL (mean)", "CCE-gap ± 95% CI (agents)",
                     "diversity [m]", "collision rate", f"TTC < {rk.TTC_CRITICAL:g} s rate", "mean min TTC [s]",
                     "mean min gap [m]", "hard brakes / agent"], rows))
    L.append("\n### Who collides\n\nEach policy agent's first collision, by its partner (the nearest other car "
             "then: driven by the policy, or another one: a replayed log, which does not react) and by the contact in "
             "the agent's frame (hit from behind, ran into a car ahead, crossing / side / head-on); rates per policy "
             "agent-episode (`tg_gpudrive/evaluation/risk.py`).\n\n")
    keys = ["collision_rate", "collision_with_policy_rate", "collision_with_other_rate",
            *rk.CONTACT_KEYS]
    L.append(_table(["policy", "collision rate", "with a policy car", "with a non-policy car",
                     *(f"contact: {c}" for c in rk.CONTACTS)],
                    [[r["label"], *(r["risk"].get(k, "-") for k in keys)] for r in results]))
    L.extend(_flexibility_section(results, logged_hist))
    L.append("\n## Fidelity per feature (logged vs generated)\n\n![fidelity](fidelity.png)\n\n")
    rows = []
    for r in results:
        for name, v in r["fidelity"]["per_feature"].items():
            rows.append([r["label"], name, v["hellinger"], v["kl"], v["w1"], v["likelihood"],
                         v.get("mean_logged"), v.get("mean_generated")])
    L.append(_table(["policy", "feature", "Hellinger", "KL(log || gen)", "W1", "likelihood", "mean logged",
                     "mean generated"], rows))
    L.append("\n## Multipliers during training\n\n![multipliers](multipliers.png)\n")
    L.extend(_gap_sections(results, meta.get("cce_gap", True)))
    L.append("\n## Diversity per scenario type [m]\n\n")
    rows = [[r["label"], t, v] for r in results for t, v in r["diversity"]["per_type"].items()]
    L.append(_table(["policy", "scenario type", "mean pairwise displacement"], rows))
    worst = meta.get("worst_scenes") or {}
    if worst.get("scenes"):
        L.append(f"\n## Worst scenes of {worst['label']}\n\nThe scenes where its agents collided or left the road "
                 "most often (per agent-episode), each drawn as its episode ends.\n\n![worst scenes](worst_scenes.png)\n\n")
        L.append(_table(["scene", "agent-episodes", "collisions", "off-road", "failure rate"],
                        [[w["scene_id"], w["agent_episodes"], w["collisions"], w["offroad"], w["failure_rate"]]
                         for w in worst["scenes"]]))
    L.append("\n## Most safety-critical generated scenarios\n\n")
    rows = [[c["label"], c["scene_id"], c["seed"], c["collisions"], c["min_ttc_s"], c["min_gap_m"], c["hard_brakes"],
             c.get("file", "-")] for r in results if r.get("kind") for c in r["critical"]]
    L.append(_table(["run", "scene", "seed", "colliding agents", "min TTC [s]", "min gap [m]", "hard brakes",
                     "exported"], rows))
    (out / "report.md").write_text("\n".join(L))


# --------------------------------------------------------------------- main
@dataclasses.dataclass
class _Collected:
    """What a report gathers over its policies before it writes: per policy its results and recorded
    episodes, training curves, CCE-gaps and gap curves; the grid's frames; the logs of the first run's
    scenes; the first run's worst scenes; the best-response settings used."""

    results: list = dataclasses.field(default_factory=list)
    generated: dict = dataclasses.field(default_factory=dict)
    curves: dict = dataclasses.field(default_factory=dict)
    gaps: dict = dataclasses.field(default_factory=dict)
    gap_curves: dict = dataclasses.field(default_factory=dict)
    cells: dict = dataclasses.field(default_factory=dict)
    grid_scene: str = ""
    logged: object = None
    worst: dict | None = None
    br: dict = dataclasses.field(default_factory=dict)

    def keep(self, res: dict, gen) -> None:
        self.results.append(res)
        self.generated[res["label"]] = gen
        if res["cce_gap"]:
            self.gaps[res["label"]] = res["cce_gap"]


def report_main(runs: Sequence[str | Path], out: str | Path, options: ReportOptions | None = None) -> dict:
    """Evaluate the runs and the baselines, write the report files (FILES) into `out`; return the summary."""
    opts = options or ReportOptions()
    runs = [Path(r) for r in runs]
    if not runs:
        raise ValueError("report: give at least one run directory")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    threads = torch.get_num_threads()
    first = _run_files(runs[0])[0]
    discrete = first.env.discrete  # the behaviour-prior baseline needs it
    with_wm = discrete or bool(first.prior_model)  # a continuous run names its own (continuous) world model
    n_base = (2 + discrete + with_wm) if opts.baselines else 0
    bar = tqdm(total=len(runs) + n_base, desc="report", unit="policy", disable=not opts.progress)
    if not 0 <= opts.grid_scene < opts.scenes:
        raise ValueError(f"--grid-scene {opts.grid_scene}: the report evaluates scenes 0 .. {opts.scenes - 1}")
    got = _Collected()
    try:
        for i, run in enumerate(runs):
            _report_run(i, run, got, opts, out, bar, discrete, with_wm)
    finally:
        torch.set_num_threads(threads)
        bar.close()
    return _write_report(got, runs, first, opts, out)


def _report_run(i: int, run: Path, got: _Collected, opts: ReportOptions, out: Path, bar, discrete: bool,
                with_wm: bool) -> None:
    """Evaluate run `i` (and, with the first, the baselines) into `got`: its scenes, rollouts, CCE-gaps,
    worst scenes (the first run), grid frame and exported critical scenarios."""
    cfg, ckpt = _run_files(run)
    device = resolve_device(opts.device or cfg.device, flag="--device")
    if device == "cpu":
        torch.set_num_threads(1)  # per-step batches are tiny: a thread pool only adds overhead
    scenes = _scenes(cfg, opts.scenes, opts)
    sim, masks = trained_sim(cfg, scenes, device)  # the run's policy in worlds of them (agents)
    cfg = dataclasses.replace(cfg, env=sim.cfg)  # a slot for every agent
    logged = logged_episodes(sim)
    copies = _br_copies(opts, device)
    nb = len(scenes) if opts.br_scenes is None else max(1, min(opts.br_scenes, len(scenes)))
    got.br = {"copies": copies, "scenes": nb}
    gsim = ex.deviation_sim(scenes[:nb], masks[:nb], cfg.env, device, copies)
    label = run.name
    if i == 0:
        got.logged = logged
    if i == 0 and opts.baselines:  # baselines on the first run's scenes and engine, keyed by its checkpoint
        _baselines(got, opts, out, bar, cfg, ckpt, sim, gsim, scenes, masks, logged, discrete, with_wm)
    got.curves[label] = _read_metrics(run)
    kept = kept_policies(run) if run.is_dir() else []
    last_update = int(got.curves[label][-1]["update"]) if got.curves[label] else None

    def evaluate_run():  # called at once, in this iteration
        actor = load_actor(ckpt, gsim)[0]
        res, gen = _evaluate(label, sim, load_policy(ckpt, sim), logged, opts,
                             lambda s: ex.SimGame(gsim, actor=actor), bar, cfg.gamma)
        if kept:
            bar.set_postfix_str(f"{label}: CCE-gap of {len(kept)} kept policies")
        res["kept_gaps"] = kept_gaps(kept, gsim, opts, cfg.gamma, last_update) if opts.cce_gap else []
        return res, gen

    res, gen = _cached(out, label, [ckpt, *(p for _, p in kept)], opts, evaluate_run, bar)
    got.keep(res, gen)
    if i == 0:  # where the report's first policy fails most, drawn as its episodes end
        worst = worst_scenes(gen)
        frames = [_last_frame(cfg, scenes[w["scene"]], masks[w["scene"]], ckpt, device, opts.frame_size,
                              out / "frames" / f"worst_{k}.png") for k, w in enumerate(worst)]
        if frames:
            plot_worst_scenes(frames, worst, label, out / "worst_scenes.png")
        else:
            (out / "worst_scenes.png").unlink(missing_ok=True)
        got.worst = {"label": label, "scenes": worst}
    # the starting policy's gap is shared by the runs that fine-tuned it, so the process that does
    # the baselines does it (report parts: the first), and every run's curve reads it back
    start = start_gap(run, cfg, gsim, opts, out, bar) if run.is_dir() and opts.baselines and opts.cce_gap else None
    res["gap_curve"] = gap_curve(start, res.get("kept_gaps", []), res["cce_gap"], last_update)
    if res["gap_curve"]:
        got.gap_curves[label] = res["gap_curve"]
    res["kind"] = run_kind(cfg)
    res["beta"], res["alpha"] = cfg.env.beta, cfg.alpha
    res["train_tail"] = _tail_means(got.curves[label], ("lambda", "mean_min_distance", "mean_speed", "cost"))
    if res["kind"] == "CCE-MAPPO":
        g = opts.grid_scene
        got.cells[(cfg.env.beta, cfg.alpha)] = _last_frame(cfg, scenes[g], masks[g], ckpt, device, opts.frame_size,
                                                           out / "frames" / f"{label}.png", gif=opts.grid_gifs)
        got.grid_scene = scenes[g].scene_id
    # the most critical scenarios, as GPUDrive JSON with their risk figures
    crit = res["critical"]
    files = export_episodes(gen, [c["episode"] for c in crit], out / "scenarios" / label, crit)
    for c, f in zip(crit, files):
        c["file"] = str(f.relative_to(out))


def _baselines(got: _Collected, opts: ReportOptions, out: Path, bar, cfg, ckpt, sim, gsim, scenes, masks, logged,
               discrete: bool, with_wm: bool) -> None:
    """The log replay, the expert, the behaviour prior (discrete) and the world model alone, in the first
    run's worlds; cached under its checkpoint. Their best responses discount with that run's gamma."""

    def replay():
        bar.set_postfix_str("log replay")
        replayed = replay_episodes(scenes, masks, cfg.env, sim.device)
        bar.update(1)
        return _measure("log replay", replayed, logged, opts), replayed

    def baseline(name, make):
        return _cached(out, name, [ckpt], opts, lambda: _evaluate(
            name, sim, make(sim), logged, opts, lambda s: ex.SimGame(gsim, make(gsim)), bar, cfg.gamma), bar)

    got.keep(*_cached(out, "log replay", [ckpt], opts, replay, bar))
    got.keep(*baseline("expert (inverse dynamics)", lambda s: expert_policy))
    if discrete:
        got.keep(*baseline("behaviour prior", prior_policy))
    if with_wm:
        got.keep(*baseline("world model", lambda s: world_model_policy(cfg, s)))


def _write_report(got: _Collected, runs: list[Path], first: TrainConfig, opts: ReportOptions, out: Path) -> dict:
    """The pictures, report.md and summary.json of what `got` gathered; returns the summary."""
    plot_grid(got.cells, out / "grid.png", scene=got.grid_scene)
    plot_multipliers(got.curves, out / "multipliers.png")
    fid.plot_histograms(got.logged, got.generated, out / "fidelity.png")
    # the CCE-gap pictures this pass has, and no earlier report's beside this one's text
    for name, plot, data in (("cce_gap.png", plot_gaps, got.gaps if opts.cce_gap else None),
                             ("cce_gap_curve.png", plot_gap_curves, got.gap_curves or None)):
        if data is None:
            (out / name).unlink(missing_ok=True)
        else:
            plot(data, out / name)
    meta = {"runs": [str(r) for r in runs], "scenes": opts.scenes, "seeds": list(opts.seeds),
            "eval_scenes": eval_scenes_text(first, opts), "cce_gap": opts.cce_gap, "worst_scenes": got.worst,
            "br_seeds": list(opts.br_seeds),
            "best_response": {"max_iters": opts.br_iters, "tol": opts.br_tol, "window": opts.br_window,
                              "patience": opts.br_patience, "min_iters": opts.br_min_iters,
                              "copies": got.br["copies"], "scenes": got.br["scenes"], "lr": opts.br_lr,
                              "eval_rounds": opts.br_rounds,
                              "gamma": "the run's" if opts.br_gamma is None else opts.br_gamma}}
    write_markdown(out, got.results, meta, fid.histograms(got.logged) if got.logged is not None else None)
    summary = {"meta": meta, "results": [{k: v for k, v in r.items() if k != "figures"} for r in got.results]}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=_json_default))
    return summary


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(type(o))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tg-gpudrive report", description=__doc__, formatter_class=HelpFormatter)
    d = ReportOptions()
    p.add_argument("--runs", nargs="+", required=True,
                   help="training run directories (or checkpoint files; shipped: the packaged policy) (required)")
    p.add_argument("--out", default="report", help="output directory")
    p.add_argument("--scenes", type=int, default=d.scenes, help="evaluation scenes (worlds) per run")
    p.add_argument("--scene-seed", type=int, default=d.scene_seed,
                   help="first procedural seed of the evaluation scenes: held out when the runs never trained on it "
                        "(an overlap with a run's training seeds is an error); -1: the runs' own training scenes")
    p.add_argument("--eval-scenes", default=None, metavar="SPEC",
                   help="scene spec of the evaluation scenes (default: each run's own; file and store specs have "
                        "no seed, so name held-out files here)")
    p.add_argument("--no-cce-gap", action="store_true",
                   help="skip the CCE-gaps (the PPO best responses that take most of a report's time)")
    p.add_argument("--seeds", type=int, nargs="+", default=list(d.seeds), metavar="SEED",
                   help=f"rollout seeds; diversity needs at least two (default: {' '.join(map(str, d.seeds))})")
    p.add_argument("--br-iters", type=int, default=d.br_iters,
                   help="CCE-gap: cap on the PPO iterations of each best response (it stops earlier at a plateau)")
    p.add_argument("--br-seeds", type=int, nargs="+", default=list(d.br_seeds), metavar="SEED",
                   help=f"seeds of the best-response training (default: {' '.join(map(str, d.br_seeds))})")
    p.add_argument("--br-lr", type=float, default=d.br_lr, help="learning rate of the best response (actor)")
    p.add_argument("--br-tol", type=float, default=d.br_tol,
                   help="plateau tolerance: a best response stops when its moving-mean discounted return has not "
                        "beaten its best by tol * max(1, |best|) for --br-patience iterations")
    p.add_argument("--br-window", type=int, default=d.br_window, help="iterations per moving mean of the plateau rule")
    p.add_argument("--br-patience", type=int, default=d.br_patience,
                   help="iterations without a new best moving mean before a best response stops")
    p.add_argument("--br-min-iters", type=int, default=d.br_min_iters,
                   help="PPO iterations a best response always runs before the plateau rule may stop it")
    p.add_argument("--br-copies", type=int, default=d.br_copies,
                   help="episodes per agent and PPO iteration (each agent deviates in this many worlds; "
                        "default: 16 on a GPU, 4 on the CPU)")
    p.add_argument("--br-scenes", type=int, default=d.br_scenes,
                   help="CCE-gap: the first N evaluation scenes play the deviation game (default: all; a multiple "
                        "of the scenario types keeps them balanced)")
    p.add_argument("--br-rounds", type=int, default=d.br_rounds,
                   help="fresh evaluation batches of J(pi) and of J(BR) each")
    p.add_argument("--br-gamma", type=float, default=None,
                   help="discount of the best response's returns (default: the run's gamma)")
    p.add_argument("--top", type=int, default=d.top, help="critical scenarios exported per run")
    p.add_argument("--device", default="auto",
                   help="auto (default: cuda when Warp and torch see one, else cpu), cpu, cuda or cuda:N")
    p.add_argument("--grid-scene", type=int, default=d.grid_scene,
                   help="evaluation scene (0 .. --scenes - 1) that grid.png shows in every beta x alpha cell")
    p.add_argument("--grid-gifs", action="store_true",
                   help="also write frames/<run>.gif, the whole episode of that scene, per cell (default: off)")
    p.add_argument("--no-baselines", action="store_true",
                   help="leave out log replay, expert, behaviour prior and world model, and the CCE-gap of the "
                        "policy runs started from (a process that fills the cache for some of the runs, beside "
                        "one that does these shared parts)")
    return p


def main(argv: list[str] | None = None) -> int:
    """`tg-gpudrive report --runs DIR [DIR ...] --out DIR`; returns the exit status."""
    args = build_parser().parse_args(argv)
    opts = ReportOptions(scenes=args.scenes, scene_seed=None if args.scene_seed == -1 else args.scene_seed,
                         eval_scenes=args.eval_scenes, cce_gap=not args.no_cce_gap,
                         seeds=tuple(args.seeds), br_iters=args.br_iters,
                         br_seeds=tuple(args.br_seeds), br_lr=args.br_lr, br_tol=args.br_tol, br_window=args.br_window,
                         br_patience=args.br_patience, br_min_iters=args.br_min_iters, br_copies=args.br_copies,
                         br_scenes=args.br_scenes, br_rounds=args.br_rounds,
                         br_gamma=args.br_gamma, top=args.top, device=args.device,
                         grid_scene=args.grid_scene, grid_gifs=args.grid_gifs, baselines=not args.no_baselines)
    if opts.cce_gap:  # the slow part: say so before it starts, and how to skip it
        print(f"tg-gpudrive report: the CCE-gap trains a PPO best response for every agent of each policy "
              f"({len(opts.br_seeds)} seed(s), up to {opts.br_iters} iterations each): minutes per policy on a GPU, "
              f"about 20 minutes for one small run on a 2-core CPU; --no-cce-gap leaves it out", file=sys.stderr)
    try:
        report_main(args.runs, args.out, opts)
    except (ValueError, FileNotFoundError) as e:
        print(f"tg-gpudrive report: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {Path(args.out) / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
