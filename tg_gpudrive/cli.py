"""`tg-gpudrive`: the one command-line entry.

    tg-gpudrive simulate  --scenes procedural:all --worlds 64 --policy expert
    tg-gpudrive simulate  --control nearest_conflict --control-k 2 --background world_model
    tg-gpudrive benchmark --device cuda --json
    tg-gpudrive convert   womd_dir/ --out store/
    tg-gpudrive train     --config configs/train/small_cpu.yaml
    tg-gpudrive evaluate  --checkpoint runs/small_cpu --collision-mode stop
    tg-gpudrive render    --scenes procedural:merge --policy expert --out episode.gif
    tg-gpudrive report    --runs runs/grid/* --out report/

The engine config: simulate, benchmark, evaluate and render take `--env-config`
(default configs/env/default.yaml) plus `--set key=value` overrides (evaluate
and render with a checkpoint policy: the engine it was trained in, plus
--collision-mode); train and train-world-model take their own `--config` YAML
(the engine config is its `env:` section) plus `--set`; report and convert take
neither. The device is `--device auto` unless given (train, train-world-model:
the config's `device`, also auto by default): cuda when Warp and torch see one,
else cpu; JSON reports name the device that ran, and asking for CUDA where
there is none exits 2 in one line. `tg-gpudrive COMMAND --help` shows every
option of a command with its default.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import json
import logging
import os
import sys
import time
from pathlib import Path

import torch.multiprocessing as mp

from tg_gpudrive.benchmark import main as benchmark_main
from tg_gpudrive.checkpoint import check_resume_config
from tg_gpudrive.cli_help import HelpFormatter
from tg_gpudrive.config import (
    BACKGROUNDS,
    REPO_CONFIGS,
    ConfigError,
    EngineConfig,
    TrainConfig,
    apply_overrides,
    from_dict,
    load_config,
    load_yaml,
)
from tg_gpudrive.data.sampler import SceneSampler
from tg_gpudrive.data.sources import resolve_scenes, source_report
from tg_gpudrive.data.store import convert
from tg_gpudrive.engine.simulator import resolve_device
from tg_gpudrive.scene import scene_defaults
from tg_gpudrive.evaluation import report as report_module
from tg_gpudrive.evaluation.report import ReportOptions, report_main
from tg_gpudrive.learn import distributed
from tg_gpudrive.agents import BUILTIN, open_policy
from tg_gpudrive.learn.rundir import RunLock, claim_run_dir
from tg_gpudrive.learn.train import train_main
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.rollout import run_rollout
from tg_gpudrive.enums import CollisionMode, ControlMode
from tg_gpudrive.worldmodel.cli import add_arguments as world_model_args
from tg_gpudrive.worldmodel.cli import run as run_world_model

log = logging.getLogger("tg_gpudrive")

COLLISION_MODES = [str(m) for m in CollisionMode]  # ignore, stop, remove
CONTROL_CHOICES = [str(ControlMode.VEHICLES), str(ControlMode.NEAREST_CONFLICT)]  # the --control selections


def _engine_args(p: argparse.ArgumentParser) -> None:
    default = REPO_CONFIGS / "env" / "default.yaml"
    p.add_argument("--env-config", default=str(default) if default.exists() else None,
                   help="engine YAML (default: configs/env/default.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override an engine config key, e.g. --set beta=3 --set reward.collision=-2 "
                        "(repeatable; default: none)")
    p.add_argument("--device", default="auto",
                   help="auto (default: cuda when Warp and torch see one, else cpu), cpu, cuda or cuda:N")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the scene draw (procedural scenes, sampling), the random policy and the "
                        "world-model background")


def _scene_args(p: argparse.ArgumentParser, default: str = "procedural:all",
                num_scenes_default: str = "min(worlds, source size)") -> None:
    p.add_argument("--scenes", default=default,
                   help="procedural:<type> | procedural:all, either with generator knobs such as "
                        "procedural:all[parking=0.8,stop_lines=0.5,kerb_stops=0.5] | a store, .json/.tfrecord "
                        "file or directory | mix:<spec>=<weight>,...")
    p.add_argument("--num-scenes", type=positive_int, default=None,
                   help=f"distinct scenes to draw from the source (default: {num_scenes_default})")


def _background_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--control", choices=CONTROL_CHOICES, default=None,
                   help="who the policy drives: every eligible vehicle (default: the engine config's `control`) "
                        "or the --control-k vehicles nearest the scene's conflict point")
    p.add_argument("--control-k", type=int, default=5, help="nearest_conflict: how many (default 5)")
    p.add_argument("--background", choices=list(BACKGROUNDS), default="log",
                   help="who drives the other eligible vehicles: log replay (default), the world model, or idm "
                        "(each on its logged path and timing, braking for whoever is on that path); the last two "
                        "react to the policy's vehicles")
    p.add_argument("--background-model", default=None, metavar="PATH",
                   help="--background world_model: a world-model checkpoint (model.pt or a train-world-model "
                        "run directory, or small_cpu: the packaged CPU model; default: the shipped model of the "
                        "action space, shipped or shipped_continuous)")


def positive_int(text: str) -> int:
    """argparse type of counts (worlds, steps, episodes, scenes): 0 and negatives are errors, not defaults."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


