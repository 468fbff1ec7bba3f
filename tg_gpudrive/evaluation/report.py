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

    report.md           the findings, one row per policy (or cell, feature, training point): comparison
                        against baselines, fidelity per feature, CCE-gap per scenario type (PPO best
                        responses trained to a plateau on the first --br-scenes evaluation scenes,
                        exploitability.py; --br-* flags), diversity per scenario type, each run's most
                        critical scenario; it names the two CSV files below and holds none of their rows
    per_agent.csv       the CCE-gap of every agent of every policy (report_markdown.PER_AGENT_COLUMNS)
    per_scene.csv       every exported critical scenario of every run (report_markdown.PER_SCENE_COLUMNS)
    grid.png            the paper's beta x alpha figure: one scene per CCE-MAPPO cell, beta down the rows,
                        alpha across, whole trajectories drawn beside every cell at one shared moment zoomed
                        in (grid_moment); the scene is --grid-scene, or by default
                        the one where the knob moves the distance the cells' agents keep most
                        (report_stats.knob_scene)
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

This module runs the policies and caches what they did; the numbers come from report_stats.py, the
pictures from report_figures.py, report.md and the CSV files from report_markdown.py, and the
command line (`tg-gpudrive report`) from tg_gpudrive.cli.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import pickle
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from tqdm import tqdm

from tg_gpudrive.agents import trained_sim
from tg_gpudrive.checkpoint import checkpoint_path, kept_policies, load_checkpoint
from tg_gpudrive.config import TrainConfig, from_dict
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.engine.simulator import Simulator, resolve_device
from tg_gpudrive.evaluation import exploitability as ex
from tg_gpudrive.evaluation import fidelity as fid
from tg_gpudrive.evaluation import risk as rk
from tg_gpudrive.evaluation.export import export_episodes
from tg_gpudrive.evaluation.episodes import logged_episodes, record_episodes, record_rollouts, replay_episodes
from tg_gpudrive.evaluation.report_figures import (plot_gap_curves, plot_gaps, plot_grid, plot_multipliers,
                                                   plot_worst_scenes)
from tg_gpudrive.evaluation.report_markdown import PER_AGENT_CSV, PER_SCENE_CSV, write_csv_tables, write_markdown
from tg_gpudrive.evaluation.report_stats import (cell_label, episode_figures, gap_curve, knob_scene, measure,
                                                 scene_distances, tail_means, worst_scenes)
from tg_gpudrive.agents.prior import ExpertPrior
from tg_gpudrive.learn import bar_watch
from tg_gpudrive.agents.policy import load_actor, load_policy
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.worldmodel.prior import WorldModelDriver, load_world_model

FILES = ("report.md", PER_AGENT_CSV, PER_SCENE_CSV, "grid.png", "multipliers.png", "fidelity.png", "cce_gap.png",
         "worst_scenes.png", "summary.json")


@dataclasses.dataclass
class ReportOptions:
    """What a report evaluates and how: its scenes and rollout seeds, the best responses of the CCE-gap,
    the exported scenarios, the device, the pictures and which shared parts (baselines) this process does."""

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
    br_iters: int = 200  # cap on the PPO iterations of one best response
    br_seeds: tuple[int, ...] = (0, 1)
    br_lr: float = 3e-3
    br_rounds: int = 2  # fresh evaluation batches of J_pi and of J_br
    br_tol: float = 0.01  # plateau: no new best moving mean by tol * max(1, |best|) ...
    br_window: int = 5  # ... of this many iterations ...
    br_patience: int = 10  # ... for this many iterations ...
    br_min_iters: int = 100  # ... and never before this many
    br_copies: int | None = None  # episodes per agent and PPO iteration; None: 16 on a GPU, 4 on the CPU
    # the first br_scenes evaluation scenes play the deviation game (None: all of them); scene sources
    # cycle over the scenario types, so a multiple of their number keeps the types balanced
    br_scenes: int | None = None
    br_gamma: float | None = None  # discount of the returns; None: the run's gamma (baselines: the first run's)
    top: int = 3  # critical scenarios exported per run
    device: str | None = "auto"  # auto (cuda when one is visible, else cpu) | cpu | cuda:N; None: the run's config
    frame_size: int = 320
    # which evaluation scene (0 .. scenes-1) the beta x alpha figure shows; None: the scene where the knob
    # moves the distance kept most (report_stats.knob_scene), so that the rows differ where they can
    grid_scene: int | None = None
    grid_gifs: bool = False  # also write frames/<run>.gif, the whole episode of that scene, per cell
    progress: bool = True  # a tqdm bar over the policies evaluated (stderr)
    # log replay, expert, behaviour prior and world model on the first run's scenes, and the CCE-gap of
    # the policy the runs started from (init_policy): what report parts share
    baselines: bool = True


