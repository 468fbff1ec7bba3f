"""Risk of generated scenarios: collisions, time-to-collision, gaps, hard braking, and a ranking.

Definitions (per policy agent and episode; "other" = any other agent present
at the same step, policy-driven or replayed):

    collision      the engine flagged a box overlap at some step of the episode
    min_gap        m, smallest centre-to-centre distance to another agent (the engine's and the
                   cost's `beta` convention)
    start_gap      m, the same distance at the agent's first step: the state the log hands over, which
                   no policy changes, so min_gap can never exceed it
    min_gap_ahead  m, smallest centre distance to another agent over the next ANTICIPATION seconds of any
                   step, both moving on with their velocity then: the distance the look-ahead cost
                   (`env.cost_horizon`) charges, which a car can keep small by slowing down
    close_time     share of the agent's steps with another agent's centre within CLOSE_DISTANCE (5 m,
                   the reference TrafficGamer code's default distance limit): how much of the time it
                   drives close to someone, where min_gap is its single closest moment
    min_ttc        s, smallest constant-velocity time-to-collision over the episode: every agent
                   is covered by TTC_DISCS discs of radius width/2 along its length, both move on
                   with their current velocity, TTC is the first time any disc pair touches
                   (0 when they already overlap); no contact within TTC_HORIZON counts as
                   TTC_HORIZON
    hard_brakes    events with accel < HARD_BRAKE (-4 m/s^2): a run of consecutive such steps is
                   one event

Who a collision involves (`collision_partners`), at the agent's first collided step: the partner
is the other agent with the nearest centre among those present then or the step before (one that
reaches its goal in the step of the contact leaves the scene in that step: goal_behaviour remove); "policy" when the policy drives it too, else
"other" (a replayed log or background car, which does not react); the contact is "from behind"
when the partner is behind the agent (in the agent's frame) and heads within CONTACT_ANGLE of it,
"ahead" when it is in front and heads the same way, else "crossing" (side, head-on or crossing).

Where the closest approach is (`closest_partners`), at the agent's closest step (the step of its
min_gap): the partner is the other agent with the nearest centre then, "parked" when it never moves
faster than PARKED_SPEED in the episode, "policy" as above; its place in the agent's frame is
"abreast" when its centre lies more than ABREAST_OFFSET to the side (the next lane, a parked car at the
kerb, crossing traffic: a gap a car cannot widen by its speed alone), else "ahead" or "behind".
`closest_moment` is the same moment for an episode's nearest pair of all (the report's zoomed pictures).
`lane_approach_moment` is the moment a policy car came nearest another ahead of or behind it in its lane
(within ABREAST_OFFSET of its heading line) after its first step, which the log hands over: a gap the policy
keeps by its speed, where a car abreast in the next lane or the handed-over start often is the nearest of all
(the moment the report's grid draws every cell at; `lane_gap` is that distance at a given step).

Scenario criticality ranks episodes by (any collision, lowest min TTC, lowest
min gap, most hard brakes), most critical first.
"""

from __future__ import annotations

import numpy as np

from tg_gpudrive.evaluation.episodes import NEAREST_CAP, Trajectories

HARD_BRAKE = -4.0  # m/s^2
TTC_HORIZON = 10.0  # s
TTC_DISCS = 3
TTC_CRITICAL = 1.5  # s, "near miss" threshold reported as a rate
ANTICIPATION = 1.0  # s: min_gap_ahead's look-ahead, the grids' env.cost_horizon
CLOSE_DISTANCE = 5.0  # m, centre to centre: close_time's threshold
CONTACT_ANGLE = np.pi / 4  # rad: headings closer than this count as "the same way" (collision_partners)
CONTACTS = ("from behind", "ahead", "crossing")
CONTACT_KEYS = tuple(f"collision_{c.replace(' ', '_')}_rate" for c in CONTACTS)  # their rates in `summarize`
PARKED_SPEED = 1.0  # m/s: a partner never faster than this in its episode is parked (closest_partners)
ABREAST_OFFSET = 2.0  # m: a partner's centre further than this to the agent's side is abreast of it
PLACES = ("abreast", "ahead", "behind")
PLACE_KEYS = tuple(f"closest_{p}_share" for p in PLACES)  # their shares in `summarize`


