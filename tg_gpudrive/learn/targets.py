"""Training's quality targets (`target_*` of TrainConfig): the window of the last RATE_WINDOW updates'
episodes that the progress bar, the final line and the stop read, and the held-out check that must agree
before a run stops at quality."""

from __future__ import annotations

import torch

from tg_gpudrive.agents import trained_sim
from tg_gpudrive.agents.policy import actor_policy
from tg_gpudrive.config import TrainConfig
from tg_gpudrive.data.sources import resolve_scenes
from tg_gpudrive.learn import distributed as dist_util
from tg_gpudrive.learn.quality import RATE_WINDOW, meets_quality
from tg_gpudrive.rollout import run_rollout


class RateWindow:
    """Episode outcomes (goal, collided, off-road, episodes) of the last RATE_WINDOW updates, all ranks."""

    def __init__(self):
        self.recent: list[tuple[float, ...]] = []

    def add(self, stats: dict) -> None:
        now = tuple(float(stats[k]) for k in ("goal", "collided", "offroad", "episodes"))
        self.recent = (self.recent + [now])[-RATE_WINDOW:]

    def state_dict(self) -> dict:
        return {"recent": [list(x) for x in self.recent]}

    def load_state_dict(self, state: dict) -> None:
        self.recent = [tuple(x) for x in state.get("recent", [])]

    def rates(self) -> dict | None:
        """Goal, collision and off-road rates over the window's episodes (None before one ended)."""
        if not self.recent:
            return None
        goals, coll, off, eps = (sum(x) for x in zip(*self.recent))
        if eps <= 0:
            return None
        return {"goal_rate": goals / eps, "collision_rate": coll / eps, "offroad_rate": off / eps}

    def reached(self, cfg: TrainConfig) -> bool:
        """Whether the full window meets goal rate >= target_goal_rate, collision rate <= target_max_collision
        and off-road rate <= target_max_offroad (never with target_goal_rate 0: off)."""
        rates = self.rates()
        if cfg.target_goal_rate <= 0 or len(self.recent) < RATE_WINDOW or rates is None:
            return False
        return meets_quality(rates, cfg.target_goal_rate, cfg.target_max_collision, cfg.target_max_offroad)


class HeldoutCheck:
    """`target_heldout`: whether the current policy meets the bar on held-out scenes too. The lead rank plays
    one episode in every held-out world (built once, on first use) and tells the others (those in scope:
    distributed.among)."""

    def __init__(self, cfg: TrainConfig, device: str, lead: bool):
        self.cfg, self.device, self.lead = cfg, device, lead
        self.sim = None
        self.rates: dict | None = None  # the latest check's rates

    def __call__(self, actor) -> bool:
        cfg = self.cfg
        met = torch.zeros((), device=self.device)
        if self.lead:
            if self.sim is None:
                src = resolve_scenes(cfg.target_heldout, n=cfg.target_heldout_worlds, seed=cfg.target_heldout_seed)
                scenes = [src.get(i) for i in range(min(cfg.target_heldout_worlds, len(src)))]
                self.sim = trained_sim(cfg, scenes, self.device)[0]
            rates = run_rollout(self.sim, actor_policy(actor, self.sim, cfg.actor_history), self.sim.episode_length,
                                episodes_per_world=1)
            ok = meets_quality(rates, cfg.target_goal_rate, cfg.target_max_collision, cfg.target_max_offroad)
            self.rates = {k: rates[k] for k in ("goal_rate", "collision_rate", "offroad_rate", "episodes")}
            met.fill_(float(ok))
        dist_util.all_reduce_sum_({"met": met})  # the lead rank's answer to every rank
        return bool(met > 0)

    def describe(self, update: int, ok: bool) -> str:
        r, cfg = self.rates, self.cfg
        return (f"held-out check after update {update} ({cfg.target_heldout}, seed {cfg.target_heldout_seed}): goal "
                f"{r['goal_rate']:.3f}, collision {r['collision_rate']:.3f}, off-road {r['offroad_rate']:.3f}"
                f"{'' if ok else ': not yet'}")
