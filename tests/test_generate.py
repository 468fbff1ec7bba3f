"""`tg-gpudrive generate`: fine-tune under the knobs, roll out, export the most critical scenarios as
GPUDrive JSON (which load back as scenes), a GIF each and their risk / fidelity table."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import pytest

from tg_gpudrive import cli
from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.enums import ControlMode
from tg_gpudrive.evaluation.generate import FINE_TUNE, KNOB_RECIPE, KNOBS_ALONE, SHIPPED_RECIPE, TABLE, pick_scenarios


@pytest.mark.parametrize("traffic", [[], ["--set", "control=nearest_conflict", "--set", "control_k=1",
                                           "--set", "background=idm"]], ids=["all-policy", "idm-traffic"])
def test_generate_exports_critical_scenarios_that_load_back(tmp_path, capsys, traffic):
    out = tmp_path / "gen"
    assert cli.main(["generate", "--scenes", "procedural:merge", "--beta", "2", "--alpha", "0.125", "--num", "2",
                     "--out", str(out), "--seconds", "3", "--num-scenes", "2", "--worlds", "2",
                     "--rollout-seeds", "2", "--device", "cpu", "--json", *traffic]) == 0
    res = json.loads(capsys.readouterr().out)  # stdout is the JSON alone: training notes go to stderr
    run = json.loads((out / "policy" / "config.json").read_text())
    assert run["env"]["beta"] == 2.0 and run["alpha"] == 0.125 and run["init_policy"] == "shipped"
    assert run["entropy_coef"] == FINE_TUNE["entropy_coef"]  # not the shipped run's
    assert run["lambda_warmup"] == FINE_TUNE["lambda_warmup"] > 0  # held while a critic recipe's cost critic learns
    assert (run["lr"], run["env"]["cost_shape"], run["lambda_lr"]) == (
        KNOB_RECIPE["lr"], "approach", KNOB_RECIPE["lambda_lr"])  # the built-in constraint recipe
    assert run["act_temperature"] == 1.0 != load_checkpoint("shipped", "shipped")["config"]["act_temperature"]
    assert run["act_guard_s"] == 0.0  # its scenarios are not filtered by the shipped policy's guard
    shipped = load_checkpoint("shipped", "shipped")["config"]["env"]["reward"]
    assert shipped["ttc"] < 0 and run["env"]["reward"] == {**shipped, **KNOBS_ALONE}  # the knobs alone keep distance
    assert run["background"] == ("idm" if traffic else "log")
    rows = list(csv.DictReader(open(out / "scenarios.csv")))
    assert tuple(rows[0]) == TABLE and 1 <= len(rows) == len(res["scenarios"]) <= 2
    # most critical first: more collisions, then a shorter time to collision
    keys = [(-int(r["collisions"]), float(r["min_ttc_s"])) for r in rows]
    assert keys == sorted(keys)
    assert len({r["scene_id"] for r in rows}) == len(rows)  # two scenes, two scenarios: one of each
    src = resolve_scenes("procedural:merge", n=2)
    source = {src[i].scene_id for i in range(len(src))}
    for r in rows:
        scene = load_gpudrive_json(out / r["file"])  # a scene GPUDrive and this tool read back
        assert scene.num_agents > 0 and r["scene_id"] in source
        assert (out / r["file"]).with_suffix(".gif").stat().st_size > 0
        assert 0.0 <= float(r["hellinger_to_logs"]) <= 1.0


@pytest.mark.parametrize("args, message", [
    (["--beta", "-1", "--alpha", "0.5"], "beta"),
    (["--beta", "4", "--alpha", "1"], "alpha"),
    (["--beta", "4", "--alpha", "0.5", "--max-hellinger", "2"], "--max-hellinger"),
    (["--beta", "4", "--alpha", "0.5", "--recipe", "no_such_grid.yaml"], "no_such_grid.yaml"),
])
def test_generate_refuses_bad_knobs_before_training(tmp_path, capsys, args, message):
    assert cli.main(["generate", "--scenes", "procedural:merge", "--out", str(tmp_path / "g"), "--device", "cpu",
                     *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "g" / "policy").exists()


def test_generate_set_overrides_the_fine_tunes_config_and_names_a_bad_key():
    from tg_gpudrive.config import ConfigError
    from tg_gpudrive.evaluation.generate import GenerateOptions, training_config

    opts = GenerateOptions(scenes="procedural:merge", beta=2.0, alpha=0.125,
                           overrides=("env.cost_horizon=1", "env.cost_shape=hinge", "lr=0.0001"))
    cfg = training_config(opts)
    assert cfg.env.cost_horizon == 1.0 and cfg.env.cost_shape == "hinge" and cfg.lr == 0.0001
    assert cfg.env.beta == 2.0 and cfg.alpha == 0.125  # the knobs stay
    with pytest.raises(ConfigError, match="cost_horizn"):
        training_config(GenerateOptions(scenes="procedural:merge", beta=2.0, alpha=0.125,
                                        overrides=("env.cost_horizn=1",)))


def test_generate_recipe_takes_a_grids_constraint_but_keeps_its_own_scenes_sizes_and_knobs(tmp_path):
    """The real grid's recipe sets the cost, bar and multiplier step; the grid's scenes, sizes and seeds stay
    generate's; --set still comes last; a yaml that is not a grid is an error naming the file."""
    from tg_gpudrive.config import ConfigError
    from tg_gpudrive.evaluation.generate import GenerateOptions, training_config

    recipe = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "grid_cvar_real_cap.yaml"
    opts = GenerateOptions(scenes="procedural:merge", beta=6.0, alpha=0.875, num_scenes=4, seconds=30.0,
                           recipe=str(recipe), overrides=("lambda_lr=0.02",))
    cfg, plain = training_config(opts), training_config(dataclasses.replace(opts, recipe=SHIPPED_RECIPE))
    assert (cfg.env.cost_shape, cfg.env.cost_horizon, cfg.cost_limit_mode, cfg.cost_limit, cfg.lambda_max,
            cfg.lambda_init) == ("approach", 1.5, "start", 0.75, 4.0, 1.0)
    assert (plain.env.cost_shape, plain.lambda_max) != ("approach", 4.0)  # the shipped policy's own recipe
    assert cfg.lambda_lr == 0.02  # --set after the recipe
    assert (cfg.scenes, cfg.num_scenes, cfg.num_worlds, cfg.updates, cfg.init_policy, cfg.time_limit_s) == (
        "procedural:merge", 4, plain.num_worlds, plain.updates, "shipped", 30.0)  # not the grid's 44 real scenes
    assert (cfg.env.beta, cfg.alpha) == (6.0, 0.875)
    bad = tmp_path / "not_a_grid.yaml"
    bad.write_text("lr: 0.001\n")
    with pytest.raises(ConfigError, match="not_a_grid.yaml"):
        training_config(dataclasses.replace(opts, recipe=str(bad)))


