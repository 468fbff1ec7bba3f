"""`tg-gpudrive generate`: the main job in one command, scenes and knobs in, critical scenarios out.

Given scenes (real or procedural), the distance constraint `beta`, the risk level `alpha` and a time
budget, it fine-tunes the shipped policy on those scenes under those knobs (CCE-MAPPO, the shipped
policy's own training settings otherwise), rolls the result out on the same scenes, and writes the `num`
most safety-critical episodes (most collisions, then the shortest time to collision, the smallest gap,
the most hard brakes; evaluation/risk.py; one per scene before any scene's second) as:

    OUT/scenarios/<name>.json   GPUDrive processed JSON: `--scenes OUT/scenarios` plays them back
    OUT/scenarios/<name>.gif    each scenario replayed (every agent on its generated track)
    OUT/scenarios.csv           their risk (collisions, min TTC, min gap, hard brakes, who was involved)
                                and their fidelity to the logs (mean Hellinger distance over the speed,
                                acceleration, nearest-agent and curvature histograms; 0: the logs' own)
    OUT/policy/                 the fine-tuned policy's run (checkpoint, metrics.csv, curves.png)

`max_hellinger` keeps only episodes at most that far from the logs: critical but realistic. The fine-tune runs
under a constraint recipe, the cost, bar and multiplier step under which an experiment grid measured what beta and
alpha move: KNOB_RECIPE (configs/experiments/grid_sampled_cvar_ref.yaml's) unless `recipe` names another grid's
yaml, or `shipped` for the shipped policy's own settings, under which the multiplier stays near 0 and the knobs move
little but the traffic's speed.
"""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np

from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.config import (AugmentConfig, ConfigError, EngineConfig, TrainConfig, apply_overrides, from_dict,
                                load_experiment, override_text, to_dict)
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.enums import ControlMode
from tg_gpudrive.evaluation.episodes import logged_episodes, record_rollouts
from tg_gpudrive.evaluation.export import export_episodes
from tg_gpudrive.evaluation.fidelity import episode_histograms, hellinger_of_sums, histograms
from tg_gpudrive.evaluation.risk import collision_partners, episode_risk, rank_scenarios

TABLE = ("file", "scene_id", "seed", "collisions", "min_ttc_s", "min_gap_m", "hard_brakes", "involved",
         "hellinger_to_logs")


@dataclasses.dataclass(frozen=True)
class GenerateOptions:
    """What `tg-gpudrive generate` takes (see the module docstring)."""

    scenes: str
    beta: float
    alpha: float
    num: int = 5
    out: str = "generated"
    seconds: float = 120.0  # training wall-clock budget
    updates: int = 10_000  # at most this many updates (the time budget usually ends first)
    num_scenes: int = 16
    num_worlds: int = 0  # 0: 8 on the CPU, 256 on a GPU
    rollout_seeds: int = 2  # episodes per scene after training
    max_hellinger: float = 1.0  # 1.0: no realism filter
    device: str = "cpu"
    seed: int = 0
    gif: bool = True
    recipe: str = ""  # "": KNOB_RECIPE; an experiment grid's yaml (recipe_overrides); SHIPPED_RECIPE: none
    overrides: tuple[str, ...] = ()  # train-config KEY=VALUE, applied last (e.g. env.cost_horizon=1)
    one_per_scene: bool = True  # distinct scenes before a second episode of any scene (pick_scenarios)

    def __post_init__(self):
        # the knobs and sizes are checked with the training config (training_config); these two are not in it
        if not 0 <= self.max_hellinger <= 1:
            raise ValueError(f"max_hellinger (--max-hellinger): expected a number in [0, 1], got {self.max_hellinger}")
        if not self.seconds > 0:  # 0 would switch the time limit off, not train for no time
            raise ValueError(f"seconds (--seconds): expected a positive number, got {self.seconds}")


# the steps of a fine-tune, whatever the shipped policy was trained with: a trained driver moved with the
# from-scratch recipe's learning rate and entropy bonus unlearns its driving within a hundred updates. The
# scenarios are the fine-tuned policy's samples at temperature 1 and without a safety guard, not the shipped
# policy's sharper, guarded acting: the knobs, not a sharper sampling or a filter, decide how close the traffic presses.
# The multipliers are held for the first updates: under a recipe that steps them on the cost critic (lambda_on: cvar),
# the critic the shipped policy brings is fitted to another cost, and stepped on its first values they climb
# several-fold at every beta and alpha alike
FINE_TUNE = {"lr": 3e-4, "entropy_coef": 0.0, "act_temperature": 1.0, "act_guard_s": 0.0, "lambda_warmup": 20}
# reward terms that hold a driver back from its neighbours whatever the knobs (the shipped policy trains with a
# time-to-collision charge): off in a fine-tune and in every run of a knob grid (scripts/run_experiments.py), so
# that beta and alpha alone decide how close the traffic presses
KNOBS_ALONE = {"ttc": 0.0}


