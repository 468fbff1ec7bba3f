"""Recorded episodes: what every evaluation metric reads.

`record_episodes(sim, policy)` runs the first episode of every world under a
`policy(sim)` and keeps each slot's state per step; `logged_episodes(sim)`
builds the same object from the logs the worlds replay (no stepping), and
`replay_episodes` records the engine replaying those logs for the policy's
agents (the "log replay" baseline). Metrics (fidelity, diversity, risk, export)
work on these host arrays only, so they do not care which device made them.

Acceleration and curvature are derived from the positions alone, the same way
for logs and rollouts (`path_kinematics`), so they measure the driving and not
the action representation: a discrete grid's 2 m/s^2 steps or a delta-local
action show only through the path they produce.

`Trajectories` fields (E episodes, A agent slots, K = episode_length + 1 steps;
k = 0 is the state at the scene's init_step, k is log step init_step + k):

    name        shape        dtype    unit / meaning
    pos         (E, A, K, 2) float32  m, agent centre
    yaw         (E, A, K)    float32  rad
    vel         (E, A, K, 2) float32  m/s
    speed       (E, A, K)    float32  m/s
    accel       (E, A, K)    float32  m/s^2, change of path speed |p_k - p_k-1| / dt from k-1 to k, over dt
    curvature   (E, A, K)    float32  1/m, change of path heading (direction of p_k - p_k-1) over the arc
                                      p_k-1 -> p_k; 0 where either arc is under 5 cm (standing still)
    nearest     (E, A, K)    float32  m, centre distance to the nearest other present agent, capped at
                                      NEAREST_CAP (recomputed from positions, for logs and rollouts alike:
                                      the engine's own value is capped at its broad-phase cell, ~5 m)
    valid       (E, A, K)    bool     agent present in the scene at step k (of the recorded episode)
    kin_valid   (E, A, K)    bool     accel and curvature are defined: present at k-2, k-1 and k
    collided    (E, A, K)    bool
    offroad     (E, A, K)    bool
    policy      (E, A)       bool     the policy's agents (what metrics count)
    length      (E, A)       float32  m
    width       (E, A)       float32  m
    slot_agent  (E, A)       int64    scene agent index of the slot, -1 for an empty slot
    scene_index (E,)         int64    index into `scenes`
    seed        (E,)         int64    rollout seed of the episode
    scenes      list[Scene]  -        the distinct scenes, `scene_index` points here
    init_step   int          -        log step of k = 0
    dt          float        s
    label       str          -        who drove ("expert", "log", a run name, ...)

Only the first episode of each world is kept: with the engine's auto-reset,
the step that ends an episode already shows the world reset, so it and every
later step of that world are marked invalid.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np
import torch

from tg_gpudrive.engine.simulator import Simulator

NEAREST_CAP = 50.0  # m

_PER_STEP = ("pos", "yaw", "vel", "speed", "accel", "curvature", "nearest", "valid", "kin_valid",
             "collided", "offroad")
_PER_AGENT = ("policy", "length", "width", "slot_agent")


@dataclasses.dataclass
class Trajectories:
    pos: np.ndarray
    yaw: np.ndarray
    vel: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    curvature: np.ndarray
    nearest: np.ndarray
    valid: np.ndarray
    kin_valid: np.ndarray
    collided: np.ndarray
    offroad: np.ndarray
    policy: np.ndarray
    length: np.ndarray
    width: np.ndarray
    slot_agent: np.ndarray
    scene_index: np.ndarray
    seed: np.ndarray
    scenes: list
    init_step: int
    dt: float
    label: str = ""

    @property
    def num_episodes(self) -> int:
        return int(self.pos.shape[0])

    @property
    def scene_ids(self) -> list[str]:
        return [self.scenes[int(i)].scene_id for i in self.scene_index]

    def scenario_types(self) -> list[str]:
        return [str(self.scenes[int(i)].metadata.get("scenario_type", "unknown")) for i in self.scene_index]

    def select(self, episodes) -> "Trajectories":
        idx = np.asarray(episodes)
        kw = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name in _PER_STEP + _PER_AGENT + ("scene_index", "seed"):
            kw[name] = kw[name][idx]
        return Trajectories(**kw)

    @staticmethod
    def concat(parts: Sequence["Trajectories"], label: str | None = None) -> "Trajectories":
        """Episodes of several recordings (same K and A; scenes are merged by identity)."""
        scenes: list = []
        index_of: dict[int, int] = {}
        scene_index = []
        for p in parts:
            for i in p.scene_index:
                sc = p.scenes[int(i)]
                if id(sc) not in index_of:
                    index_of[id(sc)] = len(scenes)
                    scenes.append(sc)
                scene_index.append(index_of[id(sc)])
        kw = {name: np.concatenate([getattr(p, name) for p in parts]) for name in _PER_STEP + _PER_AGENT + ("seed",)}
        return Trajectories(**kw, scene_index=np.asarray(scene_index, np.int64), scenes=scenes,
                            init_step=parts[0].init_step, dt=parts[0].dt,
                            label=parts[0].label if label is None else label)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu").numpy()


def record_episodes(sim, policy: Callable, *, seed: int = 0, label: str = "") -> Trajectories:
    """Reset `sim`, run one episode of every world under `policy(sim)` and record it.

    Seeds torch's global RNG with `seed` first (policies from `load_policy` sample from it)."""
    torch.manual_seed(seed)
    W, A, K = sim.num_worlds, sim.max_agents, sim.episode_length + 1
    out = {
        "pos": np.zeros((W, A, K, 2), np.float32), "yaw": np.zeros((W, A, K), np.float32),
        "vel": np.zeros((W, A, K, 2), np.float32), "speed": np.zeros((W, A, K), np.float32),
        "nearest": np.zeros((W, A, K), np.float32), "valid": np.zeros((W, A, K), bool),
        "collided": np.zeros((W, A, K), bool), "offroad": np.zeros((W, A, K), bool),
    }
    sim.reset()
    live = np.ones(W, bool)  # world still in its first episode

    def grab(k: int) -> None:
        keep = live[:, None]
        out["pos"][:, :, k] = _np(sim.pos)
        out["yaw"][:, :, k] = _np(sim.yaw)
        out["vel"][:, :, k] = _np(sim.vel)
        out["speed"][:, :, k] = _np(sim.speed)
        out["valid"][:, :, k] = keep & (_np(sim.present) != 0) & (_np(sim.slot_valid) != 0) & (_np(sim.removed) == 0)
        out["collided"][:, :, k] = keep & (_np(sim.collided) != 0)
        out["offroad"][:, :, k] = keep & (_np(sim.offroad) != 0)

    grab(0)
    out["collided"][:, :, 0] = False  # the reset state carries no events
    out["offroad"][:, :, 0] = False
    for k in range(1, K):
        policy(sim)
        sim.step()
        live &= _np(sim.world_reset) == 0
        grab(k)
        live &= _np(sim.world_ended) == 0
        if not live.any():
            break
    out["nearest"] = nearest_distance(out["pos"], out["valid"], NEAREST_CAP)
    out["accel"], out["curvature"], out["kin_valid"] = path_kinematics(out["pos"], out["valid"], sim.model.dt)
    return Trajectories(
        **out,
        policy=_np(sim.policy_agents).astype(bool),
        length=_np(sim.length).astype(np.float32), width=_np(sim.width).astype(np.float32),
        slot_agent=np.asarray(sim.model.slot_agent, np.int64).copy(),
        scene_index=np.arange(W, dtype=np.int64), seed=np.full(W, seed, np.int64),
        scenes=list(sim.model.scenes), init_step=int(sim.model.init_step), dt=float(sim.model.dt), label=label)


