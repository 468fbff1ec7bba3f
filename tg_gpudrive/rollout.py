"""The rollout loop that turns episodes into rates (`run_rollout`, `EpisodeStats`).

A policy is a callable `policy(sim) -> None` that writes the action buffers of the simulator in place
(agents.builtin: the built-in policies and background drivers). Rollouts run any number of steps; every
finished episode of every controlled agent is counted once, with the outcome flags the engine kept for it.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from tqdm import tqdm

from tg_gpudrive.agents.builtin import Policy
from tg_gpudrive.engine.simulator import Simulator


def timed_out(goal, collided, offroad):
    """Episodes that ended without a goal, a collision or leaving the road: the vehicle had not arrived
    (elementwise over the engine's outcome flags)."""
    return (goal == 0) & (collided == 0) & (offroad == 0)


class EpisodeStats:
    """Sums of episode outcomes per scenario type, accumulated on the device; where the scenes mark
    kerb stops (procedural `kerb_stops`: vehicles whose goal lies at the kerb, off the lane centre),
    also over those agents alone (`summary()["kerb_stops"]`)."""

    KEYS = ("episodes", "goal", "collided", "offroad", "cost", "min_dist", "return", "steps", "score", "timeout")
    SLOT_KEYS = ("episodes", "goal", "collided", "offroad", "score")  # also kept per (world, slot)

    def __init__(self, sim: Simulator, episodes_per_world: int | None = None):
        """`episodes_per_world`: count only each world's first N episodes. Without it a world whose
        episodes end early (fast drivers, early collisions) adds more of them within the same steps, and
        the rates lean towards short episodes; with it every world that finished N weighs the same."""
        self.sim = sim
        self.episodes_per_world = episodes_per_world
        self.world_episodes = torch.zeros(sim.num_worlds, dtype=torch.int64, device=sim.reward.device)
        types = [s.metadata.get("scenario_type", "unknown") for s in sim.model.scenes]
        self.type_names = sorted(set(types))
        self.world_type = torch.tensor([self.type_names.index(t) for t in types], device=sim.reward.device)
        n = len(self.type_names)
        self.sums = {k: torch.zeros(n, dtype=torch.float64, device=sim.reward.device) for k in self.KEYS}
        slot_agent = np.asarray(sim.model.slot_agent)
        kerb = np.zeros(slot_agent.shape, bool)
        for w, sc in enumerate(sim.model.scenes):
            if sc.metadata.get("kerb_stops"):
                kerb[w] = np.isin(slot_agent[w], sc.metadata["kerb_stops"]) & (slot_agent[w] >= 0)
        self.kerb = torch.as_tensor(kerb, device=sim.reward.device) if kerb.any() else None
        self.kerb_sums = {k: torch.zeros((), dtype=torch.float64, device=sim.reward.device) for k in self.KEYS}
        self.slot_sums = {k: torch.zeros(sim.policy_agents.shape, dtype=torch.float64, device=sim.reward.device)
                          for k in self.SLOT_KEYS}
        self.speed_sum = torch.zeros((), dtype=torch.float64, device=sim.reward.device)
        self.scene_episodes = torch.zeros((), dtype=torch.float64, device=sim.reward.device)
        self.alive_steps = torch.zeros((), dtype=torch.float64, device=sim.reward.device)

    def _add(self, rows: torch.Tensor, goal, collided, offroad, cost, min_dist, ret, steps) -> None:
        wt = self.world_type[:, None].expand_as(rows)[rows]
        kerb = None if self.kerb is None else self.kerb & rows
        score = (goal != 0) & (collided == 0) & (offroad == 0)  # a goal reached cleanly
        timeout = timed_out(goal, collided, offroad)
        for key, val in (("episodes", torch.ones_like(goal, dtype=torch.float64)), ("goal", goal),
                         ("collided", collided), ("offroad", offroad), ("cost", cost), ("min_dist", min_dist),
                         ("return", ret), ("steps", steps), ("score", score), ("timeout", timeout)):
            v = val.to(torch.float64)
            self.sums[key].index_add_(0, wt, v[rows])
            if kerb is not None:
                self.kerb_sums[key] += (v * kerb).sum()
            if key in self.slot_sums:
                self.slot_sums[key] += v * rows

    def after_step(self) -> None:
        s = self.sim
        alive = s.alive * s.policy_agents  # background vehicles are alive too, but not the policy's
        self.speed_sum += (s.speed * alive).sum()
        self.alive_steps += alive.sum()
        ended = s.world_ended != 0
        if self.episodes_per_world is not None:
            counted = ended & (self.world_episodes < self.episodes_per_world)
            self.world_episodes += ended
            ended = counted
        rows = ended[:, None] & s.policy_agents
        self.scene_episodes += rows.any(1).sum()
        self._add(rows, s.final_goal, s.final_collided, s.final_offroad, s.final_cost, s.final_min_dist,
                  s.final_return, s.final_steps)

    def add_unfinished(self) -> None:
        """Count episodes still running (used when a rollout ends before any episode did)."""
        s = self.sim
        rows = s.policy_agents & (s.ep_steps > 0)
        self.scene_episodes += rows.any(1).sum()
        self._add(rows, s.ep_goal, s.ep_collided, s.ep_offroad, s.ep_cost, s.ep_min_dist, s.ep_return, s.ep_steps)

    def summary(self) -> dict:
        tot = {k: float(v.sum()) for k, v in self.sums.items()}

        def rates(d: dict) -> dict:
            n = max(d["episodes"], 1.0)
            return {
                "episodes": int(d["episodes"]),
                "goal_rate": d["goal"] / n,
                "score_rate": d["score"] / n,  # goals reached without a collision or leaving the road
                "collision_rate": d["collided"] / n,
                "offroad_rate": d["offroad"] / n,
                # episodes that ended without a goal, a collision or leaving the road: the vehicle had not arrived
                "timeout_rate": d["timeout"] / n,
                "mean_cost": d["cost"] / max(d["steps"], 1.0),  # per controlled agent-step
                "mean_min_distance": d["min_dist"] / n,  # m, of distances capped at Model.nearest_cap
                "mean_return": d["return"] / n,
            }

        out = rates(tot)
        # "episodes" counts agent-episodes (one per policy agent and episode), the unit of every rate
        out["agent_episodes"] = out["episodes"]
        out["scene_episodes"] = int(self.scene_episodes)
        out["mean_speed"] = float(self.speed_sum / self.alive_steps.clamp(min=1))
        if len(self.type_names) > 1:
            out["per_type"] = {name: rates({k: float(v[i]) for k, v in self.sums.items()})
                               for i, name in enumerate(self.type_names)}
        if self.kerb is not None:
            out["kerb_stops"] = rates({k: float(v) for k, v in self.kerb_sums.items()})
        out["ci95"] = self.intervals()
        return out

    RATE_KEYS = {"goal_rate": "goal", "collision_rate": "collided", "offroad_rate": "offroad", "score_rate": "score"}

    def intervals(self, n_boot: int = 1000, seed: int = 0) -> dict[str, list[float]]:
        """95 % bootstrap intervals of the rates, resampling scenes (the worlds' agent-episodes move
        together: agents of one scene are not independent draws)."""
        per = {k: v.sum(1).cpu().numpy() for k, v in self.slot_sums.items()}  # (W,) per world
        has = per["episodes"] > 0
        if not has.any():
            return {}
        idx = np.random.default_rng(seed).integers(0, int(has.sum()), (n_boot, int(has.sum())))
        eps = per["episodes"][has][idx].sum(1)
        return {name: np.percentile(per[key][has][idx].sum(1) / eps, [2.5, 97.5]).round(4).tolist()
                for name, key in self.RATE_KEYS.items()}

    def per_agent(self) -> list[dict]:
        """One row per (world, policy agent) with counted episodes: scene, agent id and type, its
        agent-episodes and outcome counts."""
        m = self.sim.model
        slot_agent = np.asarray(m.slot_agent)
        sums = {k: v.cpu().numpy() for k, v in self.slot_sums.items()}
        rows = []
        for w, a in zip(*np.nonzero(sums["episodes"] > 0)):
            sc, i = m.scenes[w], int(slot_agent[w, a])
            rows.append({"world": int(w), "scene_id": sc.scene_id, "source": sc.metadata.get("source", ""),
                         "agent": i, "agent_id": int(sc.agent_id[i]), "agent_type": int(sc.agent_type[i]),
                         **{k: int(sums[k][w, a]) for k in self.SLOT_KEYS}})
        return rows

    def per_scene(self, n_boot: int = 1000, seed: int = 0) -> list[dict]:
        """One row per scene (worlds holding the same scene pooled): agent-episodes, rates, and 95 %
        bootstrap intervals over the scene's agent-episodes; the worst scenes (lowest score) first."""
        by: dict[str, list[dict]] = {}
        for r in self.per_agent():
            by.setdefault(r["scene_id"], []).append(r)
        rng = np.random.default_rng(seed)
        rows = []
        for sid, agents in by.items():
            eps = np.array([r["episodes"] for r in agents], np.float64)
            row = {"scene_id": sid, "source": agents[0]["source"], "agents": len(agents),
                   "agent_episodes": int(eps.sum())}
            idx = rng.integers(0, len(agents), (n_boot, len(agents)))
            for name, key in self.RATE_KEYS.items():
                val = np.array([r[key] for r in agents], np.float64)
                row[name] = float(val.sum() / eps.sum())
                lo, hi = np.percentile(val[idx].sum(1) / eps[idx].sum(1), [2.5, 97.5])
                row[f"{name}_lo"], row[f"{name}_hi"] = float(lo), float(hi)
            rows.append(row)
        return sorted(rows, key=lambda r: (r["score_rate"], -r["agent_episodes"], r["scene_id"]))


def run_rollout(sim: Simulator, policy: Policy, steps: int, progress: bool = False,
                background: Policy | None = None, desc: str = "simulate",
                episodes_per_world: int | None = None, seed: int | None = None, tables: bool = False) -> dict:
    """Reset, run `steps` steps under `policy`, return rates over the finished episodes and speed.

    `background`: a driver of the background rows (`make_background_driver`), run after the policy.
    `episodes_per_world`: count each world's first N episodes only (`EpisodeStats`); with `steps` = N
    episode lengths every world finishes exactly N, so every scene weighs the same. `seed` seeds torch's
    generator first, which trained policies (`policy.load_policy`) sample from: a repeatable evaluation.
    `tables`: also return the rows of `EpisodeStats.per_scene` and `per_agent` (keys "per_scene",
    "per_agent")."""
    if seed is not None:
        torch.manual_seed(seed)
    sim.reset()
    stats = EpisodeStats(sim, episodes_per_world)
    bar = None
    if progress:
        bar = tqdm(total=steps, desc=desc, unit="step", leave=False)
    if sim.is_cuda:
        torch.cuda.synchronize(sim.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        policy(sim)
        if background is not None:
            background(sim)
        sim.step()
        stats.after_step()
        if bar is not None:
            bar.update(1)
    if sim.is_cuda:
        torch.cuda.synchronize(sim.device)
    seconds = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    if float(stats.sums["episodes"].sum()) == 0:
        stats.add_unfinished()
    out = stats.summary()
    n_ctrl = int(sim.policy_agents.sum())
    out.update({
        "worlds": sim.num_worlds,
        "agents_controlled": n_ctrl,
        "agents_background": int((sim.background != 0).sum()),
        "steps": steps,
        "seconds": seconds,
        "agent_steps_per_s": n_ctrl * steps / seconds,
        "slot_steps_per_s": sim.num_worlds * sim.max_agents * steps / seconds,
        "device": sim.device,
    })
    if tables:
        out["per_scene"], out["per_agent"] = stats.per_scene(), stats.per_agent()
    return out