POLICY_HELP = ("expert: tracks the logged trajectory (closed-loop inverse dynamics); random: a uniformly random "
               "action each step; constant: zero acceleration and zero curvature")
COLLISION_HELP = ("what a collision or leaving the road does to the agent: ignore (counted, it drives on), stop "
                  "(frozen, done) or remove (taken out, done) (default: the engine config's collision_mode, ignore "
                  "in configs/env/default.yaml)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tg-gpudrive", description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="log INFO messages too (engine build reports, timings; default: warnings only); "
                             "give it before the command: tg-gpudrive -v simulate ...")
    sub = parser.add_subparsers(dest="command", required=True)
    _simulate_parser(sub)
    _benchmark_parser(sub)
    _train_parser(sub)
    _train_world_model_parser(sub)
    _evaluate_parser(sub)
    _render_parser(sub)
    _report_parser(sub)
    _generate_parser(sub)
    _convert_parser(sub)
    for command in sub.choices.values():  # every option's help shows its default
        command.formatter_class = HelpFormatter
    return parser


def _simulate_parser(sub) -> None:
    p = sub.add_parser("simulate", help="roll out a built-in policy and report goal/collision/off-road rates")
    _scene_args(p)
    _engine_args(p)
    p.add_argument("--worlds", type=positive_int, default=16, help="worlds simulated in parallel, one scene each")
    p.add_argument("--steps", type=positive_int, default=None, help="steps to run (default: one episode)")
    p.add_argument("--policy", default="expert", choices=BUILTIN, help=POLICY_HELP)
    p.add_argument("--collision-mode", choices=COLLISION_MODES, default=None, help=COLLISION_HELP)
    _background_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a table)")


def _benchmark_parser(sub) -> None:
    p = sub.add_parser("benchmark", help="engine agent steps/s for several world counts")
    _scene_args(p, num_scenes_default="36")
    _engine_args(p)
    p.add_argument("--worlds", type=positive_int, nargs="*", default=None,
                   help="world counts to time (default: 1 64 256 on cpu; 1 64 1024 4096 8192 16384 on cuda)")
    p.add_argument("--steps", type=positive_int, default=50, help="steps timed per world count")
    p.add_argument("--no-graph", action="store_true", help="plain launches instead of a CUDA graph")
    p.add_argument("--json", action="store_true", help="one JSON object per line")


def _train_parser(sub) -> None:
    p = sub.add_parser("train", help="CCE-MAPPO training (TrafficGamer)")
    p.add_argument("--config", default=None,
                   help="configs/train/<name>.yaml (required, except with --resume: the run's own config.json)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a train config key, e.g. --set alpha=0.25 --set env.beta=3 "
                        "(repeatable; default: none)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the run saved in DIR exactly (default: start a new run)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run already in the run directory (default: a new directory NAME-2, ...)")
    p.add_argument("--out", default=None, help="run directory (default: out_dir of the config)")
    p.add_argument("--auto-resume", action="store_true",
                   help="continue the run in --out exactly if it has a checkpoint, else start it there: the flag "
                        "for torchrun --max-restarts, whose restarts rerun the same command (default: off)")
    p.add_argument("--nproc", type=int, default=1,
                   help="processes (one per GPU with device cuda; gloo processes on cpu); torchrun works too. "
                        "num_worlds is per process: --set num_worlds=W/N keeps one process's batch")
    p.add_argument("--json", action="store_true", help="print the last update's metrics as JSON")


