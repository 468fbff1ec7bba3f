"""The command line of the world model: `tg-gpudrive train-world-model` (tg_gpudrive.cli adds
these arguments to its subcommand and calls `run`), also `python -m tg_gpudrive.worldmodel.cli`.

It only parses, reads the config and prints; the work is train.train_world_model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tg_gpudrive.config import ConfigError, apply_overrides, from_dict, load_yaml
from tg_gpudrive.worldmodel import train


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="configs/worldmodel/<name>.yaml (required)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set steps=500 --set env.road_k=64 (repeatable; default: none)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the run saved in DIR (default: start a new run)")
    p.add_argument("--out", default=None, help="run directory (default: out_dir of the config)")
    p.add_argument("--json", action="store_true", help="print the final metrics as JSON")


def run(args) -> int:
    """`tg-gpudrive train-world-model` with parsed `args` (see add_arguments)."""
    if args.resume and (Path(args.resume) / "config.json").exists():
        data = json.loads((Path(args.resume) / "config.json").read_text())
    else:
        data = load_yaml(args.config)
    cfg = from_dict(train.WorldModelConfig, apply_overrides(data, args.set), args.config)
    res = train.train_world_model(cfg, out_dir=args.out or args.resume, resume=args.resume, progress=not args.json)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"world model: {res['model']}  val nll {res.get('val_nll', float('nan')):.3f}  "
              f"baselines {json.dumps(res.get('val_baselines', {}))}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="tg-gpudrive train-world-model", description=train.__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"tg-gpudrive train-world-model: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
