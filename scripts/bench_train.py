"""Training throughput of CCE-MAPPO: end-to-end controlled-agent steps/s per config variant.

    python scripts/bench_train.py --config configs/train/gpu.yaml --updates 8 \
        --variant base: --variant e1mb8:epochs=1,minibatches=8 [--out bench_train.jsonl]

Each variant is the base config plus its `key=value` overrides (comma-separated,
`--set` syntax). It trains `--updates` updates with tg_gpudrive.learn.train.Trainer
and prints one JSON line: the median over the updates after the first two
(warm-up: allocation, cuDNN/cuBLAS heuristics) of the end-to-end and rollout-only
agent steps/s, seconds per update, and the peak GPU memory. Numbers only; it
never fails on them.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from tg_gpudrive.config import TrainConfig, load_config
from tg_gpudrive.learn.train import Trainer

CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # this checkout's (an installed package has none)


def run_variant(config: str, overrides: list[str], updates: int) -> dict:
    cfg = load_config(TrainConfig, config, overrides + [f"updates={updates}", "checkpoint_every=100000",
                                                        "resample_every=0", "target_goal_rate=0"])
    cuda = cfg.device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        tr = Trainer(cfg, out, progress=False)
        setup = time.perf_counter() - t0
        tr.train()
        rows = list(csv.DictReader((Path(out) / "metrics.csv").open()))
    steady = rows[2:] or rows
    med = lambda k: statistics.median(float(r[k]) for r in steady)  # noqa: E731
    per_update = [float(b["wall_s"]) - float(a["wall_s"]) for a, b in zip(rows, rows[1:])][1:]
    return {
        "worlds": cfg.num_worlds, "rollout_steps": cfg.rollout_steps, "epochs": cfg.epochs,
        "minibatches": cfg.minibatches, "agent_steps_per_s": med("agent_steps_per_s"),
        "rollout_agent_steps_per_s": med("rollout_agent_steps_per_s"),
        "seconds_per_update": statistics.median(per_update) if per_update else float("nan"),
        "agent_steps_per_update": med("agent_steps") / max(med("update"), 1),
        "goal_rate_last": float(rows[-1]["goal_rate"]), "setup_s": setup,
        "peak_gpu_mem_gb": torch.cuda.max_memory_allocated() / 2**30 if cuda else None,
        "device": torch.cuda.get_device_name() if cuda else "cpu",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(CONFIGS / "train" / "gpu.yaml"))
    ap.add_argument("--updates", type=int, default=8)
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:k=v,k=v",
                    help="a named set of overrides (repeatable); default: the config as it is")
    ap.add_argument("--set", action="append", default=[], help="overrides for every variant")
    ap.add_argument("--out", default=None, help="append the JSON lines to this file too")
    args = ap.parse_args()
    for spec in args.variant or ["base:"]:
        name, _, kv = spec.partition(":")
        over = args.set + [x for x in kv.split(",") if x]
        res = {"variant": name, "overrides": over} | run_variant(args.config, over, args.updates)
        line = json.dumps(res)
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(line + "\n")


if __name__ == "__main__":
    main()
