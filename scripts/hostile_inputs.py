"""Hostile inputs against the CLI, as a new user would type them: each case runs in a fresh process and
the table says what came out (exit code, the last line on stderr, whether a traceback was printed).

    python scripts/hostile_inputs.py [--work DIR]      # prints a markdown table (CPU, a few minutes)

The cases need no dataset: procedural scenes, a tiny training run made first (its checkpoint), the
shipped policy and world model, and files damaged on purpose in --work. Numbers only: it never fails;
the tests (tests/test_reliability.py, tests/test_fuzz.py) hold the behaviour.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SMALL = REPO / "configs" / "train" / "small_cpu.yaml"
TINY = ["--config", str(SMALL), "--set", "num_worlds=2", "--set", "num_scenes=2", "--set", "rollout_steps=4",
        "--set", "epochs=1", "--set", "minibatches=1", "--set", "hidden=16", "--set", "quantiles=4", "--set",
        "updates=1", "--set", "device=cpu"]
POLICY = REPO / "tg_gpudrive" / "policies" / "shipped.pt"
WORLD_MODEL = REPO / "tg_gpudrive" / "worldmodel" / "shipped.pt"


def cases(work: Path, run: Path) -> list[tuple[str, list[str]]]:
    (work / "cut.json").write_text('{"name": "x", "objects": [')
    (work / "a_file").write_text("not a folder")
    (work / "bad.yaml").write_text("lr: [1, 2\n")
    damaged = work / "damaged_run"
    damaged.mkdir(exist_ok=True)
    (damaged / "checkpoint.pt").write_bytes(b"\0" * 64)
    ev = ["evaluate", "--checkpoint", str(run), "--scenes", "procedural:merge", "--episodes", "2"]
    return [
        ("train --set env.beta=-1", ["train", "--out", str(work / "r1"), *TINY, "--set", "env.beta=-1"]),
        ("train --set lr=0", ["train", "--out", str(work / "r1"), *TINY, "--set", "lr=0"]),
        ("train --set lr=-0.001", ["train", "--out", str(work / "r1"), *TINY, "--set", "lr=-0.001"]),
        ("train --set alpha=1 (CVaR level in [0, 1))", ["train", "--out", str(work / "r1"), *TINY, "--set", "alpha=1"]),
        ("train --set minibatches=1000", ["train", "--out", str(work / "r1"), *TINY, "--set", "minibatches=1000"]),
        ("train --set env.partner_k=.nan", ["train", "--out", str(work / "r1"), *TINY, "--set", "env.partner_k=.nan"]),
        ("train --set bogus_key=3", ["train", "--out", str(work / "r1"), *TINY, "--set", "bogus_key=3"]),
        ("train --config <broken YAML>", ["train", "--config", str(work / "bad.yaml")]),
        ("train --set lr=[1 (broken YAML value)", ["train", *TINY, "--set", "lr=[1"]),
        ("train without --config", ["train", "--out", str(work / "r1")]),
        ("train --resume <run> --set env.partner_k=3", ["train", "--resume", str(run), "--set", "env.partner_k=3"]),
        ("train --resume <missing>", ["train", "--resume", str(work / "missing")]),
        ("train --set prior_model=<policy checkpoint>", ["train", "--out", str(work / "r1"), *TINY, "--set",
                                                         f"prior_model={POLICY}"]),
        ("evaluate --checkpoint <run> --set bogus_key=3", [*ev, "--set", "bogus_key=3"]),
        ("evaluate --checkpoint <run> --set partner_k=3", [*ev, "--set", "partner_k=3"]),
        ("evaluate --checkpoint <run> --set dynamics=delta_local", [*ev, "--set", "dynamics=delta_local"]),
        ("evaluate --checkpoint <run> --set collision_mode=stop (applied)", [*ev, "--set", "collision_mode=stop"]),
        ("evaluate --checkpoint <world model>", ["evaluate", "--checkpoint", str(WORLD_MODEL), "--scenes",
                                                 "procedural:merge", "--episodes", "2"]),
        ("evaluate --checkpoint <damaged, no previous>", ["evaluate", "--checkpoint", str(damaged), "--scenes",
                                                          "procedural:merge", "--episodes", "2"]),
        ("simulate --background-model <policy checkpoint>", ["simulate", "--scenes", "procedural:merge", "--worlds",
                                                             "2", "--background", "world_model", "--background-model",
                                                             str(POLICY), "--control", "nearest_conflict",
                                                             "--control-k", "1"]),
        ("simulate --scenes <cut-off JSON>", ["simulate", "--scenes", str(work / "cut.json"), "--worlds", "1"]),
        ("convert --simplify nan", ["convert", str(REPO / "tests" / "data"), "--out", str(work / "s1"),
                                    "--simplify", "nan"]),
        ("convert --out <a file>", ["convert", str(REPO / "tests" / "data"), "--out", str(work / "a_file")]),
        ("render --out x.txt", ["render", "--scenes", "procedural:merge", "--out", str(work / "x.txt")]),
    ]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    args = p.parse_args(argv)
    work = Path(args.work or tempfile.mkdtemp(prefix="hostile_"))
    work.mkdir(parents=True, exist_ok=True)
    run = work / "run"
    cli = [sys.executable, "-m", "tg_gpudrive.cli"]
    subprocess.run([*cli, "train", "--out", str(run), "--overwrite", *TINY, "--set", "env.partner_k=4"],
                   capture_output=True, check=True)
    print("| input | exit | traceback | what the user reads (last stderr line) |")
    print("|---|---:|---|---|")
    for name, argv_ in cases(work, run):
        r = subprocess.run([*cli, *argv_], capture_output=True, text=True)
        lines = [ln for ln in r.stderr.replace("\r", "\n").splitlines() if ln.strip() and "it/s" not in ln
                 and "update/s" not in ln]
        last = (lines[-1] if lines else "(nothing)").replace("|", "\\|").replace(str(work), "<work>")
        print(f"| `{name}` | {r.returncode} | {'yes' if 'Traceback' in r.stderr else 'no'} | {last[:220]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