def test_generate_fine_tunes_under_the_sampled_cvar_grids_recipe_unless_told_otherwise():
    """The built-in recipe is configs/experiments/grid_sampled_cvar_ref.yaml's, the grid whose knobs were measured;
    `shipped` keeps the shipped policy's own constraint settings (and FINE_TUNE's learning rate)."""
    from tg_gpudrive.evaluation.generate import GenerateOptions, training_config

    grid = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "grid_sampled_cvar_ref.yaml"
    opts = GenerateOptions(scenes="procedural:merge", beta=0.5, alpha=0.875)
    built_in = training_config(opts)
    assert built_in == training_config(dataclasses.replace(opts, recipe=str(grid)))
    assert (built_in.env.cost_shape, built_in.control, built_in.lambda_lr) == (
        "approach", ControlMode.NEAREST_CONFLICT, 0.08)
    # one bar for every beta, measured under beta 2; the multiplier answers to the alpha tail of the vehicles, capped
    assert (built_in.env.beta, built_in.alpha, built_in.cost_limit_beta) == (0.5, 0.875, 2.0)
    assert (built_in.lambda_on, built_in.lambda_max) == ("sampled_cvar", 6.0)
    own = training_config(dataclasses.replace(opts, recipe=SHIPPED_RECIPE))
    shipped = load_checkpoint("shipped", "shipped")["config"]
    assert (own.env.cost_shape, own.lambda_lr, own.lr) == (shipped["env"]["cost_shape"], shipped["lambda_lr"],
                                                           FINE_TUNE["lr"])


def test_scenarios_are_distinct_scenes_before_a_scene_repeats():
    # ranked most critical first: scene a under three rollout seeds, then b, then c
    ranked = [{"scene_id": sid, "episode": e} for e, sid in enumerate(["a", "a", "b", "a", "c"])]
    pick = lambda num, one: [r["episode"] for r in pick_scenarios(ranked, num, one)]  # noqa: E731
    assert pick(3, True) == [0, 2, 4]  # a, b, c: one each, in rank order
    assert pick(4, True) == [0, 1, 2, 4]  # then a's second episode, kept in rank order
    assert pick(5, True) == [0, 1, 2, 3, 4] and pick(9, True) == [0, 1, 2, 3, 4]
    assert pick(3, False) == [0, 1, 2]  # --repeat-scenes: the ranking alone
    assert pick(2, True) == [0, 2] and pick(0, True) == []