def disc_centres(pos: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(E, A, K, D, 2): D discs of radius width/2 spaced along the box's long axis."""
    off = np.linspace(-1.0, 1.0, TTC_DISCS) if TTC_DISCS > 1 else np.zeros(1)
    offs = 0.5 * np.maximum(length - width, 0.0)[..., None] * off  # (E, A, D)
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)  # (E, A, K, 2)
    return pos[..., None, :] + heading[..., None, :] * offs[:, :, None, :, None]


def pair_ttc(p: np.ndarray, v: np.ndarray, r: np.ndarray, horizon: float = TTC_HORIZON) -> np.ndarray:
    """Constant-velocity TTC of discs with relative position p (..., 2), relative velocity v, radius sum r."""
    c = (p * p).sum(-1) - r * r
    a = (v * v).sum(-1)
    b = 2.0 * (p * v).sum(-1)
    disc = b * b - 4.0 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
    hit = (a > 1e-12) & (disc >= 0) & (t >= 0)
    ttc = np.where(hit, t, np.inf)
    ttc = np.where(c <= 0, 0.0, ttc)
    return np.minimum(ttc, horizon)


def min_ttc(tr: Trajectories) -> np.ndarray:
    """(E, A) min TTC of every policy agent over its episode (TTC_HORIZON where none)."""
    E, A, K = tr.valid.shape
    out = np.full((E, A), TTC_HORIZON, np.float64)
    centres = disc_centres(tr.pos, tr.yaw, tr.length, tr.width)  # (E, A, K, D, 2)
    rad = 0.5 * tr.width  # (E, A)
    for e in range(E):
        rows = np.nonzero(tr.policy[e] & tr.valid[e].any(-1))[0]
        if len(rows) == 0:
            continue
        ci, cj = centres[e, rows], centres[e]  # (R, K, D, 2), (A, K, D, 2)
        p = cj[None, :, :, None, :, :] - ci[:, None, :, :, None, :]  # (R, A, K, Di, Dj, 2)
        v = (tr.vel[e][None, :, :, None, None, :] - tr.vel[e, rows][:, None, :, None, None, :])
        r = (rad[e, rows][:, None] + rad[e][None, :])[:, :, None, None, None]
        ttc = pair_ttc(p, np.broadcast_to(v, p.shape), r).min(axis=(-1, -2))  # (R, A, K)
        ok = tr.valid[e, rows][:, None, :] & tr.valid[e][None, :, :]
        ok &= rows[:, None, None] != np.arange(A)[None, :, None]
        out[e, rows] = np.where(ok, ttc, TTC_HORIZON).min(axis=(1, 2))
    return out


def min_gap(tr: Trajectories) -> np.ndarray:
    """(E, A) smallest centre distance to another agent (the recording's `nearest`, capped there)."""
    near = np.where(tr.valid, tr.nearest, np.inf).min(-1)
    return near


