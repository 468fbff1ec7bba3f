"""`mix:` scene specs (`MixedSource`): parsing, the virtual index layout, labels, errors, a simulator."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from tg_gpudrive.data.sampler import SceneSampler
from tg_gpudrive.data.sources import MixedSource, SceneListSource, resolve_scenes
from tg_gpudrive.scene import make_scene

DATA = Path(__file__).parent / "data"  # two GPUDrive WOMD JSON scenes
SPEC = f"mix:procedural:merge=0.75,{DATA}=0.25"


def test_parse_and_layout():
    mix = resolve_scenes(SPEC, n=8, seed=0)
    assert isinstance(mix, MixedSource)
    assert [p.name for p in mix.parts] == ["procedural:merge", str(DATA)]
    assert mix.weights == [0.75, 0.25] and mix.counts == [6, 2] and mix.slots == [6, 2]
    assert len(mix) == 8 and mix.num_distinct == 8
    # every distinct scene is reachable, and the layout is a pure function of the spec
    assert sorted(mix.locate(i) for i in range(8)) == [(0, j) for j in range(6)] + [(1, 0), (1, 1)]
    again = resolve_scenes(SPEC, n=8, seed=0)
    assert [again.locate(i) for i in range(8)] == [mix.locate(i) for i in range(8)]
    # a prefix is already mixed: the first four indices hold one real scene
    assert Counter(mix.locate(i)[0] for i in range(4)) == {0: 3, 1: 1}

    # a real part smaller than its share: it keeps its weight by repetition, the others fill n
    big = resolve_scenes(SPEC, n=40, seed=0)
    assert big.counts == [38, 2] and big.num_distinct == 40
    assert big.slots == [39, 13] and len(big) == 52  # exact 3:1
    reals = [big.locate(i)[1] for i in range(len(big)) if big.locate(i)[0] == 1]
    assert Counter(reals) == {0: 7, 1: 6}
    # omitted weights mean 1
    even = resolve_scenes(f"mix:procedural:merge,{DATA}", n=4)
    assert even.weights == [0.5, 0.5] and even.counts == [2, 2]


def test_sampler_draws_follow_the_weights():
    mix = resolve_scenes(SPEC, n=8, seed=0)
    s = SceneSampler(mix, 4, replacement=False, seed=3)
    types = Counter(sc.metadata["scenario_type"] for _ in range(20) for sc in s.sample())  # 10 passes
    assert types == {"merge": 60, "womd": 20}
    r = SceneSampler(resolve_scenes(SPEC, n=40, seed=0), 64, replacement=True, seed=1)
    src = r.source
    parts = np.array([src.locate(i)[0] for _ in range(50) for i in r.sample_indices()])
    assert abs(parts.mean() - 0.25) < 0.02


def test_every_scene_has_a_scenario_type():
    mix = resolve_scenes(SPEC, n=8, seed=0)
    got = mix.get_many(range(len(mix)))
    assert [sc.metadata["scenario_type"] for sc in got] == [
        "merge" if mix.locate(i)[0] == 0 else "womd" for i in range(len(mix))]
    real = [sc for i, sc in enumerate(got) if mix.locate(i)[0] == 1]
    assert {sc.scene_id for sc in real} == {"1c365f15b70ebdbf", "db4edc9bd0c9d18c"}
    assert all("sdc_track_index" in sc.metadata and "source" in sc.metadata for sc in real)  # loader's kept
    # scenes without a type (older stores, in-memory sets) are labelled "womd"
    bare = make_scene(np.zeros((1, 3, 2), np.float32), np.zeros((1, 3)), scene_id="bare")
    assert "scenario_type" not in bare.metadata
    one = MixedSource([(SceneListSource([bare]), 1.0)])
    assert len(one) == 1 and one.get(0).metadata["scenario_type"] == "womd"


def test_generator_knobs_in_a_spec_and_in_a_mix():
    src = resolve_scenes("procedural:t_junction[parking=1,stop_lines=0.5,max_parked=4]", n=3, seed=7)
    assert src.params.parking == 1.0 and src.params.stop_lines == 0.5 and src.params.max_parked == 4
    sc = src.get(0)
    assert sc.metadata["params"]["parking"] == 1.0 and 0 < sc.metadata["num_parked"] <= 4
    assert sc.metadata["scenario_type"] == "t_junction" and sc.metadata["seed"] == 7
    plain = resolve_scenes("procedural:t_junction", n=3, seed=7)
    assert plain.params is None and plain.get(0).metadata["num_parked"] == 0
    # '=' inside the brackets is not a weight; a weight follows the closing bracket
    mix = resolve_scenes("mix:procedural:merge=3,procedural:all[parking=0.5,kerb_stops=0.5]", n=8)
    assert mix.weights == [0.75, 0.25] and mix.parts[1].params.kerb_stops == 0.5
    mix = resolve_scenes("mix:procedural:merge,procedural:all[parking=0.5]=3", n=8)
    assert mix.weights == [0.25, 0.75] and mix.parts[1].params.parking == 0.5


@pytest.mark.parametrize("spec, why", [
    ("procedural:all[parkng=0.5]", "unknown generator knob 'parkng'"),
    ("procedural:all[parking=lots]", "parking='lots' is not a valid value"),
    ("procedural:all[parking=2]", "must be in [0, 1]"),
    ("procedural:all[parking]", "is not key=value"),
    ("procedural:all[parking=0.5", "must end with ']'"),
    ("procedural:dense[parking=0.5]", "takes no generator knobs"),
    ("mix:procedural:merge=1,procedural:all[parkng=1]=2", "mix part 'procedural:all[parkng=1]=2'"),
])
def test_bad_generator_knobs_are_one_line_errors(spec, why):
    with pytest.raises(ValueError) as e:
        resolve_scenes(spec, n=4)
    assert why in str(e.value).splitlines()[0]


def test_path_with_equals_sign(tmp_path):
    d = tmp_path / "a=b"
    d.mkdir()
    shutil.copy(sorted(DATA.glob("*.json"))[0], d)
    mix = resolve_scenes(f"mix:{d},procedural:merge=3", n=4)
    assert [p.name for p in mix.parts] == [str(d), "procedural:merge"] and mix.weights == [0.25, 0.75]


@pytest.mark.parametrize("body, part, why", [
    ("", None, "empty mix"),
    (" ", None, "empty mix"),
    ("procedural:merge=1,,DATA", "''", "empty part"),
    ("procedural:merge=0,DATA", "'procedural:merge=0'", "positive"),
    ("procedural:merge=-2", "'procedural:merge=-2'", "positive"),
    ("procedural:merge=nan", "'procedural:merge=nan'", "positive"),
    ("procedural:merge=lots", "'procedural:merge=lots'", "not a number"),
    ("procedural:merge=", "'procedural:merge='", "empty weight"),
    ("=0.5,DATA", "'=0.5'", "empty scene spec"),
    ("procedural:spaghetti=1,DATA", "'procedural:spaghetti=1'", "unknown scenario type"),
    ("DATA=0.5,no/such/dir=0.5", "'no/such/dir=0.5'", "no such file"),
    ("mix:procedural:all=1", "'mix:procedural:all=1'", "another mix"),
])
def test_errors_are_one_line_and_name_the_part(body, part, why):
    spec = "mix:" + body.replace("DATA", str(DATA))
    with pytest.raises(ValueError) as e:
        resolve_scenes(spec, n=4)
    msg = str(e.value)
    assert "\n" not in msg and why in msg and repr(spec.strip()) in msg  # specs are read stripped
    if part is not None:
        assert f"mix part {part}" in msg


def test_simulator_from_a_mixed_batch():
    import torch

    from tg_gpudrive.config import EngineConfig
    from tg_gpudrive.rollout import EpisodeStats
    from tg_gpudrive.engine.simulator import Simulator

    mix = resolve_scenes(SPEC, n=4, seed=0)  # 3 merge + 1 real, one pass = 4 worlds
    scenes = SceneSampler(mix, 4, replacement=False, seed=0).sample()
    assert Counter(sc.metadata["scenario_type"] for sc in scenes) == {"merge": 3, "womd": 1}
    sim = Simulator(scenes, EngineConfig(max_agents=32, road_k=32, partner_k=8), "cpu")
    sim.reset()
    sim.step(torch.zeros((sim.num_worlds, sim.max_agents), dtype=torch.int32))
    assert sim.num_worlds == 4 and torch.isfinite(sim.reward).all()
    assert EpisodeStats(sim).type_names == ["merge", "womd"]