# ------------------------------------------------------------------ helpers
def run_config(run: Path) -> TrainConfig:
    """The TrainConfig of a run directory (its config.json)."""
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
        return run_config(run), ckpt
    ckpt = checkpoint_path(str(run), "--runs")
    return from_dict(TrainConfig, load_checkpoint(ckpt, "--runs")["config"], str(ckpt)), ckpt


def run_kind(cfg) -> str:
    """MAPPO when the config switches the magnet, the proximal term and the constraint off, else CCE-MAPPO."""
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


def _frame_sim(cfg, scene, mask, device) -> Simulator:
    """One world of `scene` with the run's controlled agents `mask` and without auto-reset (the final state stays
    to be drawn): what the report's pictures of one episode drive."""
    return Simulator([scene], dataclasses.replace(cfg.env, auto_reset=False), device, controlled=[mask])


def _last_frame(sim, ckpt, size: int, path: Path, gif: bool = False, zoom=None) -> np.ndarray:
    """Last frame of world 0's episode (`_frame_sim`) under the run's policy, with every agent's whole trajectory,
    saved to `path`, and to its right a zoom on one moment of the same episode, saved as *_closest.png:
    `zoom(sim, make_policy, zoom_path, kw)` draws it (the grid's shared moment, `_moment_frame`), by default
    `_closest_frame` (the episode's own closest approach). The two side by side are returned. With `gif` also
    the whole episode (`path` with .gif)."""
    # drawing needs the render extra (matplotlib, Pillow): imported when a report draws, so that the
    # report's parser and its numbers do not need it
    from PIL import Image

    from tg_gpudrive.render import render_episode

    path.parent.mkdir(parents=True, exist_ok=True)
    # the view fits the controlled cars' paths: the interaction the knobs change, not the whole map; the
    # same seed makes the GIF the picture's episode; a dot on each trail every second shows the cells'
    # timing and spacing, which whole trajectories of the same routes alone do not
    kw = dict(world=0, size=(size, size), legend=False, fit="controlled", seed=0,
              trail_ticks=max(1, round(1.0 / sim.model.scenes[0].dt)))
    render_episode(sim, load_policy(ckpt, sim), out=path, **kw)
    if gif:
        render_episode(sim, load_policy(ckpt, sim), out=path.with_suffix(".gif"), **kw)
    whole = np.asarray(Image.open(path).convert("RGB"))
    near = (zoom or _closest_frame)(sim, lambda: load_policy(ckpt, sim), path.with_name(path.stem + "_closest.png"),
                                    kw)
    return whole if near is None else np.concatenate([whole, near[:whole.shape[0], :, :3]], axis=1)


def _closest_frame(sim, make_policy, path: Path, kw: dict, margin: float = 8.0) -> np.ndarray | None:
    """The moment of world 0's episode (kw's seed: the same episode as kw's other pictures) when a policy car came
    nearest another (risk.closest_moment over its recording), drawn centred on that car with half-side the
    distance plus `margin` m (at least 10) and saved to `path`: the zoom of a picture drawn alone (the worst
    scenes; the grid's cells where its shared moment finds none). None when no car ever had company."""
    from tg_gpudrive.render import render_episode

    moment = rk.closest_moment(record_episodes(sim, make_policy(), seed=kw["seed"]))
    if moment is None:
        return None
    k, a, _, dist = moment
    title = f"closest approach: centres {dist:.1f} m apart at {k * sim.model.scenes[0].dt:.1f} s"
    return render_episode(sim, make_policy(), steps=k, out=path, **dict(kw, center_agent=a, title=title,
                                                                         view_radius=max(10.0, dist + margin)))[-1]


