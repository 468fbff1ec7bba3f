"""Scene sources: one indexable interface over the generator, a packed store and raw files.

`resolve_scenes(spec)` turns a command-line / YAML string into a `SceneSource`
(``len(src)``, ``src.get(i) -> Scene``, ``src.name``) for the sampler. Accepted
specs (`SPEC_FORMS`):

    procedural:<type>      one generator type, scene i = generate_scene(type, seed + i)
    procedural:all         all six types, scene i = generate_scene(type i % 6, seed + i)
    procedural:dense       WOMD-size benchmark scenes, scene i = dense_scene(seed + i): 64-128 agents,
                           20-40 k road points (tiles of all six types, data/procedural/dense.py)
    procedural:<type or all>[key=value,...]
                           generator knobs (fields of `ProceduralParams`), e.g. urban streets with
                           parked cars and queues at stop lines: "procedural:all[parking=0.8,stop_lines=0.5]"
    <dir with manifest>    a packed store (`store.open_store`)
    <file>.json            one GPUDrive processed WOMD JSON
    <file> *tfrecord*      one raw WOMD TFRecord (all its scenes, read at resolve time)
    <file>.pkl             one ScenarioNet / MetaDrive scenario pickle (sd_*.pkl; read without
                           running pickled code, `womd.scenarionet`)
    <dir>                  every *.json / *tfrecord* / sd_*.pkl file under it, recursively (a
                           ScenarioNet directory's dataset_summary.pkl / dataset_mapping.pkl are skipped)
    mix:<spec>=<w>,...     worlds filled from several of the above in proportion to the
                           weights (`MixedSource`), e.g. "mix:procedural:all=0.7,tests/data=0.3"

File sources are for quick looks: each JSON or pickle is parsed on first use (a small LRU
cache keeps recent ones); pack large sets with `store.convert` for training.
Opening a source validates what it can cheaply (a directory's scenes are checked when it opens).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import multiprocessing
import os
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import yaml
from tqdm import tqdm

from tg_gpudrive.config import ConfigError, coerce_field
from tg_gpudrive.data.procedural import SCENARIO_TYPES, ProceduralParams, generate_scene
from tg_gpudrive.data.log_audit import ENGINE_DEFAULTS, infeasible_mask, too_short, unplayable
from tg_gpudrive.data.procedural.dense import dense_scene
from tg_gpudrive.data.store import (_is_json, _is_scenarionet, _is_tfrecord, expand_inputs, is_store, load_file,
                                    open_store)
from tg_gpudrive.scene import Scene

log = logging.getLogger(__name__)

DEFAULT_PROCEDURAL_SCENES = 10_000
SPEC_FORMS = (
    "procedural:<type> (type one of merge, dual_lane_intersection, t_junction, dense_intersection, "
    "roundabout, y_junction)",
    "procedural:all",
    "procedural:<type or all>[<ProceduralParams field>=<value>,...], e.g. procedural:all[parking=0.8,stop_lines=0.5]",
    "a packed store directory (holding manifest.json)",
    "a GPUDrive .json file",
    "a WOMD .tfrecord file (or a name containing 'tfrecord')",
    "a ScenarioNet / MetaDrive scenario pickle (sd_*.pkl)",
    "a directory of such files",
    "mix:<spec>=<weight>,<spec>=<weight>,... (any of the above; a weight may be omitted for 1)",
)


def _spec_error(spec: str, why: str) -> ValueError:
    forms = "\n  ".join(SPEC_FORMS)
    err = ValueError(f"scene spec {spec!r}: {why}; accepted forms:\n  {forms}")
    err.why = why  # the reason alone, for one-line messages about a part of a mix: spec
    return err


class SceneSource:
    """Indexable scenes: `len(src)`, `src.get(i)` (also `src[i]`), `src.name`."""

    name: str = "scenes"

    def __len__(self) -> int:
        raise NotImplementedError

    def get(self, i: int) -> Scene:
        raise NotImplementedError

    def __getitem__(self, i: int) -> Scene:
        return self.get(i)

    # scenes kept by `_cached` (the least recently used dropped first; 0: none kept)
    cache_size = 20_000

    def _cached(self, i: int, make: Callable[[int], Scene]) -> Scene:
        """Scene i from the source's cache, made by `make(i)` when missing. One object per scene: a
        batch that repeats a scene holds it once, and the Model builder does its work once."""
        cache = self.__dict__.setdefault("_cache", OrderedDict())
        if i in cache:
            cache.move_to_end(i)
            return cache[i]
        scene = make(i)
        if self.cache_size > 0:
            cache[i] = scene
            if len(cache) > self.cache_size:
                cache.popitem(last=False)
        return scene

    def _check(self, i: int) -> int:
        n = len(self)
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"{self.name}: scene index {i} out of range [0, {n})")
        return i

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, len={len(self)})"


class SceneListSource(SceneSource):
    """Scenes already in memory (tests, small sets)."""

    def __init__(self, scenes: Sequence[Scene], name: str = "memory"):
        self.scenes, self.name = list(scenes), name

    def __len__(self) -> int:
        return len(self.scenes)

    def get(self, i: int) -> Scene:
        return self.scenes[self._check(i)]


class ProceduralSource(SceneSource):
    """Generated scenes: scene i is ``generate_scene(types[i % k], seed + i, params)``.

    Same order as ``procedural.generate_scenes`` ("all" cycles the types), so a
    store written from `generate_scenes(kind, n, seed)` holds the same scenes.
    `params` is a `procedural.ProceduralParams` (None: defaults).
    """

    def __init__(self, types: Sequence[str], n: int = DEFAULT_PROCEDURAL_SCENES, seed: int = 0,
                 params=None, name: str | None = None):
        if n <= 0:
            raise ValueError(f"procedural source needs n > 0, got {n}")
        self.types, self.n, self.seed, self.params = list(types), int(n), int(seed), params
        self.name = name or f"procedural:{'+'.join(self.types)}"

    def __len__(self) -> int:
        return self.n

    # generated scenes are kept (about 50 kB each, `cache_size`) so resampling does not generate them again
    def _args(self, i: int) -> tuple:
        return self.types[i % len(self.types)], self.seed + i, self.params

    def get(self, i: int) -> Scene:
        return self._cached(self._check(i), lambda j: _generate(self._args(j)))

    def get_many(self, indices: Sequence[int]) -> list[Scene]:
        """Scenes for `indices`; missing ones are generated in worker processes when there are many."""
        cache = self.__dict__.setdefault("_cache", OrderedDict())
        missing = sorted({self._check(i) for i in indices} - set(cache))
        workers = min(os.cpu_count() or 1, 16)
        if len(missing) >= 64 and workers > 2:
            # spawn, not fork: the parent may already hold a CUDA context
            try:
                with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                    for i, sc in zip(missing, pool.map(_generate, [self._args(i) for i in missing], chunksize=16)):
                        cache[i] = sc
            except BrokenProcessPool:
                raise RuntimeError(
                    f"{self.name}: the worker processes that generate its scenes died. They start with 'spawn', "
                    "which imports the main script again in each of them: a script that builds scenes (a "
                    "Trainer, a Simulator, resolve_scenes) at its top level needs that code under "
                    "`if __name__ == \"__main__\":`") from None
            while len(cache) > self.cache_size:
                cache.popitem(last=False)
        return [self.get(i) for i in indices]


def _generate(args: tuple) -> Scene:
    kind, seed, params = args
    scene = dense_scene(seed) if kind == "dense" else generate_scene(kind, seed, params)
    # the control rule's audit with the engine's defaults, here where get_many runs it in parallel
    infeasible_mask(scene, ENGINE_DEFAULTS.init_steps, ENGINE_DEFAULTS.goal_radius)
    return scene


class StoreSource(SceneSource):
    """A packed store; scenes are read-only views of its memory-mapped arrays, the same Scene
    object each time a scene is asked for again (while it is among the last `cache_size`)."""

    def __init__(self, path: str | Path, n: int | None = None):
        self.store = open_store(path)
        self.name = f"store:{Path(path)}"
        # the scenes `convert` found unplayable, and any too short (a store written by `write_store`)
        steps = self.store.num_steps
        why = dict(self.store.unplayable)
        for i, t in enumerate(steps.tolist()):
            if i not in why and too_short(t):
                why[i] = too_short(t)
        short = np.zeros(len(steps), bool)
        short[list(why)] = True
        self._index = np.nonzero(~short)[0]
        self.unplayable = [(self.name, self.store.scene_ids[i], w) for i, w in sorted(why.items())]
        if self.unplayable:
            log.warning("%s: %d scene(s) that cannot be played are skipped (first: %s: %s)", self.name,
                        len(self.unplayable), *self.unplayable[0][1:])
        if short.all() and len(short):
            raise ValueError(f"scene spec {str(path)!r}: no scene of the store can be played")
        self.n = len(self._index) if n is None else min(int(n), len(self._index))

    def __len__(self) -> int:
        return self.n

    def get(self, i: int) -> Scene:
        return self._cached(self._check(i), lambda j: self.store.get(int(self._index[j])))


class FileSource(SceneSource):
    """One-scene files (GPUDrive JSON, ScenarioNet pickles) plus TFRecord scenes, every file checked
    when the source opens.

    A file that does not load (bad JSON, a bad field, a refused or truncated pickle, a truncated or
    CRC-broken TFRecord) is skipped with a warning and listed in `skipped` ((path, reason) pairs), so
    a training run that resamples never meets it mid-way; opening fails only when no scene is left.
    One-scene files (`json_files`: *.json and *.pkl) are parsed again on demand (LRU-cached) rather
    than all held in memory; TFRecord scenes are kept.
    For thousands of files, pack them into a store once (`tg-gpudrive convert`)."""

    def __init__(self, json_files: Sequence[Path], tfrecord_files: Sequence[Path], name: str,
                 n: int | None = None, cache_size: int = 256):
        self.name, self.cache_size = name, int(cache_size)
        self._cache: OrderedDict[int, Scene] = OrderedDict()
        self._load: Callable[[Path], list[Scene]] = load_file
        self._items: list[Path | Scene] = []
        self.skipped: list[tuple[str, str]] = []
        self.unplayable: list[tuple[str, str, str]] = []  # (file, scene id, reason) of the scenes left out
        files = [(f, True) for f in json_files] + [(f, False) for f in tfrecord_files]
        bar = None
        if len(files) > 64:
            bar = tqdm(total=len(files), desc=f"checking {name}", unit="file", leave=False)
        for f, one_scene in files:
            if n is not None and len(self._items) >= n:
                break
            try:
                scenes = load_file(f)
            except Exception as e:  # noqa: BLE001 - any unreadable file is skipped and counted
                reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                self.skipped.append((str(f), f"{type(e).__name__}: {reason}"))
                log.warning("%s: skipped, it does not load (%s: %s)", f, type(e).__name__, reason)
                scenes = []
            scenes = self._playable(f, scenes)
            if one_scene and scenes:
                self._items.append(f)
                if len(self._cache) < self.cache_size:
                    self._cache[len(self._items) - 1] = scenes[0]
            else:
                self._items.extend(scenes)
            if bar is not None:
                bar.update(1)
        if bar is not None:
            bar.close()
        if n is not None:
            self._items = self._items[: int(n)]
        if not self._items:
            first = (f"; first: {self.skipped[0][0]}: {self.skipped[0][1]}" if self.skipped else
                     f"; first: {self.unplayable[0][0]} (scene {self.unplayable[0][1]}): {self.unplayable[0][2]}"
                     if self.unplayable else "")
            raise ValueError(f"scene spec {name!r}: no scene loads ({len(self.skipped)} file(s) skipped, "
                             f"{len(self.unplayable)} scene(s) unplayable{first})")
        if self.skipped:
            log.warning("%s: %d of %d file(s) skipped because they do not load", name, len(self.skipped), len(files))
        if self.unplayable:
            log.warning("%s: %d scene(s) skipped because they cannot be played (first: %s, scene %s: %s)", name,
                        len(self.unplayable), *self.unplayable[0])

    def _playable(self, path: Path, scenes: list[Scene]) -> list[Scene]:
        keep = []
        for sc in scenes:
            why = unplayable(sc)
            if why is None:
                keep.append(sc)
            else:
                self.unplayable.append((str(path), sc.scene_id, why))
        return keep

    def __len__(self) -> int:
        return len(self._items)

    def get(self, i: int) -> Scene:
        i = self._check(i)
        item = self._items[i]
        if isinstance(item, Scene):
            return item
        return self._cached(i, lambda j: self._load(self._items[j])[0])


def source_report(src: SceneSource) -> dict:
    """What opening `src` (and the parts of a mix) left out: files that do not load and scenes that
    cannot be played (`data.log_audit.unplayable`), as counts for the commands' JSON reports."""
    while hasattr(src, "source"):  # a wrapper such as a rank's shard
        src = src.source
    parts = getattr(src, "parts", [src])
    return {"scene_files_skipped": sum(len(getattr(p, "skipped", ())) for p in parts),
            "scenes_unplayable": sum(len(getattr(p, "unplayable", ())) for p in parts)}



