"""Scene sources: one indexable interface over the generator, a packed store and raw files.

`resolve_scenes(spec)` turns a command-line / YAML string into a `SceneSource`
(``len(src)``, ``src.get(i) -> Scene``, ``src.name``) for the sampler. Accepted
specs (`SPEC_FORMS`):

    procedural:<type>      one generator type, scene i = generate_scene(type, seed + i)
    procedural:all         all six types, scene i = generate_scene(type i % 6, seed + i)
    <dir with manifest>    a packed store (`store.open_store`)
    <file>.json            one GPUDrive processed WOMD JSON
    <file> *tfrecord*      one raw WOMD TFRecord (all its scenes, read at resolve time)
    <dir>                  every *.json / *tfrecord* file under it, recursively

File sources are for quick looks: each JSON is parsed on first use (a small LRU
cache keeps recent ones); pack large sets with `store.convert` for training.
Loaders and the generator are imported lazily so this module imports alone.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Callable, Sequence

from tg_gpudrive.scene import Scene

DEFAULT_PROCEDURAL_SCENES = 10_000
SPEC_FORMS = (
    "procedural:<type> (type one of merge, dual_lane_intersection, t_junction, dense_intersection, "
    "roundabout, y_junction)",
    "procedural:all",
    "a packed store directory (holding manifest.json)",
    "a GPUDrive .json file",
    "a WOMD .tfrecord file (or a name containing 'tfrecord')",
    "a directory of such files",
)


def _spec_error(spec: str, why: str) -> ValueError:
    forms = "\n  ".join(SPEC_FORMS)
    return ValueError(f"scene spec {spec!r}: {why}; accepted forms:\n  {forms}")


class SceneSource:
    """Indexable scenes: `len(src)`, `src.get(i)` (also `src[i]`), `src.name`."""

    name: str = "scenes"

    def __len__(self) -> int:
        raise NotImplementedError

    def get(self, i: int) -> Scene:
        raise NotImplementedError

    def __getitem__(self, i: int) -> Scene:
        return self.get(i)

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

    # generated scenes are kept (about 50 kB each) so resampling does not generate them again
    cache_size = 20_000

    def _args(self, i: int) -> tuple:
        return self.types[i % len(self.types)], self.seed + i, self.params

    def get(self, i: int) -> Scene:
        from tg_gpudrive.data.procedural import generate_scene

        i = self._check(i)
        cache = self.__dict__.setdefault("_cache", OrderedDict())
        if i not in cache:
            cache[i] = generate_scene(*self._args(i))
            if len(cache) > self.cache_size:
                cache.popitem(last=False)
        return cache[i]

    def get_many(self, indices: Sequence[int]) -> list[Scene]:
        """Scenes for `indices`; missing ones are generated in worker processes when there are many."""
        import os

        cache = self.__dict__.setdefault("_cache", OrderedDict())
        missing = sorted({self._check(i) for i in indices} - set(cache))
        workers = min(os.cpu_count() or 1, 16)
        if len(missing) >= 64 and workers > 2:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: the parent may already hold a CUDA context
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                for i, sc in zip(missing, pool.map(_generate, [self._args(i) for i in missing], chunksize=16)):
                    cache[i] = sc
            while len(cache) > self.cache_size:
                cache.popitem(last=False)
        return [self.get(i) for i in indices]


def _generate(args: tuple) -> Scene:
    from tg_gpudrive.data.procedural import generate_scene

    return generate_scene(*args)


class StoreSource(SceneSource):
    """A packed store; scenes are read-only views of its memory-mapped arrays."""

    def __init__(self, path: str | Path, n: int | None = None):
        from tg_gpudrive.data.store import open_store

        self.store = open_store(path)
        self.n = len(self.store) if n is None else min(int(n), len(self.store))
        self.name = f"store:{Path(path)}"

    def __len__(self) -> int:
        return self.n

    def get(self, i: int) -> Scene:
        return self.store.get(self._check(i))


class FileSource(SceneSource):
    """GPUDrive JSON files (parsed on demand, LRU-cached) plus TFRecord scenes (read up front)."""

    def __init__(self, json_files: Sequence[Path], tfrecord_files: Sequence[Path], name: str,
                 n: int | None = None, cache_size: int = 256):
        from tg_gpudrive.data.store import load_file

        self._items: list[Path | Scene] = list(json_files)
        for f in tfrecord_files:
            if n is not None and len(self._items) >= n:
                break
            self._items.extend(load_file(f))
        if n is not None:
            self._items = self._items[: int(n)]
        self.name, self.cache_size = name, int(cache_size)
        self._cache: OrderedDict[int, Scene] = OrderedDict()
        self._load: Callable[[Path], list[Scene]] = load_file

    def __len__(self) -> int:
        return len(self._items)

    def get(self, i: int) -> Scene:
        i = self._check(i)
        item = self._items[i]
        if isinstance(item, Scene):
            return item
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        scene = self._load(item)[0]
        if self.cache_size > 0:
            self._cache[i] = scene
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return scene


def resolve_scenes(spec: str, *, n: int | None = None, seed: int = 0) -> SceneSource:
    """The `SceneSource` named by `spec` (see module docstring / `SPEC_FORMS`).

    `n` caps the number of scenes (procedural default: 10,000 distinct seeds);
    `seed` offsets the procedural seeds and is unused by file and store specs.
    Raises ValueError for an unknown spec or generator type, or a directory
    without scene files; StoreError / SceneError for a bad store or file.
    """
    spec = str(spec).strip()
    if n is not None and int(n) <= 0:
        raise ValueError(f"scene spec {spec!r}: n must be positive, got {n}")
    if spec.lower().startswith("procedural:"):
        kind = spec.split(":", 1)[1].strip().lower()
        try:
            from tg_gpudrive.data.procedural import SCENARIO_TYPES
        except ImportError as e:
            raise _spec_error(spec, f"the procedural generator is unavailable ({e})") from e
        if kind == "all":
            types = list(SCENARIO_TYPES)
        elif kind in SCENARIO_TYPES:
            types = [kind]
        else:
            raise _spec_error(spec, f"unknown scenario type {kind!r} (types: {', '.join(SCENARIO_TYPES)})")
        return ProceduralSource(types, DEFAULT_PROCEDURAL_SCENES if n is None else int(n), seed,
                                name=f"procedural:{kind}")

    from tg_gpudrive.data.store import _is_json, _is_tfrecord, expand_inputs, is_store

    path = Path(spec).expanduser()
    if is_store(path):
        return StoreSource(path, n)
    if path.is_file():
        if not (_is_json(path) or _is_tfrecord(path)):
            raise _spec_error(spec, "file is neither *.json nor a *tfrecord* file")
        files = [path.resolve()]
    elif path.is_dir():
        files = expand_inputs([path])
        if not files:
            raise _spec_error(spec, "directory holds no *.json or *tfrecord* files and no store manifest")
    else:
        raise _spec_error(spec, "not a procedural spec and no such file or directory")
    return FileSource([f for f in files if _is_json(f)], [f for f in files if _is_tfrecord(f)],
                      name=str(path), n=n)
