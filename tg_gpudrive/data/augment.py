"""Augmentation that stretches a few real scenes into many training worlds.

Each knob (`AugmentConfig`, the `augment:` section of a training config) makes a new Scene from one
the sampler drew, never changing the source's own:

    knob              what it does to a scene
    mirror            with this probability, mirror it across its x axis (y -> -y, headings and
                      velocities with it): left turns become right turns, and the driving side flips
    rotate            turn it by a uniform random angle about its origin (the whole map and every log)
    start_shift       start its log up to this many steps later (a uniform draw; the first k steps are
                      cut, so control begins k steps into the original log), keeping at least
                      MIN_PLAY_STEPS after init_step
    perturb_pos       m: Gaussian noise on each candidate vehicle's position over the warm-up steps up to
                      init_step (one offset per vehicle, so its warm-up motion is kept)
    perturb_yaw       rad: the same for its heading (velocities turn with it)
    delay_share       each candidate vehicle is delayed with this probability: its whole log runs
                      1 to `max_delay` steps later than the scene's (drawn per vehicle, taken from the
                      steps before the scene's start that a start shift cuts, so a delay of k + init_step
                      steps at most), the steps before its log begins invalid and its goal the end of its
                      delayed log. The real geometry then meets new timings: a car that crossed before
                      another pulled out arrives while it might. A delay that would make its box meet
                      another's over the DELAY_CLEAR_STEPS up to init_step is not taken.
    max_delay         the longest delay, in steps
    control_fraction  (applied to the control masks, `subset_mask`): each of the policy's agents stays
                      the policy's with this probability, the others replay their logs; at least one
                      stays

The control rule's log audit travels with the copies: mirror and rotate preserve it, a start shift
takes the source's audit at the later init step (cached on the source, so each shift is audited once),
and the perturbations and delays keep the unperturbed log's (the rule's exclusions are those of the real log; a
perturbation that makes two warm-up boxes meet is a collision the policy meets in training). Must not:
touch the engine, or mutate its input.
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.config import AugmentConfig
from tg_gpudrive.data.log_audit import MIN_PLAY_STEPS, candidates, carry_audit
from tg_gpudrive.data.procedural.checks import box_box_overlap
from tg_gpudrive.scene import Scene

__all__ = ["augment_scene", "mirror", "rotate", "shift_start", "perturb_start", "delay_agents", "subset_mask"]

DELAY_CLEAR_STEPS = 6  # steps up to init_step over which a delayed vehicle's box must meet nobody's

_XY_FIELDS = ("log_pos", "log_vel", "goal", "road_points", "tl_stop_point")


def _transform(scene: Scene, matrix: np.ndarray, yaw) -> Scene:
    """A copy of `scene` with every position, velocity and goal mapped by the 2 x 2 `matrix` (so is a
    procedural scene's conflict point) and its valid headings by `yaw(headings)`."""
    s = scene.copy()
    for name in _XY_FIELDS:
        arr = getattr(s, name)
        arr[...] = (arr.astype(np.float64) @ matrix.T).astype(arr.dtype)
    wrapped = (yaw(s.log_yaw.astype(np.float64)) + np.pi) % (2 * np.pi) - np.pi
    s.log_yaw[:] = np.where(s.log_valid, wrapped, 0.0)
    if s.metadata.get("conflict_point") is not None:
        s.metadata["conflict_point"] = (np.asarray(s.metadata["conflict_point"], np.float64) @ matrix.T).tolist()
    return s


def mirror(scene: Scene) -> Scene:
    """`scene` mirrored across its x axis."""
    return _transform(scene, np.diag([1.0, -1.0]), lambda yaw: -yaw)


def rotate(scene: Scene, angle: float) -> Scene:
    """`scene` turned by `angle` (rad) about its origin."""
    c, sn = np.cos(angle), np.sin(angle)
    return _transform(scene, np.array([[c, -sn], [sn, c]]), lambda yaw: yaw + angle)


def shift_start(scene: Scene, k: int, init_step: int | None = None, goal_radius: float | None = None,
                max_shift: int | None = None) -> Scene:
    """`scene` with its first `k` logged steps cut. With `init_step` and `goal_radius` the new scene's
    log audit is the source's at init_step + k (`log_audit.carry_audit`: audited once per shift, however
    often the shift is drawn); without them it is dropped and recomputed on use."""
    if k <= 0:
        return scene
    s = scene.copy()
    for name in ("log_pos", "log_yaw", "log_vel", "log_valid"):
        setattr(s, name, np.ascontiguousarray(getattr(s, name)[:, k:]))
    s.tl_state = np.ascontiguousarray(s.tl_state[k:])
    s.metadata.pop("log_audit", None)
    s.metadata["start_shift"] = int(k)
    if init_step is not None and goal_radius is not None:
        carry_audit(scene, s, k, init_step, goal_radius, max_shift)
    return s


def perturb_start(scene: Scene, init_step: int, goal_radius: float, pos_std: float, yaw_std: float,
                  rng: np.random.Generator) -> Scene:
    """`scene` with the warm-up (steps up to `init_step`) of its candidate vehicles moved by one Gaussian
    offset each (`pos_std` m) and turned by one Gaussian angle each (`yaw_std` rad) about their position."""
    if pos_std <= 0 and yaw_std <= 0:
        return scene
    s = scene.copy()
    init = min(init_step, s.num_steps - 1)
    rows = np.nonzero(candidates(s, init, goal_radius))[0]
    for i in rows:
        ok = s.log_valid[i, :init + 1]
        dp = rng.normal(0.0, pos_std, 2) if pos_std > 0 else np.zeros(2)
        da = rng.normal(0.0, yaw_std) if yaw_std > 0 else 0.0
        c, sn = np.cos(da), np.sin(da)
        s.log_pos[i, :init + 1][ok] += dp.astype(np.float32)
        v = s.log_vel[i, :init + 1][ok].astype(np.float64)
        s.log_vel[i, :init + 1][ok] = np.stack([c * v[:, 0] - sn * v[:, 1], sn * v[:, 0] + c * v[:, 1]], -1)
        s.log_yaw[i, :init + 1][ok] = (s.log_yaw[i, :init + 1][ok] + da + np.pi) % (2 * np.pi) - np.pi
    return s


def delay_agents(scene: Scene, source: Scene, k: int, init_step: int, goal_radius: float, share: float,
                 max_delay: int, rng: np.random.Generator) -> Scene:
    """`scene` (`source` with its first `k` steps cut, `shift_start`) with each candidate vehicle delayed with
    probability `share` by 1 to `max_delay` steps (module docstring): row i of the logs reads the source's at
    step t + k - d, invalid before the source's first step."""
    if share <= 0 or max_delay <= 0:
        return scene
    init = min(init_step, scene.num_steps - 1)
    rows = np.flatnonzero(candidates(scene, init, goal_radius))
    chosen = rows[rng.random(len(rows)) < share]
    if len(chosen) == 0:
        return scene
    s = scene.copy()
    t = np.arange(s.num_steps)
    window = np.arange(max(init - DELAY_CLEAR_STEPS + 1, 0), init + 1)
    delays = {}
    for i, d in zip(chosen, rng.integers(1, max_delay + 1, len(chosen))):
        d = int(min(d, init + k))
        src_t = t + k - d
        at = np.maximum(src_t, 0)
        ok = (src_t >= 0) & source.log_valid[i, at]
        if not ok[window].all():
            continue
        pos = np.where(ok[:, None], source.log_pos[i, at], 0.0)
        yaw = np.where(ok, source.log_yaw[i, at], 0.0)
        if _meets_anyone(s, i, pos, yaw, window):
            continue
        s.log_pos[i], s.log_yaw[i], s.log_valid[i] = pos, yaw, ok
        s.log_vel[i] = np.where(ok[:, None], source.log_vel[i, at], 0.0)
        s.goal[i] = pos[np.flatnonzero(ok)[-1]]
        delays[int(i)] = d
    s.metadata["agent_delays"] = delays
    return s


def _meets_anyone(s: Scene, i: int, pos: np.ndarray, yaw: np.ndarray, steps: np.ndarray) -> bool:
    """Would vehicle i at `pos`, `yaw` meet another agent's box of `s` at any of `steps`?"""
    others = np.flatnonzero(np.arange(s.num_agents) != i)
    for t in steps:
        there = others[s.log_valid[others, t]]
        if len(there) and box_box_overlap(pos[t], yaw[t], s.length[i] / 2, s.width[i] / 2, s.log_pos[there, t],
                                          s.log_yaw[there, t], s.length[there] / 2, s.width[there] / 2).any():
            return True
    return False


def augment_scene(scene: Scene, cfg: AugmentConfig, init_step: int, goal_radius: float,
                  rng: np.random.Generator) -> Scene:
    """One augmented copy of `scene` (the scene itself when every knob is off)."""
    out, k = scene, 0
    if cfg.start_shift > 0:
        room = scene.num_steps - (init_step + 1 + MIN_PLAY_STEPS)
        top = min(cfg.start_shift, max(room, 0))
        k = int(rng.integers(0, top + 1))
        out = shift_start(out, k, init_step, goal_radius, top)
    out = delay_agents(out, scene, k, init_step, goal_radius, cfg.delay_share, cfg.max_delay, rng)
    if cfg.mirror > 0 and rng.random() < cfg.mirror:
        out = mirror(out)
    if cfg.rotate:
        out = rotate(out, float(rng.uniform(-np.pi, np.pi)))
    out = perturb_start(out, init_step, goal_radius, cfg.perturb_pos, cfg.perturb_yaw, rng)
    return out


def subset_mask(mask: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """`mask` keeping each of its agents with probability `fraction`, at least one when it has any."""
    mask = np.asarray(mask, bool)
    if fraction >= 1.0 or not mask.any():
        return mask
    keep = mask & (rng.random(mask.shape) < fraction)
    if not keep.any():
        keep[rng.choice(np.nonzero(mask)[0])] = True
    return keep
