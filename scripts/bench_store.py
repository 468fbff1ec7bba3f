"""Benchmark the packed scene store: write rate, open time, sampler fill time, resident memory.

Builds (or reuses) a store of N procedural scenes (all six types; synthetic
WOMD-sized `make_scene` scenes if the generator is absent), then opens it and
fills W worlds with the sampler in a fresh child process so its memory
figures are not inflated by the build. Prints one JSON object. Reports
numbers only; it never fails on them.

    python scripts/bench_store.py --n 2000 --worlds 4096
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tg_gpudrive.data.procedural import SCENARIO_TYPES, generate_scene  # noqa: E402  (after the path)
from tg_gpudrive.data.sampler import SceneSampler  # noqa: E402
from tg_gpudrive.data.sources import StoreSource  # noqa: E402
from tg_gpudrive.data.store import is_store, open_store, write_store  # noqa: E402
from tg_gpudrive.scene import make_scene  # noqa: E402
from tg_gpudrive.enums import RoadType  # noqa: E402


def rss_mb(key: str = "VmRSS") -> float:
    """A /proc/self/status memory figure of this process (VmRSS: resident; RssAnon: heap only), MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def synthetic_scene(k: int, n_agents: int = 48, steps: int = 91, polylines: int = 150, points: int = 60):
    """A WOMD-sized random scene: n_agents x 91 steps, 150 polylines of 60 points."""
    rng = np.random.default_rng(k)
    pos = np.cumsum(rng.normal(size=(n_agents, steps, 2)), axis=1)
    roads = [(RoadType.LANE if r % 3 else RoadType.ROAD_EDGE, np.cumsum(rng.normal(size=(points, 2)), 0))
             for r in range(polylines)]
    return make_scene(pos, rng.normal(size=(n_agents, steps)), roads=roads, scene_id=f"synthetic_{k}",
                      metadata={"scenario_type": "synthetic", "seed": k})


def _one(args):
    i, kind = args
    if kind == "procedural":
        return generate_scene(SCENARIO_TYPES[i % len(SCENARIO_TYPES)], i)  # = generate_scenes("all", n, 0)
    return synthetic_scene(i)


class TimedScenes:
    """Scene i of the benchmark set, made in `workers` processes; `wait_s` is time spent waiting for them."""

    def __init__(self, n: int, kind: str, workers: int):
        self.n, self.kind, self.workers, self.wait_s = n, kind, workers, 0.0

    def __iter__(self):
        jobs = ((i, self.kind) for i in range(self.n))
        if self.workers > 1:
            with mp.get_context("spawn").Pool(self.workers) as pool:
                yield from self._timed(pool.imap(_one, jobs, chunksize=8))
        else:
            yield from self._timed(map(_one, jobs))

    def _timed(self, it):
        while True:
            t0 = time.perf_counter()
            try:
                s = next(it)
            except StopIteration:
                return
            self.wait_s += time.perf_counter() - t0
            yield s


def read_phase(out: Path, worlds: int) -> dict:
    """Open the store and fill `worlds` worlds; run in a fresh process."""
    res = {"rss_mb_before_open": rss_mb()}
    t0 = time.perf_counter()
    src = StoreSource(out)
    res["open_s"] = time.perf_counter() - t0
    res["rss_mb_after_open"] = rss_mb()
    sampler = SceneSampler(src, worlds, replacement=False, seed=0)
    t0 = time.perf_counter()
    filled = sampler.sample()
    res["fill_views_s"] = time.perf_counter() - t0
    res["rss_mb_after_fill_views"] = rss_mb()
    t0 = time.perf_counter()
    copies = [src.store.get(int(i), copy=True) for i in sampler.sample_indices()]
    res["fill_copies_s"] = time.perf_counter() - t0
    res["rss_mb_after_fill_copies"] = rss_mb()
    # VmRSS counts mapped file pages (reclaimable page cache); RssAnon is what the copies cost
    res["rss_anon_mb_after_fill_copies"] = rss_mb("RssAnon")
    res["worlds"] = worlds
    res["agents_in_fill"] = int(sum(s.num_agents for s in filled))
    res["bytes_copied_mb"] = sum(a.nbytes for s in copies for a in vars(s).values()
                                 if isinstance(a, np.ndarray)) / 2**20
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000, help="scenes in the store")
    ap.add_argument("--worlds", type=int, default=4096, help="worlds filled by the sampler")
    ap.add_argument("--out", type=Path, default=None, help="store directory (default: temp dir by N)")
    ap.add_argument("--source", choices=["auto", "procedural", "synthetic"], default="auto")
    ap.add_argument("--rebuild", action="store_true", help="rebuild even if a store of N scenes exists")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes generating scenes")
    ap.add_argument("--read-phase", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    kind = args.source
    if kind == "auto":
        kind = "procedural" if importlib.util.find_spec("tg_gpudrive.data.procedural") else "synthetic"
    out = args.out or Path(tempfile.gettempdir()) / f"tg_store_bench_{kind}_{args.n}"
    if args.read_phase:
        print(json.dumps(read_phase(out, args.worlds)))
        return

    res: dict = {"n": args.n, "source": kind, "store": str(out), "rss_mb_start": rss_mb()}
    reuse = not args.rebuild and is_store(out) and len(open_store(out)) == args.n
    if reuse:
        res["reused_store"] = True
    else:
        src = TimedScenes(args.n, kind, args.workers)
        rep = write_store(src, out, overwrite=True, progress=sys.stderr.isatty())
        pack_s = rep.seconds - src.wait_s  # write_store's own time: validate, pack, np.save, manifest
        res.update(reused_store=False, workers=args.workers, write_s=rep.seconds,
                   generate_plus_write_scenes_per_s=rep.scenes_per_s,
                   pack_only_s=pack_s, pack_only_scenes_per_s=args.n / pack_s if pack_s > 0 else None)
        res["rss_mb_after_build"] = rss_mb()
    res["store_mb_on_disk"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
    child = subprocess.run([sys.executable, __file__, "--read-phase", "--out", str(out),
                            "--worlds", str(args.worlds), "--source", kind, "--n", str(args.n)],
                           capture_output=True, text=True, check=True)
    res.update(json.loads(child.stdout.strip().splitlines()[-1]))
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in res.items()}, indent=1))


if __name__ == "__main__":
    main()