class MixedSource(SceneSource):
    """Several sources behind one index space, so uniform index draws mix them by weight.

    `parts` are (source, weight) pairs (weights > 0, normalised here); `counts[k]` (default
    ``len(source)``, at most that) is how many distinct scenes part k contributes: its scenes
    ``0 .. counts[k] - 1``.

    Index layout: ``len(mix)`` is the size V of a *virtual* index space. Part k owns
    ``slots[k]`` of the V indices, proportional to its normalised weight (to whole slots, so
    within 1/V) and never fewer than ``counts[k]``; slot j of part k maps to its scene
    ``j % counts[k]``, so a small real set is repeated to fill its share. The slots of all parts
    are interleaved evenly (slot j of part k sits at (j + 0.5) / slots[k] of the way through
    [0, V), ties to the earlier part), so any prefix ``range(m)`` is mixed in nearly the same
    proportions too. What it is for: a sampler that draws indices uniformly (`SceneSampler`,
    `ShardSource`) then fills worlds in the requested proportions: exactly per pass over the V
    indices without replacement, in expectation with replacement; readers that take the first
    m indices (evaluation, benchmark) get a mix rather than only the first part.

    What it must not do: be taken for V distinct scenes (``num_distinct`` is that; a sampler's
    ``visited`` counts slots, so every repeat of a small set counts); depend on anything but
    (parts, weights, counts), with no shuffling or randomness of its own: a sampler's resume
    state records only V and its position, so the same spec, n and seed must map each index to
    the same scene after a restart (shuffling is the sampler's job); materialise scenes up front.

    Every scene handed out has ``metadata["scenario_type"]`` (per-type episode rates group on
    it): scenes without one get `default_type` ("womd": real scenes; the loaders set it
    already), set on the scene's own metadata dict.
    """

    def __init__(self, parts: Sequence[tuple[SceneSource, float]], counts: Sequence[int] | None = None,
                 name: str | None = None, default_type: str = "womd"):
        if not parts:
            raise ValueError("a scene mix needs at least one part")
        self.parts = [src for src, _ in parts]
        raw = [float(w) for _, w in parts]
        if not all(math.isfinite(w) and w > 0 for w in raw):
            raise ValueError(f"scene mix weights must be positive numbers, got {raw}")
        total = sum(raw)
        self.weights = [w / total for w in raw]
        counts = [len(src) for src in self.parts] if counts is None else [int(c) for c in counts]
        if len(counts) != len(self.parts):
            raise ValueError(f"scene mix: {len(counts)} counts for {len(self.parts)} parts")
        for src, c in zip(self.parts, counts):
            if not 1 <= c <= len(src):
                raise ValueError(f"scene mix part {src.name!r}: count {c} outside [1, {len(src)}]")
        self.counts = counts
        self.default_type = default_type
        self.slots = self._slots(self.weights, counts)
        # (V,) part of each virtual index and the part's scene it maps to
        part = np.concatenate([np.full(c, k, np.int64) for k, c in enumerate(self.slots)])
        j = np.concatenate([np.arange(c, dtype=np.int64) for c in self.slots])
        where = np.concatenate([(np.arange(c) + 0.5) / c for c in self.slots])
        order = np.lexsort((part, where))
        self._part = part[order]
        self._local = j[order] % np.asarray(counts, np.int64)[self._part]
        self.name = name or "mix:" + ",".join(f"{s.name}={w:.4g}" for s, w in zip(self.parts, self.weights))

    @staticmethod
    def _slots(weights: Sequence[float], counts: Sequence[int]) -> list[int]:
        """Whole slots per part: proportional to `weights` (largest remainder), each >= its count.

        V is the smallest size that holds every count, or a slightly larger one (up to 2x, at
        most 2,000 more) whose shares match the weights better: exactly when the weights allow
        (0.75 / 0.25 over 2 real and 38 procedural scenes: V = 52, not 51)."""
        def at(v: int) -> tuple[float, list[int]]:
            exact = [v * w for w in weights]
            slots = [max(c, math.floor(x + 1e-9)) for c, x in zip(counts, exact)]
            rest = v - sum(slots)
            for k in sorted(range(len(slots)), key=lambda k: (slots[k] - exact[k], k))[:max(rest, 0)]:
                slots[k] += 1
            return max(abs(s / sum(slots) - w) for s, w in zip(slots, weights)), slots

        v0 = max(math.ceil(c / w - 1e-9) for c, w in zip(counts, weights))
        best = at(v0)
        for v in range(v0 + 1, v0 + min(v0, 2000) + 1):
            if best[0] < 1e-9:
                break
            cand = at(v)
            if cand[0] < best[0] - 1e-12:
                best = cand
        return best[1]

    @property
    def num_distinct(self) -> int:
        """Distinct scenes behind the V indices (sum of the parts' counts)."""
        return sum(self.counts)

    def __len__(self) -> int:
        return len(self._part)

    def locate(self, i: int) -> tuple[int, int]:
        """(part number, scene index within that part) of virtual index `i`."""
        i = self._check(i)
        return int(self._part[i]), int(self._local[i])

    def _label(self, scene: Scene) -> Scene:
        if "scenario_type" not in scene.metadata:
            scene.metadata["scenario_type"] = self.default_type
        return scene

    def get(self, i: int) -> Scene:
        k, j = self.locate(i)
        return self._label(self.parts[k].get(j))

    def get_many(self, indices: Sequence[int]) -> list[Scene]:
        """Scenes for `indices`, fetched part by part (through the part's `get_many` when it has one)."""
        where = [self.locate(i) for i in indices]
        out: list[Scene | None] = [None] * len(where)
        for k, src in enumerate(self.parts):
            pos = [p for p, (kk, _) in enumerate(where) if kk == k]
            if not pos:
                continue
            local = [where[p][1] for p in pos]
            got = src.get_many(local) if hasattr(src, "get_many") else [src.get(j) for j in local]
            for p, sc in zip(pos, got):
                out[p] = self._label(sc)
        return out

    def describe(self) -> list[str]:
        """One line per part: weight, distinct scenes, share of the index space."""
        v = len(self)
        return [f"{src.name}: weight {w:.3g}, {c} distinct scene(s) of {len(src)}, {s}/{v} index slots "
                f"({s / v:.1%})" for src, w, c, s in zip(self.parts, self.weights, self.counts, self.slots)]


