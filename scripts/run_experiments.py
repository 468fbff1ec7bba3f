"""Run the experiment grid (configs/experiments/grid.yaml) in batches, then the report.

    python scripts/run_experiments.py --config configs/experiments/grid.yaml --out runs/experiments \
        [--batch 4] [--gpus 0,1] [--set device=cuda] [--seeds 1,2] [--dry-run] [--report-only] [--no-report]

Every cell (beta x alpha) and every baseline is one `tg-gpudrive train` process
(`python -m tg_gpudrive.cli train ...`); `--batch` of them run at the same time
(on one GPU they share it; W worlds each; `--gpus` deals them out over several,
one CUDA_VISIBLE_DEVICES each, round robin). A run directory that already holds a
checkpoint of its final update is skipped, so an interrupted grid resumes. When
all runs are done, the flexibility table (how the knobs moved the multiplier,
gaps, speed and cost during training: the mean of each run's last `--tail`
updates, and the update from which the trainer warned that a run's constraint bar was out of reach,
learn/bar_watch.py) goes to <out>/flexibility.md and .json, then
`tg_gpudrive.evaluation.report.report_main` writes <out>/report/ (skip it with
`--no-report`). The report caches each policy's evaluation (<out>/report/cache/):
`--report-part K/N` evaluates every N-th run from the K-th (part 0 also the
baselines), so N processes, one per GPU, share the work, and a last
`--report-only` reads it all back and writes the report.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

from tg_gpudrive.config import ConfigError, load_experiment, load_yaml, override_text
from tg_gpudrive.evaluation.generate import KNOBS_ALONE
from tg_gpudrive.evaluation.report import ReportOptions, report_main, run_config
from tg_gpudrive.learn import bar_watch

CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # this checkout's (an installed package has none)


def plan(exp: dict, extra: list[str], seeds: list[int] | None = None) -> list[tuple[str, list[str]]]:
    """(run name, train overrides) for every cell and baseline, once per training seed (`seeds`, else the
    experiment's). Every run starts with the reward terms that keep
    distance whatever beta and alpha say turned off (generate.KNOBS_ALONE: a base such as real_mix.yaml charges
    closing in), so the grid measures the knobs; the grid's own overrides may turn them back on."""
    common = [override_text(f"env.reward.{k}", v) for k, v in KNOBS_ALONE.items()]
    common += [override_text(k, v) for k, v in (exp.get("overrides") or {}).items()]
    cells = [(f"beta{beta}_alpha{alpha}", [f"env.beta={beta}", f"alpha={alpha}"])
             for beta in exp["beta"] for alpha in exp["alpha"]]
    cells += [(name, [override_text(k, v) for k, v in over.items()])
              for name, over in (exp.get("baselines") or {}).items()]
    seeds = exp.get("seeds") if seeds is None else seeds  # every cell and baseline once each, named <run>_s<seed>
    if seeds is None:
        return [(name, common + sets + extra) for name, sets in cells]
    return [(f"{name}_s{seed}", common + sets + [f"seed={seed}"] + extra) for name, sets in cells for seed in seeds]


def report_options(exp: dict) -> ReportOptions:
    """The experiment's `report:` keys over ReportOptions' own defaults (an unknown key is a TypeError naming it)."""
    r = exp.get("report") or {}
    return dataclasses.replace(ReportOptions(), **{k: tuple(v) if isinstance(v, list) else v for k, v in r.items()})


FLEX_COLUMNS = ("lambda", "cvar", "mean_min_distance", "mean_speed", "cost", "collision_rate", "goal_rate")


def flexibility(out: Path, runs: list[tuple[str, list[str]]], tail: int = 5) -> list[dict]:
    """Mean of the last `tail` updates of each run's metrics.csv, per cell: written as
    <out>/flexibility.json and a Markdown table <out>/flexibility.md, and returned."""
    rows = []
    for name, sets in runs:
        path = out / name / "metrics.csv"
        if not path.exists():
            continue
        every = list(csv.DictReader(path.open()))
        metrics = every[-tail:]
        kv = dict(a.split("=", 1) for a in sets)
        # the run's resolved config: baselines inherit beta / alpha
        cfg = run_config(out / name) if (out / name / "config.json").exists() else None
        if cfg is not None:
            kv = {"env.beta": str(cfg.env.beta), "alpha": str(cfg.alpha), **kv}
        row = {"run": name, "beta": kv.get("env.beta", "-"), "alpha": kv.get("alpha", "-"),
               "updates": int(metrics[-1]["update"]) if metrics else 0,
               "bar out of reach": bar_watch.label(bar_watch.replay(cfg, every) if cfg is not None else None)}
        for k in FLEX_COLUMNS:
            vals = [float(m[k]) for m in metrics if m.get(k) not in (None, "", "nan")]
            row[k] = sum(vals) / len(vals) if vals else math.nan
        rows.append(row)
    (out / "flexibility.json").write_text(json.dumps(rows, indent=1))
    head = ["run", "beta", "alpha", "updates", *FLEX_COLUMNS, "bar out of reach"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append("| " + " | ".join(f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in head) + " |")
    (out / "flexibility.md").write_text(f"Mean of the last {tail} training updates per run.\n\n" + "\n".join(lines) + "\n")
    return rows


def done(run: Path, updates: int | None) -> bool:
    rows = (run / "metrics.csv").read_text().splitlines() if (run / "metrics.csv").exists() else []
    return (run / "checkpoint.pt").exists() and updates is not None and len(rows) - 1 >= updates


def train_batches(todo: list[tuple[str, list[str]]], base: Path, out: Path, batch: int, gpus: list[str],
                  dry_run: bool) -> int:
    """Train `todo`'s runs `batch` at a time (each from the start in its own directory, its GPU dealt from
    `gpus` in turn); the first failing run's exit code, else 0. `dry_run` prints the commands only."""
    for i in range(0, len(todo), batch):
        procs = []
        for j, (name, sets) in enumerate(todo[i:i + batch]):
            cmd = [sys.executable, "-m", "tg_gpudrive.cli", "train", "--config", str(base), "--out",
                   str(out / name), "--overwrite"] + [x for s in sets for x in ("--set", s)]
            env = dict(os.environ, CUDA_VISIBLE_DEVICES=gpus[j % len(gpus)]) if gpus else None
            print((f"CUDA_VISIBLE_DEVICES={env['CUDA_VISIBLE_DEVICES']} " if env else "") + " ".join(cmd), flush=True)
            if not dry_run:
                (out / name).mkdir(parents=True, exist_ok=True)
                log = (out / name / "train.log").open("w")
                procs.append((name, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log))
        for name, p, log in procs:
            rc = p.wait()
            log.close()
            print(f"{name}: exit {rc}", flush=True)
            if rc != 0:
                print(f"{name} failed; see {out / name / 'train.log'}", file=sys.stderr)
                return rc
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(CONFIGS / "experiments" / "grid.yaml"))
    ap.add_argument("--out", default="runs/experiments")
    ap.add_argument("--batch", type=int, default=None, help="runs trained at once (default: the config's)")
    ap.add_argument("--set", action="append", default=[], help="extra train override for every run")
    ap.add_argument("--gpus", default="", help="GPU ids to deal the runs of a batch over, e.g. 0,1 (default: "
                    "the environment's CUDA_VISIBLE_DEVICES for every run)")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--report-part", default="", metavar="K/N",
                    help="report-only, for runs K, K + N, ... (and the baselines when K is 0): one of N processes "
                         "filling the report's cache")
    ap.add_argument("--no-report", action="store_true", help="train and tabulate, skip the report")
    ap.add_argument("--tail", type=int, default=5, help="updates averaged in the flexibility table")
    ap.add_argument("--seeds", default="", help="training seeds in place of the experiment's, e.g. 1,2: one "
                    "seed's cells per GPU call")
    args = ap.parse_args(argv)
    part = None
    if args.report_part:
        try:
            part = tuple(int(x) for x in args.report_part.split("/"))
            if len(part) != 2 or not 0 <= part[0] < part[1]:
                raise ValueError
        except ValueError:
            ap.error(f"--report-part: expected K/N with 0 <= K < N, got {args.report_part!r}")
        args.report_only = True
    cfg_path = Path(args.config)
    try:
        exp = load_experiment(cfg_path)
    except ConfigError as e:
        ap.error(str(e))
    base = Path(exp["base"])
    if not base.is_absolute():  # beside the experiment config, in its configs/train/, or the repo's
        tries = [cfg_path.parent / base, cfg_path.parent.parent / "train" / base, CONFIGS / "train" / base]
        base = next((p for p in tries if p.exists()), tries[-1])
    out = Path(args.out)
    try:
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()] or None
    except ValueError:
        ap.error(f"--seeds: expected comma-separated integers, got {args.seeds!r}")
    runs = plan(exp, args.set, seeds)
    updates = dict(a.split("=", 1) for _, sets in runs[:1] for a in sets).get("updates")
    if updates is None:
        try:
            updates = load_yaml(base).get("updates")
        except ConfigError as e:
            ap.error(f"{cfg_path}: field 'base': {e}")
    batch = args.batch or int(exp.get("batch", 1))
    todo = [(n, s) for n, s in runs if not done(out / n, int(updates) if updates is not None else None)]
    gpus = [g.strip() for g in args.gpus.split(",") if g.strip()]
    if not args.report_only:
        rc = train_batches(todo, base, out, batch, gpus, args.dry_run)
        if rc != 0:
            return rc
    if args.dry_run:
        return 0
    flexibility(out, runs, args.tail)
    print((out / "flexibility.md").read_text(), flush=True)
    if args.no_report:
        return 0
    opts = report_options(exp)
    paths = [out / n for n, _ in runs]
    if part is not None:
        k, n = part
        paths = paths[k::n]
        opts = dataclasses.replace(opts, baselines=k == 0)
        if not paths:
            return 0
    report_main(paths, out / "report", opts)
    print(f"wrote {out / 'report' / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
