"""One CCE-MAPPO update over a rollout (TrafficGamer), read top to bottom: `ppo_update`.

1. Advantages: GAE of the reward against the critic; the cost critic (as it was during the rollout, a
   target network updated once per PPO update) gives CVaR_alpha-GAE advantages of the cost and n-step
   targets for its quantiles (losses.gae, losses.cvar_gae, losses.cost_quantile_targets).
2. The Lagrange step: lambda >= 0 rises while CVaR_alpha of the cost-to-go, averaged over the agents'
   live states (per agent slot with `per_agent_lambda`), exceeds the budget. The multiplier the actor
   loss uses is the one from before this step.
3. Epochs of shuffled minibatches of groups (one group = one world at one step): per agent the actor
   minimises PPO-clip(A_reward - lambda A_cost) - entropy_coef H + eta1 KL(pi || prior)
   + (1 / eta2) KL(pi || pi_rollout) on its live rows (losses.cce_mappo_actor_loss); the critic
   regresses the reward lambda-returns and the quantile critic the cost targets (quantile Huber).
   Actor and critic share one Adam optimiser but their gradients are clipped apart.

The loss parts accumulate on the device and are read back once, at the end (the row selections of the
live agents are the only other host syncs).
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch.profiler import record_function as phase  # named ranges for scripts/profile_train.py

from tg_gpudrive.agents.policy import BehaviourPrior
from tg_gpudrive.config import TrainConfig
from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn import losses as L
from tg_gpudrive.learn.collector import ByName, Networks, NonFinite, Rollout
from tg_gpudrive.learn.compiling import Compiled

if TYPE_CHECKING:
    from tg_gpudrive.learn.graphs import StepGraphs

Tensor = torch.Tensor
MAX_TARGET_SAMPLES = 16  # target quantiles per row in the quantile loss (its N x M term is the update's largest)


@dataclass
class Targets:
    """What step 1 computes, (T, W, C, ...) like the rollout: the reward advantages and lambda-returns,
    the cost advantages, CVaR_alpha and the mean of every state's cost-to-go ((T + 1, W, C)) and the
    quantile targets."""

    adv_r: Tensor
    ret_r: Tensor
    adv_c: Tensor
    cvar: Tensor
    q_target: Tensor
    ctg_mean: Tensor

    def constraint(self, cfg: TrainConfig, cost: Tensor) -> Tensor:
        """The per-state value lambda is stepped on (`lambda_on`), (T + 1, W, C) like the critic's (row T
        unused): the critic's CVaR_alpha or mean, or each step's sampled cost `cost` (T, W, C) x 1 / (1 - gamma)."""
        if cfg.lambda_on.startswith("sampled"):  # the rollout's own costs, no critic
            rate = cost / (1.0 - cfg.gamma)
            return torch.cat([rate, torch.zeros_like(rate[:1])])
        return self.cvar if cfg.lambda_on == "cvar" else self.ctg_mean


@dataclass
class Groups(ByName):
    """A rollout and its targets as (T * W, C, ...) groups, one group = one world at one step: what a
    minibatch indexes (see Rollout for the entries it shares)."""

    obs: Tensor
    act: Tensor
    logp: Tensor
    mask: Tensor
    prior: Tensor
    old: Tensor | tuple[Tensor, Tensor]
    adv_r: Tensor
    adv_c: Tensor
    ret_r: Tensor
    q_target: Tensor
    hist: Tensor | None = None
    prior_weight: Tensor | None = None


def advantages(cfg: TrainConfig, batch: Rollout) -> Targets:
    """Step 1 over the (world, slot) columns that act at some step of the rollout, under half of W x C on
    procedural scenes; the other columns get zeros, which nothing reads (the losses and the multipliers read
    live rows). The critic's quantiles come sorted (Rollout.quant), so CVaR reads them as they are."""
    T, W, C = batch.mask.shape
    cols = batch.mask.reshape(T, W * C).any(0).nonzero(as_tuple=True)[0]  # a host sync

    def take(x: Tensor) -> Tensor:
        return x.reshape(x.shape[0], W * C, *x.shape[3:])[:, cols]

    def put(x: Tensor) -> Tensor:
        full = x.new_zeros((x.shape[0], W * C, *x.shape[2:]))
        full[:, cols] = x
        return full.view(x.shape[0], W, C, *x.shape[2:])

    targets = compiled_column_targets() if cfg.compile_rollout else column_targets
    out = targets(cfg, take(batch.reward), take(batch.value), take(batch.cost), take(batch.quant),
                  take(batch.done) != 0)
    return Targets(*(put(x) for x in out))


