"""How good a world model is: likelihood of the logged actions, baselines, and closed-loop driving.

    dataset_nll            NLL (nats) of the expert actions of a sample set (data.collect), with top-1
                           accuracy (discrete) or the top component's absolute error (continuous)
    baseline_nlls          the same for input-blind baselines (uniform, constant velocity, marginal)
                           and an oracle bound (a Gaussian on the true logged action)
    sampled_displacement   minADE / minFDE (m) over sampled roll-outs against the logs
    background_rates       collision / off-road of background vehicles the model drives

The figures the shipped models reach on these metrics are in BENCHMARKS.md ("World model"). This
module only measures: it never changes a model's weights.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from tg_gpudrive.config import EngineConfig
from tg_gpudrive.engine.control import control_masks
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.agents.policy import action_grid
from tg_gpudrive.worldmodel.data import full_horizon_env
from tg_gpudrive.worldmodel.model import WorldModel
from tg_gpudrive.worldmodel.prior import WorldModelDriver


@torch.no_grad()
def dataset_nll(model: WorldModel, data: dict, batch: int = 4096) -> dict:
    """Mean negative log-likelihood (nats; per 2-D action when continuous) of the expert actions, and
    top-1 accuracy (discrete) or the mean absolute error of the most probable component's location
    (continuous: `mae_accel` m/s^2, `mae_curvature` 1/m)."""
    model.eval()
    model.set_layout(*data["layout"])
    dev = next(model.parameters()).device
    nll, hit, n = 0.0, 0, data["target"].shape[0]
    err = torch.zeros(2, dtype=torch.float64)
    for s in range(0, n, batch):
        out = model(data["obs"][s:s + batch].to(dev), data["hist"][s:s + batch].to(dev))
        y = data["target"][s:s + batch].to(dev)
        nll += float(model.nll(out, y).sum())
        if model.discrete:
            hit += int((out.argmax(-1) == y).sum())
        else:
            err += (out.mode_loc() - y).abs().sum(0).double().cpu()
    if model.discrete:
        return {"nll": nll / max(n, 1), "accuracy": hit / max(n, 1)}
    mae = (err / max(n, 1)).tolist()
    return {"nll": nll / max(n, 1), "mae_accel": mae[0], "mae_curvature": mae[1]}


def baseline_nlls(data: dict, env: EngineConfig, train: dict | None = None) -> dict:
    """NLL of the baselines on `data` (continuous configs: `continuous_baseline_nlls`):

    uniform            log(num_actions)
    constant_velocity  a discretised Gaussian centred on the no-op (a = 0, kappa = 0); its widths
                       are the best of a small sweep on `data` itself (a generous baseline)
    marginal           the action frequencies of `train` (add-one smoothed), when given
    expert_oracle      a discretised Gaussian (widths 0.7 m/s^2, 0.01 1/m: ExpertPrior's defaults, without
                       its uniform floor) centred on the true logged action: an oracle bound, not a rival"""
    if not env.discrete:
        return continuous_baseline_nlls(data, train)
    y = data["target"]
    grid = action_grid(env)
    out = {"uniform": math.log(env.num_actions)}
    best = float("inf")
    for sa in (0.5, 1.0, 2.0, 4.0):
        for sk in (0.01, 0.03, 0.1):
            logits = -0.5 * (((grid) / torch.tensor([sa, sk])) ** 2).sum(-1)
            lp = torch.log_softmax(logits, -1)
            best = min(best, float(-lp[y].mean()))
    out["constant_velocity"] = best
    if train is not None:
        counts = torch.bincount(train["target"], minlength=env.num_actions).float() + 1.0
        out["marginal"] = float(-torch.log(counts / counts.sum())[y].mean())
    z = (grid - data["expert"][:, None, :2]) / torch.tensor([0.7, 0.01])
    lp = torch.log_softmax(-0.5 * (z**2).sum(-1), -1)
    out["expert_oracle"] = float(-lp.gather(-1, y[:, None]).mean())
    return out


def continuous_baseline_nlls(data: dict, train: dict | None = None) -> dict:
    """NLL (nats per 2-D action) of continuous baselines on `data` (targets (N, 2)):

    constant_velocity_laplace   factorised Laplace centred on the no-op (0, 0), scales fitted to
                                `data` itself by maximum likelihood (a generous baseline)
    constant_velocity_gaussian  the same with a diagonal Gaussian
    marginal                    factorised Laplace at the median of `train`, scales fitted on `train`
    expert_oracle               ExpertPrior's Gaussian (0.7 m/s^2, 0.01 1/m) on the true logged action: it
                                knows the answer but its widths are fixed, so a sharp model can beat it"""
    y = data["target"].double()
    b = y.abs().mean(0).clamp(min=1e-9)
    out = {"constant_velocity_laplace": float((torch.log(2 * b) + 1).sum()),
           "constant_velocity_gaussian": float((0.5 * torch.log(2 * math.pi * math.e * (y**2).mean(0).clamp(
               min=1e-18))).sum())}
    if train is not None:
        t = train["target"].double()
        med = t.median(0).values
        bm = (t - med).abs().mean(0).clamp(min=1e-9)
        out["marginal"] = float((torch.log(2 * bm) + (y - med).abs() / bm).sum(-1).mean())
    sig = torch.tensor([0.7, 0.01], dtype=torch.float64)  # ExpertPrior's default widths
    z = (y - data["expert"][:, :2].double()) / sig
    out["expert_oracle"] = float((0.5 * z**2 + torch.log(sig * math.sqrt(2 * math.pi))).sum(-1).mean())
    return out


@torch.no_grad()
def sampled_displacement(policy_factory, scenes, env: EngineConfig, *, samples: int = 6, horizon: int = 60,
                         device: str = "cpu") -> dict:
    """minADE / minFDE (m) over `samples` rollouts of `horizon` steps from init_step, every controlled
    vehicle driven by `policy_factory()` (a fresh `policy(sim)`), against the logged positions.
    ADE averages the steps where the log is valid; FDE counts agents valid at the horizon."""
    env = sized_for(full_horizon_env(env), scenes)  # every agent of the scenes gets a slot
    S, n = samples, len(scenes)
    sim = Simulator([sc for sc in scenes for _ in range(S)], env, device)  # world = scene * S + sample
    sim.reset()
    W, A, T = sim.num_worlds, sim.max_agents, sim.model.num_steps
    ctrl = sim.policy_agents.clone()
    err_sum = torch.zeros(W, A, device=sim.pos.device)
    err_n = torch.zeros(W, A, device=sim.pos.device)
    policy = policy_factory()
    start = sim.world_step.long().clone()
    horizon = min(horizon, int(T - 1 - start.max()))
    for _ in range(horizon):
        policy(sim)
        sim.step()
        lp = sim.log_at("log_pos", sim.world_step)
        v = (sim.log_at("log_valid", sim.world_step) != 0) & ctrl
        e = (sim.pos - lp).norm(dim=-1)
        err_sum += e * v
        err_n += v
    fde_ok = v
    ade = (err_sum / err_n.clamp(min=1)).view(n, S, A)
    fde = e.view(n, S, A)
    ok = (err_n > 0).view(n, S, A)[:, 0]
    fok = fde_ok.view(n, S, A)[:, 0]
    return {"minADE": float(ade.min(1).values[ok].mean()), "minFDE": float(fde.min(1).values[fok].mean()),
            "agents": int(ok.sum()), "horizon_steps": horizon, "samples": S}


def drive_steps(sim, driver, steps: int | None = None):
    """Step `sim` `steps` times (default: to the episode's end), its background rows driven by `driver(sim)`
    or, when driver is None, by the expert replay; yields after each step, for the caller to read the state."""
    for _ in range(steps or sim.episode_length - 1):
        if driver is None:
            sim.use_expert_actions()
        else:
            driver(sim)
        sim.step()
        yield


@torch.no_grad()
def background_rates(driver, scenes, env: EngineConfig, *, steps: int | None = None, device: str = "cpu") -> dict:
    """Every eligible vehicle is a background vehicle driven by `driver(sim)` (or by the expert
    replay when driver is None) for one episode; rates of those that ever collide / go off-road."""
    env = sized_for(full_horizon_env(env), scenes)  # every agent of the scenes gets a slot
    bg = control_masks(scenes, env, "vehicles")
    sim = Simulator(scenes, env, device, controlled=[np.zeros_like(m) for m in bg], background=bg)
    sim.reset()
    rows = sim.background != 0
    coll = torch.zeros_like(rows)
    off = torch.zeros_like(rows)
    for _ in drive_steps(sim, driver, steps):
        coll |= sim.collided != 0
        off |= sim.offroad != 0
    n = int(rows.sum())
    return {"vehicles": n, "collision_rate": float((coll & rows).sum()) / max(n, 1),
            "offroad_rate": float((off & rows).sum()) / max(n, 1)}


def model_policy_factory(model: WorldModel, seed: int = 0):
    counter = iter(range(10**9))
    return lambda: WorldModelDriver(model, rows="policy", seed=seed + next(counter))