def _split_top(text: str) -> list[str]:
    """`text` split on commas outside brackets and quotes."""
    parts, depth, quote, cur = [], 0, "", []
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "([{":
            depth += 1
        elif ch in ")]}":
            depth = max(depth - 1, 0)
        elif ch == "," and depth == 0:
            parts.append("".join(cur))
            cur = []
            continue
        cur.append(ch)
    parts.append("".join(cur))
    return parts


def _mix_part(part: str, spec: str) -> tuple[str, float]:
    """(sub-spec, weight) of one `spec=weight` part; the weight is the text after the last '='."""
    def bad(why: str) -> ValueError:
        return ValueError(f"scene spec {spec!r}: mix part {part!r}: {why}")

    text, weight = part.strip(), 1.0
    if not text:
        raise bad("empty part")
    if "=" in text.rpartition("]")[2]:  # '=' inside a procedural spec's [knobs] is not a weight
        head, tail = text.rsplit("=", 1)
        try:
            w = float(tail)
        except ValueError:
            w = None
        if w is not None:
            if not (math.isfinite(w) and w > 0):
                raise bad(f"weight {tail.strip()!r} must be a positive number")
            text, weight = head.strip(), w
        elif not Path(text).expanduser().exists():  # a path may hold '=' (then the weight is 1)
            raise bad(f"weight {tail.strip()!r} is not a number" if tail.strip() else "empty weight")
    text = text.strip().strip("'\"").strip()
    if not text:
        raise bad("empty scene spec")
    if text.lower().startswith("mix:"):
        raise bad("a mix cannot hold another mix")
    return text, weight