def column_targets(cfg: TrainConfig, reward: Tensor, value: Tensor, cost: Tensor, quant: Tensor,
                   done: Tensor) -> tuple[Tensor, ...]:
    """Step 1 on the acting columns (T or T + 1 rows, columns): the Targets fields in their order."""
    adv_r, ret_r = L.gae(reward, value, done, cfg.gamma, cfg.gae_lambda)
    # the cost critic is read inside the cost-to-go's support (targets, advantages, constraint)
    quant = quant.clamp(0.0, L.cost_to_go_bound(cfg.gamma))
    if cfg.cost_advantage == "tail":
        adv_c, cvar = L.cvar_tail_advantage(cost, quant, done, cfg.alpha, cfg.gamma, cfg.gae_lambda)
    else:
        adv_c, cvar = L.cvar_gae(cost, quant, done, cfg.alpha, cfg.gamma, cfg.gae_lambda, presorted=True)
    q_target = L.cost_quantile_targets(cost, quant, done, cfg.gamma, cfg.cost_nstep)
    return adv_r, ret_r, adv_c, cvar, q_target, quant.mean(-1)


@functools.cache
def compiled_column_targets():
    """column_targets through torch.compile (compile_rollout, compiling.Compiled): the recursions over the
    rollout's steps unrolled and fused, the column count (dimension 1 of the five tensors) a dynamic size."""
    return Compiled(column_targets, "advantages and targets", tuple((i, 1) for i in range(1, 6)))


def vehicle_lagrange_step(cfg: TrainConfig, mask: Tensor, value: Tensor, lagrange: L.LagrangeMultiplier,
                          budget: Tensor, world_keys: Tensor, step: bool = True) -> tuple[Tensor, Tensor]:
    """`lambda_per_vehicle`: the multipliers are a (scenes, env.max_agents) table; world w holds scene
    `world_keys[w]` (its index in the whole source, the same on every rank), so its slot c is the vehicle
    (world_keys[w], c). Each vehicle's constraint is the mean of `value` over its live states in every world
    that holds its scene, on every rank; only vehicles with states move. (the multipliers before the step
    per world and slot, (W, C); which vehicles had states). `step` False: the multipliers stay as they are."""
    C = mask.shape[-1]
    S, A = lagrange.value.shape
    total = torch.zeros((S, A), device=mask.device)
    count = torch.zeros((S, A), device=mask.device)
    total[:, :C].index_add_(0, world_keys, (value[:-1] * mask).sum(0))
    count[:, :C].index_add_(0, world_keys, mask.sum(0).float())
    dist_util.all_reduce_sum_({"total": total, "count": count})
    seen = count > 0
    lam = lagrange.value.detach().clone()
    if not cfg.constraint:
        lam = torch.zeros_like(lam)
    elif step:  # a vehicle without states keeps its multiplier
        lagrange.update(torch.where(seen, total / count.clamp(min=1), budget), budget)
    return lam[world_keys, :C], seen


def vehicle_cvar(value: Tensor, mask: Tensor, alpha: float) -> Tensor:
    """(C,): per slot, CVaR_alpha over the vehicles that held it (one a world) of each one's mean `value` (T, W, C)
    over its live steps: the mean of the largest ceil((1 - alpha) x vehicles), at least one; 0 for a slot no
    vehicle held."""
    n = mask.sum(0)
    per_vehicle = (value * mask).sum(0) / n.clamp(min=1)
    held = n > 0
    count = held.sum(0)
    k = torch.ceil((1.0 - alpha) * count).clamp(min=1)
    ranked = torch.where(held, per_vehicle, -torch.inf).sort(0, descending=True).values
    top = torch.arange(ranked.shape[0], device=value.device)[:, None] < torch.minimum(k, count)
    return torch.where(top, ranked, 0.0).sum(0) / k