def _train_world_model_parser(sub) -> None:
    p = sub.add_parser("train-world-model", help="train the world model (behaviour prior / reactive traffic)")
    world_model_args(p)


def _evaluate_parser(sub) -> None:
    p = sub.add_parser("evaluate", help="goal/collision/off-road rates of a checkpoint or built-in policy")
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--checkpoint", help="a training checkpoint (checkpoint.pt or its run directory), or shipped "
                                          "(the policy packaged with tg_gpudrive; shipped_v4 to shipped_v1: the ones before it); this or --policy is required")
    who.add_argument("--policy", choices=BUILTIN,
                     help="a built-in policy instead: " + POLICY_HELP + "; this or --checkpoint is required")
    _scene_args(p)
    _engine_args(p)
    p.add_argument("--collision-mode", choices=COLLISION_MODES, default=None, help=COLLISION_HELP)
    p.add_argument("--episodes", type=positive_int, default=64, help="scene episodes to run (worlds x rounds)")
    p.add_argument("--worlds", type=positive_int, default=None, help="parallel worlds (default: min(episodes, 256))")
    _acting_args(p)
    p.add_argument("--per-scene", default=None, metavar="FILE.csv",
                   help="write one row per scene (and collision mode): agent-episodes, goal / collision / off-road "
                        "/ score rates with 95 %% bootstrap intervals, worst scenes first (default: none)")
    p.add_argument("--per-agent", default=None, metavar="FILE.csv",
                   help="write one row per scene agent the policy drove, with its outcome counts (default: none)")
    _background_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a table)")


def _acting_args(p) -> None:
    p.add_argument("--temperature", type=float, default=None, metavar="T",
                   help="checkpoint policies: sample their actions sharpened by T (logits / T), 0 takes the mode "
                        "(default: the checkpoint's act_temperature, 1 unless its run set one; shipped: 0.5)")
    p.add_argument("--deterministic", action="store_true", help="checkpoint policies: the mode (--temperature 0)")
    p.add_argument("--guard", type=float, default=None, metavar="S",
                   help="checkpoint policies: act behind the safety guard looking S seconds ahead (agents/guard.py), "
                        "0 without it (default: the checkpoint's act_guard_s, 0 unless its run set one)")


def _render_parser(sub) -> None:
    p = sub.add_parser("render", help="draw one world of an episode: .gif / .mp4, or its last frame as .png")
    _scene_args(p)
    _engine_args(p)
    p.add_argument("--policy", default="expert",
                   help="expert | random | constant | shipped (the packaged policy; shipped_v4 to shipped_v1: the ones before) | a training checkpoint "
                        "(checkpoint.pt or its run directory)")
    _acting_args(p)
    _background_args(p)
    p.add_argument("--steps", type=positive_int, default=None, help="at most this many steps (default and most: one episode)")
    p.add_argument("--world", type=int, default=0, help="which world to draw")
    p.add_argument("--worlds", type=positive_int, default=None, help="worlds to simulate (default: world + 1)")
    p.add_argument("--collision-mode", choices=COLLISION_MODES, default=None, help=COLLISION_HELP)
    p.add_argument("--out", default="episode.gif", help="episode.gif | episode.mp4 | frame.png")
    p.add_argument("--size", default="640", metavar="PX or WxH", help="picture size in pixels (default 640)")
    p.add_argument("--center-agent", type=int, default=None, metavar="SLOT",
                   help="follow this agent slot of the world (default: none; the view fits --fit)")
    p.add_argument("--fit", choices=["controlled", "all"], default="controlled",
                   help="without --center-agent, the view fits the paths of the policy's vehicles (default) or of "
                        "every agent, parked cars included")
    p.add_argument("--view-radius", type=float, default=None, metavar="METRES",
                   help="half the shorter side of the view (default 40 m with --center-agent)")
    p.add_argument("--fps", type=float, default=10.0, help="frames per second of a .gif / .mp4")
    p.add_argument("--highlight", choices=["controlled", "all", "none"], default="controlled",
                   help="whose collisions / off-road events are outlined")


