"""Where one CCE-MAPPO training iteration spends its time, phase by phase.

    python scripts/profile_train.py --config configs/train/gpu.yaml --set num_worlds=4096 [--iters 3]
        [--warmup 2] [--trace trace.json] [--json]

The trainer's rollout and update carry named ranges (torch.profiler.record_function): per step of the
rollout `magnet.context` (the magnet's history window), `live_rows` (which agents act: the step's host sync),
`actor`, `sample`, `magnet` (its context kept), `engine` and `buffers`, and after the steps `critic` (the
values of every step) and `magnet.forward` (the world model's logits);
in the update `advantages`, `lagrange`, per epoch `live_rows` (every minibatch's live rows: its host
sync), and per minibatch `forward` (actor, critic, quantiles, the KL terms), `backward` and `optimizer`
(clipping and Adam); with `--set cuda_graphs=true` a minibatch's `forward` is the replay of its captured
forward and backward pass. After `--warmup` plain iterations it times
`--iters` more without the profiler (the wall clock of rollout and update, synchronised), then
profiles as many: per range the host time and the device time of the kernels launched inside it, per
iteration, then the `--rows` operators that took the most device (or, on the CPU, host) time. `--trace`
also writes the Chrome trace. Numbers only; it never fails on them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from tg_gpudrive.config import TrainConfig, load_config
from tg_gpudrive.learn.train import Trainer

CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # this checkout's (an installed package has none)
PREFIXES = ("rollout/", "update/")


def iteration(tr: Trainer) -> tuple[float, float, int]:
    """One rollout and one update, synchronised: (rollout s, update s, controlled agent-steps)."""
    t0 = time.perf_counter()
    batch, stats = tr.collect()
    tr._sync()
    t1 = time.perf_counter()
    tr.learn(batch)
    tr._sync()
    return t1 - t0, time.perf_counter() - t1, int(stats["alive"])


def device_us(evt) -> float:
    """The device time of a profiler event's kernels, in microseconds (the attribute's name changed
    across torch versions)."""
    for name in ("device_time_total", "cuda_time_total"):
        if hasattr(evt, name):
            return float(getattr(evt, name))
    return 0.0


def phases(prof, iters: int) -> dict[str, dict[str, float]]:
    """Per named range: its host and device milliseconds per iteration and its calls per iteration."""
    out = {}
    # a range appears twice under CUDA: as the host's annotation (host time, its kernels' device time)
    # and as the device's (the span on the GPU); each figure is taken from the entry that holds it
    for evt in prof.key_averages():
        if evt.key.startswith(PREFIXES):
            row = out.setdefault(evt.key, {"host_ms": 0.0, "device_ms": 0.0, "calls": 0.0})
            row["host_ms"] = max(row["host_ms"], evt.cpu_time_total / 1e3 / iters)
            row["device_ms"] = max(row["device_ms"], device_us(evt) / 1e3 / iters)
            row["calls"] = max(row["calls"], evt.count / iters)
    return dict(sorted(out.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(CONFIGS / "train" / "gpu.yaml"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides")
    ap.add_argument("--warmup", type=int, default=2, help="iterations before any measurement")
    ap.add_argument("--iters", type=int, default=3, help="iterations timed, then as many profiled")
    ap.add_argument("--rows", type=int, default=15, help="top operators to print (0: none)")
    ap.add_argument("--trace", default=None, help="write the profiled iterations' Chrome trace here")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = ap.parse_args()
    cfg = load_config(TrainConfig, args.config, args.set + ["resample_every=0", "target_goal_rate=0"])
    cuda = cfg.device.startswith("cuda")
    with tempfile.TemporaryDirectory() as out:
        tr = Trainer(cfg, out, progress=False)
        for _ in range(args.warmup):
            iteration(tr)
        timed = [iteration(tr) for _ in range(args.iters)]
        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        with profile(activities=acts) as prof:
            for _ in range(args.iters):
                iteration(tr)
    if args.trace:
        prof.export_chrome_trace(args.trace)
    roll, upd = statistics.median(t[0] for t in timed), statistics.median(t[1] for t in timed)
    steps = statistics.median(t[2] for t in timed)
    res = {"config": args.config, "overrides": args.set, "worlds": cfg.num_worlds, "rollout_steps": cfg.rollout_steps,
           "epochs": cfg.epochs, "minibatches": cfg.minibatches, "amp": cfg.amp,
           "rollout_s": roll, "update_s": upd, "agent_steps_per_iteration": steps,
           "agent_steps_per_s": steps / (roll + upd), "rollout_agent_steps_per_s": steps / roll,
           "device": torch.cuda.get_device_name() if cuda else "cpu", "phases": phases(prof, args.iters)}
    if args.json:
        print(json.dumps(res))
        return
    print(f"{res['device']}, {cfg.num_worlds} worlds x {cfg.rollout_steps} steps, {cfg.epochs} epochs x "
          f"{cfg.minibatches} minibatches: rollout {roll:.3f} s + update {upd:.3f} s per iteration, "
          f"{res['agent_steps_per_s']:,.0f} controlled agent-steps/s ({res['rollout_agent_steps_per_s']:,.0f} in the rollout)")
    print(f"{'phase':<22}{'host ms':>10}{'device ms':>11}{'calls':>8}")
    for name, p in res["phases"].items():
        print(f"{name:<22}{p['host_ms']:>10.1f}{p['device_ms']:>11.1f}{p['calls']:>8.0f}")
    if args.rows:
        key = "device_time_total" if cuda else "cpu_time_total"
        print(prof.key_averages().table(sort_by=key, row_limit=args.rows))


if __name__ == "__main__":
    main()
