"""Rollout collection for CCE-MAPPO: drive every world for `rollout_steps` steps under the current actor
and keep what the update reads.

Per step the actor runs on the live rows only (often under half of W x C; when the steps replay from CUDA
graphs, graphs.RolloutGraphs, on the fixed set of slots the policy drives, live or not) and samples from
draws made with the trainer's own generator at the rollout's start (so a resumed run replays the same
actions); the magnet (the behaviour prior) keeps its context; the engine steps; rewards, costs, ends and
the episodes that ended go into the buffers and the rollout's counters, all on the device. Controlled
agents sit in slots [0, C) of every world, so every buffer is a (T, W, C, ...) block. The buffers are
allocated once per shape (several GB at 4,096 worlds) and overwritten by every rollout.

What acting does not need waits for the rollout's end: the critic's values and the world model's magnet
logits are then computed from the stored observations and contexts in a few large batches, not in one
small call per step (each such call paid its kernels' launch latency with nothing to hide it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
from torch.profiler import record_function as phase  # named ranges for scripts/profile_train.py

from tg_gpudrive.agents.policy import BehaviourPrior, PolicyHead
from tg_gpudrive.config import TrainConfig
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HistoryBuffer, hist_dim
from tg_gpudrive.learn.compiling import Compiled
from tg_gpudrive.rollout import timed_out

Tensor = torch.Tensor
STAT_KEYS = ("alive", "episodes", "goal", "collided", "offroad", "timeout", "min_dist", "speed")
# the batches of the computations after the rollout: agent slots per critic call, rows per magnet call
# (a few hundred MB of activations each at gpu.yaml's sizes)
CRITIC_SLOTS = 1 << 20
MAGNET_ROWS = 1 << 17


class NonFinite(RuntimeError):
    """NaN or inf in what the networks produced (a rollout's policy output, an update's loss): the
    weights in memory are spoilt. `what` names it, `detail` adds the numbers; the trainer says which
    update it was and which checkpoint is the last good one."""

    def __init__(self, what: str, detail: str = ""):
        super().__init__(f"{what} ({detail})" if detail else what)
        self.what, self.detail = what, detail


class TrainingError(RuntimeError):
    """Training cannot go on (a non-finite policy output or loss): stopped without saving, so the
    checkpoint on disk stays the last good one."""


class ByName:
    """Read access by field name, `batch["mask"]`, and `dict(batch, prior=...)` copies, for the scripts
    and tests that handle a batch as a mapping; `of` turns such a mapping back into the dataclass."""

    def keys(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None]

    def __getitem__(self, key: str):
        if key not in self.keys():
            raise KeyError(key)
        return getattr(self, key)

    def __contains__(self, key: str) -> bool:
        return key in self.keys()

    @classmethod
    def of(cls, batch):
        """`batch` itself when it is one already, else the dataclass of the mapping's entries."""
        return batch if isinstance(batch, cls) else cls(**{k: batch[k] for k in batch.keys()})