def _report_parser(sub) -> None:
    """`tg-gpudrive report`: its options, defaults from ReportOptions."""
    p = sub.add_parser("report", description=report_module.__doc__,
                       help="scenario-quality report of training runs (tg-gpudrive report --runs DIR... --out DIR)")
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
    _report_br_args(p, d)
    p.add_argument("--top", type=int, default=d.top, help="critical scenarios exported per run")
    p.add_argument("--device", default="auto",
                   help="auto (default: cuda when Warp and torch see one, else cpu), cpu, cuda or cuda:N")
    p.add_argument("--grid-scene", type=_grid_scene, default=d.grid_scene, metavar="INDEX|auto",
                   help="evaluation scene (0 .. --scenes - 1) that grid.png shows in every beta x alpha cell; "
                        "auto (default): the one where the knob moves the distance the agents keep most")
    p.add_argument("--grid-gifs", action="store_true",
                   help="also write frames/<run>.gif, the whole episode of that scene, per cell (default: off)")
    p.add_argument("--no-baselines", action="store_true",
                   help="leave out log replay, expert, behaviour prior and world model, and the CCE-gap of the "
                        "policy runs started from (a process that fills the cache for some of the runs, beside "
                        "one that does these shared parts)")


def _grid_scene(text: str) -> int | None:
    """--grid-scene: a scene index, or auto (None: report_stats.knob_scene picks it)."""
    if text == "auto":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a scene index or auto, got {text!r}") from None


def _report_br_args(p: argparse.ArgumentParser, d: ReportOptions) -> None:
    """The report's --br-* options: how each agent's PPO best response (the CCE-gap) is trained."""
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


def _generate_parser(sub) -> None:
    from tg_gpudrive.evaluation import generate as gen_module

    d = gen_module.GenerateOptions
    p = sub.add_parser("generate", description=gen_module.__doc__,
                       help="the main job in one command: fine-tune under beta and alpha, export the most critical scenarios")
    p.add_argument("--scenes", required=True,
                   help="scene spec: procedural:<type>, a store, .json/.tfrecord file or directory, mix:... (required)")
    p.add_argument("--beta", type=float, required=True,
                   help="m, the distance constraint (required): under the built-in recipe every beta is held to "
                        "one bar, beta 2's, so below 2 the traffic presses closer and above 2 it keeps its distance")
    p.add_argument("--alpha", type=float, required=True,
                   help="the CVaR risk level in [0, 1): under the built-in recipe the multiplier answers to the worst "
                        "1 - alpha of the vehicles' costs, so lower is less risk-averse (required)")
    p.add_argument("--num", type=positive_int, default=d.num, help="scenarios to export")
    p.add_argument("--out", default=d.out, metavar="DIR", help="where the scenarios, their table and the policy go")
    p.add_argument("--seconds", type=float, default=d.seconds, help="training time budget (s)")
    p.add_argument("--num-scenes", type=positive_int, default=d.num_scenes, help="distinct scenes to draw")
    p.add_argument("--worlds", type=positive_int, default=None, help="training worlds (default: 8 on the CPU, 256 on a GPU)")
    p.add_argument("--rollout-seeds", type=positive_int, default=d.rollout_seeds, help="episodes per scene after training")
    p.add_argument("--max-hellinger", type=float, default=d.max_hellinger,
                   help="export only episodes at most this far from the logs (mean Hellinger, 0-1; 1: all)")
    p.add_argument("--device", default="auto", help="auto (cuda when present), cpu, cuda or cuda:N")
    p.add_argument("--seed", type=int, default=d.seed, help="training, scene and rollout seed")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF of each scenario")
    p.add_argument("--repeat-scenes", action="store_true",
                   help="rank every episode alike (default: each scene's most critical episode before any second one)")
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a table)")
    p.add_argument("--recipe", default="", metavar="YAML",
                   help="fine-tune under another experiment grid's constraint recipe (its `overrides:` but the "
                        "scenes, sizes and knobs), e.g. configs/experiments/grid_cvar_real_cap.yaml, or `shipped`: "
                        "the shipped policy's own settings, under which the knobs move little but speed (default: "
                        "configs/experiments/grid_sampled_cvar_ref.yaml's, built in)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a key of the fine-tune's train config, after the knobs above, e.g. "
                        "--set env.cost_horizon=1 --set env.cost_shape=hinge (repeatable; default: none)")


def _convert_parser(sub) -> None:
    p = sub.add_parser("convert", help="pack WOMD files (json / tfrecord) into a memory-mapped store")
    p.add_argument("inputs", nargs="+", help="files or directories")
    p.add_argument("--out", required=True, metavar="DIR", help="the store directory to write (required)")
    p.add_argument("--no-resume", action="store_true", help="start over instead of skipping converted files")
    p.add_argument("--simplify", type=float, default=None, metavar="METRES",
                   help="simplify road polylines with this tolerance (default: keep every point)")


