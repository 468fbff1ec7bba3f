"""Scene sampler (determinism, coverage, resume) and `resolve_scenes` specs."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from tg_gpudrive.data.sampler import SceneSampler
from tg_gpudrive.data.sources import SceneListSource, resolve_scenes
from tg_gpudrive.data.store import write_store
from tg_gpudrive.scene import make_scene

DATA = Path(__file__).parent / "data"
HAVE_PROCEDURAL = importlib.util.find_spec("tg_gpudrive.data.procedural") is not None
HAVE_JSON_LOADER = importlib.util.find_spec("tg_gpudrive.data.womd.gpudrive_json") is not None


class CountSource:
    """Index-only source of `n` scenes (sampler tests never materialise these)."""

    def __init__(self, n: int):
        self.n, self.name = n, f"count{n}"

    def __len__(self):
        return self.n

    def get(self, i):
        return i


def tiny(k: int):
    """One car driving 20 m along x from (k, k): the shortest scene a source plays (init step 10 + 10)."""
    pos = np.stack([np.arange(21.0) + k, np.full(21, float(k))], -1)[None].astype(np.float32)
    return make_scene(pos, np.zeros((1, 21)), scene_id=f"s{k}")


# ------------------------------------------------------------------ sampler
@pytest.mark.parametrize("replacement", [False, True])
def test_deterministic_per_seed(replacement):
    a = SceneSampler(CountSource(50), 7, replacement=replacement, seed=3)
    b = SceneSampler(CountSource(50), 7, replacement=replacement, seed=3)
    c = SceneSampler(CountSource(50), 7, replacement=replacement, seed=4)
    xs = [a.sample_indices() for _ in range(10)]
    ys = [b.sample_indices() for _ in range(10)]
    zs = [c.sample_indices() for _ in range(10)]
    assert all(np.array_equal(x, y) for x, y in zip(xs, ys))
    assert not all(np.array_equal(x, z) for x, z in zip(xs, zs))
    assert np.array_equal(SceneSampler(CountSource(50), 7, replacement=replacement, seed=3).sample_indices(), xs[0])


@pytest.mark.parametrize("w", [4096, 1000, 3])
def test_without_replacement_covers_all(w):
    n = 10_000 if w != 3 else 10
    s = SceneSampler(CountSource(n), w, replacement=False, seed=0)
    draws = math.ceil(n / w)
    idx = np.concatenate([s.sample_indices() for _ in range(draws)])
    assert s.visited == n and s.draws == draws
    # the first n picks are a permutation: nothing repeats before everything was seen
    assert np.array_equal(np.sort(idx[:n]), np.arange(n))
    assert s.epoch == (draws * w) // n


def test_more_worlds_than_scenes():
    s = SceneSampler(CountSource(5), 12, replacement=False, seed=1)
    idx = s.sample_indices()
    assert len(idx) == 12 and s.visited == 5
    for e in range(2):
        assert sorted(idx[5 * e : 5 * e + 5]) == list(range(5))


def test_with_replacement_in_range():
    s = SceneSampler(CountSource(37), 500, replacement=True, seed=9)
    for _ in range(5):
        idx = s.sample_indices()
        assert idx.shape == (500,) and idx.dtype == np.int64
        assert idx.min() >= 0 and idx.max() < 37
    assert s.visited == 37


@pytest.mark.parametrize("replacement", [False, True])
def test_state_dict_resumes_exactly(replacement):
    a = SceneSampler(CountSource(23), 5, replacement=replacement, seed=11)
    for _ in range(7):
        a.sample_indices()
    state = json.loads(json.dumps(a.state_dict()))  # plain Python: survives JSON
    expected = [a.sample_indices() for _ in range(8)]
    b = SceneSampler(CountSource(23), 5, replacement=replacement, seed=0)
    b.load_state_dict(state)
    assert b.draws == 7
    got = [b.sample_indices() for _ in range(8)]
    assert all(np.array_equal(x, y) for x, y in zip(expected, got))
    assert b.visited == a.visited
    with pytest.raises(ValueError, match="23 scenes"):
        SceneSampler(CountSource(24), 5, replacement=replacement, seed=11).load_state_dict(state)
    with pytest.raises(ValueError, match="replacement"):
        SceneSampler(CountSource(23), 5, replacement=not replacement, seed=11).load_state_dict(state)


def test_sample_materialises_scenes():
    src = SceneListSource([tiny(k) for k in range(4)])
    s = SceneSampler(src, 6, replacement=False, seed=0)
    scenes = s.sample()
    assert [sc.scene_id for sc in scenes] == [f"s{i}" for i in s.last_indices]


def test_should_resample():
    assert [SceneSampler.should_resample(k, 3) for k in range(7)] == [False, False, False, True, False, False, True]
    assert not SceneSampler.should_resample(5, 0)


def test_bad_sampler_args():
    with pytest.raises(ValueError, match="empty"):
        SceneSampler(CountSource(0), 4, replacement=False, seed=0)
    with pytest.raises(ValueError, match="num_worlds"):
        SceneSampler(CountSource(3), 0, replacement=False, seed=0)


# ------------------------------------------------------------------ sources
def test_resolve_store(tmp_path):
    write_store([tiny(k) for k in range(5)], tmp_path / "st")
    src = resolve_scenes(str(tmp_path / "st"))
    assert len(src) == 5 and src.get(3).scene_id == "s3" and "st" in src.name
    assert len(resolve_scenes(str(tmp_path / "st"), n=2)) == 2
    with pytest.raises(IndexError):
        src.get(5)
    s = SceneSampler(src, 5, replacement=False, seed=0)
    assert sorted(sc.scene_id for sc in s.sample()) == [f"s{k}" for k in range(5)]


def test_resolve_bad_specs(tmp_path):
    with pytest.raises(ValueError, match="accepted forms"):
        resolve_scenes(str(tmp_path / "nothing_here"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no .*json"):
        resolve_scenes(str(tmp_path / "empty"))
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(ValueError, match="neither"):
        resolve_scenes(str(tmp_path / "x.txt"))
    with pytest.raises(ValueError, match="procedural:"):
        resolve_scenes("procedural:spaghetti_junction")


@pytest.mark.skipif(not HAVE_PROCEDURAL, reason="tg_gpudrive.data.procedural not written yet")
def test_resolve_procedural():
    from tg_gpudrive.data.procedural import SCENARIO_TYPES

    one = resolve_scenes("procedural:merge", n=5, seed=2)
    assert len(one) == 5 and one.name == "procedural:merge"
    assert one.get(1).num_agents > 0
    allsrc = resolve_scenes("procedural:all", seed=0)
    assert len(allsrc) == 10_000 and len(SCENARIO_TYPES) == 6
    a, b = allsrc.get(7), allsrc.get(7)
    np.testing.assert_array_equal(a.log_pos, b.log_pos)


@pytest.mark.skipif(not HAVE_JSON_LOADER, reason="tg_gpudrive.data.womd.gpudrive_json not written yet")
def test_resolve_json_file_and_dir():
    files = sorted(DATA.glob("*.json"))
    one = resolve_scenes(str(files[0]))
    assert len(one) == 1 and one.get(0).num_agents > 0
    both = resolve_scenes(str(DATA))
    assert len(both) == len(files)
    assert both.get(1) is both.get(1)  # cached


@pytest.mark.skipif(importlib.util.find_spec("tg_gpudrive.data.womd.scenario_proto") is None,
                    reason="tg_gpudrive.data.womd.scenario_proto not written yet")
def test_resolve_tfrecord(tmp_path):
    from tg_gpudrive.data.womd.scenario_proto import write_tfrecord_scenes

    f = tmp_path / "validation.tfrecord-00000-of-00001"
    write_tfrecord_scenes(f, [tiny(k) for k in range(3)])
    src = resolve_scenes(str(f))
    assert len(src) == 3 and [src.get(i).scene_id for i in range(3)] == ["s0", "s1", "s2"]
    assert len(resolve_scenes(str(tmp_path), n=2)) == 2