def slot_constraint(cfg: TrainConfig, mask: Tensor, value: Tensor) -> Tensor:
    """(C,): each slot's constraint of the rollout: the mean of `value` (T + 1, W, C) over its live states, or
    with `lambda_on: sampled_cvar` the CVaR_alpha over its vehicles of theirs (vehicle_cvar)."""
    if cfg.lambda_on == "sampled_cvar":
        return vehicle_cvar(value[:-1], mask, cfg.alpha)
    return (value[:-1] * mask).sum((0, 1)) / mask.sum((0, 1)).clamp(min=1)


def lagrange_step(cfg: TrainConfig, mask: Tensor, value: Tensor, lagrange: L.LagrangeMultiplier,
                  budget: Tensor, step: bool = True) -> tuple[Tensor, Tensor]:
    """Step the multipliers on this rollout's constraint (equal on all ranks); `value` (T + 1, W, C) is
    each state's CVaR_alpha or mean cost-to-go (`Targets.constraint`). (the multipliers the actor loss
    uses: those from before the step, per slot [0, C) or one; which of the env.max_agents slots had
    agents in the rollout on any rank). `step` False: the multipliers stay as they are."""
    C = mask.shape[-1]
    jc = torch.zeros(cfg.env.max_agents, device=mask.device)
    jc[:C] = slot_constraint(cfg, mask, value)
    seen = torch.zeros(cfg.env.max_agents, dtype=torch.bool, device=mask.device)
    seen[:C] = mask.any((0, 1))
    jc, seen = dist_util.all_reduce_mean(jc), dist_util.all_reduce_mean(seen.float()) > 0
    if not cfg.per_agent_lambda:  # one multiplier for all: the mean over the slots that had agents
        jc = (jc * seen).sum() / seen.sum().clamp(min=1)
    lam = lagrange.value.detach().clone()
    if not cfg.constraint:
        lam = torch.zeros_like(lam)
    elif step:  # a slot without agents in this rollout keeps its multiplier
        lagrange.update(jc if not cfg.per_agent_lambda else torch.where(seen, jc, budget), budget)
    return (lam[:C] if cfg.per_agent_lambda else lam), seen


def flatten(batch: Rollout, tg: Targets, discrete: bool) -> Groups:
    T, W = batch.reward.shape[:2]
    flat = lambda x: None if x is None else x.reshape(T * W, *x.shape[2:])  # noqa: E731
    old = flat(batch.old) if discrete else (flat(batch.old[0]), flat(batch.old[1]))
    return Groups(obs=flat(batch.obs), act=flat(batch.act), logp=flat(batch.logp), mask=flat(batch.mask),
                  prior=flat(batch.prior), old=old, adv_r=flat(tg.adv_r), adv_c=flat(tg.adv_c),
                  ret_r=flat(tg.ret_r), q_target=flat(tg.q_target), hist=flat(batch.hist),
                  prior_weight=flat(batch.prior_weight))


def live_only(x: Tensor, w: Tensor) -> Tensor:
    """`x` (R, ...) with the rows where `w` (R,) is 0 set to 0: dead rows read finite, valid values (action 0,
    zero observations), so their zero weight cannot meet a non-finite filler in the backward pass."""
    keep = (w > 0).reshape(-1, *(1,) * (x.dim() - 1))
    return torch.where(keep, x, 0)