@dataclass
class Rollout(ByName):
    """One rollout of T steps in W worlds for the C controlled slots, as the update reads it. A row
    (step, world, slot) counts where `mask` is set (the agent acted); the others hold filler."""

    obs: Tensor  # (T, W, C, obs_dim); bf16 under GPU autocast (what the networks round it to anyway)
    act: Tensor  # (T, W, C) action indices (discrete) or (T, W, C, act_dim) actions; the no-op where not live
    logp: Tensor  # (T, W, C) log-probability of `act` under the rollout's policy
    mask: Tensor  # (T, W, C) bool: the agent was live (acted) at that step
    reward: Tensor  # (T, W, C) the step's reward
    cost: Tensor  # (T, W, C) the step's cost (what the constraint bounds)
    done: Tensor  # (T, W, C) 1.0 where the agent's episode ended at that step (terminated or world ended)
    value: Tensor  # (T + 1, W, C) the critic's reward value; row T bootstraps the last step
    quant: Tensor  # (T + 1, W, C, quantiles) the cost critic's quantiles of the discounted cost-to-go, ascending
    prior: Tensor  # (T, W, C, P) the magnet: its logits (discrete), its context (continuous), P 0 (eta1 0)
    old: Tensor | tuple[Tensor, Tensor]  # the rollout policy's output: logits, or (mean, log_std)
    hist: Tensor | None = None  # (T, W, C, actor_history, hist_dim) the motion window the actor sees, if it has one
    # (T, W, C) the weight of each row's KL to the magnet: 1 / magnet_fraction on the rows whose prior
    # logits were computed, 0 elsewhere; None: every live row has them (magnet_fraction 1)
    prior_weight: Tensor | None = None
    # (T, W, C, context_dim) the discrete magnet's context, from which its logits are computed after the
    # rollout; None without a discrete magnet
    prior_ctx: Tensor | None = None
    # the rollout's counters, summed on the device (and over the ranks by the trainer): reward `terms`,
    # `alive` agent-steps, their `speed`, and the `episodes` that ended with their `goal`, `collided`,
    # `offroad` and `min_dist` outcomes
    stats: dict[str, Tensor] = field(default_factory=dict)


@dataclass
class Networks:
    """The learner's networks: actor and critic, the head that turns the actor's output into a
    distribution, and whether they run under bf16 autocast (GPU with `amp`; losses stay float32)."""

    actor: torch.nn.Module
    critic: torch.nn.Module
    head: PolicyHead
    amp: bool = False

    def autocast(self, cache: bool = True):
        """bf16 autocast around the networks' forward passes when `amp`, else nothing. `cache`: keep the
        bf16 copies of the weights for the forward's duration (not inside a CUDA graph's capture)."""
        return torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.amp, cache_enabled=cache)

    def float_out(self, out):
        """The actor's output in float32: logits, or (mean, log_std)."""
        return out.float() if self.head.discrete else (out[0].float(), out[1].float())


def ranked_pick(keys: Tensor, mask: Tensor, frac: float) -> Tensor:
    """The ceil(frac x n) entries of `mask`'s n True ones with the smallest `keys` (a uniform draw per entry):
    a random subset of a fixed share, found on the device without reading the host. A mask of `mask`'s shape."""
    live = mask.reshape(-1)
    k = torch.ceil(frac * live.sum().double())
    order = torch.where(live, keys.reshape(-1), 2.0).argsort()
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order), device=order.device)
    return ((rank < k) & live).reshape(mask.shape)