def _engine_config(args) -> EngineConfig:
    overrides = list(args.set)
    if getattr(args, "collision_mode", None):
        overrides.append(f"collision_mode={args.collision_mode}")
    return load_config(EngineConfig, args.env_config, overrides)


def _load_scenes(args, worlds: int) -> tuple[list, dict]:
    """`worlds` scenes of --scenes, and what loading them left out or filled in (files that do not load,
    scenes that cannot be played, fields an older format revision lacks), for the JSON report."""
    n = args.num_scenes or worlds
    src = resolve_scenes(args.scenes, n=n, seed=args.seed)
    scenes = SceneSampler(src, worlds, replacement=False, seed=args.seed).sample()
    return scenes, {**source_report(src), "scene_defaults": scene_defaults(scenes)}


def _check_background_args(args) -> None:
    if args.background_model is not None and args.background != "world_model":
        raise ValueError("--background-model: only used with --background world_model")
    if args.control == str(ControlMode.NEAREST_CONFLICT) and args.control_k < 1:
        raise ValueError(f"--control-k: expected >= 1, got {args.control_k}")


def _temperature(args) -> float | None:
    """--temperature, 0 with --deterministic, None (the checkpoint's) without either."""
    t = getattr(args, "temperature", None)
    if getattr(args, "deterministic", False):
        if t not in (None, 0):
            raise ValueError(f"--deterministic is --temperature 0; got --temperature {t} as well")
        return 0.0
    if t is not None and not t >= 0:
        raise ValueError(f"--temperature: expected a number >= 0, got {t}")
    return t


def _guard(args) -> float | None:
    """--guard (seconds >= 0), None (the checkpoint's) without it."""
    s = getattr(args, "guard", None)
    if s is not None and not 0 <= s <= 60:
        raise ValueError(f"--guard: expected seconds in [0, 60], got {s}")
    return s


def _open(args, spec: str, scenes, *, engine, auto_reset: bool = True, option: str = "--checkpoint"):
    """`spec` in worlds of `scenes` with the command's options (agents.open_policy)."""
    opened = open_policy(spec, scenes, args.device, engine=engine, overrides=args.set,
                         collision_mode=args.collision_mode, control=getattr(args, "control", None),
                         control_k=getattr(args, "control_k", None), background=getattr(args, "background", "log"),
                         background_model=getattr(args, "background_model", None), seed=args.seed,
                         temperature=_temperature(args), guard_s=_guard(args), auto_reset=auto_reset, option=option)
    if opened.background is not None and not bool((opened.sim.background != 0).any()):
        log.warning("--background %s: no background vehicle (the policy drives every eligible one); "
                    "choose fewer with --control nearest_conflict --control-k K", args.background)
    return opened


def _background_report(args, opened) -> dict:
    """Who drove: the background, its model, and the control rule open_policy applied."""
    model = (args.background_model or "shipped") if args.background == "world_model" else None
    control = args.control or (opened.trained.control if opened.trained is not None else opened.sim.cfg.control)
    return {"background": args.background, "background_model": model, "control": str(control)}


def cmd_simulate(args) -> int:
    _check_background_args(args)
    engine = _engine_config(args)
    scenes, skipped = _load_scenes(args, args.worlds)
    opened = _open(args, args.policy, scenes, engine=engine)
    sim, cfg = opened.sim, opened.sim.cfg
    steps = args.steps or sim.episode_length
    # progress goes to stderr, so --json keeps stdout to one line and a long run still shows it is alive
    out = run_rollout(sim, opened.policy, steps, progress=True, background=opened.background)
    out.update({"policy": args.policy, "collision_mode": str(cfg.collision_mode), "scenes": args.scenes,
                **skipped, **sim.report(), **_background_report(args, opened)})
    if args.json:
        print(json.dumps(out))
    else:
        _print_rates(out)
    return 0