def minibatch_loss(cfg: TrainConfig, b: Groups, idx: Tensor, lam: Tensor, nets: Networks,
                   prior: BehaviourPrior, live: tuple[Tensor, Tensor] | None = None,
                   row_weight: Tensor | None = None, autocast: bool = True) -> tuple[Tensor, dict]:
    """CCE-MAPPO loss of the groups `idx`: the actor on their live rows, the critics on the groups
    (attention over each group's slots) with their heads on the live rows only. `live`: the live rows as
    (position in idx, slot), in row-major order, when the caller has them (else found here, a host sync).
    `row_weight`: `live` is then rows of a fixed count (padded_rows), the live ones weighted 1 and fillers 0
    in every mean (the same losses and gradients, whatever the fillers read): shapes that do not depend on
    the minibatch's live rows, as a CUDA graph needs (graphs.StepGraphs). `autocast`: the networks' forward
    passes under nets.autocast here; False: the caller runs the whole loss under it (compiled_loss), and what
    follows the networks is the same float32 arithmetic either way."""
    mi = b.mask[idx]
    weight, w = 1.0, row_weight
    if w is not None:
        g, c = live
    else:
        # the actor is per agent: run it on the live rows only (often under half of W x C)
        g, c = mi.nonzero(as_tuple=True) if live is None else live
        if len(g) == 0:  # a zero-weight dummy row: the step's backward pass still reaches every weight
            g, c, weight = torch.zeros(1, dtype=torch.long, device=idx.device), torch.zeros(
                1, dtype=torch.long, device=idx.device), 0.0
    rows = idx[g]

    def pick(x):  # the rows' entries of a (groups, C, ...) tensor
        return x[rows, c] if w is None else live_only(x[rows, c], w)

    if lam.dim() == 2:  # per vehicle: (W, C) of the rollout's worlds; group t * W + w is world w at step t
        lam_rows = lam[rows % lam.shape[0], c]
    else:
        lam_rows = lam[c] if cfg.per_agent_lambda else lam
    obs = pick(b.obs)
    flat = g * mi.shape[1] + c
    with nets.autocast(cache=w is None) if autocast else contextlib.nullcontext():
        out = nets.actor(obs, c, None if b.hist is None else pick(b.hist))
        v, q = nets.critic(b.obs[idx], mi, None if weight == 0.0 else flat, head_rows=flat, row_weight=w)
    out, v, q = nets.float_out(out), v.float(), q.float()
    head = nets.head
    d = head.dist(out)
    logp = d.log_prob(pick(b.act))
    old_out = pick(b.old) if head.discrete else (pick(b.old[0]), pick(b.old[1]))
    if cfg.eta1 <= 0:  # plain MAPPO: no magnet to evaluate
        kl_prior = torch.zeros_like(logp)
    else:
        if head.discrete:  # the discrete magnet's logits are stored
            prior_out = pick(b.prior)
        else:  # the continuous one is rebuilt from its context, in float32 even under a caller's autocast
            with torch.autocast("cuda", enabled=False):
                prior_out = prior.distribution(pick(b.prior), obs.float())
        kl_prior = head.kl(out, prior_out)
        if b.prior_weight is not None:  # the magnet of a share of the rows (magnet_fraction)
            kl_prior = kl_prior * pick(b.prior_weight)
    loss_pi, st = L.cce_mappo_actor_loss(
        logp, pick(b.logp), pick(b.adv_r), pick(b.adv_c), lam_rows,
        d.entropy(), kl_prior, head.kl(out, old_out), clip_eps=cfg.clip, entropy_coef=cfg.entropy_coef,
        eta1=cfg.eta1, eta2=cfg.eta2, normalize_advantages=cfg.normalize_advantages, mask=w)
    loss_v = L.masked_mean((v - pick(b.ret_r)).pow(2), w)
    # quantile loss on live rows, against at most MAX_TARGET_SAMPLES evenly spaced target samples
    tq = pick(b.q_target)
    if tq.shape[-1] > MAX_TARGET_SAMPLES:
        tq = tq[..., torch.linspace(0, tq.shape[-1] - 1, MAX_TARGET_SAMPLES, device=tq.device).round().long()]
    loss_q = L.quantile_huber_loss(q, tq, kappa=cfg.cost_kappa, mask=w)
    loss = weight * (loss_pi + cfg.value_coef * (loss_v + loss_q))
    parts = {"loss/policy": loss_pi, "loss/value": loss_v, "loss/cost_quantile": loss_q,
             "kl/prior": st["kl_prior"], "kl/prev": st["kl_prev"], "entropy": st["entropy"],
             "clip_frac": st["clip_frac"]}
    return loss, parts


