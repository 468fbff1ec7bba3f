"""How much of the actor's advantage the distance cost carries, and how much the risk level alpha moves it.

    python scripts/advantage_balance.py --runs RUN [RUN ...] --scenes STORE [--alphas 0.125 0.875] \\
        [--num-worlds 32] [--rollouts 2] [--device cpu] [--cost-advantage gae|tail] [--json]

The actor of CCE-MAPPO ascends A = A_r - lambda A_c (update.minibatch_loss, losses.cce_mappo_actor_loss), where
A_c is the cost's advantage read from the run's quantile critic by the run's rule (TrainConfig.cost_advantage, or
`--cost-advantage` for every run: the same rollouts read by the other rule). alpha can move a policy only
through A_c, so two things bound what it can do: how large lambda A_c is beside A_r, and how different A_c is at
two alphas. Per run, its own networks and last multipliers drive its own training scenes (`--scenes` replaces a
store path that no longer exists here) for `--rollouts` rollouts of `--num-worlds` worlds, and over the live rows:
- std of A_r and of lambda A_c at the run's alpha (and their ratio);
- per alpha in `--alphas`, the std of lambda A_c and its correlation with the run's own;
- the share of live rows whose combined advantage changes sign between the first and the last alpha, and the mean
  |change| of A against the std of A (the normalised step the actor sees);
- the critic's tail: over the live states whose mean cost-to-go exceeds 1e-3, the median of CVaR at the last alpha
  over CVaR at the first, from the quantiles the critic gives each state (how much the risk level can tell states
  apart: a critic whose atoms crowd towards the mean, see TrainConfig.cost_kappa, gives little more than 1);
- which way each part of the advantage leans on speed: the correlation of A_r, and of -lambda A_c, with the
  acceleration of the action taken (negative: the part favours braking over speeding up); the cost's lean also
  per alpha in `--alphas`, the same rollouts and critic read at another risk level (0: the mean cost-to-go);
- where the actions lead in the critic's tail: the correlation of the taken action's acceleration with the change,
  from its state to the next, of the state's CVaR at the last alpha less its CVaR at the first (positive: speeding
  up leads into states whose cost tail stands further above their low-alpha reading).
Numbers only; it never fails on them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import torch

from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.cli import one_line_errors
from tg_gpudrive.config import TrainConfig, apply_overrides, from_dict
from tg_gpudrive.learn import losses as L
from tg_gpudrive.learn.train import Trainer
from tg_gpudrive.learn.update import advantages


def run_config(run: str, scenes: str | None, num_worlds: int, device: str,
               rule: str | None = None) -> tuple[TrainConfig, dict]:
    ck = load_checkpoint(run, "--runs")
    sets = [f"init_policy={Path(run) / 'checkpoint.pt' if Path(run).is_dir() else run}", f"num_worlds={num_worlds}",
            f"device={device}", "cuda_graphs=false", "compile_update=false", "resample_every=0"]
    if scenes:
        sets.append(f"scenes={scenes}")
    if rule:
        sets.append(f"cost_advantage={rule}")
    return from_dict(TrainConfig, apply_overrides(ck["config"], sets), run), ck


def accelerations(cfg: TrainConfig, act: torch.Tensor) -> torch.Tensor:
    """m/s^2 of each action taken: its bin of the acceleration grid (discrete), or its first component."""
    env = cfg.env
    if act.dim() > 3:
        return act[..., 0].float()
    grid = torch.linspace(-env.max_accel, env.max_accel, env.accel_bins, device=act.device)
    return grid[torch.div(act.long(), env.curvature_bins, rounding_mode="floor").clamp(0, env.accel_bins - 1)]


def balance(run: str, scenes: str | None, alphas: list[float], num_worlds: int, rollouts: int, device: str,
            rule: str | None = None) -> dict:
    cfg, ck = run_config(run, scenes, num_worlds, device, rule)
    with tempfile.TemporaryDirectory() as out:
        tr = Trainer(cfg, out, progress=False)
        lam = ck["lagrange"]["lam"].to(tr.device) if "lagrange" in ck else torch.zeros((), device=tr.device)
        rows = {"a_r": [], **{a: [] for a in alphas}, "own": []}
        quant, lam_used, accel, tail_step, step_accel = [], [], [], [], []
        for _ in range(rollouts):
            b = tr.collector.collect()
            C = b.mask.shape[-1]
            lam_c = lam[:C] if lam.dim() == 1 else lam.mean()  # per slot; one for all (0-d) or per vehicle (their mean)
            live = b.mask
            lam_used.append((lam_c * torch.ones(C, device=lam.device))[live.any(0).any(0)])
            quant.append(b.quant[:-1][live])
            acc_t = accelerations(cfg, b.act)
            accel.append(acc_t[live])
            # the critic's tail beyond its low-alpha reading, and how it changes from each state to the next
            q_all = b.quant.clamp(0.0, L.cost_to_go_bound(cfg.gamma))
            excess = L.cvar_from_quantiles(q_all, alphas[-1], True) - L.cvar_from_quantiles(q_all, alphas[0], True)
            on = live & (b.done == 0)  # the next state is the same agent's
            tail_step.append((excess[1:] - excess[:-1])[on])
            step_accel.append(acc_t[on])
            for a in {*alphas, cfg.alpha}:  # the update's own targets (update.advantages) at each risk level
                tg = advantages(dataclasses.replace(cfg, alpha=a), b)
                weighted = (lam_c * tg.adv_c)[live]
                if a in rows:
                    rows[a].append(weighted)
                if a == cfg.alpha:
                    rows["own"].append(weighted)
                    rows["a_r"].append(tg.adv_r[live])
    cat = {k: torch.cat(v).float() for k, v in rows.items()}
    a_r, own = cat["a_r"], cat["own"]
    first, last = cat[alphas[0]], cat[alphas[-1]]
    comb_first, comb_last = a_r - first, a_r - last
    q = torch.cat(quant).float()
    held = q.mean(-1) > 1e-3
    tail = L.cvar_from_quantiles(q[held], alphas[-1], True) / L.cvar_from_quantiles(q[held], alphas[0], True)
    corr = lambda x, y: float(torch.corrcoef(torch.stack([x, y]))[0, 1]) if x.std() > 0 and y.std() > 0 else 0.0  # noqa: E731
    acc = torch.cat(accel).float()
    return {
        "run": run, "alpha": cfg.alpha, "beta": cfg.env.beta, "live_rows": int(a_r.numel()),
        "lambda_mean": float(torch.cat(lam_used).mean()),  # over the slots that held agents
        "std_a_r": float(a_r.std()), "std_lambda_a_c": float(own.std()),
        "cost_share": float(own.std() / a_r.std().clamp(min=1e-12)),
        "per_alpha": {str(a): {"std_lambda_a_c": float(cat[a].std()), "corr_with_own": corr(cat[a], own),
                               "cost_lean": corr(-cat[a], acc)} for a in alphas},
        "sign_flips": float(((comb_first > 0) != (comb_last > 0)).float().mean()),
        "mean_abs_change_over_std": float((comb_first - comb_last).abs().mean() / comb_first.std().clamp(min=1e-12)),
        "tail_ratio": float(tail.median()) if len(tail) else float("nan"),
        "cost_advantage": cfg.cost_advantage,
        "reward_lean": corr(a_r, acc), "cost_lean": corr(-own, acc),
        "tail_step_lean": corr(torch.cat(tail_step).float(), torch.cat(step_accel).float()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", nargs="+", required=True, help="run directories or policy checkpoints")
    p.add_argument("--scenes", default=None, help="the runs' training scenes here (default: as their configs say)")
    p.add_argument("--alphas", type=float, nargs="+", default=[0.125, 0.875])
    p.add_argument("--num-worlds", type=int, default=32)
    p.add_argument("--rollouts", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--cost-advantage", choices=("gae", "tail"), default=None,
                   help="read every run's cost advantage by this rule (default: each run's own)")
    p.add_argument("--json", action="store_true", help="one JSON line per run instead of the table")
    args = p.parse_args(argv)
    if not args.json:
        print("| run | beta | alpha | live rows | lambda | std A_r | std lambda A_c | cost share | "
              + " | ".join(f"std at alpha {a} (corr, cost lean)" for a in args.alphas)
              + f" | sign flips {args.alphas[0]} -> {args.alphas[-1]} | mean change / std A"
              + f" | critic's CVaR {args.alphas[-1]} / {args.alphas[0]} | rule | reward lean | cost lean"
              + " | tail step lean |")
        print("|" + "---|" * (15 + len(args.alphas)))
    for run in args.runs:
        r = balance(run, args.scenes, args.alphas, args.num_worlds, args.rollouts, args.device, args.cost_advantage)
        if args.json:
            print(json.dumps(r), flush=True)
            continue
        per = " | ".join(f"{v['std_lambda_a_c']:.4f} ({v['corr_with_own']:.2f}, {v['cost_lean']:+.3f})"
                        for v in r["per_alpha"].values())
        print(f"| {Path(run).name} | {r['beta']} | {r['alpha']} | {r['live_rows']} | {r['lambda_mean']:.2f} | "
              f"{r['std_a_r']:.4f} | {r['std_lambda_a_c']:.4f} | {r['cost_share']:.3f} | {per} | "
              f"{r['sign_flips']:.3f} | {r['mean_abs_change_over_std']:.3f} | {r['tail_ratio']:.2f} | "
              f"{r['cost_advantage']} | {r['reward_lean']:+.3f} | {r['cost_lean']:+.3f} | {r['tail_step_lean']:+.3f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(one_line_errors("advantage_balance.py", main))