class RolloutCollector:
    """Fills a Rollout from the simulator under the current actor (see the module docstring). `prior` may
    be replaced between rollouts (the magnet is read at every step)."""

    def __init__(self, cfg: TrainConfig, sim: Simulator, nets: Networks, prior: BehaviourPrior,
                 gen: torch.Generator, device, actor_hist: HistoryBuffer | None = None):
        self.cfg, self.sim, self.nets, self.prior, self.gen, self.device = cfg, sim, nets, prior, gen, device
        self.actor_hist = actor_hist  # the actor's own motion window: kept in step with the engine
        self.background = None  # a driver of the background rows (agents.builtin.make_background_driver), or None
        self.prior_logits = nets.head.discrete and cfg.eta1 > 0  # store the magnet's logits in the rollout
        # a RolloutGraphs (graphs.py) replays the steps from CUDA graphs; the steps then act on every policy slot
        self.graphs = None
        # a magnet whose context launches engine kernels is read before a step's captured part, into `_ctx`
        # (allocated when first needed), which that part reads: a torch capture records neither the kernel nor
        # its wait on the engine's stream
        self._ctx_outside = False
        self._ctx: Tensor | None = None
        self._buf: Rollout | None = None
        self._buf_key = None
        self._rows_of = None  # the engine model whose policy rows `_rows` holds
        self._rows: tuple[Tensor, Tensor] | None = None
        self._compiled: dict[str, tuple[object, object]] = {}  # compile_rollout: per pass, (its owner, compiled fn)

    @torch.no_grad()
    def collect(self) -> Rollout:
        """Drive every world for `rollout_steps` steps; raises NonFinite if the policy's output was not
        finite (checked once per rollout)."""
        sim = self.sim
        T, C = self.cfg.rollout_steps, max(sim.max_controlled, 1)
        buf = self._buffers(T, sim.num_worlds, C)
        for v in self._stats.values():
            v.zero_()
        self._bad.zero_()
        # the rollout's random draws, made at once: the steps read their rows (fixed shapes, no generator inside)
        if self.nets.head.discrete:
            self._noise.uniform_(generator=self.gen)
        else:
            self._noise.normal_(generator=self.gen)
        if self._keys is not None:
            self._keys.uniform_(generator=self.gen)
        # a failed capture sends the rollouts back to the live rows (graphs.RolloutGraphs.capturable)
        graphs = self.graphs if self.background is None and self.graphs is not None and self.graphs.capturable else None
        dense = graphs is not None
        for hist in (getattr(self.prior, "history", None), self.actor_hist):
            if hist is not None:
                hist.fixed_shapes = dense
        owners = (sim.model, buf, self.prior, self.nets.actor)  # what the captured steps read
        self._ctx_outside = dense and self.cfg.eta1 > 0 and not self.prior.capturable
        shape = (sim.num_worlds, C, self.prior.context_dim) if self._ctx_outside else None
        if shape is not None and (self._ctx is None or tuple(self._ctx.shape) != shape):
            self._ctx = torch.zeros(shape, device=self.device)
        for t in range(T):
            if self._ctx_outside:
                with phase("rollout/magnet.context"):
                    self._ctx.copy_(self.prior.context(sim, C))
            self._run(graphs, owners, ("act", t), lambda: self._bad.logical_or_(self._act(buf, t, C, dense)))
            if self.background is not None:
                with phase("rollout/background"):
                    self.background(sim)
            with phase("rollout/engine"):
                sim.step()
            with phase("rollout/buffers"):
                self._run(graphs, owners, ("record", t), lambda: self._record_step(buf, self._stats, t, C))
        with phase("rollout/critic"):
            self._values(buf, T, C)
        if self.prior_logits:
            with phase("rollout/magnet.forward"):
                self._prior_logits(buf)
        if bool(self._bad):
            raise NonFinite("non-finite policy output")
        return dataclasses.replace(buf, stats={k: v.clone() for k, v in self._stats.items()})

    @staticmethod
    def _run(graphs, owners: tuple, name, fn) -> None:
        """Step part `name`: through `graphs` (graphs.RolloutGraphs) when given, else as it is."""
        if graphs is None:
            fn()
        else:
            graphs.run(owners, name, fn)

    def _values(self, buf: Rollout, T: int, C: int) -> None:
        """The critic's values and cost quantiles of every step's stored observations, a few steps per call,
        and of the state after the last step (the bootstrap row T)."""
        sim = self.sim
        chunk = max(1, CRITIC_SLOTS // (sim.num_worlds * C))
        for t0 in range(0, T, chunk):
            t1 = min(T, t0 + chunk)
            self._critic_rows(buf.obs[t0:t1], buf.mask[t0:t1], buf.value[t0:t1], buf.quant[t0:t1])
        self._critic_rows(sim.obs[:, :C], sim.active[:, :C] != 0, buf.value[T], buf.quant[T])

    def _critic_rows(self, obs: Tensor, mask: Tensor, value: Tensor, quant: Tensor) -> None:
        """The critic's heads on `mask`'s live rows only (under half the slots in most worlds) into `value` and
        `quant`; 0 at the other rows, which no target reads (a row after a live one that is not live ends its
        episode, and the ends cut the bootstrap)."""
        rows = mask.reshape(-1).nonzero(as_tuple=True)[0]
        critic = self._maybe_compiled("critic", self.nets.critic, (("rows", 0),))  # head_rows: the same tensor
        with self.nets.autocast():
            v, q = critic(obs, mask, rows=rows, head_rows=rows)
        value.zero_()
        quant.zero_()
        value.view(-1)[rows] = v.float()
        quant.view(-1, quant.shape[-1])[rows] = q.float()

    def _prior_logits(self, buf: Rollout) -> None:
        """The magnet's logits on the rows that take it (every live row, or the `magnet_fraction` picked per
        step), from the stored contexts and observations, in batches of MAGNET_ROWS (bf16 under autocast on
        the GPU; a fixed target, so computing them once per rollout rather than per minibatch and epoch)."""
        take = buf.mask if buf.prior_weight is None else buf.prior_weight > 0
        t, w, c = take.nonzero(as_tuple=True)  # the rollout's one host sync after its steps
        magnet = self._maybe_compiled("magnet", self.prior.distribution, ((0, 0), (1, 0)))
        with self.nets.autocast():
            for s in range(0, len(t), MAGNET_ROWS):
                i = (t[s:s + MAGNET_ROWS], w[s:s + MAGNET_ROWS], c[s:s + MAGNET_ROWS])
                buf.prior[i] = magnet(buf.prior_ctx[i], buf.obs[i]).float()

    def _maybe_compiled(self, name: str, fn, dynamic: tuple):
        """`fn` (the critic, or a method of the magnet) as it is, or with compile_rollout through torch.compile
        (compiling.Compiled, `dynamic` its arguments' changing sizes), compiled once per owner (the module, or
        the method's object: a new magnet gets its own)."""
        if not self.cfg.compile_rollout:
            return fn
        owner = getattr(fn, "__self__", fn)
        hit = self._compiled.get(name)
        if hit is None or hit[0] is not owner:
            hit = self._compiled[name] = (owner, Compiled(fn, f"rollout's {name} pass", dynamic))
        return hit[1]

    def _act(self, buf: Rollout, t: int, C: int, dense: bool = False) -> Tensor:
        """Step t before the engine steps: sample the live agents' actions, store them with the rollout
        policy's output, the observations and the magnet's context (or, continuous, the prior's), and hand
        the actions to the engine. Whether the policy's output was non-finite (a device bool; it acts as 0 here).
        `dense`: the actor runs on every slot the policy drives (`_policy_rows`), dead ones fed zeros and given
        the no-op, so that nothing depends on how many act (a CUDA graph's fixed shapes, no host sync); the
        live rows get the same actions either way (the same draws)."""
        sim, nets, head = self.sim, self.nets, self.nets.head
        # the motion windows first: their reset checks read the host, and here that read waits only for the
        # engine's step, which the live rows' count waits for anyway, not for the networks queued after it
        ctx = None
        if self._ctx_outside:
            ctx = self._ctx
        elif self.cfg.eta1 > 0:
            with phase("rollout/magnet.context"):
                ctx = self.prior.context(sim, C)
        if self.actor_hist is not None:
            self.actor_hist.sync(sim)
        with phase("rollout/live_rows"):  # the host sync of a step: how many rows act
            obs = sim.obs[:, :C]
            mask = sim.active[:, :C] != 0
            if dense:  # the slots the policy drives, live or not: a fixed set for a batch of scenes
                w_idx, c_idx = self._policy_rows()
                live = mask[w_idx, c_idx]
                rows_obs = torch.where(live[:, None], obs[w_idx, c_idx], 0.0)
            else:  # the other slots get the no-op action, which the engine ignores for agents that do not act
                w_idx, c_idx = mask.nonzero(as_tuple=True)
                live = None
                rows_obs = obs[w_idx, c_idx]
        hist = None
        if self.actor_hist is not None:  # the actor's motion window
            buf.hist[t] = self.actor_hist.features(sim, slice(0, C), self.cfg.actor_history_partners)
            hist = buf.hist[t][w_idx, c_idx]
        with phase("rollout/actor"), nets.autocast(cache=not dense):
            out = nets.float_out(nets.actor(rows_obs, c_idx, hist))
        with phase("rollout/sample"):
            if head.discrete:
                bad = ~torch.isfinite(out).all()
                out = torch.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
            else:
                bad = ~(torch.isfinite(out[0]).all() & torch.isfinite(out[1]).all())
                out = (torch.nan_to_num(out[0]), torch.nan_to_num(out[1]))
            d = head.dist(out)
            a = self._sample(out, self._noise[t][w_idx, c_idx])
        with phase("rollout/buffers"):
            self._store(buf, t, obs, mask, w_idx, c_idx, a, d.log_prob(a), out, live)
        with phase("rollout/magnet"):
            self._magnet(buf, t, C, ctx, mask, None if dense else (w_idx, c_idx))
        act = buf.act[t]
        if head.discrete:
            sim.actions_index[:, :C] = act.to(torch.int32)
        else:
            sim.actions[:, :C, : act.shape[-1]] = act
        return bad

    def _store(self, buf: Rollout, t: int, obs: Tensor, mask: Tensor, w_idx: Tensor, c_idx: Tensor, a: Tensor,
               logp: Tensor, out, live: Tensor | None = None) -> None:
        """Step t's observations, live mask, actions (the no-op where not live), their log-probabilities and
        the rollout policy's output into the buffers (`live`: which of the rows act, when not all of them do;
        the others' actions are replaced by the no-op)."""
        act = buf.act[t]
        noop = self.cfg.env.noop_index if self.nets.head.discrete else 0.0
        if live is not None:
            a = torch.where(live if a.dim() == 1 else live[:, None], a, noop)
        act.fill_(noop)  # rows that do not act
        act[w_idx, c_idx] = a.to(act.dtype)
        buf.logp[t][w_idx, c_idx] = logp
        if self.nets.head.discrete:
            buf.old[t][w_idx, c_idx] = out
        else:
            buf.old[0][t][w_idx, c_idx], buf.old[1][t][w_idx, c_idx] = out
        buf.obs[t].copy_(obs)
        buf.mask[t] = mask

    def _sample(self, out, noise: Tensor) -> Tensor:
        """Actions of the rows, from their draws `noise`: a uniform per row inverts the categorical's CDF
        (discrete); a standard normal per dimension scales the Gaussian's std (continuous)."""
        if not self.nets.head.discrete:
            return out[0] + out[1].exp() * noise
        cdf = torch.softmax(out, -1).cumsum(-1)
        return torch.searchsorted(cdf, noise[:, None].to(cdf.dtype)).squeeze(-1).clamp(max=out.shape[-1] - 1)

    def _magnet(self, buf: Rollout, t: int, C: int, ctx: Tensor | None, mask: Tensor,
                live: tuple[Tensor, Tensor] | None = None) -> None:
        """The magnet of step t: the prior's context `ctx` (discrete: its logits follow after the rollout) and,
        with `magnet_fraction` < 1, which live rows take them (the share with the smallest draws: among the
        `live` rows when given, else through ranked_pick over the mask)."""
        if self.prior_logits:
            buf.prior_ctx[t] = ctx
            if buf.prior_weight is not None:  # a random subset of the live rows, of a fixed share
                frac = self.cfg.magnet_fraction
                if live is None:
                    buf.prior_weight[t] = ranked_pick(self._keys[t], mask, frac).float() / frac
                else:
                    w_idx, c_idx = live
                    pick = self._keys[t][w_idx, c_idx].topk(math.ceil(frac * len(w_idx)), largest=False).indices
                    buf.prior_weight[t].zero_()
                    buf.prior_weight[t][w_idx[pick], c_idx[pick]] = 1.0 / frac
        elif ctx is not None:
            buf.prior[t] = ctx

    def _record_step(self, buf: Rollout, stats: dict, t: int, C: int) -> None:
        """After step t: its rewards, costs and ends into the buffers; its reward terms, speed and the
        outcomes of the episodes that ended into the rollout's stats (on the device, no host sync)."""
        sim = self.sim
        alive = sim.alive[:, :C].float()
        buf.reward[t] = sim.reward[:, :C]
        buf.cost[t] = sim.cost[:, :C]
        buf.done[t] = ((sim.terminated[:, :C] != 0) | (sim.world_ended[:, None] != 0)).float()
        stats["terms"] += (sim.reward_terms[:, :C] * alive[..., None]).sum((0, 1))
        stats["alive"] += alive.sum()
        stats["speed"] += (sim.speed[:, :C] * alive).sum()
        ended = (sim.world_ended[:, None] != 0) & sim.policy_agents[:, :C]
        stats["episodes"] += ended.sum()
        stats["goal"] += (sim.final_goal[:, :C] * ended).sum()
        stats["collided"] += (sim.final_collided[:, :C] * ended).sum()
        stats["offroad"] += (sim.final_offroad[:, :C] * ended).sum()
        stats["timeout"] += (timed_out(sim.final_goal[:, :C], sim.final_collided[:, :C], sim.final_offroad[:, :C])
                             & ended).sum()
        stats["min_dist"] += (sim.final_min_dist[:, :C] * ended).sum()

    def _buffers(self, T: int, W: int, C: int) -> Rollout:
        """Rollout storage, allocated once per shape and reused: every entry is overwritten by each
        rollout, so nothing needs clearing."""
        key = (T, W, C)
        if self._buf_key == key:
            return self._buf
        cfg, sim, dev, discrete = self.cfg, self.sim, self.device, self.nets.head.discrete
        self._buf = None  # drop the old storage before allocating the new one
        act = (T, W, C) if discrete else (T, W, C, cfg.env.act_dim)
        # under bf16 autocast the networks round their inputs to bf16 anyway: store them so
        obs_dtype = torch.bfloat16 if sim.is_cuda and cfg.amp else torch.float32
        steps = lambda *rest, dtype=torch.float32: torch.zeros((T, W, C, *rest), dtype=dtype, device=dev)  # noqa: E731
        self._buf = Rollout(
            obs=steps(sim.obs_dim, dtype=obs_dtype), act=torch.zeros(act, device=dev), logp=steps(),
            mask=steps(dtype=torch.bool), reward=steps(), cost=steps(), done=steps(),
            value=torch.zeros((T + 1, W, C), device=dev), quant=torch.zeros((T + 1, W, C, cfg.quantiles), device=dev),
            prior=steps(self._prior_dim()),
            old=steps(sim.num_actions) if discrete else (torch.zeros(act, device=dev), torch.zeros(act, device=dev)),
            hist=steps(cfg.actor_history, hist_dim(cfg.actor_history_partners)) if self.actor_hist is not None else None,
            prior_weight=steps() if self.prior_logits and cfg.magnet_fraction < 1 else None,
            prior_ctx=steps(self.prior.context_dim) if self.prior_logits else None)
        # the rollout's random draws (a uniform per slot and step for the action, a second one for the magnet's
        # pick; normals per action dimension when continuous), its counters and its non-finite flag
        self._noise = torch.zeros(act, device=dev)
        self._keys = steps() if self.prior_logits and cfg.magnet_fraction < 1 else None
        self._stats = {"terms": torch.zeros(len(sim.reward_term_names), device=dev),
                       **{k: torch.zeros((), device=dev) for k in STAT_KEYS}}
        self._bad = torch.zeros((), dtype=torch.bool, device=dev)
        self._buf_key = key
        return self._buf

    def _policy_rows(self) -> tuple[Tensor, Tensor]:
        """(world, slot) of every controlled slot the engine's model integrates: a superset of the live rows
        at any step of its batch of scenes (an agent acts only while integrated), found once per model. The
        fixed-shape steps act on these: at procedural scenes' sizes under half of the W x C slots."""
        model = self.sim.model
        if self._rows_of is not model:
            C = max(self.sim.max_controlled, 1)
            self._rows = (self.sim.integrated[:, :C] != 0).nonzero(as_tuple=True)
            self._rows_of = model
        return self._rows

    def _prior_dim(self) -> int:
        """Per row and step: the magnet's logits (discrete), its context (continuous), nothing (eta1 0)."""
        if self.cfg.eta1 <= 0:
            return 0
        return self.sim.num_actions if self.prior_logits else self.prior.context_dim