def _allocate(n: int, weights: Sequence[float], caps: Sequence[int | None]) -> list[int]:
    """Split `n` scenes over parts by weight: a part with a cap gets at most that and the rest goes
    to the others (largest remainder); every part gets at least one."""
    counts, active, left = [0] * len(weights), list(range(len(weights))), n
    while active:
        tw = sum(weights[k] for k in active)
        full = [k for k in active if caps[k] is not None and caps[k] <= left * weights[k] / tw]
        if not full:
            break
        for k in full:
            counts[k] = caps[k]
            left -= caps[k]
        active = [k for k in active if k not in full]
    if active and left > 0:
        tw = sum(weights[k] for k in active)
        exact = {k: left * weights[k] / tw for k in active}
        for k in active:
            counts[k] = math.floor(exact[k])
        for k in sorted(active, key=lambda k: (counts[k] - exact[k], k))[:left - sum(counts[k] for k in active)]:
            counts[k] += 1
    for k in range(len(counts)):
        if counts[k] == 0:  # a part too light for a whole scene still gets one, from the largest
            big = max(range(len(counts)), key=lambda i: counts[i])
            if counts[big] > 1:
                counts[big] -= 1
            counts[k] = 1
    return counts


def _resolve_mix(spec: str, body: str, n: int | None, seed: int) -> MixedSource:
    if not body.strip():
        raise ValueError(f"scene spec {spec!r}: empty mix (expected mix:<spec>=<weight>,...)")
    parsed = [_mix_part(p, spec) for p in _split_top(body)]
    sources = []
    for part, (sub, _) in zip(_split_top(body), parsed):
        try:
            sources.append(resolve_scenes(sub, n=n, seed=seed))
        except ValueError as e:  # StoreError and SceneError are ValueErrors too
            why = getattr(e, "why", None) or str(e).splitlines()[0]
            raise ValueError(f"scene spec {spec!r}: mix part {part.strip()!r}: {why}") from None
    total = sum(w for _, w in parsed)
    weights = [w / total for _, w in parsed]
    procedural = [isinstance(s, ProceduralSource) for s in sources]
    if n is None:
        counts = [len(s) for s in sources]
    else:
        counts = _allocate(int(n), weights, [None if p else len(s) for s, p in zip(sources, procedural)])
        for (sub, _), s, w, c, p in zip(parsed, sources, weights, counts, procedural):
            want = round(int(n) * w)
            if not p and c < want:
                log.warning("scene mix: %r has %d scene(s) for its share of %d (of num_scenes=%d); the "
                            "other parts contribute the rest, and its scenes repeat to keep weight %.3g",
                            sub, c, want, int(n), w)
        if sum(counts) != int(n):
            log.warning("scene mix %r: %d distinct scenes in all for num_scenes=%d", spec, sum(counts), int(n))
    offset = 0  # procedural parts take consecutive seed ranges, so no two parts share a seed
    for k, (s, p) in enumerate(zip(sources, procedural)):
        if p:
            sources[k] = ProceduralSource(s.types, counts[k], seed + offset, s.params, name=s.name)
            offset += counts[k]
    mix = MixedSource(list(zip(sources, weights)), counts)
    for line in mix.describe():
        log.info("scene mix: %s", line)
    return mix


