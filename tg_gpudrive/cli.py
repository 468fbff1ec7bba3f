"""`tg-gpudrive`: the one command-line entry.

    tg-gpudrive simulate  --scenes procedural:all --worlds 64 --policy expert
    tg-gpudrive benchmark --device cuda --json
    tg-gpudrive convert   womd_dir/ --out store/

Every subcommand takes the engine config (`--env-config`, default
configs/env/default.yaml, plus `--set key=value` overrides).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys

from tg_gpudrive.config import REPO_CONFIGS, ConfigError, EngineConfig, load_config

log = logging.getLogger("tg_gpudrive")


def _engine_args(p: argparse.ArgumentParser) -> None:
    default = REPO_CONFIGS / "env" / "default.yaml"
    p.add_argument("--env-config", default=str(default) if default.exists() else None,
                   help="engine YAML (default: configs/env/default.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override an engine config key, e.g. --set beta=3 --set reward.collision=-2")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--seed", type=int, default=0)


def _scene_args(p: argparse.ArgumentParser, default: str = "procedural:all") -> None:
    p.add_argument("--scenes", default=default,
                   help="procedural:<type> | procedural:all | a store, .json/.tfrecord file or directory")
    p.add_argument("--num-scenes", type=int, default=None,
                   help="distinct scenes to draw from the source (default: min(worlds, source size))")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tg-gpudrive", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="roll out a built-in policy and report goal/collision/off-road rates")
    _scene_args(p)
    _engine_args(p)
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--steps", type=int, default=None, help="default: one episode")
    p.add_argument("--policy", default="expert", choices=["expert", "random", "constant"])
    p.add_argument("--collision-mode", choices=["ignore", "stop", "remove"], default=None)
    p.add_argument("--json", action="store_true", help="print one JSON object")

    p = sub.add_parser("benchmark", help="engine agent steps/s for several world counts")
    _scene_args(p)
    _engine_args(p)
    p.add_argument("--worlds", type=int, nargs="*", default=None)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--no-graph", action="store_true", help="plain launches instead of a CUDA graph")
    p.add_argument("--json", action="store_true", help="one JSON object per line")

    p = sub.add_parser("convert", help="pack WOMD files (json / tfrecord) into a memory-mapped store")
    p.add_argument("inputs", nargs="+", help="files or directories")
    p.add_argument("--out", required=True)
    p.add_argument("--no-resume", action="store_true", help="start over instead of skipping converted files")
    p.add_argument("--simplify", type=float, default=None, metavar="METRES",
                   help="simplify road polylines with this tolerance")
    return parser


def _engine_config(args) -> EngineConfig:
    overrides = list(args.set)
    if getattr(args, "collision_mode", None):
        overrides.append(f"collision_mode={args.collision_mode}")
    return load_config(EngineConfig, args.env_config, overrides)


def _load_scenes(args, worlds: int):
    from tg_gpudrive.data.sampler import SceneSampler
    from tg_gpudrive.data.sources import resolve_scenes

    n = args.num_scenes or worlds
    src = resolve_scenes(args.scenes, n=n, seed=args.seed)
    sampler = SceneSampler(src, worlds, replacement=False, seed=args.seed)
    return sampler.sample()


def cmd_simulate(args) -> int:
    from tg_gpudrive.rollout import builtin_policy, run_rollout
    from tg_gpudrive.simulator import Simulator

    cfg = _engine_config(args)
    scenes = _load_scenes(args, args.worlds)
    sim = Simulator(scenes, cfg, args.device)
    steps = args.steps or sim.episode_length
    out = run_rollout(sim, builtin_policy(args.policy, args.seed, sim.device), steps, progress=not args.json)
    out.update({"policy": args.policy, "collision_mode": cfg.collision_mode, "scenes": args.scenes})
    if args.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            if k != "per_type":
                print(f"{k:>22}: {v:.4g}" if isinstance(v, float) else f"{k:>22}: {v}")
        for name, r in out.get("per_type", {}).items():
            print(f"{name:>22}: goal {r['goal_rate']:.3f}  collision {r['collision_rate']:.3f}  "
                  f"offroad {r['offroad_rate']:.3f}  ({r['episodes']} agent episodes)")
    return 0


def cmd_benchmark(args) -> int:
    from tg_gpudrive.benchmark import main

    args.engine_config = _engine_config(args)
    args.num_scenes = args.num_scenes or 36
    return main(args)


def cmd_convert(args) -> int:
    from tg_gpudrive.data.store import convert

    report = convert(args.inputs, args.out, resume=not args.no_resume, progress=True,
                     simplify_tolerance=args.simplify)
    d = dataclasses.asdict(report) if dataclasses.is_dataclass(report) else dict(vars(report))
    print(json.dumps(d, default=str, indent=1))
    return 0


COMMANDS = {"simulate": cmd_simulate, "benchmark": cmd_benchmark, "convert": cmd_convert}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return COMMANDS[args.command](args)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        print(f"tg-gpudrive {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
