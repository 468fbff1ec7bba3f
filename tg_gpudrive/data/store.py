"""Packed scene store: many `Scene`s in one directory of memory-mappable `.npy` files.

Why: parsing one WOMD JSON takes tens of milliseconds, so 10k scenes would take
minutes to load; a packed store opens in milliseconds and hands out any scene
as views of memory-mapped arrays, touching only that scene's pages.

Layout (format version 1)::

    <store>/
      manifest.json           format, version, shard list, inputs already converted
      failed.txt              bad inputs of the last `convert` run: "path<TAB>reason"
      shard_00000/            one shard per ~`shard_size` scenes (cut at input-file boundaries)
        index.npy             (S + 1, 8)   int64    per-scene start offsets into each segment
        num_steps.npy         (S,)         int64    T of each scene
        origin.npy            (S, 2)       float64  m, Scene.origin
        dt.npy                (S,)         float64  s, Scene.dt
        scenes.json           scene_ids, sources (input file of each scene), metadata
        <field>.npy           every Scene array field, concatenated over the shard's scenes

Scene fields are concatenated along their leading axis and indexed by one of
eight segments (columns of ``index.npy``; scene j of a shard owns rows
``index[j, c]:index[j + 1, c]`` of every field in segment c). Scenes may differ
in T, so per-step fields are stored flattened to one row per (agent, step) and
reshaped on access:

    field          stored shape     dtype    segment
    log_pos        (sum N*T, 2)     float32  agent_step
    log_yaw        (sum N*T,)       float32  agent_step
    log_vel        (sum N*T, 2)     float32  agent_step
    log_valid      (sum N*T,)       bool     agent_step
    length         (sum N,)         float32  agent       (also width, height)
    agent_type     (sum N,)         int8     agent
    agent_id       (sum N,)         int64    agent
    goal           (sum N, 2)       float32  agent
    is_sdc         (sum N,)         bool     agent       (also is_interest)
    road_points    (sum P, 2)       float32  point
    road_offsets   (sum R + 1,)     int64    road_offset (scene-local, start at 0)
    road_type      (sum R,)         int8     poly        (also road_id, int64)
    lane_edges     (sum E, 2)       int32    edge        (scene-local polyline indices)
    tl_lane        (sum L,)         int64    signal      (also tl_stop_point (sum L, 2) float32)
    tl_state       (sum T*L,)       int8     signal_step

Crash safety: a shard is written to ``shard_XXXXX.tmp/``, renamed, and only then
listed in the manifest (written to a temp file and `os.replace`d), so the
manifest is the commit point. Shards or temp dirs it does not list are ignored
by `open_store` and removed by the next `convert`; the inputs they held are
not marked done and are converted again. One writer per store at a time.

Source formats: GPUDrive processed JSON (one scene per file), WOMD TFRecord
shards (many per file) and ScenarioNet / MetaDrive scenario pickles (`sd_*.pkl`,
one per file, read without running pickled code). This module must not parse
source formats itself: it calls the loaders in `data/womd` and only packs
`Scene`s.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np
from tqdm import tqdm

from tg_gpudrive.data.log_audit import unplayable
from tg_gpudrive.data.simplify import simplify_scene
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.data.womd.scenario_proto import read_tfrecord_scenes
from tg_gpudrive.data.womd.scenarionet import load_scenarionet
from tg_gpudrive.scene import Scene, SceneError, scene_defaults

FORMAT = "tg_gpudrive.scene_store"
VERSION = 1
MANIFEST = "manifest.json"
FAILED = "failed.txt"
SHARD_SCENES = "scenes.json"
DEFAULT_SHARD_SIZE = 1000

_SEGMENTS = ("agent", "agent_step", "point", "poly", "road_offset", "edge", "signal", "signal_step")
_SEG = {name: c for c, name in enumerate(_SEGMENTS)}

# field: (dtype, trailing shape of one stored row, segment)
_FIELDS: dict[str, tuple[Any, tuple[int, ...], str]] = {
    "log_pos": (np.float32, (2,), "agent_step"),
    "log_yaw": (np.float32, (), "agent_step"),
    "log_vel": (np.float32, (2,), "agent_step"),
    "log_valid": (np.bool_, (), "agent_step"),
    "length": (np.float32, (), "agent"),
    "width": (np.float32, (), "agent"),
    "height": (np.float32, (), "agent"),
    "agent_type": (np.int8, (), "agent"),
    "agent_id": (np.int64, (), "agent"),
    "goal": (np.float32, (2,), "agent"),
    "is_sdc": (np.bool_, (), "agent"),
    "is_interest": (np.bool_, (), "agent"),
    "road_points": (np.float32, (2,), "point"),
    "road_offsets": (np.int64, (), "road_offset"),
    "road_type": (np.int8, (), "poly"),
    "road_id": (np.int64, (), "poly"),
    "lane_edges": (np.int32, (2,), "edge"),
    "tl_lane": (np.int64, (), "signal"),
    "tl_stop_point": (np.float32, (2,), "signal"),
    "tl_state": (np.int8, (), "signal_step"),
}
# per-scene tables: file -> (dtype, trailing shape)
_TABLES: dict[str, tuple[Any, tuple[int, ...]]] = {
    "num_steps": (np.int64, ()),
    "origin": (np.float64, (2,)),
    "dt": (np.float64, ()),
}
_SHARD_RE = re.compile(r"^shard_(\d{5,})(\.tmp)?$")


class StoreError(ValueError):
    """A store directory is missing, incomplete or corrupt. The message names the path and file."""

    def __init__(self, path: str | Path, file: str, problem: str):
        self.path, self.file, self.problem = str(path), file, problem
        super().__init__(f"scene store {path}: {file}: {problem}")


@dataclasses.dataclass
class ConvertReport:
    """Outcome of `convert` / `write_store`.

    converted         scenes written by this run
    converted_files   input files converted by this run
    skipped_existing  input files skipped because the manifest lists them as done
    failed            (path, reason) of every input that could not be converted
    unplayable        (path, scene id, reason) of every scene that cannot be played (`log_audit.unplayable`:
                      too short, or no vehicle the control rule would drive); stored, listed in the
                      manifest, and skipped by the store's scene source
    duplicates        (path, scene id) of every scene not stored because the store (or an earlier input
                      of this run) already holds a scene of that id
    defaults          fields an older format revision lacked, filled in by the loaders: how many
                      objects, roads or files each default was used for (`sources.scene_defaults`)
    seconds           wall time of the run
    scenes_per_s      converted / seconds
    num_scenes        scenes in the store after the run
    out               the store directory
    """

    converted: int = 0
    converted_files: int = 0
    skipped_existing: int = 0
    failed: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    unplayable: list[tuple[str, str, str]] = dataclasses.field(default_factory=list)
    duplicates: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    defaults: dict[str, int] = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    scenes_per_s: float = 0.0
    num_scenes: int = 0
    out: str = ""


# ====================================================================== writing
def _json_default(obj: Any) -> Any:
    # metadata from loaders may carry numpy scalars / arrays
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (set, tuple)):
        return list(obj)
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"metadata value of type {type(obj).__name__} is not JSON-serialisable")


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _checked(scene: Scene) -> Scene:
    """Validated scene ready to pack (a copy when its arrays are read-only, e.g. store views)."""
    arrays = [getattr(scene, f) for f in _FIELDS if isinstance(getattr(scene, f), np.ndarray)]
    s = scene.copy() if any(not a.flags.writeable for a in arrays) else dataclasses.replace(scene)
    return s.validate()


def _prepared(scenes: list[Scene], simplify_tolerance: float | None) -> list[Scene]:
    """Validated (and simplified) copies; metadata normalised to what the store will give back."""
    scenes = [_checked(s) for s in scenes]
    for s in scenes:
        # fails this input (TypeError) rather than the whole shard write later
        s.metadata = json.loads(json.dumps(s.metadata, default=_json_default))
    if simplify_tolerance is not None:
        scenes = [simplify_scene(s, simplify_tolerance)[0] for s in scenes]
    return scenes


class _Writer:
    """Appends shards to a store directory and commits them through the manifest."""

    def __init__(self, out: Path, *, resume: bool, shard_size: int, simplify_tolerance: float | None):
        self.out = Path(out)
        self.shard_size = int(shard_size)
        if simplify_tolerance is not None and not (math.isfinite(simplify_tolerance) and simplify_tolerance >= 0):
            raise ValueError(f"simplify tolerance: expected a finite number of metres >= 0, got {simplify_tolerance}")
        self.simplify_tolerance = simplify_tolerance
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"scene store {self.out}: a file is there; the store is a folder (choose another --out)")
        self.out.mkdir(parents=True, exist_ok=True)
        manifest = _read_manifest(self.out) if resume and (self.out / MANIFEST).exists() else None
        if manifest is None:
            self._remove_store_files()
            manifest = {"format": FORMAT, "version": VERSION, "num_scenes": 0,
                        "simplify_tolerance": simplify_tolerance, "shards": [], "inputs": {}}
        elif manifest.get("simplify_tolerance") != simplify_tolerance:
            raise ValueError(
                f"scene store {self.out}: resuming with simplify_tolerance={simplify_tolerance!r}, "
                f"but the store was written with {manifest.get('simplify_tolerance')!r}; "
                "use the same value or resume=False")
        self.manifest = manifest
        self._remove_uncommitted_shards()
        self.buf_scenes: list[Scene] = []
        self.buf_sources: list[str] = []
        self.buf_inputs: dict[str, int] = {}
        self.buf_unplayable: dict[int, str] = {}  # buffer index -> why the scene cannot be played
        # scene ids the store holds (its committed shards) or this run added: a scene id is stored once
        self.ids: set[str] = {sid for sh in self.manifest["shards"]
                              for sid in _shard_scene_ids(self.out / sh["name"])}

    def _remove_store_files(self) -> None:
        for p in self.out.iterdir():
            if p.is_dir() and _SHARD_RE.match(p.name):
                shutil.rmtree(p)
            elif p.name in (MANIFEST, MANIFEST + ".tmp", FAILED, FAILED + ".tmp"):
                p.unlink()

    def _remove_uncommitted_shards(self) -> None:
        committed = {s["name"] for s in self.manifest["shards"]}
        for p in self.out.iterdir():
            if p.is_dir() and _SHARD_RE.match(p.name) and p.name not in committed:
                shutil.rmtree(p)

    def done(self, key: str) -> bool:
        return key in self.manifest["inputs"]

    def claim(self, scene_id: str) -> bool:
        """True (and remembered) when no scene of this id is stored yet."""
        if scene_id in self.ids:
            return False
        self.ids.add(scene_id)
        return True

    def add(self, scenes: list[Scene], source: str, input_key: str | None = None,
            unplayable: list[str | None] | None = None) -> None:
        """Buffer the scenes of one input (with, per scene, why it cannot be played or None); flush a
        shard once the buffer is full."""
        for k, why in enumerate(unplayable or []):
            if why is not None:
                self.buf_unplayable[len(self.buf_scenes) + k] = why
        self.buf_scenes.extend(scenes)
        self.buf_sources.extend([source] * len(scenes))
        if input_key is not None:
            self.buf_inputs[input_key] = len(scenes)
        if len(self.buf_scenes) >= self.shard_size:
            self.flush()

    def flush(self) -> None:
        if not self.buf_scenes and not self.buf_inputs:
            return
        name = None
        if self.buf_scenes:
            name = f"shard_{len(self.manifest['shards']):05d}"
            _write_shard(self.out / name, self.buf_scenes, self.buf_sources)
            self.manifest["shards"].append({"name": name, "num_scenes": len(self.buf_scenes)})
            for k, why in self.buf_unplayable.items():
                self.manifest.setdefault("unplayable", {})[str(self.manifest["num_scenes"] + k)] = why
            self.manifest["num_scenes"] += len(self.buf_scenes)
        for key, count in self.buf_inputs.items():
            self.manifest["inputs"][key] = {"shard": name, "scenes": count}
        self.commit()
        self.buf_scenes, self.buf_sources, self.buf_inputs, self.buf_unplayable = [], [], {}, {}

    def commit(self) -> None:
        _atomic_write_text(self.out / MANIFEST, json.dumps(self.manifest, indent=1))


def _shard_scene_ids(shard: Path) -> list[str]:
    try:
        return [str(v) for v in json.loads((shard / SHARD_SCENES).read_text(encoding="utf-8"))["scene_ids"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise StoreError(shard.parent, f"{shard.name}/{SHARD_SCENES}", f"unreadable: {e}") from e


def _write_shard(final: Path, scenes: list[Scene], sources: list[str]) -> None:
    tmp = final.with_name(final.name + ".tmp")
    for d in (tmp, final):
        if d.exists():
            shutil.rmtree(d)
    tmp.mkdir()
    counts = np.zeros((len(scenes), len(_SEGMENTS)), np.int64)
    for j, s in enumerate(scenes):
        n, t, l_ = s.num_agents, s.num_steps, len(s.tl_lane)
        counts[j] = (n, n * t, len(s.road_points), s.num_polylines, s.num_polylines + 1,
                     len(s.lane_edges), l_, t * l_)
    index = np.zeros((len(scenes) + 1, len(_SEGMENTS)), np.int64)
    np.cumsum(counts, axis=0, out=index[1:])
    np.save(tmp / "index.npy", index)
    np.save(tmp / "num_steps.npy", np.array([s.num_steps for s in scenes], np.int64))
    np.save(tmp / "origin.npy", np.array([s.origin for s in scenes], np.float64).reshape(-1, 2))
    np.save(tmp / "dt.npy", np.array([s.dt for s in scenes], np.float64))
    for field, (dtype, trail, _) in _FIELDS.items():
        parts = [np.asarray(getattr(s, field), dtype).reshape((-1,) + trail) for s in scenes]
        np.save(tmp / f"{field}.npy", np.concatenate(parts))
    info = {"scene_ids": [str(s.scene_id) for s in scenes], "sources": sources,
            "metadata": [s.metadata for s in scenes]}
    (tmp / SHARD_SCENES).write_text(json.dumps(info, default=_json_default), encoding="utf-8")
    os.replace(tmp, final)


def write_store(scenes: Iterable[Scene], out: str | Path, *, shard_size: int = DEFAULT_SHARD_SIZE,
                overwrite: bool = False, simplify_tolerance: float | None = None,
                progress: bool = False) -> ConvertReport:
    """Pack in-memory (or generated) scenes into a new store at `out`.

    `scenes` may be a generator, so large procedural stores are streamed shard by
    shard. Each scene is validated first. The source recorded per scene is
    ``scene.metadata["source"]`` or "memory". Raises FileExistsError if `out`
    already holds a store and `overwrite` is False.
    """
    out = Path(out)
    if (out / MANIFEST).exists() and not overwrite:
        raise FileExistsError(f"{out} already holds a scene store; pass overwrite=True to replace it")
    t0 = time.perf_counter()
    w = _Writer(out, resume=False, shard_size=shard_size, simplify_tolerance=simplify_tolerance)
    count = 0
    with tqdm(unit="scene", disable=not progress, desc="write_store") as bar:
        for s in scenes:
            s = _prepared([s], simplify_tolerance)[0]
            w.add([s], str(s.metadata.get("source", "memory")))
            count += 1
            bar.update(1)
    w.flush()
    if not w.manifest["shards"]:
        w.commit()  # an empty store is still a store
    dt = time.perf_counter() - t0
    return ConvertReport(converted=count, seconds=dt, scenes_per_s=count / dt if dt > 0 else 0.0,
                         num_scenes=w.manifest["num_scenes"], out=str(out))


# =================================================================== converting
def _is_json(p: Path) -> bool:
    return p.suffix.lower() == ".json"


def _is_scenarionet(p: Path) -> bool:
    return p.suffix.lower() == ".pkl"


def _is_tfrecord(p: Path) -> bool:
    # GPUDrive JSONs ("tfrecord-...json") and ScenarioNet pickles ("sd_training.tfrecord-...pkl")
    # carry the shard name too: the suffix wins
    return not _is_json(p) and not _is_scenarionet(p) and "tfrecord" in p.name.lower()


def _is_scenarionet_scene(p: Path) -> bool:
    # ScenarioNet names every scenario sd_*.pkl; a directory's other pickles (dataset_summary.pkl,
    # dataset_mapping.pkl) index them and are not scenes
    return _is_scenarionet(p) and p.name.lower().startswith("sd_")


def expand_inputs(inputs: Iterable[str | Path], exclude: Path | None = None) -> list[Path]:
    """Files named by `inputs`, directories expanded recursively to *.json, *tfrecord* and sd_*.pkl files.

    Paths are resolved and de-duplicated, directory contents sorted; stores
    (and `exclude`, the store being written) and hidden files are left out. Paths
    that do not exist are kept, so `convert` reports them as failed.
    """
    seen: dict[Path, None] = {}
    excl = exclude.resolve() if exclude is not None else None
    for item in inputs:
        p = Path(item).expanduser().resolve()
        if not p.is_dir():
            seen.setdefault(p, None)
            continue
        found = []
        for root, dirs, names in os.walk(p):
            r = Path(root)
            if (excl is not None and r == excl) or _looks_like_store(r):
                dirs[:] = []  # a store's own manifest/scenes JSONs are not inputs
                continue
            dirs[:] = [d for d in dirs if not d.startswith(".")]
            found.extend(r / f for f in names
                         if not f.startswith(".") and (_is_json(Path(f)) or _is_tfrecord(Path(f))
                                                       or _is_scenarionet_scene(Path(f))))
        for q in sorted(found):
            seen.setdefault(q, None)
    return list(seen)


def _looks_like_store(d: Path) -> bool:
    try:
        with open(d / MANIFEST, "rb") as f:
            return FORMAT.encode() in f.read(256)
    except OSError:
        return False


_UNKNOWN_TYPE = ("{}: unknown scene file type (expected *.json, a name containing 'tfrecord', or a ScenarioNet "
                 "sd_*.pkl)")


def load_file(path: str | Path) -> list[Scene]:
    """All scenes of one source file: a GPUDrive JSON or a ScenarioNet pickle (one scene each) or a
    WOMD TFRecord (many).

    Raises SceneError / OSError / ValueError on a bad file, ValueError for an
    unknown file type.
    """
    p = Path(path)
    if _is_json(p):
        return [load_gpudrive_json(p)]
    if _is_scenarionet(p):
        return [load_scenarionet(p)]
    if _is_tfrecord(p):
        return list(read_tfrecord_scenes(p))
    raise ValueError(_UNKNOWN_TYPE.format(p))


# what a malformed file can raise from a loader; anything else is a bug and propagates
_FILE_ERRORS = (SceneError, OSError, ValueError, KeyError, TypeError, IndexError, EOFError)


def _load_prepared(path: Path, simplify_tolerance: float | None) -> tuple[list[Scene] | None, Any]:
    """(scenes, [why each cannot be played, or None]) of one input file ready to pack, or (None, reason
    it does not load); runs in worker processes."""
    try:
        if not path.is_file():
            raise FileNotFoundError(f"no such file: {path}")
        if not (_is_json(path) or _is_tfrecord(path) or _is_scenarionet(path)):
            raise ValueError(_UNKNOWN_TYPE.format(path))
        scenes = _prepared(load_file(path), simplify_tolerance)
    except _FILE_ERRORS as e:
        return None, f"{type(e).__name__}: {e}"
    why = []
    for sc in scenes:
        why.append(unplayable(sc))
        sc.metadata.pop("log_audit", None)  # the store keeps what the file holds; the audit runs at use
    return scenes, why


def convert(inputs: list[str | Path], out: str | Path, *, resume: bool = True, progress: bool = True,
            simplify_tolerance: float | None = None, shard_size: int = DEFAULT_SHARD_SIZE,
            workers: int = 1) -> ConvertReport:
    """Convert source files (GPUDrive JSON, WOMD TFRecord, ScenarioNet sd_*.pkl, or directories of
    them) into a store.

    Per-file errors are caught and reported (also in ``<out>/failed.txt``) and
    the conversion goes on; a file is all-or-nothing. With `resume`, inputs the
    manifest lists as done are skipped (by resolved path, not by content) and
    failed ones are retried. `simplify_tolerance` (m) simplifies road polylines
    with `simplify.simplify_scene`; it must match the one a resumed store was
    written with. `workers` > 1 parses files in that many processes (parsing
    JSON dominates); the store's order is the input order either way.
    """

    t0 = time.perf_counter()
    out = Path(out)
    w = _Writer(out, resume=resume, shard_size=shard_size, simplify_tolerance=simplify_tolerance)
    files = expand_inputs(inputs, exclude=out)
    report = ConvertReport(out=str(out))
    todo = []
    for f in files:
        if w.done(str(f)):
            report.skipped_existing += 1
        else:
            todo.append(f)
    pool = None
    if workers > 1 and len(todo) > 1:
        pool = ProcessPoolExecutor(min(workers, len(todo)))
        results = pool.map(_load_prepared, todo, [simplify_tolerance] * len(todo))
    else:
        results = (_load_prepared(f, simplify_tolerance) for f in todo)
    try:
        with tqdm(unit="scene", disable=not progress, desc=f"convert -> {out.name}") as bar:
            for k, (f, (scenes, reason)) in enumerate(zip(todo, results)):
                if scenes is None:
                    report.failed.append((str(f), reason))
                else:
                    new = [w.claim(str(sc.scene_id)) for sc in scenes]
                    report.duplicates.extend((str(f), sc.scene_id) for sc, ok in zip(scenes, new) if not ok)
                    scenes = [sc for sc, ok in zip(scenes, new) if ok]
                    reason = [r for r, ok in zip(reason, new) if ok]
                    report.unplayable.extend((str(f), sc.scene_id, why) for sc, why in zip(scenes, reason) if why)
                    for key, v in scene_defaults(scenes).items():
                        report.defaults[key] = report.defaults.get(key, 0) + v
                    w.add(scenes, str(f), input_key=str(f), unplayable=reason)
                    report.converted += len(scenes)
                    report.converted_files += 1
                    bar.update(len(scenes))
                bar.set_postfix(files=f"{k + 1}/{len(todo)}", failed=len(report.failed), refresh=False)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    w.flush()
    if not (out / MANIFEST).exists():
        w.commit()
    lines = "".join(f"{p}\t{r.replace(chr(10), ' ')}\n" for p, r in report.failed)
    _atomic_write_text(out / FAILED, lines)
    report.seconds = time.perf_counter() - t0
    report.scenes_per_s = report.converted / report.seconds if report.seconds > 0 else 0.0
    report.num_scenes = w.manifest["num_scenes"]
    return report


# ====================================================================== reading
def _read_manifest(path: Path) -> dict:
    mpath = path / MANIFEST
    if not path.is_dir():
        raise StoreError(path, "-", "no such directory")
    if not mpath.is_file():
        raise StoreError(path, MANIFEST, "missing (not a scene store, or no shard was ever committed)")
    try:
        m = json.loads(mpath.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise StoreError(path, MANIFEST, f"unreadable: {e}") from e
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise StoreError(path, MANIFEST, f"not a {FORMAT} manifest")
    if m.get("version") != VERSION:
        raise StoreError(path, MANIFEST, f"format version {m.get('version')!r}, this code reads {VERSION}")
    for key in ("shards", "inputs", "num_scenes"):
        if key not in m:
            raise StoreError(path, MANIFEST, f"missing key '{key}'")
    return m


def _load_npy(root: Path, shard: str, file: str, dtype: Any, trail: tuple[int, ...], rows: int,
              mmap: bool) -> np.ndarray:
    fpath = root / shard / file
    rel = f"{shard}/{file}"
    if not fpath.is_file():
        raise StoreError(root, rel, "missing")
    try:
        arr = np.load(fpath, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise StoreError(root, rel, f"unreadable or truncated: {e}") from e
    if arr.dtype != np.dtype(dtype) or arr.shape[1:] != trail:
        raise StoreError(root, rel, f"expected dtype {np.dtype(dtype)} rows of shape {trail}, "
                                    f"got {arr.dtype} {arr.shape}")
    if rows >= 0 and arr.shape[0] != rows:
        raise StoreError(root, rel, f"expected {rows} rows from index.npy, got {arr.shape[0]}")
    return np.asarray(arr)  # plain ndarray view; keeps the mmap alive through .base


class _Shard:
    __slots__ = ("name", "index", "num_steps", "origin", "dt", "arrays", "_info")

    def __init__(self, root: Path, name: str, num_scenes: int):
        self.name = name
        if not (root / name).is_dir():
            raise StoreError(root, name, "shard directory listed in the manifest is missing")
        self.index = _load_npy(root, name, "index.npy", np.int64, (len(_SEGMENTS),), num_scenes + 1, False)
        if (self.index[0] != 0).any() or (np.diff(self.index, axis=0) < 0).any():
            raise StoreError(root, f"{name}/index.npy", "offsets must start at 0 and not decrease")
        self.num_steps = _load_npy(root, name, "num_steps.npy", np.int64, (), num_scenes, False)
        self.origin = _load_npy(root, name, "origin.npy", np.float64, (2,), num_scenes, False)
        self.dt = _load_npy(root, name, "dt.npy", np.float64, (), num_scenes, False)
        last = self.index[-1]
        self.arrays = {f: _load_npy(root, name, f"{f}.npy", dt, trail, int(last[_SEG[seg]]), True)
                       for f, (dt, trail, seg) in _FIELDS.items()}
        self._info: dict | None = None

    def info(self, root: Path) -> dict:
        if self._info is None:
            rel = f"{self.name}/{SHARD_SCENES}"
            try:
                info = json.loads((root / self.name / SHARD_SCENES).read_text(encoding="utf-8"))
                ok = all(len(info[k]) == len(self.num_steps) for k in ("scene_ids", "sources", "metadata"))
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise StoreError(root, rel, f"unreadable: {e}") from e
            if not ok:
                raise StoreError(root, rel, f"expected {len(self.num_steps)} entries per list")
            self._info = info
        return self._info


class SceneStore:
    """A packed store opened read-only; `store[i]` is a `Scene` of views into memory-mapped files.

    Opening maps the files and reads only the small per-scene offset tables;
    scene ids, sources and metadata (``scenes.json`` per shard) are read the
    first time a scene of that shard is asked for. Returned arrays are
    read-only views; use `get(i, copy=True)` for writable copies.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        manifest = _read_manifest(self.path)
        self.simplify_tolerance = manifest.get("simplify_tolerance")
        # store index -> why the scene cannot be played (`log_audit.unplayable`), as `convert` found it
        self.unplayable = {int(k): str(v) for k, v in (manifest.get("unplayable") or {}).items()}
        self._shards = [_Shard(self.path, s["name"], int(s["num_scenes"])) for s in manifest["shards"]]
        counts = np.array([len(s.num_steps) for s in self._shards], np.int64)
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        if int(self._starts[-1]) != int(manifest["num_scenes"]):
            raise StoreError(self.path, MANIFEST, f"num_scenes {manifest['num_scenes']} does not match "
                                                  f"the shards' total {int(self._starts[-1])}")
        self._scene_ids: list[str] | None = None

    # ----------------------------------------------------------------- lookup
    def __len__(self) -> int:
        return int(self._starts[-1])

    def _locate(self, i: int) -> tuple[_Shard, int]:
        n = len(self)
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"scene index {i} out of range for store {self.path} of {n} scenes")
        k = int(np.searchsorted(self._starts, i, side="right")) - 1
        return self._shards[k], i - int(self._starts[k])

    def __getitem__(self, i: int) -> Scene:
        return self.get(i)

    def __iter__(self) -> Iterator[Scene]:
        for i in range(len(self)):
            yield self.get(i)

    def get(self, i: int, *, copy: bool = False) -> Scene:
        """Scene i (negative counts from the end) as read-only views, or writable copies if `copy`."""
        sh, j = self._locate(i)
        lo, hi = sh.index[j], sh.index[j + 1]
        n, t = int(hi[0] - lo[0]), int(sh.num_steps[j])
        fields = {}
        for f, (_, trail, seg) in _FIELDS.items():
            c = _SEG[seg]
            a = sh.arrays[f][int(lo[c]) : int(hi[c])]
            if seg == "agent_step":
                a = a.reshape((n, t) + trail)
            elif seg == "signal_step":
                a = a.reshape(t, -1)
            fields[f] = np.array(a) if copy else a
        info = sh.info(self.path)
        return Scene(scene_id=info["scene_ids"][j], origin=sh.origin[j].copy(), dt=float(sh.dt[j]),
                     metadata=dict(info["metadata"][j]), **fields)

    # --------------------------------------------------------------- per scene
    @property
    def scene_ids(self) -> list[str]:
        """Scene ids in store order (reads every shard's scenes.json once)."""
        if self._scene_ids is None:
            self._scene_ids = [sid for sh in self._shards for sid in sh.info(self.path)["scene_ids"]]
        return self._scene_ids

    def metadata(self, i: int) -> dict:
        sh, j = self._locate(i)
        return dict(sh.info(self.path)["metadata"][j])

    def source(self, i: int) -> str:
        """Input file (or "memory") scene i was converted from."""
        sh, j = self._locate(i)
        return sh.info(self.path)["sources"][j]

    def _per_scene(self, col: int) -> np.ndarray:
        if not self._shards:
            return np.zeros(0, np.int64)
        return np.concatenate([np.diff(sh.index[:, col]) for sh in self._shards])

    @property
    def num_agents(self) -> np.ndarray:
        """(num_scenes,) int64: N of every scene, without materialising any (for padding sizes)."""
        return self._per_scene(_SEG["agent"])

    @property
    def num_polylines(self) -> np.ndarray:
        """(num_scenes,) int64: R of every scene."""
        return self._per_scene(_SEG["poly"])

    @property
    def num_road_points(self) -> np.ndarray:
        """(num_scenes,) int64: P of every scene."""
        return self._per_scene(_SEG["point"])

    @property
    def num_steps(self) -> np.ndarray:
        """(num_scenes,) int64: T of every scene."""
        if not self._shards:
            return np.zeros(0, np.int64)
        return np.concatenate([sh.num_steps for sh in self._shards])

    # ---------------------------------------------------------------- pickling
    def __getstate__(self) -> dict:
        # worker processes re-map the files instead of receiving copies of them
        return {"path": str(self.path)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"])

    def __repr__(self) -> str:
        return f"SceneStore({str(self.path)!r}, scenes={len(self)}, shards={len(self._shards)})"


def open_store(path: str | Path) -> SceneStore:
    """Open the store at `path` read-only (memory-mapped). Raises StoreError naming the bad file."""
    return SceneStore(path)


def is_store(path: str | Path) -> bool:
    """Whether `path` is a directory holding a store manifest (not checked further)."""
    p = Path(path)
    return p.is_dir() and (p / MANIFEST).is_file()
