"""CCE-MAPPO (TrafficGamer) on the engine's tensors: `tg-gpudrive train`.

`Trainer.train` is the loop; each update is a rollout of `rollout_steps` steps in all W worlds
(collector.RolloutCollector: a Rollout of (T, W, C, ...) blocks, controlled agents in slots [0, C)),
then PPO epochs over it (update.ppo_update: advantages, the Lagrange step on the CVaR constraint, the
actor and critic losses of losses.py). Around them the loop resamples scenes, logs (runlog.RunLog),
checks the quality targets (targets.RateWindow, targets.HeldoutCheck), saves checkpoints and stops on
the update count, the time limit, the target or a Ctrl-C (stop.StopRequest). The budget lambda
answers to is `cost_limit` (x the logged drivers' own CVaR with `cost_limit_mode: logs`, x the starting
policy's mean cost-to-go with `start`; set it above their level, or the constraint is infeasible and lambda grows
without bound).

Checkpoints are atomic (write, then rename) and hold everything a resume needs
to continue exactly: weights, optimisers, lambda, RNG states, counters, the
sampler position and the engine State mid-episode.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import random
import sys
import time
from pathlib import Path

import numpy as np
import torch

from tqdm import tqdm

from tg_gpudrive.checkpoint import (POLICY, POLICY_DIR, POOLED_KEYS, checkpoint_path, grows, load_checkpoint,
                                    network_differences, save_atomic)
from tg_gpudrive.config import ConfigError, TrainConfig, from_dict, to_dict
from tg_gpudrive.data.sampler import SceneSampler
from tg_gpudrive.data.augment import augment_scene, subset_mask
from tg_gpudrive.data.sources import resolve_scenes, source_report
from tg_gpudrive.engine.control import cap_controlled, control_masks
from tg_gpudrive.engine.model import sized_for
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.history import HistoryBuffer
from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn import losses as L
from tg_gpudrive.learn import pipeline
from tg_gpudrive.learn.collector import Networks, NonFinite, Rollout, RolloutCollector, TrainingError
from tg_gpudrive.learn.compiling import start_compiler_preload
from tg_gpudrive.learn.quality import RATE_KEYS
from tg_gpudrive.learn.bar_watch import BarWatch
from tg_gpudrive.learn.runlog import RunLog
from tg_gpudrive.learn.stop import StopRequest
from tg_gpudrive.learn.targets import HeldoutCheck, RateWindow
from tg_gpudrive.learn.graphs import RolloutGraphs, StepGraphs
from tg_gpudrive.learn.update import make_optimizer, ppo_update
from tg_gpudrive.agents.builtin import background_masks, make_background_driver
from tg_gpudrive.agents.prior import ExpertPrior
from tg_gpudrive.agents.networks import grown_actor_state
from tg_gpudrive.agents.policy import BehaviourPrior, PolicyHead, actor_policy, build_models
from tg_gpudrive.worldmodel import WorldModelPrior, load_shipped, load_world_model

log = logging.getLogger(__name__)
SMALL_MINIBATCH = 16  # world-steps: a minibatch with fewer is warned about


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

    The values are `cost_to_go(sim, gamma)` under the expert (inverse-dynamics actions of the logs);
    returns the mean of their upper (1 - alpha) tail (a scalar tensor). Over a mixture of states
    this is at least the mean over states of their own CVaR_alpha, the estimate the multipliers
    compare with the budget, so a budget of 1 x this is one the logs themselves satisfy. Leaves the
    simulator to be reset by the caller."""
    return sample_cvar(cost_to_go(sim, gamma), alpha)


def sample_cvar(vals: torch.Tensor, alpha: float) -> torch.Tensor:
    """CVaR_alpha of a flat sample: the mean of its upper (1 - alpha) tail (0 for an empty one)."""
    if vals.numel() == 0:
        return torch.zeros((), device=vals.device)
    return L.cvar_from_quantiles(vals.sort().values, alpha)