def min_gap_ahead(tr: Trajectories, horizon: float = ANTICIPATION) -> np.ndarray:
    """(E, A) least centre distance of every policy agent to another present agent over the next `horizon`
    seconds of each of its steps, both at constant velocity, capped at NEAREST_CAP as min_gap is (inf: never
    valid); `horizon` 0 is min_gap's centre distance."""
    E, A, K = tr.valid.shape
    out = np.full((E, A), np.inf)
    for e in range(E):
        rows = np.nonzero(tr.policy[e] & tr.valid[e].any(-1))[0]
        if len(rows) == 0:
            continue
        p = tr.pos[e][None] - tr.pos[e, rows][:, None]  # (R, A, K, 2)
        v = tr.vel[e][None] - tr.vel[e, rows][:, None]
        vv = (v * v).sum(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip(np.where(vv > 1e-12, -(p * v).sum(-1) / vv, 0.0), 0.0, horizon)
        d = np.linalg.norm(p + v * t[..., None], axis=-1)
        ok = tr.valid[e, rows][:, None, :] & tr.valid[e][None, :, :]
        ok &= rows[:, None, None] != np.arange(A)[None, :, None]
        out[e, rows] = np.minimum(np.where(ok, d, np.inf).min(axis=(1, 2)), NEAREST_CAP)
    return out


def start_gap(tr: Trajectories) -> np.ndarray:
    """(E, A) centre distance to the nearest other agent at each agent's first valid step (inf: never valid)."""
    first = np.argmax(tr.valid, axis=-1)[..., None]
    near = np.take_along_axis(tr.nearest, first, axis=-1)[..., 0]
    return np.where(tr.valid.any(-1), near, np.inf)


def close_time(tr: Trajectories, distance: float = CLOSE_DISTANCE) -> np.ndarray:
    """(E, A) share of each agent's valid steps with another agent nearer than `distance` (0 without steps)."""
    close = (tr.valid & (tr.nearest < distance)).sum(-1)
    return close / np.maximum(tr.valid.sum(-1), 1)


def hard_brakes(tr: Trajectories, threshold: float = HARD_BRAKE) -> np.ndarray:
    """(E, A) number of hard-braking events (runs of consecutive steps with accel < threshold)."""
    hb = tr.kin_valid & (tr.accel < threshold)  # path-derived, as for the logs
    onset = hb.copy()
    onset[..., 1:] &= ~hb[..., :-1]
    return onset.sum(-1)


def _nearest_in_frame(tr: Trajectories, e: int, a: int, k: int, others: np.ndarray) -> tuple[int, float, float]:
    """The agent among `others` (A,) with the centre nearest agent a's at step k of episode e, and its centre in
    a's frame then: (slot, ahead (+) / behind (-), to the left (+) / right (-)). `others` holds one agent or more."""
    rel = tr.pos[e, :, k] - tr.pos[e, a, k]  # (A, 2)
    b = int(np.argmin(np.where(others, np.linalg.norm(rel, axis=-1), np.inf)))
    c, s = np.cos(tr.yaw[e, a, k]), np.sin(tr.yaw[e, a, k])
    return b, float(c * rel[b, 0] + s * rel[b, 1]), float(c * rel[b, 1] - s * rel[b, 0])


def collision_partners(tr: Trajectories) -> list[dict]:
    """One row per policy agent-episode with a collision (see the module docstring): episode, agent,
    step k of the first contact, partner slot, `partner_policy` (bool), `contact` (one of CONTACTS),
    and both speeds [m/s] at that step."""
    rows = []
    hit = tr.collided & tr.valid
    for e, a in zip(*np.nonzero(tr.policy & hit.any(-1))):
        k = int(np.argmax(hit[e, a]))
        others = tr.valid[e, :, k] | tr.valid[e, :, k - 1]  # k >= 1: the reset state carries no events
        others[a] = False
        if not others.any():
            continue
        b, along, _ = _nearest_in_frame(tr, e, a, k, others)
        dyaw = np.angle(np.exp(1j * (tr.yaw[e, b, k] - tr.yaw[e, a, k])))
        same_way = abs(dyaw) < CONTACT_ANGLE
        contact = CONTACTS[2] if not same_way else (CONTACTS[0] if along < 0 else CONTACTS[1])
        rows.append({"episode": int(e), "agent": int(a), "step": k, "partner": b,
                     "partner_policy": bool(tr.policy[e, b]), "contact": contact,
                     "speed": float(tr.speed[e, a, k]), "partner_speed": float(tr.speed[e, b, k])})
    return rows


def closest_partners(tr: Trajectories) -> dict[str, np.ndarray]:
    """(E, A) arrays on the partner at each policy agent's closest step (see the module docstring): `place`
    (index into PLACES; -1 where no other agent came within NEAREST_CAP of it), `parked` and `policy`."""
    E, A, _ = tr.valid.shape
    place = np.full((E, A), -1, np.int64)
    parked, policy = np.zeros((E, A), bool), np.zeros((E, A), bool)
    moves = (np.where(tr.valid, tr.speed, 0.0) > PARKED_SPEED).any(-1)  # (E, A)
    for e, a in zip(*np.nonzero(tr.policy & tr.valid.any(-1))):
        near = np.where(tr.valid[e, a], tr.nearest[e, a], np.inf)
        k = int(np.argmin(near))
        if near[k] >= NEAREST_CAP:  # no one near: the capped distance names no closest moment
            continue
        others = tr.valid[e, :, k].copy()
        others[a] = False
        b, along, side = _nearest_in_frame(tr, e, a, k, others)
        place[e, a] = 0 if abs(side) > ABREAST_OFFSET else (1 if along >= 0 else 2)
        parked[e, a], policy[e, a] = not moves[e, b], tr.policy[e, b]
    return {"place": place, "parked": parked, "policy": policy}


def closest_moment(tr: Trajectories, e: int = 0) -> tuple[int, int, int, float] | None:
    """Episode `e`'s closest approach of any policy agent: (its step, the agent, the partner as closest_partners
    names it, their centre distance in m); None when no other agent came within NEAREST_CAP of one."""
    near = np.where(tr.valid[e] & tr.policy[e][:, None], tr.nearest[e], np.inf)  # (A, K)
    a, k = np.unravel_index(int(np.argmin(near)), near.shape)
    if not near[a, k] < NEAREST_CAP:
        return None
    others = tr.valid[e, :, k].copy()
    others[a] = False
    b, _, _ = _nearest_in_frame(tr, e, int(a), int(k), others)
    return int(k), int(a), int(b), float(near[a, k])


def _lane_distances(tr: Trajectories, e: int, a: int) -> np.ndarray:
    """(A, K) centre distance from agent a of episode e to every other agent at every step where both are present
    and the other is ahead of or behind a in its lane (|its offset to a's side| <= ABREAST_OFFSET, as
    closest_partners places it), inf elsewhere."""
    rel = tr.pos[e] - tr.pos[e, a][None]  # (A, K, 2)
    c, s = np.cos(tr.yaw[e, a])[None], np.sin(tr.yaw[e, a])[None]  # (1, K)
    side = c * rel[..., 1] - s * rel[..., 0]
    ok = tr.valid[e] & tr.valid[e, a][None] & (np.abs(side) <= ABREAST_OFFSET)
    ok[a] = False
    return np.where(ok, np.linalg.norm(rel, axis=-1), np.inf)


def lane_gap(tr: Trajectories, e: int, a: int, k: int) -> tuple[int, float, bool] | None:
    """Agent a's nearest other agent ahead of or behind it in its lane at step k of episode e (see
    `_lane_distances`): (its slot, their centre distance in m, whether it is ahead); None when a is not present
    then or no other agent is in its lane."""
    d = _lane_distances(tr, e, a)[:, k]
    if not np.isfinite(d).any():
        return None
    b, along, _ = _nearest_in_frame(tr, e, a, k, np.isfinite(d))
    return b, float(d[b]), bool(along >= 0)


def lane_approach_moment(tr: Trajectories, e: int = 0,
                         allowed: np.ndarray | None = None) -> tuple[int, int, int, float] | None:
    """Episode `e`'s closest approach of a policy agent to another ahead of or behind it in its lane, at a step
    after the agent's first (the logged start state no policy chose) and, with `allowed` ((A, K) bool), at an
    (agent, step) it marks: (its step, the agent, the partner, their centre distance in m); None when no such
    pair came within NEAREST_CAP. The report's grid draws every cell at this moment of its most pressing cell
    (allowed: where the agent is present in every cell), where `closest_moment` is often the start or a car
    abreast."""
    best = None
    for a in np.nonzero(tr.policy[e] & tr.valid[e].any(-1))[0]:
        d = _lane_distances(tr, e, int(a))
        d[:, :int(np.argmax(tr.valid[e, a])) + 1] = np.inf  # from the step after the agent's first on
        if allowed is not None:
            d[:, ~allowed[a]] = np.inf
        b, k = np.unravel_index(int(np.argmin(d)), d.shape)
        if d[b, k] < NEAREST_CAP and (best is None or d[b, k] < best[3]):
            best = (int(k), int(a), int(b), float(d[b, k]))
    return best


def episode_risk(tr: Trajectories) -> dict[str, np.ndarray]:
    """Per (episode, agent) arrays, and `agents` (E, A): the policy agents that appear; `contact` (index
    into CONTACTS, -1 without a collision) and `partner_policy` describe the first collision."""
    agents = tr.policy & tr.valid.any(-1)
    contact = np.full(agents.shape, -1, np.int64)  # index into CONTACTS of the first collision, -1: none
    partner_policy = np.zeros(agents.shape, bool)
    for row in collision_partners(tr):
        contact[row["episode"], row["agent"]] = CONTACTS.index(row["contact"])
        partner_policy[row["episode"], row["agent"]] = row["partner_policy"]
    return {"agents": agents, "collided": (tr.collided & tr.valid).any(-1), "offroad": (tr.offroad & tr.valid).any(-1),
            "min_ttc": min_ttc(tr), "min_gap": min_gap(tr), "start_gap": start_gap(tr), "close_time": close_time(tr),
            "min_gap_ahead": min_gap_ahead(tr),
            "hard_brakes": hard_brakes(tr),
            "contact": contact, "partner_policy": partner_policy,
            **{f"closest_{k}": v for k, v in closest_partners(tr).items()}}


def summarize(tr: Trajectories, risk: dict | None = None) -> dict:
    """Rates over policy agent-episodes."""
    r = risk or episode_risk(tr)
    m = r["agents"]
    n = int(m.sum())
    if n == 0:
        return {"agent_episodes": 0}
    gap = r["min_gap"][m]
    return {
        "agent_episodes": n,
        "collision_rate": float(r["collided"][m].mean()),
        "offroad_rate": float(r["offroad"][m].mean()),
        "mean_min_ttc_s": float(r["min_ttc"][m].mean()),
        "near_miss_rate": float((r["min_ttc"][m] < TTC_CRITICAL).mean()),
        "mean_min_gap_m": float(gap[np.isfinite(gap)].mean()) if np.isfinite(gap).any() else float("nan"),
        "close_time_share": float(r["close_time"][m].mean()),
        "hard_brakes_per_agent": float(r["hard_brakes"][m].mean()),
        "hard_brake_rate": float((r["hard_brakes"][m] > 0).mean()),
        # collisions split by partner and by contact (they add up to the collision rate, less those
        # with no other agent present)
        "collision_with_policy_rate": float(((r["contact"] >= 0) & r["partner_policy"])[m].mean()),
        "collision_with_other_rate": float(((r["contact"] >= 0) & ~r["partner_policy"])[m].mean()),
        **{key: float((r["contact"] == i)[m].mean()) for i, key in enumerate(CONTACT_KEYS)},
        # where each agent's closest approach was (shares of the agent-episodes; an agent that no other
        # came within NEAREST_CAP of counts in none)
        **{key: float((r["closest_place"] == i)[m].mean()) for i, key in enumerate(PLACE_KEYS)},
        "closest_parked_share": float(r["closest_parked"][m].mean()),
        "closest_policy_share": float(r["closest_policy"][m].mean()),
    }


def rank_scenarios(tr: Trajectories, risk: dict | None = None, top: int = 10) -> list[dict]:
    """The `top` most safety-critical episodes, most critical first (see the module docstring)."""
    r = risk or episode_risk(tr)
    rows = []
    for e in range(tr.num_episodes):
        m = r["agents"][e]
        if not m.any():
            continue
        rows.append({
            "episode": e, "scene_id": tr.scenes[int(tr.scene_index[e])].scene_id,
            "scenario_type": tr.scenes[int(tr.scene_index[e])].metadata.get("scenario_type", "unknown"),
            "seed": int(tr.seed[e]), "label": tr.label,
            "collisions": int(r["collided"][e][m].sum()),
            "min_ttc_s": float(r["min_ttc"][e][m].min()),
            "min_gap_m": float(r["min_gap"][e][m].min()),
            "hard_brakes": int(r["hard_brakes"][e][m].sum()),
        })
    rows.sort(key=lambda x: (-x["collisions"], x["min_ttc_s"], x["min_gap_m"], -x["hard_brakes"]))
    return rows[:top]
