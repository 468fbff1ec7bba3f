"""Where a CCE-MAPPO update spends its time: torch.profiler over a few updates of a config.

    python scripts/profile_train.py --config configs/train/gpu.yaml --updates 3 [--set eta1=0 ...]

Trains `--warmup` updates untimed, then profiles `--updates` updates and prints the top
operators by device time (CUDA) or CPU time, and the wall-clock of rollout and learning.
Numbers only; it never fails on them.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import torch
from torch.profiler import ProfilerActivity, profile

from tg_gpudrive.config import TrainConfig, load_config
from tg_gpudrive.learn.train import Trainer


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True)
    p.add_argument("--set", action="append", default=[], help="key=value override")
    p.add_argument("--updates", type=int, default=2)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--rows", type=int, default=25, help="operators to print")
    args = p.parse_args(argv)
    cfg = load_config(TrainConfig, args.config, args.set + ["checkpoint_every=100000", "resample_every=0"])
    with tempfile.TemporaryDirectory() as out:
        tr = Trainer(cfg, out, progress=False)
        cuda = tr.sim.is_cuda
        sync = (lambda: torch.cuda.synchronize(tr.device)) if cuda else (lambda: None)  # noqa: E731
        for _ in range(args.warmup):
            tr.learn(tr.collect()[0])
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        t_roll = t_learn = 0.0
        with profile(activities=acts) as prof:
            for _ in range(args.updates):
                sync()
                t0 = time.perf_counter()
                buf, _ = tr.collect()
                sync()
                t1 = time.perf_counter()
                tr.learn(buf)
                sync()
                t_roll += t1 - t0
                t_learn += time.perf_counter() - t1
    print(f"per update: rollout {t_roll / args.updates:.3f} s, learn {t_learn / args.updates:.3f} s")
    key = "cuda_time_total" if cuda else "cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=args.rows))
    print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=args.rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