# the constraint recipe of a fine-tune unless `recipe` names another: configs/experiments/grid_sampled_cvar_ref.yaml's
# `overrides:` less generate's own keys (a test keeps them in step). A pass costs the depth of its closest approach
# within beta over a 1.5 s look-ahead; each slot's multiplier steps fast on the CVaR_alpha over its vehicles of
# their sampled cost rate against one bar for every beta and alpha, 0.75 x the starting policy's mean cost rate
# under beta 2, capped; the game is played by the 5 vehicles nearest a conflict. Beta then loosens below 2 as well
# as tightens above it, and a higher alpha holds a higher multiplier at every beta (BENCHMARKS.md)
KNOB_RECIPE = {"control": "nearest_conflict", "control_k": 5, "lr": 0.001, "minibatches": 8,
               "cost_limit_mode": "start", "cost_limit": 0.75, "cost_limit_beta": 2.0, "lambda_on": "sampled_cvar",
               "lambda_init": 1.0, "lambda_lr": 0.08, "lambda_max": 6.0, "env.cost_shape": "approach",
               "env.cost_partners": "all", "env.cost_horizon": 1.5}
SHIPPED_RECIPE = "shipped"  # `recipe`: the shipped policy's own constraint settings, no grid's


def recipe_overrides(path: str | Path, own: set[str]) -> list[str]:
    """KEY=VALUE overrides from an experiment grid's yaml (configs/experiments/*.yaml, its `overrides:`): the
    cost, bar, multiplier step and training steps under which that grid measured what the knobs move, less the
    keys in `own` (what generate's options set: scenes, sizes, time budget, starting policy, knobs, outputs; the
    grid's values for them are not the user's). A file that is not a grid (config.load_experiment) or sets no
    overrides is a ConfigError naming it."""
    over = load_experiment(path).get("overrides")
    if not over:
        raise ConfigError(f"{path}: field 'overrides': the grid sets no train-config keys, so it has no recipe "
                          "(e.g. configs/experiments/grid_cvar_real_cap.yaml has)")
    return [override_text(k, v) for k, v in over.items() if k not in own]


def training_config(opts: GenerateOptions) -> TrainConfig:
    """The shipped policy's training config, fine-tuning it on `opts.scenes` under the knobs: fine-tuning's
    steps (FINE_TUNE), no distance-keeping reward terms (KNOBS_ALONE), no augmentation, no resampling, the time
    budget, one checkpoint at the end, then the constraint recipe (KNOB_RECIPE, `opts.recipe`'s grid through
    recipe_overrides, or none for SHIPPED_RECIPE), then `opts.overrides` (e.g. env.cost_horizon=1 keeps beta ahead
    of time, env.cost_shape=hinge). Every value is checked as a config file's are (ConfigError naming the key)."""
    base = to_dict(from_dict(TrainConfig, load_checkpoint("shipped", "shipped")["config"], "the shipped policy"))
    base["augment"] = to_dict(AugmentConfig())
    worlds = opts.num_worlds or (8 if opts.device == "cpu" else 256)
    settings = {"scenes": opts.scenes, "num_scenes": opts.num_scenes, "num_worlds": worlds, "resample_every": 0,
                "init_policy": "shipped", "device": opts.device, "seed": opts.seed, "updates": opts.updates,
                "time_limit_s": opts.seconds, "alpha": opts.alpha,
                "checkpoint_every": opts.updates, "keep_policy_every": 0, "target_goal_rate": 0.0,
                "target_heldout": "", "out_dir": str(Path(opts.out) / "policy")}
    base.update(settings, **FINE_TUNE)
    base["env"] = {**base["env"], "beta": opts.beta, "reward": {**base["env"]["reward"], **KNOBS_ALONE}}
    if opts.recipe == SHIPPED_RECIPE:
        recipe = []
    elif opts.recipe:
        recipe = recipe_overrides(opts.recipe, {*settings, "env.beta"})
    else:
        recipe = [override_text(k, v) for k, v in KNOB_RECIPE.items()]
    return from_dict(TrainConfig, apply_overrides(base, recipe + list(opts.overrides)), "tg-gpudrive generate")


def _involved(partners: list[dict], episode: int) -> str:
    """Who collided in `episode`: slot -> partner slot (the partner's kind), `;`-separated."""
    rows = [p for p in partners if p["episode"] == episode]
    return ";".join(f"{p['agent']}->{p['partner']} ({'policy' if p['partner_policy'] else 'replayed'}, "
                    f"{p['contact']})" for p in rows)