def record_rollouts(sim, policy: Callable, seeds: Sequence[int], label: str = "") -> Trajectories:
    """`record_episodes` once per seed, concatenated (the diversity metric needs several per scene)."""
    return Trajectories.concat([record_episodes(sim, policy, seed=s, label=label) for s in seeds], label)


def path_kinematics(pos: np.ndarray, valid: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Acceleration and curvature of a path from its positions alone: accel, curvature and kin_valid,
    (..., K) each, as the Trajectories table defines them (finite differences over three steps).

    Curvature is 0 where either arc is shorter than 5 cm (standing still: no steering to see)."""
    d = pos[..., 1:, :] - pos[..., :-1, :]
    arc = np.sqrt((d * d).sum(-1))  # (..., K-1), arc k-1 -> k
    step_ok = valid[..., 1:] & valid[..., :-1]
    v = np.where(step_ok, arc / dt, 0.0)
    heading = np.arctan2(d[..., 1], d[..., 0])
    ok = np.zeros(valid.shape, bool)
    ok[..., 2:] = step_ok[..., 1:] & step_ok[..., :-1]
    accel = np.zeros(valid.shape, np.float64)
    curv = np.zeros(valid.shape, np.float64)
    accel[..., 2:] = np.where(ok[..., 2:], (v[..., 1:] - v[..., :-1]) / dt, 0.0)
    turn = np.angle(np.exp(1j * (heading[..., 1:] - heading[..., :-1])))
    moving = (arc[..., 1:] > 0.05) & (arc[..., :-1] > 0.05)
    with np.errstate(divide="ignore", invalid="ignore"):
        curv[..., 2:] = np.where(ok[..., 2:] & moving, turn / np.maximum(arc[..., 1:], 1e-9), 0.0)
    return accel.astype(np.float32), curv.astype(np.float32), ok


def nearest_distance(pos: np.ndarray, valid: np.ndarray, cap: float = NEAREST_CAP) -> np.ndarray:
    """(E, A, K) centre distance to the nearest other valid agent of the episode, capped at `cap` m."""
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)  # (E, A, A, K)
    ok = valid[:, :, None] & valid[:, None]
    A = pos.shape[1]
    ok &= ~np.eye(A, dtype=bool)[None, :, :, None]
    d = np.where(ok, d, np.inf).min(axis=2)
    return np.minimum(d, cap).astype(np.float32)


def logged_episodes(sim, label: str = "log") -> Trajectories:
    """The logs of `sim`'s worlds from init_step on, as a Trajectories (the reference of fidelity)."""
    m = sim.model
    h = m.host
    T0 = m.init_step
    pos = h["log_pos"][:, :, T0:].astype(np.float32)
    yaw = h["log_yaw"][:, :, T0:].astype(np.float32)
    vel = h["log_vel"][:, :, T0:].astype(np.float32)
    valid = (h["log_valid"][:, :, T0:] != 0) & (h["slot_valid"][:, :, None] != 0)
    speed = np.linalg.norm(vel, axis=-1).astype(np.float32)
    accel, curv, kin_valid = path_kinematics(pos, valid, m.dt)
    near = nearest_distance(pos, valid, NEAREST_CAP)
    W, A = valid.shape[:2]
    return Trajectories(
        pos=pos, yaw=yaw, vel=vel, speed=speed, accel=accel, curvature=curv, nearest=near, valid=valid,
        kin_valid=kin_valid, collided=np.zeros_like(valid), offroad=np.zeros_like(valid),
        policy=_np(sim.policy_agents).astype(bool), length=h["length"].astype(np.float32),
        width=h["width"].astype(np.float32), slot_agent=np.asarray(m.slot_agent, np.int64).copy(),
        scene_index=np.arange(W, dtype=np.int64), seed=np.zeros(W, np.int64), scenes=list(m.scenes),
        init_step=int(T0), dt=float(m.dt), label=label)


def replay_episodes(scenes: Sequence, masks: Sequence[np.ndarray], cfg, device: str,
                    label: str = "log replay") -> Trajectories:
    """The engine replaying the logs of every agent of `scenes` (nobody driven), recorded as
    `record_episodes` records a policy, with `policy` marking the agents `masks` (per scene, over
    its agents) would give a policy: the log-replay baseline, measured by the same pipeline."""
    sim = Simulator(list(scenes), cfg, device, controlled=[np.zeros(len(m), bool) for m in masks])
    tr = record_episodes(sim, lambda s: None, label=label)
    slot = tr.slot_agent
    policy = np.stack([(slot[w] >= 0) & np.asarray(masks[w], bool)[np.maximum(slot[w], 0)]
                       for w in range(len(masks))])
    return dataclasses.replace(tr, policy=policy)
