"""How the constraint's budget and a policy's own risk move with the knobs beta and alpha.

    python scripts/budget_by_knob.py --checkpoint shipped|constant|... --scenes procedural:all --num-scenes 64 \\
        --betas 2 3 4 5 6 --alphas 0 0.125 0.5 0.875 [--cost-limit 0.5] [--device cpu] [--json]

For every beta: one episode in every world under the expert replay of the logs and one under the
policy (sampled), and of each the discounted cost-to-go of every controlled agent at every step
(`learn.train.cost_to_go`, the run's gamma). Per (beta, alpha) it prints the logs' CVaR_alpha, the
budget a `cost_limit_mode: logs` run would ask (cost_limit x that), the policy's own CVaR_alpha, and
whether the policy already meets the budget (then the multiplier has nothing to push against, and the
knob acts through the cost advantage alone). alpha 0 is the plain mean: the budget of `lambda_on: mean`; the
policy's own at alpha 0, times cost_limit, is what `cost_limit_mode: start` asks of a run starting from it.
Numbers only; it never fails on them.
"""

from __future__ import annotations

import argparse
import json
import sys

import torch
import yaml

from tg_gpudrive.agents import check_specs, open_policy
from tg_gpudrive.cli import one_line_errors
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.learn.train import cost_to_go, sample_cvar


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default="shipped")
    p.add_argument("--scenes", default="procedural:all")
    p.add_argument("--num-scenes", type=int, default=64)
    p.add_argument("--seed", type=int, default=90000, help="scene seed (procedural) and sampling seed")
    p.add_argument("--betas", type=float, nargs="+", default=[2, 3, 4, 5, 6])
    p.add_argument("--alphas", type=float, nargs="+", default=[0.0, 0.125, 0.5, 0.875])
    p.add_argument("--cost-limit", type=float, default=0.5, help="the budget as a multiple of the logs' CVaR")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an engine setting for every beta, e.g. --set cost_partners=players --set cost_shape=hinge")
    p.add_argument("--device", default="cpu")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    check_specs([args.checkpoint], "--checkpoint")  # a mistyped run fails before the scenes are built
    src = resolve_scenes(args.scenes, n=args.num_scenes, seed=args.seed)
    scenes = [src.get(i) for i in range(min(args.num_scenes, len(src)))]
    rows = []
    for beta in args.betas:
        # a checkpoint runs in its own engine with beta set; a built-in policy in the default one
        sets = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.set)}  # values as --set reads them
        opened = open_policy(args.checkpoint, scenes, args.device, overrides=[f"beta={beta}", *args.set],
                             engine=EngineConfig(beta=beta, **sets), seed=args.seed, auto_reset=False)
        gamma = opened.trained.gamma if opened.trained else 0.99
        logs = cost_to_go(opened.sim, gamma)
        torch.manual_seed(args.seed)
        pol = cost_to_go(opened.sim, gamma, opened.policy)
        for alpha in args.alphas:
            lc, pc = float(sample_cvar(logs, alpha)), float(sample_cvar(pol, alpha))
            rows.append({"beta": beta, "alpha": alpha, "logs_cvar": lc, "budget": args.cost_limit * lc,
                         "policy_cvar": pc, "policy_meets_budget": pc <= args.cost_limit * lc,
                         "logs_states": int(logs.numel()), "policy_states": int(pol.numel())})
    if args.json:
        for r in rows:
            print(json.dumps(r))
        return 0
    print(f"{args.checkpoint} on {len(scenes)} scenes of {args.scenes}; budget = {args.cost_limit} x the logs' CVaR")
    print(f"{'beta':>5} {'alpha':>6} {'logs CVaR':>10} {'budget':>8} {'policy CVaR':>12}  meets")
    for r in rows:
        print(f"{r['beta']:>5g} {r['alpha']:>6g} {r['logs_cvar']:>10.3f} {r['budget']:>8.3f} {r['policy_cvar']:>12.3f}  "
              f"{'yes' if r['policy_meets_budget'] else 'no'}")
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("budget_by_knob.py", main))
