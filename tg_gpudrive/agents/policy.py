"""What a trained policy is, for everyone who runs one: the behaviour-prior interface, the action
distribution head, building the networks from a config and loading a policy from a checkpoint.

    actor, critic = build_models(train_cfg, sim, device)     # the trainer's networks
    head = PolicyHead(discrete=True)                         # sampling, log-probs, entropy, KLs
    policy = load_policy("runs/small_cpu", sim)               # policy(sim) writes sim's actions
    grid = action_grid(env_cfg)                               # (num_actions, 2) values of the grid

It sits below the learner (learn.train), the world model and the evaluation, so that none of
them reaches into another for these: it imports only the engine, the config, the checkpoint
files and `agents.networks`; the exact KLs of its distributions live here. It must not import
`learn`, `worldmodel` or `evaluation`.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from tg_gpudrive.checkpoint import load_checkpoint
from tg_gpudrive.config import TrainConfig, from_dict
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HistoryBuffer
import torch.nn.functional as F
from tg_gpudrive.agents.guard import ActionGuard
from tg_gpudrive.agents.networks import Actor, CentralCritic


class BehaviourPrior:
    """The "magnet" of CCE-MAPPO's magnetic mirror descent: for every controlled agent and step, a
    distribution over the engine's actions that stands for human driving.

    It works in two phases so the rollout buffer stays small: `context(sim)` returns a compact
    per-step tensor that the learner stores, and `distribution(context, obs)` rebuilds the
    distribution from it at update time: logits (..., num_actions) for discrete actions,
    (mean, log_std) for continuous. Implementations: agents.prior.ExpertPrior (the logged expert)
    and worldmodel.WorldModelPrior (the learned world model). The base class is also the
    stateless prior of plain MAPPO, which is never asked.

    `capturable`: whether `context` runs only torch operations on torch's current stream, so that a
    torch CUDA graph captures it; a prior that launches engine kernels (on the engine's own stream)
    is read outside the rollout's captured steps."""

    capturable = True

    def context(self, sim: Simulator, num_controlled: int) -> torch.Tensor:
        """Per-step data for the first `num_controlled` slots of every world: (W, C, ctx)."""
        raise NotImplementedError

    def distribution(self, context: torch.Tensor, obs: torch.Tensor):
        raise NotImplementedError

    def state_dict(self) -> dict:
        """What an exact resume needs besides the simulator (a stateless prior: nothing)."""
        return {}

    def load_state_dict(self, sim: Simulator, state: dict) -> None:
        pass


def categorical_kl(logits_p: torch.Tensor, logits_q: torch.Tensor) -> torch.Tensor:
    """Exact KL(p || q) of categorical distributions given by logits, shape (..., K) -> (...).

    Logits need not be normalised. Actions masked with -inf logits in p
    contribute 0; an action with p > 0 but q = 0 gives +inf, as it should.
    """
    logp = F.log_softmax(logits_p, dim=-1)
    logq = F.log_softmax(logits_q, dim=-1)
    p = logp.exp()
    terms = torch.where(p > 0, p * (logp - logq), torch.zeros_like(p))
    return terms.sum(-1)


def gaussian_kl(
    mu_p: torch.Tensor, logstd_p: torch.Tensor, mu_q: torch.Tensor, logstd_q: torch.Tensor
) -> torch.Tensor:
    """Exact KL(p || q) of diagonal Gaussians, summed over the action dim: (..., A) -> (...).

    KL = sum_a [ log s_q - log s_p + (s_p^2 + (mu_p - mu_q)^2) / (2 s_q^2) - 1/2 ].
    """
    var_ratio = torch.exp(2.0 * (logstd_p - logstd_q))
    mean_term = ((mu_p - mu_q) * torch.exp(-logstd_q)) ** 2
    return (logstd_q - logstd_p + 0.5 * (var_ratio + mean_term) - 0.5).sum(-1)


class PolicyHead:
    """Sampling, log-probs, entropy and KLs for the engine's action space."""

    def __init__(self, discrete: bool):
        self.discrete = discrete

    def dist(self, out):
        # no argument validation: it reads values back from the GPU (a sync per call), and
        # non-finite outputs are caught once per rollout / update with a clear message instead
        if self.discrete:
            return torch.distributions.Categorical(logits=out, validate_args=False)
        mean, log_std = out
        return torch.distributions.Independent(
            torch.distributions.Normal(mean, log_std.exp(), validate_args=False), 1, validate_args=False)

    def kl(self, out_p, out_q) -> torch.Tensor:
        if self.discrete:
            return categorical_kl(out_p, out_q)
        if hasattr(out_q, "kl_from"):  # a prior without a closed form (worldmodel.mixture.LaplaceMixture)
            return out_q.kl_from(out_p)
        return gaussian_kl(out_p[0], out_p[1], out_q[0], out_q[1])


def action_grid(env, device=None) -> torch.Tensor:
    """(num_actions, 2): the (accel, curvature) of each discrete action, row i = ia * curvature_bins + ik
    as the engine indexes its grid (kernels/dynamics.py)."""
    a = torch.linspace(-env.max_accel, env.max_accel, env.accel_bins, device=device)
    k = torch.linspace(-env.max_curvature, env.max_curvature, env.curvature_bins, device=device)
    return torch.stack(torch.meshgrid(a, k, indexing="ij"), -1).reshape(-1, 2)


def build_actor(env, num_actions: int, *, hidden: int = 128, heads: int = 1, history: int = 0,
                history_partners: int = 0) -> Actor:
    """An actor for the engine config `env`'s action space (its grid of `num_actions`, or the
    bicycle / delta-local action box), seeing `history` steps of its own motion and of its
    `history_partners` nearest partners', on the CPU."""
    return Actor(env.partner_k, env.road_k, discrete=env.discrete, num_actions=num_actions,
                 act_dim=env.act_dim, act_scale=list(env.act_high), hidden=hidden, heads=heads, history=history,
                 history_partners=history_partners)


def actor_of(cfg: TrainConfig, num_actions: int) -> Actor:
    """The actor a run with config `cfg` trains, on the CPU."""
    return build_actor(cfg.env, num_actions, hidden=cfg.hidden, heads=cfg.heads, history=cfg.actor_history,
                       history_partners=cfg.actor_history_partners)


def build_models(cfg: TrainConfig, sim: Simulator, device: str):
    """(actor, critic) of a CCE-MAPPO run with config `cfg`, laid out for `sim`, on `device`."""
    e = cfg.env
    actor = actor_of(cfg, sim.num_actions).to(device)
    critic = CentralCritic(e.partner_k, e.road_k, quantiles=cfg.quantiles, hidden=cfg.hidden).to(device)
    return actor, critic


def load_actor(path: str | Path, sim: Simulator) -> tuple[Actor, TrainConfig]:
    """The actor of a training checkpoint (file, run directory or "shipped"; checkpoint.checkpoint_path)
    on `sim`'s device, and the run's config; a ValueError when `sim`'s action space or observation
    layout is not the one it was trained with."""
    ck = load_checkpoint(path, "checkpoint", map_location=sim.device)
    cfg = from_dict(TrainConfig, ck["config"], str(path))
    e, s = cfg.env, sim.cfg
    if (e.action_space, e.dynamics, e.partner_k, e.road_k) != (s.action_space, s.dynamics, s.partner_k, s.road_k):
        raise ValueError(f"{path}: checkpoint expects action_space={e.action_space}, dynamics={e.dynamics}, "
                         f"partner_k={e.partner_k}, road_k={e.road_k}; the simulator differs")
    actor = actor_of(cfg, sim.num_actions)
    actor.load_state_dict(ck["actor"])
    return actor.to(sim.device), cfg


def load_policy(path: str | Path, sim: Simulator, temperature: float | None = None,
                guard_s: float | None = None):
    """A `policy(sim)` callable from a training checkpoint (used by evaluate, render and report).

    `path`: a checkpoint file, a run directory or "shipped" (checkpoint.checkpoint_path). `sim` may
    have more slots than the training engine (checkpoint.policy_engine_config): the actor is per agent.
    `temperature`: see actor_policy; None takes the checkpoint's own (TrainConfig.act_temperature).
    `guard_s`: the safety guard's horizon (s, 0: none); None takes the checkpoint's (TrainConfig.act_guard_s)."""
    actor, cfg = load_actor(path, sim)
    horizon = cfg.act_guard_s if guard_s is None else guard_s
    return actor_policy(actor.eval(), sim, cfg.actor_history,
                        cfg.act_temperature if temperature is None else temperature,
                        guard_for(sim, horizon, cfg.act_guard_margin) if horizon else None)


def guard_for(sim: Simulator, horizon: float, margin: float = 0.0) -> ActionGuard:
    """The safety guard (agents/guard.py) of `sim`'s discrete action grid, looking `horizon` seconds ahead."""
    e = sim.cfg
    if not e.discrete:
        raise ValueError(f"the action guard needs a discrete action space; the simulator's is {e.action_space}")
    return ActionGuard(action_grid(e, sim.device), e.partner_k, float(sim.model.dt), e.max_accel, horizon, margin)


def tempered(out, temperature: float):
    """The actor's output with its distribution sharpened by `temperature` (> 0): logits / T, or the
    continuous head's (mean, log-std + log T)."""
    if temperature == 1:
        return out
    if isinstance(out, torch.Tensor):
        return out / temperature
    return out[0], out[1] + math.log(temperature)


def actor_policy(actor: Actor, sim: Simulator, history: int = 0, temperature: float = 1.0,
                 guard: ActionGuard | None = None):
    """A `policy(sim)` callable that drives every slot of `sim` with `actor` (seeing `history` steps of
    its own motion), sampling its distribution sharpened by `temperature` (`tempered`; kept on it as
    `policy.temperature`), or taking its mode at temperature 0, behind `guard` if given (kept on it as
    `policy.guard`: its counts of actions checked and replaced). The actor's output of the latest call stays
    on it as `policy.last_out` (logits, or (mean, log-std), untempered): what a best response to this
    profile corrects (evaluation.exploitability.SimGame)."""
    if not temperature >= 0:
        raise ValueError(f"temperature: expected a number >= 0, got {temperature}")
    head = PolicyHead(sim.cfg.discrete)
    deterministic = temperature == 0
    slots = torch.arange(sim.max_agents, device=sim.device)
    # an actor with a motion history keeps its window in step with the simulator it drives
    window = HistoryBuffer(history) if history else None

    @torch.no_grad()
    def policy(sim_: Simulator) -> None:
        hist = None
        if window is not None:
            window.sync(sim_)
            hist = window.features(sim_, partners=getattr(actor, "history_partners", 0))
        out = policy.last_out = actor(sim_.obs, slots, hist)
        if head.discrete:
            logits = out if deterministic else tempered(out, temperature)
            a = out.argmax(-1) if deterministic else head.dist(logits).sample()
            if guard is not None:
                a = guard(sim_.obs, logits, a, deterministic, acting=(sim_.active != 0) & (sim_.background == 0))
            sim_.actions_index.copy_(a.to(torch.int32))
        else:
            a = out[0] if deterministic else head.dist(tempered(out, temperature)).sample()
            sim_.actions[..., : a.shape[-1]].copy_(a)

    policy.last_out = None
    policy.temperature = temperature
    policy.guard = guard
    return policy