def _procedural_params(spec: str, kind: str) -> tuple[str, ProceduralParams | None]:
    """("all", ProceduralParams(parking=0.8)) from "all[parking=0.8]"; (kind, None) without brackets.
    An unknown field or a bad value is a one-line ValueError naming it."""
    if "[" not in kind:
        return kind, None
    head, _, body = kind.partition("[")
    if not body.endswith("]"):
        raise _spec_error(spec, "generator knobs must end with ']'")
    fields = [f.name for f in dataclasses.fields(ProceduralParams)]
    values = {}
    for item in _split_top(body[:-1]):
        key, eq, text = (x.strip() for x in item.partition("="))
        if not key or not eq:
            raise _spec_error(spec, f"generator knob {item.strip()!r} is not key=value")
        if key not in fields:
            raise _spec_error(spec, f"unknown generator knob {key!r} (knobs: {', '.join(fields)})")
        try:  # a value as a config file or --set reads it
            values[key] = coerce_field(ProceduralParams, key, yaml.safe_load(text), spec)
        except (ConfigError, yaml.YAMLError) as e:
            why = str(e).rpartition(": ")[2] if isinstance(e, ConfigError) else "not YAML"
            raise _spec_error(spec, f"generator knob {key}={text!r} is not a valid value ({why})") from None
    if head.strip().lower() == "dense":
        raise _spec_error(spec, "procedural:dense takes no generator knobs")
    try:
        return head.strip(), ProceduralParams(**values)
    except ValueError as e:
        raise _spec_error(spec, str(e)) from None