@dataclasses.dataclass
class GridMoment:
    """The one moment every grid cell's zoom draws (`grid_moment`), so that the cells differ by what their
    policies did and not by which moment each picked: step `step` of world 0's episode, centred on policy agent
    `agent`, half-side `radius` m. `cell` is the cell it was chosen in, `centre` the agent's place there then
    (the view's centre in a cell whose episode no longer has the agent), `gaps` each cell's `risk.lane_gap` of
    the agent then and `present` whether its episode still has the agent then."""

    step: int
    agent: int
    cell: tuple[float, float]
    centre: tuple[float, float]
    radius: float
    gaps: dict
    present: dict


def grid_moment(episodes: dict, margin: float = 8.0, reach: float = 2.0) -> GridMoment | None:
    """The grid's shared zoom from each cell's recorded episode ({(beta, alpha): Trajectories}, world 0 as its
    pictures draw it): `risk.lane_approach_moment` in the most pressing cell (the least beta, then the least
    alpha), at a step where the car is present in every cell if there is one, with the half-side every cell's
    distance there fits in (the largest plus `margin` m, at least 10), but for distances beyond `reach` times
    the most pressing cell's: those cars are left out of view (their titles say how far) rather than shrink
    every cell's cars to the scale of the whole paths.
    None when that cell has no such approach (each cell then zooms on its own closest approach)."""
    if not episodes:
        return None
    ref = min(episodes)
    # a moment when the car is on the road in every cell, so no cell's zoom shows it gone (e.g. at its goal a
    # step sooner); any moment of the reference cell where there is none
    valid = [tr.valid[0] for tr in episodes.values()]
    everywhere = np.logical_and.reduce(valid) if len({v.shape for v in valid}) == 1 else None
    found = rk.lane_approach_moment(episodes[ref], allowed=everywhere) or rk.lane_approach_moment(episodes[ref])
    if found is None:
        return None
    k, a, _, dist = found
    gaps = {cell: rk.lane_gap(tr, 0, a, k) for cell, tr in episodes.items()}
    radius = max([10.0] + [min(g[1], reach * dist) + margin for g in gaps.values() if g is not None])
    centre = tuple(float(v) for v in episodes[ref].pos[0, a, k])
    present = {cell: bool(tr.valid[0, a, k]) for cell, tr in episodes.items()}
    return GridMoment(k, a, ref, centre, radius, gaps, present)


def _moment_frame(moment: GridMoment, cell):
    """The zoom of `_last_frame` for one grid cell: its episode at the shared moment, centred on the shared agent
    (on the agent's place in the reference cell when this episode no longer has it), titled with this cell's own
    distance from the agent to its nearest car ahead or behind in its lane then."""
    from tg_gpudrive.render import render_episode

    def draw(sim, make_policy, path: Path, kw: dict) -> np.ndarray:
        t = f"{moment.step * sim.model.scenes[0].dt:.1f} s"
        gap = moment.gaps.get(cell)
        if not moment.present.get(cell):
            title, view = f"{t}: car {moment.agent} has left the scene", dict(center_point=moment.centre)
        elif gap is None:
            title, view = f"{t}: no car ahead or behind in its lane", dict(center_agent=moment.agent)
        else:
            title = f"{t}: {gap[1]:.1f} m to the car {'ahead' if gap[2] else 'behind'} in its lane"
            view = dict(center_agent=moment.agent)
        return render_episode(sim, make_policy(), steps=moment.step, out=path,
                              **dict(kw, title=title, view_radius=moment.radius, **view))[-1]

    return draw