def episode_hellinger(logged, generated) -> np.ndarray:
    """(E,) mean Hellinger distance of each generated episode's feature histograms (its policy agents)
    to the logs' (all of their policy agents)."""
    rows = episode_histograms(generated, generated.policy)
    episode_of_row = np.nonzero(generated.policy)[0]  # row-major order of the (E, A) mask
    sums = np.zeros((generated.num_episodes, rows.shape[1]))
    np.add.at(sums, episode_of_row, rows)
    return hellinger_of_sums(histograms(logged), sums)


def pick_scenarios(ranked: list[dict], num: int, one_per_scene: bool) -> list[dict]:
    """`num` rows of `ranked` (most critical first), in its order. With `one_per_scene` the most critical
    episode of each scene comes before any second episode of a scene: five scenarios are five situations
    as long as there are five scenes, not one conflict under two rollout seeds."""
    if not one_per_scene:
        return ranked[:num]
    seen: set = set()
    firsts, repeats = [], []
    for i, r in enumerate(ranked):
        (repeats if r["scene_id"] in seen else firsts).append(i)
        seen.add(r["scene_id"])
    return [ranked[i] for i in sorted((firsts + repeats)[:num])]


def critical_scenarios(logged, generated, num: int, max_hellinger: float, one_per_scene: bool = True) -> list[dict]:
    """The `num` most critical episodes whose distance to the logs is at most `max_hellinger`
    (pick_scenarios: distinct scenes first), with their risk, who collided and that distance."""
    risk = episode_risk(generated)
    far = episode_hellinger(logged, generated)
    partners = collision_partners(generated)
    ranked = [r for r in rank_scenarios(generated, risk, top=generated.num_episodes)
              if not far[r["episode"]] > max_hellinger]
    rows = pick_scenarios(ranked, num, one_per_scene)
    for r in rows:
        r["involved"] = _involved(partners, r["episode"])
        r["hellinger_to_logs"] = float(far[r["episode"]])
    return rows


def write_table(rows: list[dict], path: Path) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(TABLE)
        for r in rows:
            w.writerow([r.get(k, "") for k in TABLE])
    return path


def replay_gif(scene_file: Path, device: str) -> Path:
    """A GIF of the exported scenario: every agent on its generated track (log replay)."""
    from tg_gpudrive.agents.worlds import open_policy
    from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
    from tg_gpudrive.render import render_episode

    replay = EngineConfig(control=ControlMode.NONE)  # nobody drives: every agent replays its track
    opened = open_policy("expert", [load_gpudrive_json(scene_file)], device, engine=replay, auto_reset=False)
    out = scene_file.with_suffix(".gif")
    render_episode(opened.sim, opened.policy, out=out, fit="scene")
    return out


def generate(opts: GenerateOptions, progress: bool = True) -> dict:
    """Fine-tune, roll out, export (see the module docstring); returns what was written and the rows."""
    from tg_gpudrive.agents.worlds import open_policy
    from tg_gpudrive.learn.rundir import claim_run_dir
    from tg_gpudrive.learn.train import train_main

    out = Path(opts.out)
    cfg = training_config(opts)  # bad knobs fail here, before anything is written
    run_dir, lock = claim_run_dir(out / "policy", overwrite=True)
    with lock:
        trained = train_main(cfg, str(run_dir), progress=progress)
    src = resolve_scenes(opts.scenes, n=opts.num_scenes, seed=opts.seed)
    scenes = [src[i] for i in range(len(src))]
    # the rollout's traffic is the fine-tune's: `--set background=idm` (with fewer policy vehicles, e.g.
    # `--set control=nearest_conflict --set control_k=2`) has the others react instead of replaying
    opened = open_policy(str(run_dir), scenes, opts.device, seed=opts.seed, background=cfg.background)
    logged = logged_episodes(opened.sim)
    generated = record_rollouts(opened.sim, opened.act, range(opts.seed, opts.seed + opts.rollout_seeds),
                                label=f"beta{opts.beta:g}_alpha{opts.alpha:g}")
    rows = critical_scenarios(logged, generated, opts.num, opts.max_hellinger, opts.one_per_scene)
    files = export_episodes(generated, [r["episode"] for r in rows], out / "scenarios", rows)
    for r, f in zip(rows, files):
        r["file"] = str(f.relative_to(out))
        if opts.gif:
            replay_gif(f, opts.device)
    return {"scenarios": [str(f) for f in files], "table": str(write_table(rows, out / "scenarios.csv")),
            "policy": str(run_dir), "updates": trained.get("update"), "rows": rows,
            "episodes": generated.num_episodes}
