"""The shipped YAML configs: each loads into its config class, and configs/env/default.yaml lists every
engine knob with the engine's own default (it is where a reader looks a knob up)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from tg_gpudrive.config import ConfigError, EngineConfig, TrainConfig, load_config, load_experiment, to_dict
from tg_gpudrive.worldmodel.train import WorldModelConfig

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_default_env_yaml_lists_every_engine_knob_with_its_default():
    listed = yaml.safe_load((CONFIGS / "env" / "default.yaml").read_text())
    assert listed == yaml.safe_load(yaml.safe_dump(to_dict(EngineConfig())))  # tuples as YAML lists


@pytest.mark.parametrize("path", sorted((CONFIGS / "train").glob("*.yaml")), ids=lambda p: p.name)
def test_training_configs_load(path):
    load_config(TrainConfig, path)


@pytest.mark.parametrize("path", sorted((CONFIGS / "worldmodel").glob("*.yaml")), ids=lambda p: p.name)
def test_world_model_configs_load(path):
    load_config(WorldModelConfig, path)


@pytest.mark.parametrize("path", sorted((CONFIGS / "experiments").glob("*.yaml")), ids=lambda p: p.name)
def test_experiment_grids_load(path):
    exp = load_experiment(path)
    assert exp["beta"] and exp["alpha"] and (CONFIGS / "train" / exp["base"]).exists()


@pytest.mark.parametrize("text, field", [
    ("beta: [2]\nalpha: [0.5]\n", "'base'"),
    ("base: gpu.yaml\nbeta: 2\nalpha: [0.5]\n", "'beta'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: []\n", "'alpha'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: [true]\n", "'alpha'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: [0.5]\noverrides: [lr]\n", "'overrides'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: [0.5]\nseeds: [0.5]\n", "'seeds'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: [0.5]\nbatch: 0\n", "'batch'"),
    ("base: gpu.yaml\nbeta: [2]\nalpha: [0.5]\nbetas: [3]\n", "betas"),
])
def test_a_bad_experiment_grid_names_its_file_and_field(tmp_path, text, field):
    path = tmp_path / "grid.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_experiment(path)
    assert str(path) in str(e.value) and field in str(e.value)


@pytest.mark.parametrize("value", [1e-08, 0.75, 4, True, None, "", "approach", "0.5", "a: b", "[x", [1, 2], {"a": 1.5}])
def test_override_text_reads_back_as_the_value(value):
    """What a grid or a recipe writes as key=value is what --set parses back: a float stays a float (1e-08 is a
    string to YAML), an empty string stays a string, a string of digits stays a string."""
    from tg_gpudrive.config import override_text, parse_override

    path, back = parse_override(override_text("env.cost_limit", value))
    assert path == ["env", "cost_limit"] and back == value and type(back) is type(value)
