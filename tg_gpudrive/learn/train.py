"""CCE-MAPPO (TrafficGamer) on the engine's tensors: `tg-gpudrive train`.

One update = a rollout of `rollout_steps` steps in all W worlds, then PPO
epochs. The loop reads and writes the simulator's tensors in place; the only
Python loops are over steps, epochs and minibatches. Controlled agents sit in
slots [0, C) of every world (the engine puts them first), so the learner works
on (T, W, C, ...) blocks. Per agent i the actor minimises

    PPO-clip(A_reward - lambda A_cost) - entropy_coef H
        + eta1 KL(pi || pi_prior) + (1 / eta2) KL(pi || pi_previous)

(losses.cce_mappo_actor_loss); the centralised critic regresses the reward
lambda-returns; the quantile critic learns the distribution of the discounted
cost-to-go; lambda >= 0 rises while CVaR_alpha of that distribution, averaged
over the agents' states, exceeds `cost_limit` (set it above the logged drivers'
own level, or the constraint is infeasible and lambda grows without bound).
Actor and critic share one Adam optimiser but their gradients are clipped
apart. The update reads values back from the GPU once, at its end (the row
selections of the live agents are the only other host syncs).

Checkpoints are atomic (write, then rename) and hold everything a resume needs
to continue exactly: weights, optimisers, lambda, RNG states, counters, the
sampler position and the engine State mid-episode.
"""

from __future__ import annotations

import json
import logging
import math
import random
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

from torch.nn.parallel import DistributedDataParallel as DDP
from tqdm import tqdm

from tg_gpudrive.checkpoint import (POLICY, POLICY_DIR, POOLED_KEYS, checkpoint_path, load_checkpoint,
                                    network_differences, save_atomic)
from tg_gpudrive.config import ConfigError, TrainConfig, from_dict, to_dict
from tg_gpudrive.data.sampler import SceneSampler
from tg_gpudrive.data.augment import augment_scene, subset_mask
from tg_gpudrive.data.sources import resolve_scenes, source_report
from tg_gpudrive.engine.control import cap_controlled, control_masks
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HIST_DIM, HistoryBuffer
from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn import losses as L
from tg_gpudrive.learn.quality import RATE_KEYS
from tg_gpudrive.learn.runlog import RunLog
from tg_gpudrive.learn.targets import HeldoutCheck, RateWindow
from tg_gpudrive.agents.prior import ExpertPrior
from tg_gpudrive.agents.policy import BehaviourPrior, PolicyHead, build_models
from tg_gpudrive.worldmodel import WorldModelPrior, load_shipped, load_world_model

log = logging.getLogger(__name__)
SMALL_MINIBATCH = 16  # world-steps: a minibatch with fewer is warned about


class TrainingError(RuntimeError):
    pass


def make_prior(cfg: TrainConfig, sim: Simulator) -> BehaviourPrior:
    """The magnet: the learned world model (tg_gpudrive.worldmodel) or the logged expert actions;
    none (a stateless BehaviourPrior that is never asked) for plain MAPPO, eta1 = 0. A prior reads
    the simulator it is given at every call (the world model's history rebinds to new scenes), so
    one prior serves a whole run, resamples included."""
    if cfg.eta1 <= 0:
        return BehaviourPrior()
    if cfg.prior == "world_model":
        try:
            model = load_world_model(cfg.prior_model, sim) if cfg.prior_model else load_shipped(sim)
        except FileNotFoundError as e:
            raise ConfigError(f"prior_model: {e}") from None
        return WorldModelPrior(model, sim, top_component=cfg.prior_top_component,
                               min_std=(cfg.prior_sigma_accel, cfg.prior_sigma_curvature))
    return ExpertPrior(sim, cfg.prior_sigma_accel, cfg.prior_sigma_curvature, cfg.prior_closed_loop, cfg.prior_floor)


@torch.no_grad()
def logged_cost_cvar(sim: Simulator, alpha: float, gamma: float) -> torch.Tensor:
    """CVaR_alpha of the logged drivers' discounted cost-to-go: what the constraint's budget is
    measured against (`cost_limit_mode: logs`).

    Replays the expert (inverse-dynamics actions of the logs) for one episode in every world
    and computes, for every controlled agent and step it was driven, the discounted cost-to-go
    G_t = c_t + gamma G_{t+1} to the end of its episode; returns the mean of the upper
    (1 - alpha) tail of those values (a scalar tensor). Over a mixture of states this is at
    least the mean over states of their own CVaR_alpha, the estimate the multipliers compare
    with the budget, so a budget of 1 x this is one the logs themselves satisfy. Leaves the
    simulator to be reset by the caller."""
    sim.reset()
    C = max(sim.max_controlled, 1)
    steps = sim.episode_length
    cost = torch.zeros((steps, sim.num_worlds, C), device=sim.reward.device)
    live = torch.zeros_like(cost, dtype=torch.bool)
    first = torch.ones(sim.num_worlds, dtype=torch.bool, device=cost.device)  # still in its first episode
    for t in range(steps):
        sim.use_expert_actions()
        live[t] = (sim.active[:, :C] != 0) & sim.policy_agents[:, :C] & first[:, None]
        sim.step()
        cost[t] = sim.cost[:, :C] * live[t]
        first &= sim.world_ended == 0
    ctg = torch.zeros_like(cost)
    run = torch.zeros_like(cost[0])
    for t in range(steps - 1, -1, -1):
        run = (cost[t] + gamma * run) * live[t]  # a step the agent did not act cuts the sum
        ctg[t] = run
    vals = ctg[live]
    if vals.numel() == 0:
        return torch.zeros((), device=cost.device)
    return L.cvar_from_quantiles(vals.sort().values, alpha)


