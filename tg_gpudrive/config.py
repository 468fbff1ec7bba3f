"""Configuration: frozen dataclasses whose values live in YAML under configs/.

`load_config(cls, path, overrides)` fills a dataclass (nested dataclasses
included) from a YAML file and `key.sub=value` overrides; an unknown key, or
a value of the wrong kind, is an error naming the key and the file. Dataclass
defaults equal configs/env/default.yaml (a test keeps them in step).

Modes are `tg_gpudrive.enums` IntEnums in Python and their lowercase names in YAML,
JSON and checkpoints: the dataclasses turn names into members in `__post_init__`
(so `dataclasses.replace(cfg, collision_mode="stop")` works too) and `to_dict`
turns members back into names. This module must not import the engine or Warp.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any

import yaml

from tg_gpudrive.enums import (
    ENGINE_CONTROL,
    SELECT_CONTROL,
    ActionSpace,
    CollisionMode,
    ControlMode,
    Dynamics,
    GoalBehaviour,
    NamedMode,
)

COST_SHAPES = ("step", "hinge", "approach")  # EngineConfig.cost_shape, in the order of the reward kernel's codes
COST_PARTNERS = ("all", "players")  # EngineConfig.cost_partners, in the order of the collision kernel's codes
BACKGROUNDS = ("log", "world_model", "idm")  # who drives the vehicles the policy does not (agents.builtin)
REPO_CONFIGS = Path(__file__).resolve().parent.parent / "configs"


class ConfigError(ValueError):
    pass


def _interval(text: str) -> tuple[float, float, bool, bool]:
    """'(0, 1]' -> (0.0, 1.0, False, True): bounds and whether each is included; 'inf' allowed."""
    lo, hi = (float(x) for x in text[1:-1].split(","))
    return lo, hi, text[0] == "[", text[-1] == "]"


def check_ranges(cfg, rules: dict[str, str], odd: tuple[str, ...] = ()) -> None:
    """Every field of `rules` (name -> interval as '[0, inf)', '(0, 1]') lies in its interval (each
    element of a tuple field does); the fields of `odd` are odd. A ConfigError names the first that
    does not (from_dict adds the key's prefix and the file)."""
    for name, text in rules.items():
        lo, hi, lo_in, hi_in = _interval(text)
        value = getattr(cfg, name)
        for v in value if isinstance(value, tuple) else (value,):
            if not ((v >= lo if lo_in else v > lo) and (v <= hi if hi_in else v < hi)):
                raise ConfigError(f"{name}: expected a value in {text}, got {v}")
    for name in odd:
        if getattr(cfg, name) % 2 != 1:
            raise ConfigError(f"{name}: expected an odd number (the middle bin is zero), got {getattr(cfg, name)}")


def _set_mode(cfg, name: str, mode: type[NamedMode], allowed: tuple[NamedMode, ...] | None = None) -> None:
    """Field `name` of the frozen dataclass `cfg` as a member of `mode` (from a member or its name)."""
    try:
        object.__setattr__(cfg, name, mode.parse(getattr(cfg, name), name, allowed))
    except ValueError as e:
        raise ConfigError(str(e)) from None


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Weights of the named reward terms (kernels/reward.py) and their parameters."""

    goal_progress: float = 0.1  # per metre closer to the goal
    goal_reached: float = 1.0
    collision: float = -1.0
    offroad: float = -1.0
    lane_deviation: float = -0.02  # per metre from the nearest lane centerline
    overspeed: float = -0.1  # per m/s above speed_limit
    ttc: float = 0.0  # per step, times 1 - TTC / ttc_horizon to the nearest conflict ahead (0: not computed)
    speed_limit: float = 20.0  # m/s
    lane_cap: float = 5.0  # m, lane deviation is capped here
    ttc_horizon: float = 3.0  # s, conflicts further ahead in time cost nothing

    def __post_init__(self):
        check_ranges(self, {"goal_progress": "(-inf, inf)", "goal_reached": "(-inf, inf)", "collision": "(-inf, inf)",
                            "offroad": "(-inf, inf)", "lane_deviation": "(-inf, inf)", "overspeed": "(-inf, inf)",
                            "ttc": "(-inf, inf)", "speed_limit": "(0, 1000]", "lane_cap": "[0, 1000]",
                            "ttc_horizon": "(0, 60]"})


@dataclasses.dataclass(frozen=True)
class EngineConfig:
    """Everything the engine needs besides the scenes. Units: metres, seconds, radians."""

    max_agents: int = 64  # agent slots per world (A)
    dynamics: Dynamics = Dynamics.BICYCLE  # bicycle | delta_local
    action_space: ActionSpace = ActionSpace.DISCRETE  # discrete | continuous (discrete only for bicycle)
    accel_bins: int = 7
    curvature_bins: int = 13
    max_accel: float = 6.0  # m/s^2
    max_curvature: float = 0.3  # 1/m
    delta_max: tuple[float, float, float] = (6.0, 1.0, 0.5)  # m, m, rad per step (delta_local)
    init_steps: int = 10  # steps of log warm-up before control starts
    goal_radius: float = 2.0
    collision_mode: CollisionMode = CollisionMode.IGNORE  # ignore | stop | remove
    goal_behaviour: GoalBehaviour = GoalBehaviour.REMOVE  # continue | stop | remove
    control: ControlMode = ControlMode.VEHICLES  # vehicles | all_agents | none: whom the policy drives by default
    replay_infeasible: bool = True  # marked and log-infeasible agents replay their logs, counted apart
    beta: float = 4.0  # m, distance under which the cost is 1
    # step: the cost is 1 whenever the nearest other agent is nearer than beta (TrafficGamer's); hinge:
    # (beta - d) / beta, so a deeper intrusion costs more and a contact nearly 1, a pass at beta nothing;
    # approach: how much deeper inside beta than at the agent's last step (the hinge's increase, never below 0),
    # so a pass costs the depth of its closest approach once, however long it lasts
    cost_shape: str = "step"
    # whom the cost's distance counts: all, every other present agent; players, only the agents the policy
    # drives (TrafficGamer's cost, over the agents of its game: replayed and parked ones are not counted)
    cost_partners: str = "all"
    # s: the cost's distance is the least one over the next cost_horizon seconds at constant velocity
    # (0: the distance now, TrafficGamer's), so a car closing fast pays before beta is crossed
    cost_horizon: float = 0.0
    # the cost of a step in contact with another agent: the step costs max(distance cost, cost_collision), so a
    # collision is the top of the cost's distribution whatever beta (a rear-end contact at 4.5 m costs nothing
    # under beta 2 otherwise) and the risk level alpha's tail reads it (0: the distance cost alone, TrafficGamer's)
    cost_collision: float = 0.0
    partner_k: int = 16
    partner_radius: float = 50.0
    road_k: int = 128
    road_radius: float = 50.0
    view_angle: float = 360.0  # degrees: the cone around its heading in which an agent sees partners and road
    road_query_radius: float = 5.0  # m, search (and cap) for edge and lane distances
    # m: road polylines are simplified (Ramer-Douglas-Peucker) to this tolerance when worlds are built,
    # so straight runs of densely sampled maps (WOMD: a point every 0.5 m) become long segments and the
    # road_k nearest reach metres ahead; collision and off-road move by at most this much. 0: every
    # point, what the shipped world model was fitted on (as magnet or traffic it needs 0);
    # configs/train/real_mix.yaml and the policy trained with it use 0.1
    road_simplify: float = 0.0
    max_segment_length: float = 5.0  # m, longer road segments are split
    road_cell_size: float = 5.0  # m, static road grid (5 m: fastest measured, BENCHMARKS.md)
    collision_cells: int = 128  # hashed buckets per world for the agent broad phase
    use_graph: bool = True  # capture the step as a CUDA graph on GPU
    auto_reset: bool = True  # reset a world inside step() when its episode ends (else wait for reset())
    reward: RewardConfig = RewardConfig()

    def __post_init__(self):
        _set_mode(self, "dynamics", Dynamics)
        _set_mode(self, "action_space", ActionSpace)
        _set_mode(self, "collision_mode", CollisionMode)
        _set_mode(self, "goal_behaviour", GoalBehaviour)
        _set_mode(self, "control", ControlMode, ENGINE_CONTROL)
        if self.cost_shape not in COST_SHAPES:
            raise ConfigError(f"cost_shape: expected one of {', '.join(COST_SHAPES)}, got {self.cost_shape!r}")
        if self.cost_partners not in COST_PARTNERS:
            raise ConfigError(f"cost_partners: expected all or players, got {self.cost_partners!r}")
        if self.dynamics == Dynamics.DELTA_LOCAL and self.action_space == ActionSpace.DISCRETE:
            raise ConfigError("action_space: discrete is defined for the bicycle only; use continuous")
        # sizes and search radii are bounded above too: beyond these the engine would allocate or
        # search without end rather than fail
        check_ranges(self, {
            "max_agents": "[1, 1024]", "view_angle": "(0, 360]", "accel_bins": "[3, 1001]", "curvature_bins": "[3, 1001]", "max_accel": "(0, 100]",
            "max_curvature": "(0, 10]", "delta_max": "(0, 100]", "init_steps": "[0, 10000]", "goal_radius": "(0, 1000]",
            "beta": "[0, 1000]", "cost_horizon": "[0, 60]", "cost_collision": "[0, 1]", "partner_k": "[1, 1024]", "partner_radius": "(0, 1000]", "road_k": "[1, 4096]",
            "road_radius": "(0, 1000]", "road_query_radius": "(0, 100]", "road_simplify": "[0, 10]", "max_segment_length": "[0.5, 1000]",
            "road_cell_size": "[1, 1000]", "collision_cells": "[1, 1048576]"}, odd=("accel_bins", "curvature_bins"))

    @property
    def num_actions(self) -> int:
        """Size of the discrete action grid (accel x curvature)."""
        return self.accel_bins * self.curvature_bins

    @property
    def discrete(self) -> bool:
        return self.action_space == ActionSpace.DISCRETE

    @property
    def act_dim(self) -> int:
        """Values of one continuous action: (accel, curvature) for the bicycle, (dx, dy, dyaw) for delta-local."""
        return 2 if self.dynamics == Dynamics.BICYCLE else 3

    @property
    def act_high(self) -> tuple[float, ...]:
        """The continuous action box, symmetric about 0: act_dim bounds, (max_accel, max_curvature) for the
        bicycle, delta_max for delta-local."""
        if self.dynamics == Dynamics.BICYCLE:
            return (self.max_accel, self.max_curvature)
        return tuple(self.delta_max)

    @property
    def noop_index(self) -> int:
        """Grid index of zero acceleration and zero curvature (the middle bin of each axis)."""
        return (self.accel_bins // 2) * self.curvature_bins + self.curvature_bins // 2


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Training-scene augmentation (tg_gpudrive.data.augment): every knob off by default."""

    mirror: float = 0.0  # probability of mirroring a scene across its x axis
    rotate: bool = False  # turn each scene by a uniform random angle
    start_shift: int = 0  # start each log up to this many steps later
    perturb_pos: float = 0.0  # m, std of an offset of each candidate vehicle's warm-up positions
    perturb_yaw: float = 0.0  # rad, std of a turn of each candidate vehicle's warm-up headings
    control_fraction: float = 1.0  # each policy agent stays the policy's with this probability
    delay_share: float = 0.0  # each candidate vehicle's whole log runs later with this probability ...
    max_delay: int = 20  # ... by up to this many steps

    def __post_init__(self):
        check_ranges(self, {"mirror": "[0, 1]", "control_fraction": "(0, 1]", "start_shift": "[0, 10000]",
                            "perturb_pos": "[0, 100]", "perturb_yaw": "[0, 6.3]", "delay_share": "[0, 1]",
                            "max_delay": "[0, 10000]"})


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """CCE-MAPPO training run (tg-gpudrive train). YAML files live in configs/train/."""

    env: EngineConfig = EngineConfig()
    scenes: str = "procedural:all"  # scene spec (tg_gpudrive.data.sources)
    augment: AugmentConfig = AugmentConfig()  # augmentation of the drawn scenes (tg_gpudrive.data.augment)
    num_scenes: int = 1000  # distinct scenes drawn from the source
    num_worlds: int = 64  # worlds per process (per GPU): N processes step N x num_worlds
    resample_every: int = 0  # updates between scene resamples (0: never)
    control: ControlMode = ControlMode.VEHICLES  # vehicles | nearest_conflict | ids (engine.control)
    control_k: int = 5  # nearest_conflict: how many
    control_ids: list[int] = dataclasses.field(default_factory=list)
    # who drives the eligible vehicles the policy does not (those augment.control_fraction leaves out):
    # log (replay, reacting to nobody) | idm (their logged paths and timing, braking for whoever is on
    # them: agents/idm.py) | world_model (the run's prior_model, or the shipped one)
    background: str = "log"
    device: str = "auto"  # auto (cuda when Warp and torch see one, else cpu) | cpu | cuda | cuda:N
    seed: int = 0
    # PPO
    updates: int = 100
    rollout_steps: int = 32
    epochs: int = 4
    minibatches: int = 4
    lr: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden: int = 128
    heads: int = 1  # >1: per-slot actor heads
    actor_history: int = 0  # steps of its own motion the actor sees besides its observation (pi(a | o, h)); 0: none
    # and of its nearest partners' motion over the same steps (the paper's h holds every agent's history): how
    # many of the observation's partner rows, nearest first (<= env.partner_k; needs actor_history > 0)
    actor_history_partners: int = 0
    # how evaluate, render, report and generate act with the trained policy: its action distribution sharpened by
    # this temperature (logits / T; the continuous head's standard deviation x T); 0 takes the mode. Training
    # rollouts always sample at 1; a checkpoint's value is set after training, on its training scenes
    act_temperature: float = 1.0
    # and behind this safety guard (agents/guard.py), if > 0: an action that would bring the agent's box within
    # act_guard_margin (m) of an observed partner's within act_guard_s seconds, even braking hard after it, is
    # replaced by a draw among the safe ones; 0: none. Training rollouts never use it
    act_guard_s: float = 0.0
    act_guard_margin: float = 0.0
    amp: bool = True  # bf16 autocast of the networks on GPU
    # the rollout's steps and the update's optimiser steps replayed from CUDA graphs (learn/graphs.py): both act
    # on every slot, dead ones fed zeros and weighted 0 (the same actions and losses), so that their kernels
    # launch once, not per step; on the CPU the same fixed-shape steps run without graphs
    cuda_graphs: bool = False
    # the update's loss through torch.compile: its forward and backward fused into fewer kernels (with
    # cuda_graphs, the fixed-shape loss its replays launch); the first update pays the compilation, cached on disk
    compile_update: bool = False
    # the passes over all of a rollout's rows after its steps (the critic's values and cost quantiles, the discrete
    # magnet's logits, the advantages and targets) through torch.compile, their elementwise work fused; compiled on
    # the first rollout (cached on disk), the row counts a dynamic size
    compile_rollout: bool = False
    # processes in pairs (--nproc 2, 4, ...): in each pair one acts (the rollouts, num_worlds worlds) and one learns
    # (the updates, the learners averaging their gradients), at once, the rollouts one update behind the weights
    # (learn/pipeline.py): an update then costs the longer of the two, not their sum. Off: every process does both,
    # on its own share of the scenes
    pipeline: bool = False
    normalize_advantages: bool = True  # per minibatch (and per rank when distributed)
    # TrafficGamer: magnet (eta1 KL to the prior), proximal (1/eta2 KL to the last policy), CVaR constraint
    eta1: float = 0.05
    # discrete magnet: the share of the live rows, picked at each rollout step (a random subset, the same
    # size every step), whose prior logits are computed; their KL to the prior weighs 1 / magnet_fraction, so
    # the loss's expectation is unchanged at that share of the world model's cost. 1: every row
    magnet_fraction: float = 1.0
    eta2: float = 20.0
    alpha: float = 0.5  # CVaR level of the cost critic (lower: less risk-averse)
    cost_limit: float = 1.0  # budget on CVaR_alpha of the discounted cost-to-go (see cost_limit_mode)
    # logs: cost_limit x the logged drivers' own CVaR (their mean with lambda_on: mean); absolute: cost_limit
    # itself; start: cost_limit x the starting policy's mean cost-to-go, one budget per beta for every alpha, so
    # with lambda_on: cvar a higher alpha holds a heavier tail to the same bar
    cost_limit_mode: str = "logs"
    # > 0: the logs' or the starting policy's cost (cost_limit_mode logs / start) is measured under this beta,
    # not the run's: one bar for every beta, so a beta below it is held to a bar its lighter cost already meets
    # (the constraint loosens: lambda comes down) and one above it to a bar its heavier cost exceeds (it
    # tightens); 0: under the run's own beta, which asks the same relative cut at every beta. On a cost critic
    # that reads the cost too high (a fine-tune's, still fitting) lambda can stay up below it: lambda_on sampled
    cost_limit_beta: float = 0.0
    # what lambda is stepped on: cvar, the CVaR_alpha of the discounted cost-to-go; mean, its expectation
    # E[c] (TrafficGamer's Algorithm 1), whose "logs" budget is the logs' mean, one per beta for every alpha
    # (alpha then shapes the actor's cost advantage alone); sampled, the rollout's own mean per-step cost
    # x 1 / (1 - gamma) (the discounted cost-to-go that rate adds up to), no critic in it: a critic still fitting
    # a fine-tune's new cost reads it several times too high and would lift lambda on a bar the policy meets;
    # its budget is the same figure of the logs' or the starting policy's driving (alpha again the actor's alone);
    # sampled_cvar, per slot the CVaR_alpha over the rollout's vehicles of their sampled cost rate x 1 / (1 - gamma),
    # against the same alpha-free bar (the logs' or the starting policy's mean rate): a higher alpha holds the
    # riskiest vehicles to it, the tighter constraint, with no critic in either
    lambda_on: str = "cvar"
    lambda_init: float = 0.0
    lambda_lr: float = 0.01  # lambda += lambda_lr * (CVaR - budget) per update (projected at 0)
    # > 0: lambda is projected onto [0, lambda_max], which bounds how far the cost may outweigh the reward in the
    # actor's advantage under a bar it does not meet; 0: no upper bound
    lambda_max: float = 0.0
    # the first lambda_warmup updates keep the multipliers where they start while the cost critic fits the run's
    # cost: a fine-tune from a policy whose critic learnt another cost (another shape, horizon or beta) would
    # otherwise step them on that critic's values, which can lift them many times over in the first updates and
    # leave them there (they come down by at most lambda_lr x budget an update)
    lambda_warmup: int = 0
    per_agent_lambda: bool = True  # one multiplier per controlled slot (TrafficGamer's lambda_i)
    # ... and per scene of the source too: one multiplier per vehicle (scene x slot), stepped on that
    # vehicle's own states whenever its scene is in the worlds, as Algorithm 1 has one lambda_i per agent
    # of a game; off: a slot's multiplier pools every scene it has held
    lambda_per_vehicle: bool = False
    constraint: bool = True  # false: no CVaR constraint (lambda = 0), i.e. plain MAPPO with eta1 = 0
    quantiles: int = 64
    cost_nstep: int = 8  # steps of the cost critic's distributional Bellman target (1: the one-step target)
    # the cost critic's quantile Huber threshold, in cost-to-go units: below it the loss is quadratic, and a
    # quadratic asymmetric loss fits expectiles, not quantiles. Per-step costs are at most 1 and most states'
    # cost-to-go lies well under 1, so at 1 the critic's atoms crowd towards the mean and CVaR_alpha hardly
    # depends on alpha; 0 is the plain quantile (pinball) loss, exact at any cost scale
    cost_kappa: float = 1.0
    # the actor's cost advantage: gae, GAE over the critic's CVaR_alpha values (alpha reaches it through the
    # bootstraps alone); tail, each sampled cost-to-go's excess over its state's VaR_alpha, times 1 / (1 - alpha)
    # (the CVaR policy gradient, losses.cvar_tail_advantage), which reads true quantiles: pair it with cost_kappa 0
    cost_advantage: str = "gae"
    prior: str = "world_model"  # world_model | expert: the magnet
    prior_top_component: bool = True  # world_model, continuous: the magnet is the most probable mixture component
    prior_model: str = ""  # world_model: a checkpoint (model.pt or run dir) or a packaged name (small_cpu); "" = the shipped model of the action space (shipped, shipped_continuous)
    # the continuous magnet's spread: the expert prior's sigma, and the least std of the world-model
    # prior's Laplace components (a sharper one would make its KL dominate the advantage)
    prior_sigma_accel: float = 0.7  # m/s^2 (one grid bin is 2)
    prior_sigma_curvature: float = 0.01  # 1/m (one grid bin is 0.05)
    prior_floor: float = 0.05  # expert prior (discrete): uniform share mixed in, bounds log p and keeps entropy
    prior_closed_loop: bool = True  # expert prior: the tracking action from the current state (else the logged one)
    # start the actor and critic from a trained run's weights (a checkpoint file, run directory or
    # packaged name: "shipped", "shipped_v4" to "shipped_v1"): fine-tuning, as TrafficGamer starts from a pretrained driver; the optimiser, the
    # multipliers and the update count start fresh. "" = random init; a --resume ignores it
    init_policy: str = ""
    # bookkeeping
    time_limit_s: float = 0.0  # stop (and save) once this much training wall-clock has passed (0: off)
    target_goal_rate: float = 0.0  # stop once the goal rate over the last 10 updates' episodes reaches it (0: off)
    # ... and, over the same episodes, the collision and off-road rates are at most these (a goal
    # reached through a crash or off the road is not quality); 1.0: goal rate alone
    target_max_collision: float = 1.0
    target_max_offroad: float = 1.0
    # ... and, each time the training window meets that bar, held-out scenes must too: `target_heldout`
    # is a scene spec (procedural:all, a store, a directory) drawn with `target_heldout_seed` (a seed
    # used neither in training nor in the evaluations reported, which use 50000 and 90000), one
    # episode in each of `target_heldout_worlds` worlds under the current
    # policy (sampled, as in training); every check goes to heldout.csv. "": the training window decides.
    # (The window's episodes are those that ended during the updates, so worlds that finish early
    # count more often there than in a held-out evaluation.)
    target_heldout: str = ""
    target_heldout_seed: int = 70000
    target_heldout_worlds: int = 256
    checkpoint_every: int = 10
    keep_policy_every: int = 0  # also keep the policy every N updates (policies/update_NNNNNN.pt): the report's CCE-gap curve; 0: off
    out_dir: str = "runs/train"

    def __post_init__(self):
        _set_mode(self, "control", ControlMode, SELECT_CONTROL)
        require_nonempty(self, ("scenes", "device", "out_dir"))
        if not 0.0 <= self.alpha < 1.0:
            raise ConfigError(f"alpha: CVaR level must lie in [0, 1), got {self.alpha}")
        if self.cost_limit_mode not in ("logs", "absolute", "start"):
            raise ConfigError(f"cost_limit_mode: expected logs, absolute or start, got {self.cost_limit_mode!r}")
        if self.cost_limit_beta and self.cost_limit_mode == "absolute":
            raise ConfigError("cost_limit_beta: an absolute bar (cost_limit_mode: absolute) is measured under no "
                              "beta; set cost_limit_mode to logs or start, or cost_limit_beta to 0")
        if self.lambda_per_vehicle and not self.per_agent_lambda:
            raise ConfigError("lambda_per_vehicle: needs per_agent_lambda (a multiplier per slot of each scene)")
        if self.actor_history_partners and not self.actor_history:
            raise ConfigError("actor_history_partners: needs actor_history > 0 (the steps of the partners' window)")
        if self.actor_history_partners > self.env.partner_k:
            raise ConfigError(f"actor_history_partners: at most env.partner_k ({self.env.partner_k}) partners have "
                              f"a window, got {self.actor_history_partners}")
        if self.lambda_on not in ("cvar", "mean", "sampled", "sampled_cvar"):
            raise ConfigError(f"lambda_on: expected cvar, mean, sampled or sampled_cvar, got {self.lambda_on!r}")
        if self.lambda_on.startswith("sampled") and self.gamma >= 1.0:
            raise ConfigError(f"lambda_on: {self.lambda_on} scales the cost rate by 1 / (1 - gamma), which needs "
                              "gamma < 1")
        if self.lambda_on == "sampled_cvar" and self.lambda_per_vehicle:
            raise ConfigError("lambda_on: sampled_cvar takes its tail over the vehicles of a slot, one a world; "
                              "lambda_per_vehicle has one vehicle a multiplier (use sampled)")
        if self.lambda_max > 0 and self.lambda_init > self.lambda_max:
            raise ConfigError(f"lambda_init: must not exceed lambda_max ({self.lambda_max}), got {self.lambda_init}")
        if self.cost_advantage not in ("gae", "tail"):
            raise ConfigError(f"cost_advantage: expected gae or tail, got {self.cost_advantage!r}")
        if self.background not in BACKGROUNDS:
            raise ConfigError(f"background: expected one of {', '.join(BACKGROUNDS)}, got {self.background!r}")
        if self.prior not in ("expert", "world_model"):
            raise ConfigError(f"prior: expected expert or world_model, got {self.prior!r}")
        check_ranges(self, {
            "num_scenes": "[1, inf)", "num_worlds": "[1, inf)", "updates": "[1, inf)", "rollout_steps": "[1, inf)",
            "cost_nstep": "[1, inf)", "cost_kappa": "[0, inf)", "resample_every": "[0, inf)", "control_k": "[1, inf)",
            "epochs": "[1, inf)", "lambda_max": "[0, inf)", "lambda_warmup": "[0, inf)",
            "cost_limit_beta": "[0, inf)",
            "minibatches": "[1, inf)", "lr": "(0, inf)", "gamma": "(0, 1]", "gae_lambda": "[0, 1]", "clip": "(0, inf)",
            "entropy_coef": "[0, inf)", "value_coef": "[0, inf)", "max_grad_norm": "(0, inf)", "hidden": "[1, 65536]",
            "heads": "[1, 1024]", "actor_history": "[0, 1024]", "actor_history_partners": "[0, 1024]", "act_temperature": "[0, inf)",
            "act_guard_s": "[0, 60]", "act_guard_margin": "[0, 10]",
            "eta1": "[0, inf)", "eta2": "(0, inf]",
            "magnet_fraction": "(0, 1]",
            "quantiles": "[2, 4096]", "prior_sigma_accel": "(0, inf)", "prior_sigma_curvature": "(0, inf)",
            "prior_floor": "[0, 1]", "time_limit_s": "[0, inf)", "target_goal_rate": "[0, 1]",
            "target_max_collision": "[0, 1]", "target_max_offroad": "[0, 1]", "checkpoint_every": "[1, inf)",
            "cost_limit": "[0, inf)", "lambda_init": "[0, inf)", "lambda_lr": "[0, inf)",
            "keep_policy_every": "[0, inf)"})
        if self.magnet_fraction < 1 and not self.env.discrete:
            raise ConfigError(f"magnet_fraction: {self.magnet_fraction} subsamples the discrete magnet's logits; the "
                              "continuous magnet is rebuilt in the update from its stored context (use 1)")
        if self.minibatches > self.num_worlds * self.rollout_steps:
            raise ConfigError(f"minibatches: {self.minibatches} minibatches of a batch of {self.num_worlds} worlds x "
                              f"{self.rollout_steps} steps would leave some with less than one step of each world; "
                              f"expected at most {self.num_worlds * self.rollout_steps}")
        if self.target_heldout and (self.target_heldout_worlds < 1 or self.target_goal_rate <= 0):
            raise ConfigError("target_heldout: needs target_heldout_worlds >= 1 and a target_goal_rate > 0 "
                              "(the check runs when the training window meets that target)")


def require_nonempty(cfg, keys: tuple[str, ...]) -> None:
    """ConfigError naming the first of the string fields `keys` of `cfg` that is empty: an empty scene spec,
    device or output folder would read or write the working directory."""
    for key in keys:
        if not getattr(cfg, key).strip():
            raise ConfigError(f"{key}: must not be empty")


def _coerce(tp: Any, value: Any, key: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    if isinstance(tp, type) and issubclass(tp, NamedMode):
        if not isinstance(value, (str, tp)):  # names only: an integer in YAML is a typo, not a mode
            names = ", ".join(str(m) for m in tp)
            raise ConfigError(f"{source}: {key}: expected one of {names}, got {value!r}")
        return value  # the dataclass parses it (and checks the modes it allows)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {key}: expected a mapping, got {value!r}")
        return from_dict(tp, value, source, prefix=key + ".")
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key}: expected true/false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {key}: expected a number, got {value!r}")
        if math.isnan(value):  # infinities are left to the field's range (eta2 may be inf: no proximal term)
            raise ConfigError(f"{source}: {key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if value is None:  # `key:` left empty in YAML, or `--set key=`: the empty string (e.g. no init_policy)
            return ""
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"{source}: {key}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_coerce(a, v, f"{key}[{n}]", source) for n, (a, v) in enumerate(zip(args, value)))
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return None
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return _coerce(inner[0], value, key, source)
    if origin is list:
        (a,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(f"{source}: {key}: expected a list, got {value!r}")
        return [_coerce(a, v, f"{key}[{n}]", source) for n, v in enumerate(value)]
    if origin is dict or tp is dict:
        return dict(value)
    return value


def from_dict(cls, data: dict, source: str = "<dict>", prefix: str = ""):
    """Build dataclass `cls` from a mapping; unknown keys are errors naming key and source."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in (data or {}).items():
        if key not in names:
            raise ConfigError(f"{source}: unknown key '{prefix}{key}' (known: {', '.join(sorted(names))})")
        kwargs[key] = _coerce(hints[key], value, prefix + key, source)
    try:
        return cls(**kwargs)
    except ConfigError as e:  # the field's message, its full key ("env.beta: ...") and the file
        raise ConfigError(f"{source}: {prefix}{e}") from None


def coerce_field(cls, key: str, value: Any, source: str = "<dict>") -> Any:
    """`value` (as YAML gives it) checked and converted for field `key` of dataclass `cls`, as
    `from_dict` does for every field; a wrong type is a ConfigError naming key and source."""
    return _coerce(typing.get_type_hints(cls)[key], value, key, source)


def parse_override(text: str) -> tuple[list[str], Any]:
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    try:
        value = yaml.safe_load(raw)
    except yaml.YAMLError as e:
        raise ConfigError(f"--set {text}: the value is not valid YAML ({getattr(e, 'problem', None) or e})") from None
    return key.strip().split("."), value


def override_text(key: str, value: Any) -> str:
    """`key=value` as parse_override reads it back: YAML's own writing (1e-08 would be a string, 1.0e-08 is a
    float; '' and '0.5' stay strings), a plain string as it is."""
    if isinstance(value, str) and value:
        try:
            if yaml.safe_load(value) == value:
                return f"{key}={value}"
        except yaml.YAMLError:
            pass
    return f"{key}={yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}"


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    data = dict(data)
    for text in overrides or []:
        path, value = parse_override(text)
        node = data
        for p in path[:-1]:
            node[p] = dict(node.get(p) or {})
            node = node[p]
        node[path[-1]] = value
    return data


def load_yaml(path: str | Path) -> dict:
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except yaml.YAMLError as e:  # one line: where and what (PyYAML's own text spans several)
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        what = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"{path}: invalid YAML{where}: {what}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping")
    return data


# the fields of an experiment grid (configs/experiments/*.yaml)
EXPERIMENT_FIELDS = ("base", "beta", "alpha", "overrides", "baselines", "seeds", "batch", "report")


def _numbers(v: Any, ints: bool = False) -> bool:
    kinds = (int,) if ints else (int, float)
    return isinstance(v, list) and bool(v) and all(isinstance(x, kinds) and not isinstance(x, bool) for x in v)


def load_experiment(path: str | Path) -> dict:
    """An experiment grid: `base` (the train config its runs start from), the `beta` and `alpha` values of its
    cells, and optionally `overrides` (train keys of every run), `baselines` (name: overrides), `seeds`, `batch`
    and `report` (the report's options). A missing, unknown or ill-typed field is a ConfigError naming the file
    and the field."""
    data = load_yaml(path)
    unknown = sorted(set(data) - set(EXPERIMENT_FIELDS))
    if unknown:
        raise ConfigError(f"{path}: unknown field(s) {', '.join(unknown)} (an experiment grid has "
                          f"{', '.join(EXPERIMENT_FIELDS)})")
    if not isinstance(data.get("base"), str) or not data["base"]:
        raise ConfigError(f"{path}: field 'base': expected the train config its runs start from (e.g. "
                          f"real_mix.yaml), got {data.get('base')!r}")
    for knob in ("beta", "alpha"):
        if not _numbers(data.get(knob)):
            raise ConfigError(f"{path}: field '{knob}': expected a non-empty list of numbers, got {data.get(knob)!r}")
    for field in ("overrides", "baselines", "report"):
        if data.get(field) is not None and not isinstance(data[field], dict):
            raise ConfigError(f"{path}: field '{field}': expected a mapping, got {data[field]!r}")
    if data.get("seeds") is not None and not _numbers(data["seeds"], ints=True):
        raise ConfigError(f"{path}: field 'seeds': expected a non-empty list of integers, got {data['seeds']!r}")
    batch = data.get("batch")
    if batch is not None and (not isinstance(batch, int) or isinstance(batch, bool) or batch < 1):
        raise ConfigError(f"{path}: field 'batch': expected a positive integer, got {batch!r}")
    return data


def load_config(cls, path: str | Path | None = None, overrides: list[str] | None = None):
    data = load_yaml(path) if path else {}
    return from_dict(cls, apply_overrides(data, overrides or []), str(path or "<defaults>"))


def to_dict(cfg) -> dict:
    """`cfg` as plain data for YAML, JSON and checkpoints (modes as their names); `from_dict` reads it back."""
    return _plain(dataclasses.asdict(cfg))


def _plain(value: Any) -> Any:
    if isinstance(value, NamedMode):
        return str(value)
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value)
    return value