def padded_rows(live: tuple[Tensor, Tensor], cap: int,
                out: tuple[Tensor, Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The live rows (position, slot) of a minibatch as `cap` rows for minibatch_loss's `row_weight`:
    (positions, slots, weights), the live rows first with weight 1, then fillers at (0, 0) with weight 0.
    `out`: three tensors of `cap` entries to write them into (a CUDA graph's fixed buffers)."""
    g, c = live
    n = len(g)
    if n > cap:
        raise ValueError(f"{n} live rows do not fit in {cap}")
    if out is None:
        out = (torch.empty(cap, dtype=torch.long, device=g.device), torch.empty(cap, dtype=torch.long, device=g.device),
               torch.empty(cap, device=g.device))
    for dst, src in zip(out[:2], (g, c)):
        dst[:n].copy_(src)
        dst[n:].zero_()
    out[2][:n].fill_(1.0)
    out[2][n:].zero_()
    return out


def epoch_live_rows(mask: Tensor, mb: int) -> list[tuple[Tensor, Tensor]]:
    """The live rows of each minibatch of an epoch, found at once: `mask` (groups in the epoch's order, C),
    minibatch k its groups [k mb, (k + 1) mb); per minibatch (position in it, slot), row-major. One host
    sync an epoch, not one per minibatch, so the host queues the minibatches' kernels ahead of the GPU."""
    g, c = mask.nonzero(as_tuple=True)
    counts = torch.bincount(g // mb, minlength=-(-mask.shape[0] // mb)).tolist()
    return list(zip((g % mb).split(counts), c.split(counts)))


def make_optimizer(cfg: TrainConfig, params: list[Tensor], cuda: bool) -> torch.optim.Optimizer:
    """The learner's Adam. On the GPU it is the fused one (one kernel steps every parameter; the multi-tensor
    Adam's per-tensor step counters and launches cost host time at each optimiser step), with its step counters
    on the device, so that a step holds no host sync and a CUDA graph can record it (graphs.StepGraphs). A
    captured step keeps the learning rate it was recorded with: the rate is constant over a run."""
    return torch.optim.Adam(params, lr=cfg.lr, eps=1e-5, fused=cuda, capturable=cuda)


def clip_and_adam(cfg: TrainConfig, nets: Networks, opt: torch.optim.Optimizer) -> None:
    """The optimiser step on the gradients as they stand. Actor and critic are clipped apart: one joint norm lets
    the critic's large early regression gradients scale the policy's step down to nothing."""
    torch.nn.utils.clip_grad_norm_(nets.actor.parameters(), cfg.max_grad_norm)
    torch.nn.utils.clip_grad_norm_(nets.critic.parameters(), cfg.max_grad_norm)
    opt.step()


def clip_and_step(cfg: TrainConfig, nets: Networks, opt: torch.optim.Optimizer) -> None:
    """clip_and_adam after the gradients' average over the ranks (one all-reduce, in place)."""
    dist_util.average_gradients_(p for group in opt.param_groups for p in group["params"])
    clip_and_adam(cfg, nets, opt)


def _loss_under_callers_autocast(cfg: TrainConfig, b: Groups, idx: Tensor, lam: Tensor, nets: Networks,
                                 prior: BehaviourPrior, live: tuple[Tensor, Tensor] | None = None,
                                 row_weight: Tensor | None = None) -> tuple[Tensor, dict]:
    return minibatch_loss(cfg, b, idx, lam, nets, prior, live, row_weight, autocast=False)


def compiled_loss(dynamic: bool | None = None):
    """minibatch_loss through torch.compile (compile_update; `dynamic` as torch.compile's), called with the networks'
    autocast around the compiled graph rather than inside it: torch.compile's autograd cache, which spares a warm
    start tracing the backward pass again (most of a warm first update's seconds), takes no graph that enters
    autocast."""
    fn = torch.compile(_loss_under_callers_autocast, dynamic=dynamic)

    def loss(cfg: TrainConfig, b: Groups, idx: Tensor, lam: Tensor, nets: Networks, prior: BehaviourPrior,
             live: tuple[Tensor, Tensor] | None = None, row_weight: Tensor | None = None) -> tuple[Tensor, dict]:
        with nets.autocast(cache=row_weight is None):
            return fn(cfg, b, idx, lam, nets, prior, live, row_weight)

    return loss


@functools.cache
def compiled_live_loss():
    """compiled_loss for the live rows, their count a dynamic size: compiled on the first minibatch, then reused
    whatever the count (cached on disk across runs)."""
    return compiled_loss(dynamic=True)


def eager_steps(cfg: TrainConfig, b: Groups, lam: Tensor, nets: Networks, opt: torch.optim.Optimizer,
                gen: torch.Generator, prior: BehaviourPrior) -> tuple[dict[str, Tensor], Tensor, int]:
    """`epochs` passes of shuffled minibatches, one optimiser step each, on the live rows alone: (the loss
    parts summed over the minibatches, whether a loss was not finite, the number of minibatches)."""
    loss_fn = compiled_live_loss() if cfg.compile_update else minibatch_loss
    n_groups = b.mask.shape[0]
    mb = max(1, n_groups // cfg.minibatches)
    acc: dict[str, Tensor] = {}
    bad = torch.zeros((), dtype=torch.bool, device=b.mask.device)
    n_mb = 0
    for _ in range(cfg.epochs):
        perm = torch.randperm(n_groups, generator=gen, device=b.mask.device)
        with phase("update/live_rows"):
            live = epoch_live_rows(b.mask[perm], mb)
        for s, rows in zip(range(0, n_groups, mb), live):
            idx = perm[s:s + mb]
            if cfg.compile_update:  # fresh tensors: the compiled loss guards on views' offsets, and would recompile
                idx, rows = idx.clone(), (rows[0].clone(), rows[1].clone())
            with phase("update/forward"):
                loss, parts = loss_fn(cfg, b, idx, lam, nets, prior, rows)
                bad |= ~torch.isfinite(loss)
            with phase("update/backward"):
                opt.zero_grad(set_to_none=True)
                loss.backward()
            with phase("update/optimizer"):
                clip_and_step(cfg, nets, opt)
            for k, val in parts.items():
                acc[k] = acc.get(k, 0.0) + val.detach()
            n_mb += 1
    return acc, bad, n_mb


def optimise(cfg: TrainConfig, b: Groups, lam: Tensor, nets: Networks, opt: torch.optim.Optimizer,
             gen: torch.Generator, prior: BehaviourPrior, graphs: StepGraphs | None = None) -> dict:
    """`epochs` passes of shuffled minibatches, one optimiser step each (replayed from CUDA graphs when
    `graphs` is given: graphs.StepGraphs); the mean loss parts. Raises NonFinite (after the steps: the
    weights are spoilt then) when a loss was not finite."""
    if graphs is not None:
        acc, bad, n_mb = graphs.run(b, lam, gen, prior)
    else:
        acc, bad, n_mb = eager_steps(cfg, b, lam, nets, opt, gen, prior)
    mean = {k: float(v) / max(n_mb, 1) for k, v in acc.items()}
    if bool(bad):
        raise NonFinite("non-finite loss", f"mean policy {mean['loss/policy']:.4g}, value {mean['loss/value']:.4g}, "
                                           f"cost quantiles {mean['loss/cost_quantile']:.4g}")
    return mean


def ppo_update(cfg: TrainConfig, batch: Rollout, nets: Networks, opt: torch.optim.Optimizer,
               lagrange: L.LagrangeMultiplier, budget: Tensor, gen: torch.Generator,
               prior: BehaviourPrior, world_keys: Tensor | None = None, graphs: StepGraphs | None = None,
               step_lambda: bool = True) -> dict:
    """Learn from one rollout (steps 1-3 of the module docstring): the update's row of metrics (the mean
    loss parts, CVaR, lambda and the budget). `gen` shuffles the minibatches; `prior` rebuilds a
    continuous magnet from its stored context; `graphs` replays the optimiser steps from CUDA graphs;
    `step_lambda` False keeps the multipliers as they are (TrainConfig.lambda_warmup)."""
    with phase("update/advantages"):
        tg = advantages(cfg, batch)
    with phase("update/lagrange"):
        value = tg.constraint(cfg, batch.cost)
        if cfg.lambda_per_vehicle:
            lam, seen = vehicle_lagrange_step(cfg, batch.mask, value, lagrange, budget, world_keys, step_lambda)
        else:
            lam, seen = lagrange_step(cfg, batch.mask, value, lagrange, budget, step_lambda)
    out = optimise(cfg, flatten(batch, tg, nets.head.discrete), lam, nets, opt, gen, prior, graphs)
    out["cvar"] = float(L.masked_mean(tg.cvar[:-1], batch.mask))
    out["cost_to_go"] = float(L.masked_mean(tg.ctg_mean[:-1], batch.mask))
    held = batch.mask.any((0, 1))  # what lambda was stepped on: each held slot's constraint, their mean
    out["constraint"] = float(slot_constraint(cfg, batch.mask, value)[held].mean()) if held.any() else 0.0
    lam_now = lagrange.value[seen] if cfg.per_agent_lambda else lagrange.value
    out["lambda"] = float(lam_now.mean()) if cfg.constraint and lam_now.numel() else 0.0
    out["lambda_max"] = float(lam_now.max()) if cfg.constraint and lam_now.numel() else 0.0
    out["cost_budget"] = float(budget)
    return out