def _print_rates(out: dict) -> None:
    for k, v in out.items():
        if k not in ("per_type", "episodes", "kerb_stops", "expert_replay", "ci95"):  # printed below or by name
            print(f"{k:>22}: {v:.4g}" if isinstance(v, float) else f"{k:>22}: {v}")
    for name, (lo, hi) in out.get("ci95", {}).items():  # bootstrap intervals, resampling scenes
        print(f"{name + ' 95% CI':>22}: [{lo:.3f}, {hi:.3f}]")
    groups = dict(out.get("per_type", {}))
    if "kerb_stops" in out:  # the agents whose goal lies at the kerb (procedural kerb_stops)
        groups["(kerb stops)"] = out["kerb_stops"]
    if "expert_replay" in out:  # the same worlds under the expert replay
        groups["(expert replay)"] = out["expert_replay"]
    for name, r in groups.items():
        print(f"{name:>22}: goal {r['goal_rate']:.3f}  collision {r['collision_rate']:.3f}  "
              f"offroad {r['offroad_rate']:.3f}  timeout {r['timeout_rate']:.3f}  ({r['episodes']} agent episodes)")


def cmd_benchmark(args) -> int:
    args.engine_config = _engine_config(args)
    args.num_scenes = args.num_scenes or 36
    return benchmark_main(args)


def cmd_train(args) -> int:
    if args.auto_resume:
        if args.resume or not args.out:
            raise ValueError("--auto-resume: give the run directory as --out (and no --resume)")
        if (Path(args.out) / "checkpoint.pt").is_file():
            args.resume = args.out
        else:  # a start that died before its first checkpoint left nothing to keep
            args.overwrite = True
    if args.resume:  # the run's own config, then any new overrides
        if not (Path(args.resume) / "checkpoint.pt").is_file() and not Path(args.resume).is_file():
            raise FileNotFoundError(f"--resume: no run to continue at {args.resume} (no checkpoint.pt)")
        cfg_path = Path(args.resume) / "config.json"
        if not cfg_path.exists() and not args.config:
            raise FileNotFoundError(f"--resume {args.resume}: no config.json there; give the run's --config")
        data = json.loads(cfg_path.read_text()) if cfg_path.exists() else load_yaml(args.config)
    elif not args.config:
        raise ValueError("--config is required (a YAML of configs/train/, e.g. configs/train/small_cpu.yaml)")
    else:
        data = load_yaml(args.config)
    cfg = from_dict(TrainConfig, apply_overrides(data, args.set), args.config)
    if args.resume:
        check_resume_config(from_dict(TrainConfig, data, str(cfg_path)), cfg, args.resume)
    resolve_device(cfg.device, flag="device")  # CUDA without one: a one-line error before any process starts
    # under torchrun only rank 0 writes (and locks) the run directory; the others are told it below
    lead = int(os.environ.get("RANK", "0")) == 0
    if args.resume:
        run = Path(args.resume) if Path(args.resume).is_dir() else Path(args.resume).parent
        out_dir, lock = args.resume, RunLock(run) if lead else contextlib.nullcontext()
    elif lead:
        out_dir, lock = claim_run_dir(Path(args.out or cfg.out_dir), args.overwrite)
    else:
        out_dir, lock = args.out or cfg.out_dir, contextlib.nullcontext()
    with lock:
        out = _train(args, cfg, str(out_dir))
    return _train_report(args, out)


def _train(args, cfg, out_dir) -> dict:
    """The run in this process, in `args.nproc` spawned ones, or as this torchrun rank; its summary."""
    if args.nproc > 1:
        ctx = mp.get_context("spawn")
        result = ctx.SimpleQueue()
        mp.spawn(_train_worker, args=(args.nproc, distributed.free_port(), cfg, out_dir, args.resume, result),
                 nprocs=args.nproc)
        out = result.get()
    else:
        distributed.init_from_env(cfg.device)  # a torchrun launch: join its process group
        out = train_main(cfg, out_dir=out_dir, resume=args.resume, progress=True)
        out.setdefault("device", distributed.local_device(cfg.device))  # the one that ran ("auto" resolved)
        distributed.cleanup()
    return out


def _train_report(args, out) -> int:
    if out.get("interrupted"):
        print(f"tg-gpudrive train: interrupted: the checkpoint of update {out.get('update', 0)} is in {out['out_dir']}; "
              f"continue with: tg-gpudrive train --resume {out['out_dir']}", file=sys.stderr)
    if args.json:
        print(json.dumps(out))
    else:
        w = out.get("window_rates")
        rates = (f"goal {w['goal_rate']:.3f}  collision {w['collision_rate']:.3f}  offroad {w['offroad_rate']:.3f} "
                 "(the last 10 updates' episodes)" if w else "no episode ended yet")
        print(f"run: {out['out_dir']}  {rates}  lambda {out['lambda']:.3f}")
    return 130 if out.get("interrupted") else 0