def _grid_frames(got: _Collected, opts: ReportOptions, out: Path) -> None:
    """Each cell's picture for grid.png, of one scene: --grid-scene, or the one where the knob moves the
    distance kept most (knob_scene over the cells' recorded episodes; scene 0 when it finds none), and its
    note: the same episodes' mean least distance on that scene. Each cell's zoom draws its episode at one shared
    moment (`grid_moment`), which `got.grid_zoom` describes; each its own closest approach where there is none."""
    if not got.cell_runs:
        return
    dists = {cell: scene_distances(got.generated[run[-1]]) for cell, run in got.cell_runs.items()}
    pick = None if opts.grid_scene is not None else knob_scene(dists)
    sims, episodes = {}, {}
    for cell, (cfg, scenes, masks, ckpt, device, label) in got.cell_runs.items():
        g = opts.grid_scene
        if g is None:
            g = next((k for k, s in enumerate(scenes) if pick and s.scene_id == pick[0]), 0)
        sims[cell] = _frame_sim(cfg, scenes[g], masks[g], device)
        # the pictures' episode (their seed, world 0): where the shared moment is found and measured
        episodes[cell] = record_episodes(sims[cell], load_policy(ckpt, sims[cell]), seed=0)
        got.grid_scene = scenes[g].scene_id
        here = dists[cell].get(got.grid_scene)
        if here is not None:
            got.grid_notes[cell] = f"mean least distance here {here:.1f} m"
    moment = grid_moment(episodes)
    for cell, (_, _, _, ckpt, _, label) in got.cell_runs.items():
        got.cells[cell] = _last_frame(sims[cell], ckpt, opts.frame_size, out / "frames" / f"{label}.png",
                                      gif=opts.grid_gifs, zoom=None if moment is None else _moment_frame(moment, cell))
    got.grid_zoom = _zoom_text(moment, episodes[moment.cell].dt if moment else 0.0)
    if pick:
        got.grid_scene += f" (where the knob moves the distance kept most: {pick[1]:+.2f} m)"


def _zoom_text(moment: GridMoment | None, dt: float) -> str:
    """What the grid's right-hand zooms show (`dt`: the episodes' step in s), for its title and report.md."""
    if moment is None:
        return "each cell's own closest approach zoomed in (no car came near another in its lane)"
    b, a = moment.cell
    t = moment.step * dt
    return (f"every cell at {t:.1f} s, zoomed in on car {moment.agent}, where at beta {b:g}, alpha {a:g} it came "
            "nearest a car ahead or behind in its lane")


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


def _evaluate(label, sim, policy, logged, opts, gap_game, bar, gamma: float) -> tuple[dict, object]:
    """Rollouts, fidelity, diversity and risk of one policy, then its CCE-gap (PPO best responses,
    discount `gamma` unless --br-gamma); advances `bar` by one."""
    bar.set_postfix_str(f"{label}: rollouts")
    gen = record_rollouts(sim, policy, opts.seeds, label=label)
    res = measure(label, gen, logged, opts.top)
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
    """The rows of a run's metrics.csv (one per training update); none for a checkpoint file."""
    path = run / "metrics.csv"
    return list(csv.DictReader(path.open())) if path.exists() else []