def resolve_scenes(spec: str, *, n: int | None = None, seed: int = 0) -> SceneSource:
    """The `SceneSource` named by `spec` (see module docstring / `SPEC_FORMS`).

    `n` caps the number of scenes (procedural default: 10,000 distinct seeds);
    `seed` offsets the procedural seeds and is unused by file and store specs.
    For ``mix:`` specs `n` caps the distinct scenes of all parts together: each part gets
    about n * weight, a file or store part at most what it holds (the rest goes to the
    others), and `len()` is the size of the virtual index space (`MixedSource`); a bad
    part, weight or empty mix is a one-line ValueError naming the part.
    Raises ValueError for an unknown spec or generator type, or a directory
    without scene files; StoreError / SceneError for a bad store or file.
    """
    spec = str(spec).strip()
    if not spec:  # Path("") is the working directory: never read it by accident
        raise ValueError("scene spec is empty: give procedural:<type>, a store, a folder or a scene file")
    if n is not None and int(n) <= 0:
        raise ValueError(f"scene spec {spec!r}: n must be positive, got {n}")
    if spec.lower().startswith("mix:"):
        return _resolve_mix(spec, spec[4:], n, seed)
    if spec.lower().startswith("procedural:"):
        kind = spec.split(":", 1)[1].strip()
        kind, params = _procedural_params(spec, kind)
        kind = kind.lower()
        if kind == "dense":  # WOMD-size benchmark scenes (data/procedural/dense.py), not a paper type
            return ProceduralSource(["dense"], DEFAULT_PROCEDURAL_SCENES if n is None else int(n), seed,
                                    name="procedural:dense")
        if kind == "all":
            types = list(SCENARIO_TYPES)
        elif kind in SCENARIO_TYPES:
            types = [kind]
        else:
            raise _spec_error(spec, f"unknown scenario type {kind!r} (types: {', '.join(SCENARIO_TYPES)}, all, dense)")
        return ProceduralSource(types, DEFAULT_PROCEDURAL_SCENES if n is None else int(n), seed, params,
                                name=spec if params is not None else f"procedural:{kind}")

    path = Path(spec).expanduser()
    if is_store(path):
        return StoreSource(path, n)
    if path.is_file():
        if not (_is_json(path) or _is_tfrecord(path) or _is_scenarionet(path)):
            raise _spec_error(spec, "file is neither *.json, a *tfrecord* file nor a ScenarioNet *.pkl")
        files = [path.resolve()]
    elif path.is_dir():
        files = expand_inputs([path])
        if not files:
            raise _spec_error(spec, "directory holds no *.json, *tfrecord* or sd_*.pkl files and no store "
                                    "manifest")
    else:
        raise _spec_error(spec, "not a procedural spec and no such file or directory")
    return FileSource([f for f in files if _is_json(f) or _is_scenarionet(f)], [f for f in files if _is_tfrecord(f)],
                      name=str(path), n=n)