def _train_worker(rank: int, world: int, port: int, cfg, out_dir, resume, result) -> None:
    with distributed.process_group(rank, world, port, cfg.device):
        out = train_main(cfg, out_dir=out_dir, resume=resume, progress=rank == 0)
        out.setdefault("device", distributed.local_device(cfg.device))  # rank 0's, "auto" resolved
    if rank == 0:
        result.put(out)


def cmd_evaluate(args) -> int:
    _check_background_args(args)
    engine = None if args.checkpoint else _engine_config(args)  # a checkpoint brings its own
    worlds = args.worlds or min(args.episodes, 256)
    scenes, skipped = _load_scenes(args, worlds)
    opened = _open(args, args.checkpoint or args.policy, scenes, engine=engine)
    sim, policy, background, cfg = opened.sim, opened.policy, opened.background, opened.sim.cfg
    rounds = -(-args.episodes // worlds)
    out = run_rollout(sim, policy, rounds * sim.episode_length, progress=True, background=background,
                      desc="evaluate", episodes_per_world=rounds, seed=args.seed, tables=True)
    mode = str(cfg.collision_mode)
    for csv_path, rows in ((args.per_scene, out.pop("per_scene")), (args.per_agent, out.pop("per_agent"))):
        if csv_path:
            _write_csv(csv_path, [{"collision_mode": mode, **r} for r in rows])
    if args.policy != "expert" and any(s.metadata.get("scenario_type") == "womd" for s in scenes):
        # on real scenes the expert replay, under the same rule and in the same worlds, is the reference
        ref = run_rollout(sim, expert_policy, rounds * sim.episode_length, background=background,
                          episodes_per_world=rounds, seed=args.seed)
        out["expert_replay"] = {k: ref[k] for k in ("episodes", "goal_rate", "collision_rate", "offroad_rate",
                                                     "score_rate", "timeout_rate")}
    if opened.temperature is not None:  # the acting temperature of a checkpoint policy, its own unless given
        out["temperature"] = opened.temperature
        out["guard_s"] = opened.guard_s
        if policy.guard is not None:  # the share of the policy's actions its guard replaced
            out["guard_replaced"] = policy.guard.replaced_share
    out.update({"policy": str(args.checkpoint or args.policy), "collision_mode": str(cfg.collision_mode),
                "scenes": args.scenes, "max_agents": sim.max_agents, **skipped,
                **sim.report(), **_background_report(args, opened)})
    if args.json:
        print(json.dumps(out))
    else:
        _print_rates(out)
    return 0


def _write_csv(path: str, rows: list[dict]) -> None:
    """Rows as CSV at `path` (a header only when there are none); its folder is made if missing."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with p.open("w", newline="") as f:
        if rows:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def cmd_render(args) -> int:
    # drawing needs the render extra (matplotlib, Pillow): imported by the one command that draws
    from tg_gpudrive.render import mp4_backend, render_episode

    _check_background_args(args)
    out = Path(args.out)
    if out.suffix.lower() not in (".gif", ".mp4", ".png"):
        raise ValueError(f"--out {out}: expected a .gif, .mp4 or .png file name")
    if out.suffix.lower() == ".mp4" and mp4_backend() is None:
        print("tg-gpudrive render: error: .mp4 needs ffmpeg (pip install imageio-ffmpeg, or put an ffmpeg on "
              "PATH); use --out episode.gif instead", file=sys.stderr)
        return 2
    try:
        size = tuple(int(v) for v in args.size.lower().split("x"))
        size = size * 2 if len(size) == 1 else size
        if len(size) != 2 or min(size) < 32:
            raise ValueError
    except ValueError:
        raise ValueError(f"--size: expected PX or WxH of at least 32 pixels, got {args.size!r}") from None
    if args.world < 0:
        raise ValueError(f"--world must be >= 0, got {args.world}")
    worlds = args.worlds or args.world + 1
    if args.world >= worlds:
        raise ValueError(f"--world {args.world} needs --worlds > {args.world}, got {worlds}")

    engine = None if args.policy not in BUILTIN else _engine_config(args)
    scenes, _ = _load_scenes(args, worlds)
    try:  # a built-in name, a checkpoint file, a run directory or "shipped"
        opened = _open(args, args.policy, scenes, engine=engine, auto_reset=False, option="--policy")
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{e} (expected expert, random, constant, shipped or a checkpoint path)") from None
    sim = opened.sim  # without auto-reset: the episode's final state is the last frame
    t0 = time.perf_counter()
    frames = render_episode(sim, opened.act, args.steps, world=args.world, out=out, fps=args.fps, progress=True,
                            seed=args.seed, size=size, center_agent=args.center_agent, view_radius=args.view_radius,
                            highlight=args.highlight, fit=args.fit)
    seconds = time.perf_counter() - t0
    scene = sim.model.scenes[args.world]
    print(f"wrote {out}: {len(frames)} frame(s) of {size[0]}x{size[1]}, scene {scene.scene_id}, "
          f"policy {args.policy}, {seconds:.1f} s")
    return 0


def cmd_convert(args) -> int:
    report = convert(args.inputs, args.out, resume=not args.no_resume, progress=True,
                     simplify_tolerance=args.simplify)
    d = dataclasses.asdict(report) if dataclasses.is_dataclass(report) else dict(vars(report))
    print(json.dumps(d, default=str, indent=1))
    if report.failed and report.num_scenes == 0:  # nothing usable came out: a failure, not a success
        print(f"tg-gpudrive convert: error: every input failed ({len(report.failed)}; first: "
              f"{report.failed[0][0]}: {report.failed[0][1]})", file=sys.stderr)
        return 2
    return 0


def cmd_report(args) -> int:
    """`tg-gpudrive report --runs DIR [DIR ...] --out DIR`: the options as ReportOptions, then report_main."""
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
    report_main(args.runs, args.out, opts)
    print(f"wrote {Path(args.out) / 'report.md'}")
    return 0


def cmd_train_world_model(args) -> int:
    return run_world_model(args) or 0


def cmd_generate(args) -> int:
    from tg_gpudrive.evaluation.generate import GenerateOptions, generate

    opts = GenerateOptions(scenes=args.scenes, beta=args.beta, alpha=args.alpha, num=args.num, out=args.out,
                           seconds=args.seconds, num_scenes=args.num_scenes, num_worlds=args.worlds or 0,
                           rollout_seeds=args.rollout_seeds, max_hellinger=args.max_hellinger, device=args.device,
                           seed=args.seed, gif=not args.no_gif, recipe=args.recipe, overrides=tuple(args.set),
                           one_per_scene=not args.repeat_scenes)
    res = generate(opts)
    if args.json:
        print(json.dumps({k: v for k, v in res.items() if k != "rows"} | {"rows": res["rows"]}, default=str))
        return 0
    print(f"{len(res['scenarios'])} of {res['episodes']} episodes exported to {opts.out}/scenarios "
          f"(policy fine-tuned for {res['updates']} updates: {res['policy']}); table: {res['table']}")
    for r in res["rows"]:
        print(f"  {r['file']}: collisions {r['collisions']}, min TTC {r['min_ttc_s']:.2f} s, min gap "
              f"{r['min_gap_m']:.2f} m, hard brakes {r['hard_brakes']}, Hellinger to the logs {r['hellinger_to_logs']:.3f}")
    return 0


COMMANDS = {"simulate": cmd_simulate, "train-world-model": cmd_train_world_model, "benchmark": cmd_benchmark, "convert": cmd_convert, "train": cmd_train,
            "evaluate": cmd_evaluate, "render": cmd_render, "report": cmd_report,
            "generate": cmd_generate}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")

    def run() -> int:
        # "auto" made concrete; CUDA without one fails here. Not for report: it resolves the device per run
        # and keys its cache by the option as given
        if getattr(args, "device", None) is not None and args.command != "report":
            args.device = resolve_device(args.device, flag="--device")
        return COMMANDS[args.command](args)

    return one_line_errors(f"tg-gpudrive {args.command}", run)


def one_line_errors(prog: str, run) -> int:
    """`run()`'s exit code, with bad input (ConfigError, ValueError, a missing file) as one line `prog: error:
    ...` and exit 2, an interrupt as 130, and any other OS error (a full disk, a file where a folder should be,
    no permission) as one line and exit 1: the rule of the CLI and of the scripts."""
    try:
        return run()
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a second Ctrl-C, or one outside a training loop
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except OSError as e:
        where = f": {e.filename}" if e.filename else ""
        print(f"{prog}: error: {e.strerror or e}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