def cost_to_go(sim: Simulator, gamma: float, act=None) -> torch.Tensor:
    """The discounted cost-to-go G_t = c_t + gamma G_{t+1} (to the end of its episode) of every
    controlled policy agent at every step it was driven, over one episode in every world, as a flat
    tensor. `act(sim)` writes the actions before each step; None replays the expert. Leaves the
    simulator to be reset by the caller."""
    cost, live = episode_costs(sim, act)
    ctg = torch.zeros_like(cost)
    run = torch.zeros_like(cost[0])
    for t in range(cost.shape[0] - 1, -1, -1):
        run = (cost[t] + gamma * run) * live[t]  # a step the agent did not act cuts the sum
        ctg[t] = run
    return ctg[live]


def episode_costs(sim: Simulator, act=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Every step's cost of the controlled policy agents over one episode in every world, (steps, W, C),
    and where an agent acted (the same shape, bool); `act` as in cost_to_go."""
    sim.reset()
    C = max(sim.max_controlled, 1)
    steps = sim.episode_length
    cost = torch.zeros((steps, sim.num_worlds, C), device=sim.reward.device)
    live = torch.zeros_like(cost, dtype=torch.bool)
    first = torch.ones(sim.num_worlds, dtype=torch.bool, device=cost.device)  # still in its first episode
    for t in range(steps):
        if act is None:
            sim.use_expert_actions()
        else:
            act(sim)
        live[t] = (sim.active[:, :C] != 0) & sim.policy_agents[:, :C] & first[:, None]
        sim.step()
        cost[t] = sim.cost[:, :C] * live[t]
        first &= sim.world_ended == 0
    return cost, live


class Trainer:
    """A training run: the worlds (scene source, sampler, simulator), the learner (networks, optimiser,
    Lagrange multipliers) and the loop `train` over its collaborators: the rollout collector
    (collector.py), the update (update.py), the logs (runlog.py), the quality targets (targets.py) and
    the checkpoints. `resume` continues a run from its checkpoint (exactly, on one process)."""

    def __init__(self, cfg: TrainConfig, out_dir: str | Path | None = None, resume: str | Path | None = None,
                 progress: bool = True):
        self.cfg = cfg
        self.out = Path(out_dir or cfg.out_dir)
        self.rank, self.world = dist_util.rank(), dist_util.world_size()
        self.lead = self.rank == 0  # logs and checkpoints
        if cfg.pipeline and self.world % 2:
            raise ConfigError(f"pipeline: true needs an even number of processes (--nproc 2, 4, ...), half that act "
                              f"and half that learn; this run has {self.world} (--set pipeline=false runs without it)")
        # which stream of scenes and random draws this process's worlds follow (`streams` of them, disjoint shards of
        # the source): its rank, or with `pipeline` its pair's (learner 2p and actor 2p + 1: the learner builds the
        # actor's first worlds and never steps them)
        self.streams = self.world // 2 if cfg.pipeline else self.world
        self.stream = self.rank // 2 if cfg.pipeline else self.rank
        self.learns = not cfg.pipeline or self.rank % 2 == 0  # with `pipeline`, the learners are the even ranks
        self.reported = None  # with `pipeline`, on a learner: its actor's scene counters (source_counts)
        self.pipe_keys = None  # ... and the scene keys of its last batch's worlds (world_keys)
        if self.lead:
            self.out.mkdir(parents=True, exist_ok=True)
        self.progress = progress and self.lead
        self.device = dist_util.local_device(cfg.device)
        if self.world > 1 and self.device.startswith("cuda"):
            torch.cuda.set_device(self.device)  # this rank's NCCL collectives live on it
        per_mb = cfg.num_worlds * cfg.rollout_steps // cfg.minibatches
        if self.lead and cfg.minibatches > 1 and per_mb < SMALL_MINIBATCH:
            log.warning("minibatches=%d: each minibatch holds %d world-steps (of %d worlds x %d steps), so an update "
                        "takes %d small optimiser steps an epoch: slow and noisy (4-8 minibatches is usual)",
                        cfg.minibatches, per_mb, cfg.num_worlds, cfg.rollout_steps, cfg.minibatches)
        torch.backends.cuda.matmul.allow_tf32 = True
        # the compiler's start-up beside the build, in a process that will compile: the rollout's passes run on every
        # process (the advantages on the learners), the update's loss on the learners
        compiles = cfg.compile_rollout or (cfg.compile_update and self.learns)
        preload = start_compiler_preload(self.device) if compiles else None
        ck = None if resume is None else load_checkpoint(resume, fallback=True)
        self._seed(cfg.seed + self.stream)
        # exact resume needs the same process count: engine states and samplers are per rank
        mine = saved_rank_state(ck, self.rank, self.world, cfg.pipeline)
        self._build_worlds(mine)
        self._build_learner(ck)
        self.graphs0 = 0  # graphs compiled before this trainer's first update (the preload's, an earlier trainer's)
        if preload is not None:
            preload.join()
            self.graphs0 = torch._dynamo.utils.counters["stats"]["unique_graphs"]
        self.update = 0
        self.agent_steps = 0
        self.wall = 0.0  # s of rollouts and updates (the time-to-quality clock)
        self.elapsed = 0.0  # s of training as a user waits for it: resampling, checkpoints and logging too
        self.window = RateWindow()  # the last RATE_WINDOW updates' episodes: the bar, the final line, the stop
        self.heldout = HeldoutCheck(cfg, self.device, self.lead)  # target_heldout
        self.runlog = RunLog(self.out, self.lead)
        self.bar_watch = BarWatch(cfg)  # warns once when lambda climbs and the cost stays far above its bar
        if ck is not None and "cost_budget" in ck:
            self.budget.fill_(float(ck["cost_budget"]))
        elif cfg.cost_limit_mode != "absolute" and cfg.constraint:  # plain MAPPO needs no budget
            self.budget = cfg.cost_limit * dist_util.all_reduce_mean(self._bar_cost())
        self.first_worlds = None
        self.sim.reset()
        if ck is not None:
            self._load(ck, mine)

    def _bar_cost(self) -> torch.Tensor:
        """The cost the budget is cost_limit times, on this rank's first worlds, under cost_limit_beta when it
        is set (the same worlds in a simulator of their own, freed after) or the run's beta. `logs`: the logs'
        own value of what lambda is stepped on, their CVaR_alpha or their mean (alpha 0). `start`: the starting
        policy's mean discounted cost-to-go over one sampled episode in every world, an alpha-free level, so one
        per beta holds every alpha's CVaR to the same bar (a higher alpha, a heavier tail held to it: the
        tighter constraint). With `lambda_on: sampled` or `sampled_cvar`, either one's mean per-step cost x
        1 / (1 - gamma)."""
        cfg, sim = self.cfg, self.sim
        if cfg.cost_limit_beta and cfg.cost_limit_beta != cfg.env.beta:
            scenes, masks = self.first_worlds
            env = sized_for(dataclasses.replace(cfg.env, beta=cfg.cost_limit_beta), scenes)
            sim = Simulator(scenes, env, self.device, controlled=masks,
                            background=background_masks(scenes, env, cfg.background, masks))
        act = None if cfg.cost_limit_mode == "logs" else actor_policy(self.actor, sim, cfg.actor_history)
        with torch.random.fork_rng(devices=[self.device] if sim.is_cuda else []):  # training's stream kept
            torch.manual_seed(cfg.seed + self.stream)
            if cfg.lambda_on.startswith("sampled"):  # the cost rate / (1 - gamma): lambda's figure, or its mean
                cost, live = episode_costs(sim, act)
                return cost[live].mean() / (1.0 - cfg.gamma) if live.any() else torch.zeros((), device=self.device)
            if cfg.cost_limit_mode == "logs":
                return logged_cost_cvar(sim, cfg.alpha if cfg.lambda_on == "cvar" else 0.0, cfg.gamma)
            ctg = cost_to_go(sim, cfg.gamma, act)
        return ctg.mean() if ctg.numel() else torch.zeros((), device=self.device)

    # ------------------------------------------------------------ setup bits
    def _build_worlds(self, ck: dict | None) -> None:
        """The scene source (this rank's shard), the sampler and the simulator over its first draw, or
        over the scenes of the checkpoint `ck` an exact resume continues."""
        cfg = self.cfg
        self.source = resolve_scenes(cfg.scenes, n=cfg.num_scenes, seed=cfg.seed)
        if self.streams > 1:
            self.source = dist_util.ShardSource(self.source, self.stream, self.streams)
        self.sampler = SceneSampler(self.source, cfg.num_worlds, replacement=False, seed=cfg.seed + self.stream)
        if ck is not None:
            self.sampler.load_state_dict(ck["sampler"])
            self.sampler.last_indices = np.asarray(ck["scene_indices"], np.int64)
            scenes = [self.source.get(int(i)) for i in self.sampler.last_indices]
        else:
            scenes = self.sampler.sample()
        self.left_to_replay = 0  # policy agents beyond env.max_agents per world, replayed instead (`_worlds`)
        scenes, masks = self._worlds(scenes)
        self.first_worlds = (scenes, masks)  # what the bar is measured on (_bar_cost)
        env = sized_for(cfg.env, scenes)
        self.sim = Simulator(scenes, env, self.device, controlled=masks,
                             background=background_masks(scenes, env, cfg.background, masks))

    def _build_learner(self, ck: dict | None) -> None:
        """The networks (from the checkpoint `ck`, init_policy or fresh), the magnet, the optimiser, the
        Lagrange multipliers, the sampling generator and the rollout collector."""
        cfg = self.cfg
        actor, critic = build_models(cfg, self.sim, self.device)
        self.nets = Networks(actor, critic, PolicyHead(cfg.env.discrete), amp=self.sim.is_cuda and cfg.amp)
        if ck is not None:
            actor.load_state_dict(ck["actor"])
            critic.load_state_dict(ck["critic"])
        elif cfg.init_policy:
            self._init_weights(cfg.init_policy)
        dist_util.broadcast_from_lead_((actor, critic))  # every rank starts from the same weights
        prior = make_prior(cfg, self.sim)
        # the actor's own motion window (actor_history > 0): kept in step with the engine, stored per step
        self.actor_hist = HistoryBuffer(cfg.actor_history) if cfg.actor_history else None
        self.params = [*actor.parameters(), *critic.parameters()]
        self.opt = make_optimizer(cfg, self.params, self.sim.is_cuda)
        self.graphs = StepGraphs(cfg, self.nets, self.opt) if cfg.cuda_graphs else None
        shape = (cfg.env.max_agents,) if cfg.per_agent_lambda else ()
        if cfg.lambda_per_vehicle:  # a row per scene of the whole source (every rank's shard in it)
            shape = (len(getattr(self.source, "source", self.source)), cfg.env.max_agents)
        self.lagrange = L.LagrangeMultiplier(cfg.lambda_init, cfg.lambda_lr, shape,
                                             cfg.lambda_max or math.inf).to(self.device)
        self.budget = torch.tensor(float(cfg.cost_limit), device=self.device)  # "logs": scaled in __init__
        self.gen = torch.Generator(device=self.device).manual_seed(cfg.seed + self.stream)
        self.collector = RolloutCollector(cfg, self.sim, self.nets, prior, self.gen, self.device, self.actor_hist)
        if cfg.cuda_graphs:
            self.collector.graphs = RolloutGraphs(self.device)
        # the vehicles the policy does not drive: None (they replay their logs) or a driver of their rows
        model = (cfg.prior_model or None) if cfg.background == "world_model" else None
        self.collector.background = make_background_driver(self.sim, cfg.background, model, cfg.seed + self.stream,
                                                           "prior_model")

    def _init_weights(self, source: str) -> None:
        """Actor and critic weights from the training checkpoint `source` (init_policy); per-slot heads or a
        motion window this run adds to a policy without them are grown from it (networks.grown_actor_state)."""
        path = checkpoint_path(source, "init_policy")
        ck = load_checkpoint(path, "init_policy", map_location=self.device)
        theirs = from_dict(TrainConfig, ck["config"], str(path))
        changes = network_differences(theirs, self.cfg)
        grown = [(k, was, now) for k, was, now in changes if grows(theirs, k, was)]
        diff = [f"{k} {was} (this run: {now})" for k, was, now in changes
                if k not in POOLED_KEYS and (k, was, now) not in grown]
        for k, was, now in changes:
            if k in POOLED_KEYS:
                log.info("init_policy %s: %s %s, this run observes %s", source, k, was, now)
        if diff:
            raise ConfigError(f"init_policy {source}: its networks differ from this run's: {'; '.join(diff)}")
        for k, was, now in grown:
            log.info("init_policy %s: %s %s, grown to this run's %s", source, k, was, now)
        self.actor.load_state_dict(grown_actor_state(ck["actor"], self.actor) if grown else ck["actor"])
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
        rng = np.random.default_rng([c.seed, self.stream, self.sampler.draws])
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
        env = sized_for(self.cfg.env, scenes)
        self.sim.set_scenes(scenes, controlled=masks, config=env,
                            background=background_masks(scenes, env, self.cfg.background, masks))

    # ------------------------------------------------------ collect, learn
    @property
    def prior(self) -> BehaviourPrior:
        """The magnet (make_prior); replacing it serves the next rollouts and updates."""
        return self.collector.prior

    @prior.setter
    def prior(self, prior: BehaviourPrior) -> None:
        self.collector.prior = prior

    actor = property(lambda self: self.nets.actor, doc="the policy network")
    critic = property(lambda self: self.nets.critic, doc="the reward value and cost quantile network")
    head = property(lambda self: self.nets.head, doc="the actor's output as a distribution")

    def collect(self) -> tuple[Rollout, dict]:
        """One rollout in every world (collector.RolloutCollector): (the batch, its episode and throughput
        counters, also `batch.stats`)."""
        try:
            batch = self.collector.collect()
        except NonFinite as e:
            raise self._spoilt(f"{e.what} during the rollout of update {self.update}") from None
        return batch, batch.stats

    def world_keys(self) -> torch.Tensor:
        """Each world's scene as an index into the whole source (a rank's shard maps its own indices
        back; with `pipeline`, on the learner, those of the batch it learns on): the row of its vehicles in the
        per-vehicle multiplier table."""
        if self.pipe_keys is not None:
            return self.pipe_keys
        idx = np.asarray(self.sampler.last_indices, np.int64)
        if isinstance(self.source, dist_util.ShardSource):
            idx = self.source.indices[idx]
        return torch.as_tensor(idx, device=self.device)

    def learn(self, batch: Rollout | dict) -> dict:
        """One CCE-MAPPO update on `batch` (update.ppo_update): the update's row of metrics."""
        try:
            return ppo_update(self.cfg, Rollout.of(batch), self.nets, self.opt, self.lagrange, self.budget,
                              self.gen, self.prior, self.world_keys() if self.cfg.lambda_per_vehicle else None,
                              self.graphs, step_lambda=self.update >= self.cfg.lambda_warmup)
        except NonFinite as e:
            raise self._spoilt(f"{e.what} in update {self.update} ({e.detail})") from None

    def _spoilt(self, what: str) -> TrainingError:
        # the weights in memory are spoilt, nothing is saved: the checkpoint on disk stays the last good one
        return TrainingError(f"{what}; stopped without saving, the last good checkpoint is "
                             f"{self.out / 'checkpoint.pt'}")

    # ----------------------------------------------------------------- loop
    def train(self) -> dict:
        """Update until cfg.updates, the time limit, the quality target or a Ctrl-C, under a progress bar;
        then curves.png. The last update's metrics row."""
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

    def _loop(self, bar, stop: StopRequest, t_start: float, elapsed0: float) -> dict:
        """Updates until cfg.updates, the time limit, the quality target or a Ctrl-C (which ends the
        update under way and saves it); the last update's metrics row. With `pipeline` each process runs its
        part, acting or learning (learn/pipeline.py)."""
        if self.cfg.pipeline:
            return pipeline.run(self, bar, stop, t_start, elapsed0)
        cfg = self.cfg
        last = {}
        while self.update < cfg.updates:
            if cfg.resample_every and self.update > 0 and self.update % cfg.resample_every == 0:
                self._resample()
            last, stats = self._step(elapsed0, t_start)
            save, end = self.verdict(bar, last, stats, stop.requested(self.device))
            if save:
                self.save()  # every rank: each hands its own state to the lead, which writes
            self.keep_policy(last)
            if end:
                break
        return last

    def verdict(self, bar, last: dict, stats: dict, interrupted: bool) -> tuple[bool, bool]:
        """After an update: its episodes into the window of rates, the bar, the quality target (with the
        held-out check) and the time limit; (whether to save a checkpoint, whether to stop here)."""
        cfg = self.cfg
        self.window.add(stats)  # the window of rates the bar shows and the stop reads
        warning = self.bar_watch.add(last)
        if warning and self.lead:
            log.warning("update %d: %s", self.update, warning)
        reached = self.window.reached(cfg)
        self._show(bar, last)
        if reached and cfg.target_heldout:
            reached = self._heldout_check(bar)
        out_of_time = 0 < cfg.time_limit_s <= self.wall
        save = (self.update % cfg.checkpoint_every == 0 or self.update == cfg.updates or reached or out_of_time
                or interrupted)
        if interrupted:
            last["interrupted"] = True
        elif out_of_time and not reached and bar is not None:
            bar.write(f"time limit {cfg.time_limit_s:.0f} s reached after update {self.update}", file=sys.stderr)
        if reached and not interrupted:
            last["target_reached_s"] = self.wall
            self._record_target(bar)
        return save, interrupted or out_of_time or reached

    def keep_policy(self, last: dict) -> None:
        """policies/update_NNNNNN.pt every keep_policy_every updates (not on a Ctrl-C's last one)."""
        every = self.cfg.keep_policy_every
        if self.lead and every and self.update % every == 0 and not last.get("interrupted"):
            self.save_policy()

    def _step(self, elapsed0: float, t_start: float) -> tuple[dict, dict]:
        """One update: collect, reduce the stats over the ranks, learn, count, log. (metrics row, stats)."""
        # the ranks start the update's clock together: what a rank did between updates (the lead writing a
        # checkpoint, a resampling of scenes) is then outside every rank's clock, as on one GPU, rather than
        # inside the others' wait for the slowest rollout
        dist_util.barrier()
        t0 = time.perf_counter()
        batch, stats = self.collect()
        self._sync()
        t_own = time.perf_counter() - t0  # this rank's rollout
        dist_util.all_reduce_sum_(stats)  # rates and throughput over all ranks
        self._sync()
        t_roll = time.perf_counter() - t0  # until the slowest rank's rollout is in
        row = self.learn(batch)
        self._sync()
        dt = time.perf_counter() - t0
        # where each rank's time went: its rollout, waiting for the slowest rollout, the update
        # (backward's gradient all-reduce waits for the slowest backward inside it); every rank's
        # row goes to timing.csv, rank 0's and the slowest rollout to metrics.csv
        phases = dist_util.gather_floats([t_own, t_roll - t_own, dt - t_roll], self.device)
        row.update({"time/rollout_s": t_own, "time/rollout_slowest_s": max(p[0] for p in phases),
                    "time/wait_s": t_roll - t_own, "time/update_s": dt - t_roll})
        self.wall += max(sum(p) for p in phases)  # the slowest rank's: every rank reads the same clock
        return self.count(row, batch, stats, phases, dt, t_roll, elapsed0, t_start), stats

    def count(self, row: dict, batch: Rollout, stats: dict, phases: list, dt: float, t_roll: float,
              elapsed0: float, t_start: float) -> dict:
        """The update just learnt counted and logged: its agent-steps, the metrics row (`row` completed) and
        each rank's `phases` (timing.csv). The row."""
        self.elapsed = elapsed0 + time.perf_counter() - t_start
        steps = int(stats["alive"])
        self.agent_steps += steps
        self.update += 1
        row.update(self._row(batch, stats, steps, dt, t_roll))
        self.runlog.metrics(row)
        self.runlog.timing(self.update, phases)
        return row

    def _row(self, batch: Rollout, stats: dict, steps: int, dt: float, t_roll: float) -> dict:
        """The counters, rates, reward terms and throughput of the update just done (metrics.csv)."""
        n_ep = float(stats["episodes"])
        per = lambda key: float(stats[key]) / n_ep if n_ep else float("nan")  # noqa: E731
        row = {
            "update": self.update, "agent_steps": self.agent_steps, "wall_s": self.wall,
            "elapsed_s": self.elapsed, "agent_steps_per_s": steps / dt,
            "rollout_agent_steps_per_s": steps / max(t_roll, 1e-9),
            "episodes": n_ep, "goal_rate": per("goal"), "collision_rate": per("collided"),
            "offroad_rate": per("offroad"), "timeout_rate": per("timeout"), "mean_min_distance": per("min_dist"),
            "cost": float(batch.cost.sum() / max(int(batch.mask.sum()), 1)),
            "mean_speed": float(stats["speed"]) / max(steps, 1),
            **self.source_counts(),
        }
        per_term = stats["terms"] / max(steps, 1)
        for name, v in zip(self.sim.reward_term_names, per_term.tolist()):
            row[f"reward/{name}"] = v
        row["reward"] = float(batch.reward.sum() / max(int(batch.mask.sum()), 1))
        row["ranks"] = self.world
        if self.graphs is not None:  # whether the speed knobs took: captures so far, and a fall-back to the live rows
            row["graphs/update_captures"] = self.graphs.captures
            row["graphs/optimizer_captures"] = self.graphs.opt_captures
            row["graphs/update_fell_back"] = int(self.graphs.fallen_back)
            row["graphs/rollout_captures"] = self.collector.graphs.captures
        if self.cfg.compile_update:  # compilations so far: more than one or two per shape means recompiling
            row["compile/graphs"] = torch._dynamo.utils.counters["stats"]["unique_graphs"] - self.graphs0
        if self.sim.is_cuda:
            row["gpu_mem_peak_gb"] = torch.cuda.max_memory_allocated(self.device) / 2**30
        return row

    def source_counts(self) -> dict:
        """The scenes visited so far, and the files that do not load and scenes that cannot be played; with
        `pipeline`, on a learner, its actor's, as its last batch reported them (`reported`)."""
        if self.reported is not None:
            return dict(self.reported)
        return {"scenes_visited": self.sampler.visited, **source_report(self.source)}

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
                      f"(update {self.update}, {self.agent_steps:,} agent steps)", file=sys.stderr)

    def _heldout_check(self, bar=None) -> bool:
        """The held-out check (targets.HeldoutCheck), logged to heldout.csv and shown under the bar."""
        ok = self.heldout(self.actor)
        if self.lead:
            self.runlog.heldout({"update": self.update, "wall_s": self.wall, **self.heldout.rates, "met": int(ok)})
            if bar is not None:
                bar.write(self.heldout.describe(self.update, ok), file=sys.stderr)
        return ok

    def _sync(self) -> None:
        if self.sim.is_cuda:
            torch.cuda.synchronize(self.device)

    # -------------------------------------------------------- checkpoints
    def rank_state(self) -> dict:
        """What this rank alone holds and an exact resume restores: RNG states, the scene sampler and
        the scenes of its worlds, the engine mid-episode, the prior's and the actor's motion windows."""
        rng = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
               "gen": self.gen.get_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {"rng": rng, "sampler": self.sampler.state_dict(), "scene_indices": self.sampler.last_indices.tolist(),
                "engine": self.sim.snapshot(), "prior": self.prior.state_dict(),
                "actor_history": {} if self.actor_hist is None else self.actor_hist.state_dict()}

    def state_dict(self) -> dict | None:
        """The checkpoint: everything an exact resume reads (`_load`), and the config and actor that
        evaluation and init_policy read. The lead's own rank state sits at the top level, the other
        ranks' in `other_ranks` (rank 1 first). Every rank calls it (a gather); the others get None."""
        ranks = dist_util.gather_to_lead(self.rank_state())
        if not self.lead:
            return None
        return {
            "kind": POLICY, "config": to_dict(self.cfg), "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(), "opt": self.opt.state_dict(),
            "lagrange": self.lagrange.state_dict(), "cost_budget": float(self.budget),
            "update": self.update, "agent_steps": self.agent_steps, "wall": self.wall, "elapsed": self.elapsed,
            "window": self.window.state_dict(), "world_size": self.world,
            **ranks[0], "other_ranks": ranks[1:],
        }

    def save(self) -> Path | None:
        """checkpoint.pt (the previous one kept beside it) and config.json of the run directory, written
        by the lead; every rank calls it."""
        state = self.state_dict()
        if not self.lead:
            return None
        path = save_atomic(state, self.out / "checkpoint.pt", keep_previous=True)
        (self.out / "config.json").write_text(json.dumps(to_dict(self.cfg), indent=1))
        return path

    def save_policy(self) -> Path:
        """The policy alone (config and actor weights, about a megabyte) as policies/update_NNNNNN.pt:
        what load_policy and the report read, so the CCE-gap can be followed over training."""
        snap = {"kind": POLICY, "config": to_dict(self.cfg), "actor": self.actor.state_dict(), "update": self.update,
                "agent_steps": self.agent_steps, "wall": self.wall}
        (self.out / POLICY_DIR).mkdir(exist_ok=True)
        return save_atomic(snap, self.out / POLICY_DIR / f"update_{self.update:06d}.pt")

    def _load(self, ck: dict, mine: dict | None) -> None:
        """Continue from the checkpoint `ck` (whose weights are in already): exactly from this rank's
        state `mine` (RNG states, engine state mid-episode, the prior's and the actor's motion windows),
        or, without one (another process count), its optimiser, lambda and counters; the logs lose the
        rows written after it."""
        self.opt.load_state_dict(ck["opt"])
        self.lagrange.load_state_dict(ck["lagrange"])
        self.update, self.agent_steps, self.wall = ck["update"], ck["agent_steps"], ck["wall"]
        self.elapsed = ck.get("elapsed", self.wall)  # checkpoints before elapsed_s existed
        self.window.load_state_dict(ck.get("window", {}))
        if mine is None:
            # another process count: weights, optimiser, lambda and counters carry over; episodes
            # start afresh on each rank's own scene shard
            self.gen.manual_seed(self.cfg.seed + self.stream + 7919 * self.update)
            self.runlog.trim(self.update)
            return
        rng = mine["rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self.gen.set_state(rng["gen"])
        if "cuda" in rng and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
        self.sim.restore(mine["engine"])
        self.prior.load_state_dict(self.sim, mine.get("prior", {}))
        if self.actor_hist is not None:
            self.actor_hist.load_state_dict(self.sim, mine.get("actor_history", {}))
        if "acting" in mine:  # the acting process of a pipeline: the weights it acted with, an update behind
            self.actor.load_state_dict(mine["acting"]["actor"])
            self.critic.load_state_dict(mine["acting"]["critic"])
        self.runlog.trim(self.update)


def saved_rank_state(ck: dict | None, rank: int, world: int, pipelined: bool = False) -> dict | None:
    """Rank `rank`'s own state in the checkpoint `ck` (Trainer.rank_state), when an exact resume can
    continue it: the checkpoint was written by `world` processes, as a pipeline or not as this run, and holds
    every rank's state. None otherwise (no checkpoint, another process count or layout, or a multi-process
    checkpoint without them)."""
    if ck is None or ck.get("world_size", 1) != world:
        return None
    if bool(ck.get("config", {}).get("pipeline", False)) != pipelined:
        return None
    others = ck.get("other_ranks", [])
    if len(others) != world - 1:
        return None
    return ck if rank == 0 else others[rank - 1]


def train_main(cfg: TrainConfig, out_dir=None, resume=None, progress=True) -> dict:
    """`tg-gpudrive train`: a run to its end; the last update's metrics (without NaNs) and where it is."""
    trainer = Trainer(cfg, out_dir, resume, progress)
    last = trainer.train()
    return {k: v for k, v in last.items() if not (isinstance(v, float) and math.isnan(v))} | {
        "out_dir": str(trainer.out), "checkpoint": str(trainer.out / "checkpoint.pt"),
        "agents_left_to_replay": trainer.left_to_replay,
        # episode-weighted over the last RATE_WINDOW updates (the window the quality target reads); None
        # before any episode ended
        "window_rates": trainer.window.rates()}