def run_multipliers(ckpt: Path) -> torch.Tensor:
    """The Lagrange multipliers a CCE-MAPPO run ended with: one per controlled slot (or one for all). A
    run with one per vehicle of its training scenes (`lambda_per_vehicle`) gives each slot the mean of
    its vehicles' nonzero multipliers: the deviation game's scenes are other scenes."""
    ck = load_checkpoint(ckpt, "report")
    lam = torch.as_tensor(ck["lagrange"]["lam"], dtype=torch.float32).cpu()
    if lam.dim() == 2:
        lam = lam.sum(0) / (lam > 0).sum(0).clamp(min=1)
    return lam


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
    cell_runs: dict = dataclasses.field(default_factory=dict)
    grid_scene: str = ""
    grid_zoom: str = ""
    grid_notes: dict = dataclasses.field(default_factory=dict)
    logged: object = None
    worst: dict | None = None
    br: dict = dataclasses.field(default_factory=dict)

    def keep(self, res: dict, gen) -> None:
        """Add one policy's result and recorded episodes (and its CCE-gap, if measured)."""
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
    seen: dict[str, Path] = {}
    for run in runs:  # a run's label is its folder's name: the tables, the cache and the cells key on it
        if run.name in seen:
            raise ValueError(f"report: runs {seen[run.name]} and {run} share the name {run.name!r}, which labels a "
                             "run in the report; report them separately or rename one")
        seen[run.name] = run
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    threads = torch.get_num_threads()
    first = _run_files(runs[0])[0]
    discrete = first.env.discrete  # the behaviour-prior baseline needs it
    with_wm = discrete or bool(first.prior_model)  # a continuous run names its own (continuous) world model
    n_base = (2 + discrete + with_wm) if opts.baselines else 0
    bar = tqdm(total=len(runs) + n_base, desc="report", unit="policy", disable=not opts.progress)
    if opts.grid_scene is not None and not 0 <= opts.grid_scene < opts.scenes:
        raise ValueError(f"--grid-scene {opts.grid_scene}: the report evaluates scenes 0 .. {opts.scenes - 1}")
    got = _Collected()
    try:
        for i, run in enumerate(runs):
            _report_run(i, run, got, opts, out, bar, discrete, with_wm)
        _grid_frames(got, opts, out)
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
        if opts.cce_gap and run_kind(cfg) == "CCE-MAPPO":  # the game its agents were trained to play too
            lam = run_multipliers(ckpt)
            res["cce_gap_constrained"] = ex.cce_gap(lambda s: ex.SimGame(gsim, actor=actor, cost_weight=lam),
                                                    seeds=opts.br_seeds, config=br_config(opts, cfg.gamma))
        if kept:
            bar.set_postfix_str(f"{label}: CCE-gap of {len(kept)} kept policies")
        res["kept_gaps"] = kept_gaps(kept, gsim, opts, cfg.gamma, last_update) if opts.cce_gap else []
        return res, gen

    res, gen = _cached(out, label, [ckpt, *(p for _, p in kept)], opts, evaluate_run, bar)
    if not {"episode_key", "min_gap_ahead", "scenario_type"} <= res["figures"].keys():  # cached before: from rollouts
        res["figures"].update(episode_figures(gen, rk.episode_risk(gen)))
    got.keep(res, gen)
    if i == 0:  # where the report's first policy fails most, drawn as its episodes end
        worst = worst_scenes(gen)
        frames = [_last_frame(_frame_sim(cfg, scenes[w["scene"]], masks[w["scene"]], device), ckpt, opts.frame_size,
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
    # how its rollouts acted (policy.load_policy takes the checkpoint's own): runs fine-tuned from a sharper or
    # guarded policy may act otherwise than the policy they are compared with
    res["acting"] = f"T {cfg.act_temperature:g}" + (f", guard {cfg.act_guard_s:g} s" if cfg.act_guard_s else "")
    res["beta"], res["alpha"], res["seed"] = cfg.env.beta, cfg.alpha, cfg.seed
    res["train_tail"] = tail_means(got.curves[label], ("lambda", "mean_min_distance", "mean_speed", "cost", "cvar",
                                                       "constraint", "cost_budget"))
    res["constraint"] = constraint_rule(cfg)
    res["bar_out_of_reach"] = bar_watch.replay(cfg, got.curves[label])  # the update the trainer warned at, or None
    if res["kind"] == "CCE-MAPPO" and (cfg.env.beta, cfg.alpha) not in got.cell_runs:  # a cell's first training seed
        got.cell_runs[(cfg.env.beta, cfg.alpha)] = (cfg, scenes, masks, ckpt, device, label)
    # the most critical scenarios, as GPUDrive JSON with their risk figures
    crit = res["critical"]
    files = export_episodes(gen, [c["episode"] for c in crit], out / "scenarios" / label, crit)
    for c, f in zip(crit, files):
        c["file"] = str(f.relative_to(out))


def constraint_rule(cfg: TrainConfig) -> str:
    """What a run's multipliers were stepped on and against which budget, in words."""
    if not cfg.constraint:
        return "no constraint"
    if cfg.lambda_on.startswith("sampled"):
        level, value = "mean", "the sampled cost rate / (1 - gamma)"
        if cfg.lambda_on == "sampled_cvar":
            value = f"CVaR {cfg.alpha:g} over the vehicles of their sampled cost rate / (1 - gamma)"
    else:
        level = f"CVaR {cfg.alpha:g}" if cfg.lambda_on == "cvar" else "mean"
        value = (level if cfg.lambda_on == "cvar" else "the mean") + " of the cost-to-go"
    if cfg.cost_limit_mode == "absolute":
        return f"{value} against {cfg.cost_limit:g}"
    bar = {"logs": f"the logs' {level}", "start": "the starting policy's mean"}[cfg.cost_limit_mode]
    under = f" at beta {cfg.cost_limit_beta:g}" if cfg.cost_limit_beta else ""
    return f"{value} against {cfg.cost_limit:g} x {bar}{under}"


def _baselines(got: _Collected, opts: ReportOptions, out: Path, bar, cfg, ckpt, sim, gsim, scenes, masks, logged,
               discrete: bool, with_wm: bool) -> None:
    """The log replay, the expert, the behaviour prior (discrete) and the world model alone, in the first
    run's worlds; cached under its checkpoint. Their best responses discount with that run's gamma."""

    def replay():
        bar.set_postfix_str("log replay")
        replayed = replay_episodes(scenes, masks, cfg.env, sim.device)
        bar.update(1)
        return measure("log replay", replayed, logged, opts.top), replayed

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
    """The pictures, report.md, its CSV tables and summary.json of what `got` gathered; returns the summary."""
    plot_grid(got.cells, out / "grid.png", scene=got.grid_scene, notes=got.grid_notes, zoom=got.grid_zoom)
    cells = {r["label"]: cell_label(r["beta"], r["alpha"]) for r in got.results if r.get("kind") == "CCE-MAPPO"}
    plot_multipliers(got.curves, out / "multipliers.png", cells)
    fid.plot_histograms(got.logged, got.generated, out / "fidelity.png")
    # the CCE-gap pictures this pass has, and no earlier report's beside this one's text
    for name, plot, data in (("cce_gap.png", plot_gaps, got.gaps if opts.cce_gap else None),
                             ("cce_gap_curve.png", plot_gap_curves, got.gap_curves or None)):
        if data is None:
            (out / name).unlink(missing_ok=True)
        else:
            plot(data, out / name)
    meta = _meta(got, runs, first, opts)
    write_markdown(out, got.results, meta, fid.histograms(got.logged) if got.logged is not None else None)
    write_csv_tables(out, got.results)
    summary = {"meta": meta, "results": [{k: v for k, v in r.items() if k != "figures"} for r in got.results]}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=_json_default))
    return summary


def _meta(got: _Collected, runs: list[Path], first: TrainConfig, opts: ReportOptions) -> dict:
    """The settings a report ran with (summary.json's "meta", report.md's opening)."""
    return {"runs": [str(r) for r in runs], "scenes": opts.scenes, "seeds": list(opts.seeds),
            "eval_scenes": eval_scenes_text(first, opts), "cce_gap": opts.cce_gap, "worst_scenes": got.worst,
            "grid_scene": got.grid_scene, "grid_zoom": got.grid_zoom,
            "br_seeds": list(opts.br_seeds),
            "best_response": {"max_iters": opts.br_iters, "tol": opts.br_tol, "window": opts.br_window,
                              "patience": opts.br_patience, "min_iters": opts.br_min_iters,
                              "copies": got.br["copies"], "scenes": got.br["scenes"], "lr": opts.br_lr,
                              "eval_rounds": opts.br_rounds,
                              "gamma": "the run's" if opts.br_gamma is None else opts.br_gamma}}


def _json_default(o):
    """numpy arrays and scalars as JSON lists and numbers (summary.json)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(type(o))