# ------------------------------------------------------------------- trainer
class StopRequest:
    """Ctrl-C during training: the first SIGINT asks the loop to end the update under way and save it
    (a checkpoint at the last finished update, so --resume continues exactly); a second one stops at
    once. Outside the main thread (where no handler can be installed) Ctrl-C keeps its default."""

    def __init__(self):
        self._flag = False
        self._old = None

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)

    def _handle(self, signum, frame) -> None:
        if self._flag:
            raise KeyboardInterrupt
        self._flag = True
        print("\ntg-gpudrive train: Ctrl-C: finishing this update, then saving a checkpoint "
              "(Ctrl-C again stops at once, keeping the last saved one)", file=sys.stderr)

    def requested(self, device) -> bool:
        """Whether a stop was asked for, on any rank (every rank must leave at the same update)."""
        if dist_util.world_size() == 1:
            return self._flag
        return bool(dist_util.all_reduce_mean(torch.tensor(float(self._flag), device=device)) > 0)


class Trainer:
    def __init__(self, cfg: TrainConfig, out_dir: str | Path | None = None, resume: str | Path | None = None,
                 progress: bool = True):
        self.cfg = cfg
        self.out = Path(out_dir or cfg.out_dir)
        self.rank, self.world = dist_util.rank(), dist_util.world_size()
        self.lead = self.rank == 0  # logs and checkpoints
        if self.lead:
            self.out.mkdir(parents=True, exist_ok=True)
        self.progress = progress and self.lead
        self.device = dist_util.local_device(cfg.device)
        per_mb = cfg.num_worlds * cfg.rollout_steps // cfg.minibatches
        if self.lead and cfg.minibatches > 1 and per_mb < SMALL_MINIBATCH:
            log.warning("minibatches=%d: each minibatch holds %d world-steps (of %d worlds x %d steps), so an update "
                        "takes %d small optimiser steps an epoch: slow and noisy (4-8 minibatches is usual)",
                        cfg.minibatches, per_mb, cfg.num_worlds, cfg.rollout_steps, cfg.minibatches)
        torch.backends.cuda.matmul.allow_tf32 = True
        ck = None if resume is None else load_checkpoint(resume, fallback=True)
        self._seed(cfg.seed + self.rank)
        self.source = resolve_scenes(cfg.scenes, n=cfg.num_scenes, seed=cfg.seed)
        if self.world > 1:
            self.source = dist_util.ShardSource(self.source, self.rank, self.world)
        self.sampler = SceneSampler(self.source, cfg.num_worlds, replacement=False, seed=cfg.seed + self.rank)
        # exact resume needs the same process count: engine states and samplers are per rank
        exact = ck is not None and ck.get("world_size", 1) == self.world == 1
        if exact:
            self.sampler.load_state_dict(ck["sampler"])
            self.sampler.last_indices = np.asarray(ck["scene_indices"], np.int64)
            scenes = [self.source.get(int(i)) for i in self.sampler.last_indices]
        else:
            scenes = self.sampler.sample()
        self.left_to_replay = 0  # policy agents beyond env.max_agents per world, replayed instead (`_control`)
        scenes, masks = self._worlds(scenes)
        self.sim = Simulator(scenes, sized_for(cfg.env, scenes), self.device, controlled=masks)
        self.actor, self.critic = build_models(cfg, self.sim, self.device)
        if ck is not None:  # before DDP wraps them, so every rank starts from the checkpoint
            self.actor.load_state_dict(ck["actor"])
            self.critic.load_state_dict(ck["critic"])
        elif cfg.init_policy:
            self._init_weights(cfg.init_policy)
        self.actor_fwd, self.critic_fwd = self.actor, self.critic
        if self.world > 1:
            ids = [torch.device(self.device).index] if self.device.startswith("cuda") else None
            self.actor_fwd = DDP(self.actor, device_ids=ids)
            self.critic_fwd = DDP(self.critic, device_ids=ids)
        self.head = PolicyHead(cfg.env.discrete)
        e = cfg.env
        self._noop = e.noop_index
        self.prior = make_prior(cfg, self.sim)
        # the actor's own motion window (actor_history > 0): kept in step with the engine, stored per step
        self.actor_hist = HistoryBuffer(cfg.actor_history) if cfg.actor_history else None
        self.prior_logits = self.head.discrete and cfg.eta1 > 0  # store the magnet's logits in the rollout
        self.params = [*self.actor.parameters(), *self.critic.parameters()]
        self.opt = torch.optim.Adam(self.params, lr=cfg.lr, eps=1e-5)
        shape = (cfg.env.max_agents,) if cfg.per_agent_lambda else ()
        self.lagrange = L.LagrangeMultiplier(cfg.lambda_init, cfg.lambda_lr, shape).to(self.device)
        self.budget = torch.tensor(float(cfg.cost_limit), device=self.device)  # "logs": scaled below
        self.gen = torch.Generator(device=self.device).manual_seed(cfg.seed + self.rank)
        self.update = 0
        self.agent_steps = 0
        self.wall = 0.0  # s of rollouts and updates (the time-to-quality clock)
        self.elapsed = 0.0  # s of training as a user waits for it: resampling, checkpoints and logging too
        self.window = RateWindow()  # the last RATE_WINDOW updates' episodes: the bar, the final line, the stop
        self.heldout = HeldoutCheck(cfg, self.device, self.lead)  # target_heldout
        self.runlog = RunLog(self.out, self.lead)
        if ck is not None and "cost_budget" in ck:
            self.budget.fill_(float(ck["cost_budget"]))
        elif cfg.cost_limit_mode == "logs" and cfg.constraint:  # plain MAPPO needs no budget
            self.logged_cvar = dist_util.all_reduce_mean(logged_cost_cvar(self.sim, cfg.alpha, cfg.gamma))
            self.budget = cfg.cost_limit * self.logged_cvar
        self.sim.reset()
        if ck is not None:
            self._load(ck, exact)

    # ------------------------------------------------------------ setup bits
    def _init_weights(self, source: str) -> None:
        """Actor and critic weights from the training checkpoint `source` (init_policy)."""
        path = checkpoint_path(source, "init_policy")
        ck = load_checkpoint(path, "init_policy", map_location=self.device)
        theirs = from_dict(TrainConfig, ck["config"], str(path))
        changes = network_differences(theirs, self.cfg)
        diff = [f"{k} {was} (this run: {now})" for k, was, now in changes if k not in POOLED_KEYS]
        for k, was, now in changes:
            if k in POOLED_KEYS:
                log.info("init_policy %s: %s %s, this run observes %s", source, k, was, now)
        if diff:
            raise ConfigError(f"init_policy {source}: its networks differ from this run's: {'; '.join(diff)}")
        self.actor.load_state_dict(ck["actor"])
        self.critic.load_state_dict(ck["critic"])
        log.info("actor and critic initialised from %s (update %s of that run)", path, ck.get("update"))

    @staticmethod
    def _seed(seed: int) -> None:
        random.seed(seed)
        np.random.seed(seed)
        torch.manual_seed(seed)

    def _worlds(self, drawn):
        """The sampler's scenes augmented (`augment`) and the run's control masks over them: a random
        subset (augment.control_fraction) of the agents its control mode picks, at most env.max_agents per
        world (the rest replay their logs, counted in `left_to_replay`); the engine itself gives every
        agent a slot (`sized_for`). The draws are seeded by the sampler's position, so a resumed run
        rebuilds the same worlds."""
        c, aug = self.cfg, self.cfg.augment
        rng = np.random.default_rng([c.seed, self.rank, self.sampler.draws])
        scenes = [augment_scene(s, aug, c.env.init_steps, c.env.goal_radius, rng) for s in drawn]
        masks, left = [], 0
        for scene, m in zip(scenes, control_masks(scenes, c.env, c.control, c.control_k, c.control_ids)):
            m, n = cap_controlled(scene, subset_mask(m, aug.control_fraction, rng), c.env.max_agents,
                                  c.env.init_steps)
            masks.append(m)
            left += n
        if left:
            log.warning("%d policy agents beyond env.max_agents=%d per world replay their logs in this batch",
                        left, c.env.max_agents)
        self.left_to_replay += left
        return scenes, masks

    def _resample(self) -> None:
        scenes, masks = self._worlds(self.sampler.sample())
        self.sim.set_scenes(scenes, controlled=masks, config=sized_for(self.cfg.env, scenes))

    # ------------------------------------------------------------- rollout
    def _amp(self):
        """bf16 autocast for the networks on GPU (losses stay in float32)."""
        return torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.sim.is_cuda and self.cfg.amp)

    def _policy_out(self, obs, slots, hist=None):
        with self._amp():
            out = self.actor(obs, slots, hist)
        return out.float() if self.head.discrete else (out[0].float(), out[1].float())

    @torch.no_grad()
    def collect(self) -> tuple[dict, dict]:
        """Drive every world for `rollout_steps` steps under the current policy: (the buffers the update
        reads, this rollout's episode and throughput stats)."""
        cfg, sim = self.cfg, self.sim
        T, W, C = cfg.rollout_steps, sim.num_worlds, max(sim.max_controlled, 1)
        dev = self.device
        buf = self._buffers(T, W, C)
        stats = {"terms": torch.zeros(len(sim.reward_term_names), device=dev), "alive": torch.zeros((), device=dev),
                 "episodes": torch.zeros((), device=dev), "goal": torch.zeros((), device=dev),
                 "collided": torch.zeros((), device=dev), "offroad": torch.zeros((), device=dev),
                 "min_dist": torch.zeros((), device=dev), "speed": torch.zeros((), device=dev)}
        bad = torch.zeros((), dtype=torch.bool, device=dev)  # non-finite policy output, checked once per rollout
        for t in range(T):
            obs = sim.obs[:, :C]
            mask = sim.active[:, :C] != 0
            # the actor runs on the live rows only (often under half of W x C); the other
            # slots get the no-op action, which the engine ignores for agents that do not act
            w_idx, c_idx = mask.nonzero(as_tuple=True)
            hist = None
            if self.actor_hist is not None:  # the actor's motion window, synced once per step
                self.actor_hist.sync(sim)
                buf["hist"][t] = self.actor_hist.features(sim, slice(0, C))
                hist = buf["hist"][t][w_idx, c_idx]
            out = self._policy_out(obs[w_idx, c_idx], c_idx, hist)
            if self.head.discrete:
                bad |= ~torch.isfinite(out).all()
                out = torch.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
            else:
                bad |= ~(torch.isfinite(out[0]).all() & torch.isfinite(out[1]).all())
                out = (torch.nan_to_num(out[0]), torch.nan_to_num(out[1]))
            d = self.head.dist(out)
            # sampled with our own generator, so a resumed run replays the same actions
            if self.head.discrete:
                a = torch.multinomial(torch.softmax(out, -1), 1, generator=self.gen)[:, 0] if len(w_idx) else \
                    torch.zeros(0, dtype=torch.long, device=dev)
            else:
                a = out[0] + out[1].exp() * torch.randn(out[0].shape, generator=self.gen, device=dev)
            act = buf["act"][t]
            act.fill_(self._noop if self.head.discrete else 0.0)  # rows that do not act
            act[w_idx, c_idx] = a.to(act.dtype)
            buf["logp"][t][w_idx, c_idx] = d.log_prob(a)
            if self.head.discrete:
                buf["old"][t][w_idx, c_idx] = out
            else:
                buf["old"][0][t][w_idx, c_idx], buf["old"][1][t][w_idx, c_idx] = out
            buf["obs"][t].copy_(obs)
            buf["mask"][t] = mask
            with self._amp():
                buf["value"][t], buf["quant"][t] = self.critic(obs, mask, w_idx * C + c_idx)
            if self.prior_logits:
                # the discrete magnet's logits, once per live row and step (bf16 on GPU): computing
                # them per minibatch and epoch instead doubled the update time with the world model
                ctx = self.prior.context(sim, C)
                with self._amp():
                    buf["prior"][t][w_idx, c_idx] = self.prior.distribution(ctx[w_idx, c_idx], obs[w_idx, c_idx]).float()
            elif self.cfg.eta1 > 0:
                buf["prior"][t] = self.prior.context(sim, C)
            if self.head.discrete:
                sim.actions_index[:, :C] = act.to(torch.int32)
            else:
                sim.actions[:, :C, : act.shape[-1]] = act
            sim.step()
            self._record_step(buf, stats, t, C)
        obs, mask = sim.obs[:, :C], sim.active[:, :C] != 0
        with self._amp():
            buf["value"][T], buf["quant"][T] = self.critic(obs, mask)
        if bool(bad):
            raise TrainingError(f"non-finite policy output during the rollout of update {self.update}; stopped "
                                f"without saving, the last good checkpoint is {self.out / 'checkpoint.pt'}")
        return buf, stats

    def _record_step(self, buf: dict, stats: dict, t: int, C: int) -> None:
        """After step t: its rewards, costs and ends into the buffers; its reward terms, speed and the
        outcomes of the episodes that ended into the rollout's stats (on the device, no host sync)."""
        sim = self.sim
        alive = sim.alive[:, :C].float()
        buf["reward"][t] = sim.reward[:, :C]
        buf["cost"][t] = sim.cost[:, :C]
        buf["done"][t] = ((sim.terminated[:, :C] != 0) | (sim.world_ended[:, None] != 0)).float()
        stats["terms"] += (sim.reward_terms[:, :C] * alive[..., None]).sum((0, 1))
        stats["alive"] += alive.sum()
        stats["speed"] += (sim.speed[:, :C] * alive).sum()
        ended = (sim.world_ended[:, None] != 0) & sim.policy_agents[:, :C]
        stats["episodes"] += ended.sum()
        stats["goal"] += (sim.final_goal[:, :C] * ended).sum()
        stats["collided"] += (sim.final_collided[:, :C] * ended).sum()
        stats["offroad"] += (sim.final_offroad[:, :C] * ended).sum()
        stats["min_dist"] += (sim.final_min_dist[:, :C] * ended).sum()

    def _buffers(self, T: int, W: int, C: int) -> dict:
        """Rollout storage, allocated once per shape (several GB at 4,096 worlds) and reused:
        every entry is overwritten by each rollout, so nothing needs clearing."""
        key = (T, W, C)
        if getattr(self, "_buf_key", None) == key:
            return self._buf
        cfg, sim, dev = self.cfg, self.sim, self.device
        self._buf = None  # drop the old storage before allocating the new one
        act = (T, W, C) if self.head.discrete else (T, W, C, self.cfg.env.act_dim)
        # under bf16 autocast the networks round their inputs to bf16 anyway: store them so
        obs_dtype = torch.bfloat16 if sim.is_cuda and cfg.amp else torch.float32
        buf = {
            "obs": torch.zeros((T, W, C, sim.obs_dim), dtype=obs_dtype, device=dev),
            "act": torch.zeros(act, device=dev),
            "logp": torch.zeros((T, W, C), device=dev),
            "mask": torch.zeros((T, W, C), dtype=torch.bool, device=dev),
            "reward": torch.zeros((T, W, C), device=dev),
            "cost": torch.zeros((T, W, C), device=dev),
            "done": torch.zeros((T, W, C), device=dev),
            "value": torch.zeros((T + 1, W, C), device=dev),
            "quant": torch.zeros((T + 1, W, C, cfg.quantiles), device=dev),
            "prior": torch.zeros((T, W, C, self._prior_dim()), device=dev),
        }
        if self.actor_hist is not None:
            buf["hist"] = torch.zeros((T, W, C, cfg.actor_history, HIST_DIM), device=dev)
        buf["old"] = (torch.zeros((T, W, C, sim.num_actions), device=dev) if self.head.discrete
                      else (torch.zeros(act, device=dev), torch.zeros(act, device=dev)))
        self._buf, self._buf_key = buf, key
        return buf

    def _prior_dim(self) -> int:
        """Per row and step: the magnet's logits (discrete), its context (continuous), nothing (eta1 0)."""
        if self.cfg.eta1 <= 0:
            return 0
        return self.sim.num_actions if self.prior_logits else getattr(self.prior, "context_dim", 4)

    # --------------------------------------------------------------- update
    def learn(self, buf: dict) -> dict:
        cfg = self.cfg
        T, W, C = buf["reward"].shape
        adv_r, ret_r = L.gae(buf["reward"], buf["value"], buf["done"], cfg.gamma, cfg.gae_lambda)
        # the critic as it was during the rollout is the cost critic's target network (hard update once
        # per PPO update); it is read inside the cost-to-go's support (targets, advantages, constraint)
        quant = buf["quant"].clamp(0.0, L.cost_to_go_bound(cfg.gamma))
        adv_c, cvar = L.cvar_gae(buf["cost"], quant, buf["done"], cfg.alpha, cfg.gamma, cfg.gae_lambda)
        q_target = L.cost_quantile_targets(buf["cost"], quant, buf["done"], cfg.gamma, cfg.cost_nstep)
        mask = buf["mask"]
        # the constraint per agent slot: the mean over its live states of CVaR_alpha(Z(o))
        cnt = mask.sum((0, 1))
        jc = torch.zeros(cfg.env.max_agents, device=self.device)
        jc[:C] = (cvar[:-1] * mask).sum((0, 1)) / cnt.clamp(min=1)
        seen = torch.zeros(cfg.env.max_agents, dtype=torch.bool, device=self.device)
        seen[:C] = cnt > 0
        jc, seen = dist_util.all_reduce_mean(jc), dist_util.all_reduce_mean(seen.float()) > 0  # equal lambdas on all ranks
        if not cfg.per_agent_lambda:  # one multiplier for all: the mean over the slots that had agents
            jc = (jc * seen).sum() / seen.sum().clamp(min=1)
        lam_before = self.lagrange.value.detach().clone()
        if cfg.constraint:
            # a slot without agents in this rollout keeps its multiplier
            step = jc if not cfg.per_agent_lambda else torch.where(seen, jc, self.budget)
            self.lagrange.update(step, self.budget)
        else:
            lam_before = torch.zeros_like(lam_before)
        lam = lam_before[:C] if cfg.per_agent_lambda else lam_before

        n_groups = T * W
        batch = self.flatten(buf, adv_r, adv_c, ret_r, q_target)
        mb = max(1, n_groups // cfg.minibatches)
        # loss parts accumulate on the device and are read once: a read per minibatch would
        # stall the launch queue on every one of them
        acc: dict[str, torch.Tensor] = {}
        bad = torch.zeros((), dtype=torch.bool, device=self.device)
        n_mb = 0
        for _ in range(cfg.epochs):
            perm = torch.randperm(n_groups, generator=self.gen, device=self.device)
            for s in range(0, n_groups, mb):
                loss, parts = self.minibatch_loss(batch, perm[s:s + mb], lam)
                bad |= ~torch.isfinite(loss)
                self.opt.zero_grad(set_to_none=True)
                loss.backward()  # under DDP the gradients are averaged over the ranks here
                # actor and critic clipped apart: one joint norm lets the critic's large early
                # regression gradients scale the policy's step down to nothing
                torch.nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                torch.nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
                self.opt.step()
                for k, val in parts.items():
                    acc[k] = acc.get(k, 0.0) + val.detach()
                n_mb += 1
        acc = {k: float(v) for k, v in acc.items()}
        if bool(bad):
            # the weights in memory are spoilt, nothing is saved: the checkpoint on disk stays the last good one
            raise TrainingError(
                f"non-finite loss in update {self.update} (mean policy {acc['loss/policy'] / n_mb:.4g}, value "
                f"{acc['loss/value'] / n_mb:.4g}, cost quantiles {acc['loss/cost_quantile'] / n_mb:.4g}); stopped "
                f"without saving, the last good checkpoint is {self.out / 'checkpoint.pt'}")
        out = {k: v / max(n_mb, 1) for k, v in acc.items()}
        out["cvar"] = float(L.masked_mean(cvar[:-1], mask))
        lam_now = self.lagrange.value[seen] if cfg.per_agent_lambda else self.lagrange.value
        out["lambda"] = float(lam_now.mean()) if cfg.constraint and lam_now.numel() else 0.0
        out["lambda_max"] = float(lam_now.max()) if cfg.constraint and lam_now.numel() else 0.0
        out["cost_budget"] = float(self.budget)
        return out

    def flatten(self, buf, adv_r, adv_c, ret_r, q_target) -> dict:
        """(T, W, C, ...) rollout tensors -> (T*W, C, ...) groups: one group = one world at one step."""
        T, W = buf["reward"].shape[:2]
        flat = lambda x: x.reshape(T * W, *x.shape[2:])  # noqa: E731
        b = {k: flat(buf[k]) for k in ("obs", "act", "logp", "mask", "prior", "hist") if k in buf}
        b.update(adv_r=flat(adv_r), adv_c=flat(adv_c), ret_r=flat(ret_r), q_target=flat(q_target))
        b["old"] = flat(buf["old"]) if self.head.discrete else (flat(buf["old"][0]), flat(buf["old"][1]))
        return b

    def minibatch_loss(self, b: dict, idx: torch.Tensor, lam) -> tuple[torch.Tensor, dict]:
        """CCE-MAPPO loss of the groups `idx`: actor on their live rows, critic on the groups."""
        cfg = self.cfg
        mi = b["mask"][idx]
        # the actor is per agent: run it on the live rows only (often under half of W x C)
        g, c = mi.nonzero(as_tuple=True)
        weight = 1.0
        if len(g) == 0:  # keep every rank's backward in step under DDP: a zero-weight dummy row
            g, c, weight = torch.zeros(1, dtype=torch.long, device=idx.device), torch.zeros(
                1, dtype=torch.long, device=idx.device), 0.0
        rows = idx[g]
        obs = b["obs"]
        with self._amp():
            out = self.actor_fwd(obs[rows, c], c, b["hist"][rows, c] if "hist" in b else None)
            v, q = self.critic_fwd(obs[idx], mi, None if weight == 0.0 else g * mi.shape[1] + c)
        out = out.float() if self.head.discrete else (out[0].float(), out[1].float())
        v, q = v.float(), q.float()
        d = self.head.dist(out)
        logp = d.log_prob(b["act"][rows, c])
        ent = d.entropy()
        old = b["old"]
        old_out = old[rows, c] if self.head.discrete else (old[0][rows, c], old[1][rows, c])
        if cfg.eta1 <= 0:  # plain MAPPO: no magnet to evaluate
            kl_prior = torch.zeros_like(logp)
        else:
            prior_out = b["prior"][rows, c] if self.prior_logits else \
                self.prior.distribution(b["prior"][rows, c], obs[rows, c].float())
            kl_prior = self.head.kl(out, prior_out)
        kl_prev = self.head.kl(out, old_out)
        lam_rows = lam[c] if cfg.per_agent_lambda else lam
        loss_pi, st = L.cce_mappo_actor_loss(
            logp, b["logp"][rows, c], b["adv_r"][rows, c], b["adv_c"][rows, c], lam_rows, ent, kl_prior,
            kl_prev, clip_eps=cfg.clip, entropy_coef=cfg.entropy_coef, eta1=cfg.eta1, eta2=cfg.eta2,
            normalize_advantages=cfg.normalize_advantages)
        loss_v = (v[g, c] - b["ret_r"][rows, c]).pow(2).mean()
        # quantile loss on live rows, against at most 16 evenly spaced target samples: the
        # pairwise (N x M) Huber term is otherwise the largest tensor of the update
        tq = b["q_target"][rows, c]
        if tq.shape[-1] > 16:
            tq = tq[..., torch.linspace(0, tq.shape[-1] - 1, 16, device=tq.device).round().long()]
        loss_q = L.quantile_huber_loss(q[g, c], tq, kappa=1.0)
        loss = weight * (loss_pi + cfg.value_coef * (loss_v + loss_q))
        parts = {"loss/policy": loss_pi, "loss/value": loss_v, "loss/cost_quantile": loss_q,
                 "kl/prior": st["kl_prior"], "kl/prev": st["kl_prev"], "entropy": st["entropy"],
                 "clip_frac": st["clip_frac"]}
        return loss, parts

    # ----------------------------------------------------------------- loop
    def train(self) -> dict:
        cfg = self.cfg
        bar = None
        if self.progress:
            bar = tqdm(total=cfg.updates, initial=self.update, desc="train", unit="update")
        self._bar_started = False  # the bar's clock restarts after this process's first update
        t_start, elapsed0 = time.perf_counter(), self.elapsed
        try:
            with StopRequest() as stop:
                last = self._loop(bar, stop, t_start, elapsed0)
        finally:  # an error's message then comes after the bar, not inside it
            if bar is not None:
                bar.close()
        self.runlog.plot()
        self.runlog.close()
        return last

    def _loop(self, bar, stop: "StopRequest", t_start: float, elapsed0: float) -> dict:
        """Updates until cfg.updates, the time limit, the quality target or a Ctrl-C (which ends the
        update under way and saves it); the last update's metrics row."""
        cfg = self.cfg
        last = {}
        while self.update < cfg.updates:
            if cfg.resample_every and self.update > 0 and self.update % cfg.resample_every == 0:
                self._resample()
            last, stats = self._step(elapsed0, t_start)
            self.window.add(stats)  # the window of rates the bar shows and the stop reads
            reached = self.window.reached(cfg)
            self._show(bar, last)
            if reached and cfg.target_heldout:
                reached = self._heldout_check(bar)
            out_of_time = 0 < cfg.time_limit_s <= self.wall
            interrupted = stop.requested(self.device)
            if self.lead and (self.update % cfg.checkpoint_every == 0 or self.update == cfg.updates or reached
                              or out_of_time or interrupted):
                self.save()
            if interrupted:
                last["interrupted"] = True
                break
            if self.lead and cfg.keep_policy_every and self.update % cfg.keep_policy_every == 0:
                self.save_policy()
            if out_of_time and not reached:
                if bar is not None:
                    bar.write(f"time limit {cfg.time_limit_s:.0f} s reached after update {self.update}")
                break
            if reached:
                last["target_reached_s"] = self.wall
                self._record_target(bar)
                break
        return last

    def _step(self, elapsed0: float, t_start: float) -> tuple[dict, dict]:
        """One update: collect, reduce the stats over the ranks, learn, count, log. (metrics row, stats)."""
        t0 = time.perf_counter()
        buf, stats = self.collect()
        self._sync()
        t_own = time.perf_counter() - t0  # this rank's rollout
        dist_util.all_reduce_sum_(stats)  # rates and throughput over all ranks
        self._sync()
        t_roll = time.perf_counter() - t0  # until the slowest rank's rollout is in
        row = self.learn(buf)
        self._sync()
        dt = time.perf_counter() - t0
        # where each rank's time went: its rollout, waiting for the slowest rollout, the update
        # (backward's gradient all-reduce waits for the slowest backward inside it); every rank's
        # row goes to timing.csv, rank 0's and the slowest rollout to metrics.csv
        phases = dist_util.gather_floats([t_own, t_roll - t_own, dt - t_roll], self.device)
        row.update({"time/rollout_s": t_own, "time/rollout_slowest_s": max(p[0] for p in phases),
                    "time/wait_s": t_roll - t_own, "time/update_s": dt - t_roll})
        self.wall += dt
        self.elapsed = elapsed0 + time.perf_counter() - t_start
        steps = int(stats["alive"])
        self.agent_steps += steps
        self.update += 1
        row.update(self._row(buf, stats, steps, dt, t_roll))
        self.runlog.metrics(row)
        self.runlog.timing(self.update, phases)
        return row, stats

    def _row(self, buf: dict, stats: dict, steps: int, dt: float, t_roll: float) -> dict:
        """The counters, rates, reward terms and throughput of the update just done (metrics.csv)."""
        n_ep = float(stats["episodes"])
        per = lambda key: float(stats[key]) / n_ep if n_ep else float("nan")  # noqa: E731
        row = {
            "update": self.update, "agent_steps": self.agent_steps, "wall_s": self.wall,
            "elapsed_s": self.elapsed, "agent_steps_per_s": steps / dt,
            "rollout_agent_steps_per_s": steps / max(t_roll, 1e-9),
            "episodes": n_ep, "goal_rate": per("goal"), "collision_rate": per("collided"),
            "offroad_rate": per("offroad"), "mean_min_distance": per("min_dist"),
            "cost": float(buf["cost"].sum() / max(int(buf["mask"].sum()), 1)),
            "mean_speed": float(stats["speed"]) / max(steps, 1),
            "scenes_visited": self.sampler.visited,
            **source_report(self.source),  # files that do not load, scenes that cannot be played
        }
        per_term = stats["terms"] / max(steps, 1)
        for name, v in zip(self.sim.reward_term_names, per_term.tolist()):
            row[f"reward/{name}"] = v
        row["reward"] = float(buf["reward"].sum() / max(int(buf["mask"].sum()), 1))
        row["ranks"] = self.world
        if self.sim.is_cuda:
            row["gpu_mem_peak_gb"] = torch.cuda.max_memory_allocated(self.device) / 2**30
        return row

    def _show(self, bar, row: dict) -> None:
        """The progress bar after an update: throughput, the window's rates, lambda. The first update of a
        process compiles kernels and warms caches, so the bar's clock (its ETA) restarts after it."""
        if bar is None:
            return
        if not self._bar_started:
            bar.reset(total=self.cfg.updates)
            bar.initial = bar.n = self.update
            self._bar_started = True
        else:
            bar.update(1)
        rates = self.window.rates()  # None until an episode has ended
        shown = {k: f"{rates[k]:.2f}" if rates else "-" for k in RATE_KEYS}
        bar.set_postfix(sps=f"{row['agent_steps_per_s']:.0f}", goal=shown["goal_rate"],
                        coll=shown["collision_rate"], off=shown["offroad_rate"], lam=f"{row['lambda']:.2f}")

    def _record_target(self, bar) -> None:
        """target.json, and a line under the bar, once the quality target is reached."""
        cfg = self.cfg
        if not self.lead:
            return
        (self.out / "target.json").write_text(json.dumps(
            {"target_goal_rate": cfg.target_goal_rate, "target_max_collision": cfg.target_max_collision,
             "target_max_offroad": cfg.target_max_offroad, "update": self.update, "wall_s": self.wall,
             "agent_steps": self.agent_steps, "heldout": self.heldout.rates}, indent=1))
        if bar is not None:
            bar.write(f"target (goal >= {cfg.target_goal_rate}, collision <= {cfg.target_max_collision}, "
                      f"off-road <= {cfg.target_max_offroad}) reached after {self.wall:.0f} s "
                      f"(update {self.update}, {self.agent_steps:,} agent steps)")

    def _heldout_check(self, bar=None) -> bool:
        """The held-out check (targets.HeldoutCheck), logged to heldout.csv and shown under the bar."""
        ok = self.heldout(self.actor)
        if self.lead:
            self.runlog.heldout({"update": self.update, "wall_s": self.wall, **self.heldout.rates, "met": int(ok)})
            if bar is not None:
                bar.write(self.heldout.describe(self.update, ok))
        return ok

    def _sync(self) -> None:
        if self.sim.is_cuda:
            torch.cuda.synchronize(self.device)

    # -------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        rng = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
               "gen": self.gen.get_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {
            "kind": POLICY, "config": to_dict(self.cfg), "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "opt": self.opt.state_dict(),
            "lagrange": self.lagrange.state_dict(), "cost_budget": float(self.budget),
            "update": self.update, "agent_steps": self.agent_steps, "wall": self.wall, "elapsed": self.elapsed,
            "rng": rng,
            "sampler": self.sampler.state_dict(), "scene_indices": self.sampler.last_indices.tolist(),
            "world_size": self.world,
            "engine": self.sim.snapshot(), "prior": self.prior.state_dict(),
            "actor_history": {} if self.actor_hist is None else self.actor_hist.state_dict(),
        }

    def save(self) -> Path:
        path = save_atomic(self.state_dict(), self.out / "checkpoint.pt", keep_previous=True)
        (self.out / "config.json").write_text(json.dumps(to_dict(self.cfg), indent=1))
        return path

    def save_policy(self) -> Path:
        """The policy alone (config and actor weights, about a megabyte) as policies/update_NNNNNN.pt:
        what load_policy and the report read, so the CCE-gap can be followed over training."""
        snap = {"kind": POLICY, "config": to_dict(self.cfg), "actor": self.actor.state_dict(), "update": self.update,
                "agent_steps": self.agent_steps, "wall": self.wall}
        (self.out / POLICY_DIR).mkdir(exist_ok=True)
        return save_atomic(snap, self.out / POLICY_DIR / f"update_{self.update:06d}.pt")

    def _load(self, ck: dict, exact: bool) -> None:
        self.opt.load_state_dict(ck["opt"])
        self.lagrange.load_state_dict(ck["lagrange"])
        self.update, self.agent_steps, self.wall = ck["update"], ck["agent_steps"], ck["wall"]
        self.elapsed = ck.get("elapsed", self.wall)  # checkpoints before elapsed_s existed
        if not exact:
            # another process count: weights, optimiser, lambda and counters carry over; episodes
            # start afresh on each rank's own scene shard
            self.gen.manual_seed(self.cfg.seed + self.rank + 7919 * self.update)
            self.runlog.trim(self.update)
            return
        rng = ck["rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.gen.set_state(rng["gen"])
        if "cuda" in rng and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
        self.sim.restore(ck["engine"])
        self.prior.load_state_dict(self.sim, ck.get("prior", {}))
        if self.actor_hist is not None:
            self.actor_hist.load_state_dict(self.sim, ck.get("actor_history", {}))
        self.runlog.trim(self.update)


def train_main(cfg: TrainConfig, out_dir=None, resume=None, progress=True) -> dict:
    trainer = Trainer(cfg, out_dir, resume, progress)
    last = trainer.train()
    return {k: v for k, v in last.items() if not (isinstance(v, float) and math.isnan(v))} | {
        "out_dir": str(trainer.out), "checkpoint": str(trainer.out / "checkpoint.pt"),
        "agents_left_to_replay": trainer.left_to_replay,
        # episode-weighted over the last RATE_WINDOW updates (the window the quality target reads); None
        # before any episode ended
        "window_rates": trainer.window.rates()}

