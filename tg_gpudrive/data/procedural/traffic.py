"""Traffic of the procedural generator: vehicles spawned on a RoadMap's approach
lanes and a human-like drive that becomes the scene's "log".

Each vehicle drives along its route's centreline in 1-D (arc length s), so
heading, velocity and curvature follow the lanes exactly. Longitudinal control
is IDM (desired speed, time headway, minimum gap) against:
  * the vehicle ahead on the same lanes (routes sharing lanes, merges included
    once the leader is on the shared lane),
  * conflict zones: for every pair of routes the set of arc-length pairs where
    the two (inflated) largest vehicle boxes would touch is precomputed and
    split into clusters; each cluster orders its two vehicles (in the zone or
    past the stop line first, then the priority road with gap acceptance for
    the minor road, then first come first served by a per-vehicle ticket, see
    `_decide`) and the second holds back behind the "frontier" that the first
    one's current position still leaves free (reservation of the zone),
  * the curve speed limit (lateral acceleration LAT_ACC) and the route end,
  * pedestrians crossing the road (`Crossing`): from CROSS_LEAD s before one steps off the kerb until
    it reaches the far side, a vehicle whose route crosses its path and that can still stop (braking
    at most B_HARD) holds its front CROSS_STOP m short of the path.
Kerb stops, lane changes and lane offsets (`Vehicles.lateral`) move a vehicle sideways off its
centreline, only where its route is straight, after the 1-D drive; a vehicle that pulls in at the
kerb or changes lanes stops leading its followers once it has left their lane (on its new lane it
leads no one: a vehicle there that it would touch is dropped by the overlap check). After the drive every box pair is checked exactly
(separating axes with a safety margin); an overlapping later-spawned vehicle, or one that barely
moves, is dropped and the drive repeated, so the invariants hold by construction.
Nothing here draws random numbers after spawning: the drive is deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tg_gpudrive.data.procedural.checks import box_box_overlap, box_box_overlap_cs, self_near_pairs
from tg_gpudrive.data.procedural.geometry import MAX_LEN, MAX_WID, SWEEP_INFLATE, Path, RoadMap

DS = 0.5  # m, route grid spacing for pose look-up and conflict tables
DS_ZONE = 1.5  # m, lane sample spacing for conflict zones
ZONE_INFLATE = 0.35  # m added to each half extent of the boxes that define conflict zones
CHECK_MARGIN = 0.15  # m added to each half extent in the final overlap check (0.3 m between boxes)
A_MIN, A_MAX_HARD = -4.0, 2.5  # m/s^2, hard acceleration bounds of the drive
B_HARD = 3.5  # m/s^2, braking a yielding vehicle may need
LAT_ACC = 2.5  # m/s^2, lateral acceleration that sets the curve speed
B_CURVE = 1.5  # m/s^2, deceleration ahead of curves
GAP_ACCEPT = 1.0  # s, time a minor-road vehicle wants between clearing and the major's arrival
# Holding a yielding vehicle at its stop line (instead of at the conflict zone inside the junction)
# avoids some waiting in the junction box but roughly halves throughput and interactions, so it is
# off unless a scene asks for it (`drive(hold_at_stop_line=True)`, ProceduralParams.stop_lines):
# then queues form at the stop lines, as at the stop-controlled junctions of WOMD.
MIN_MOVE_AFTER_10 = 5.5  # m, a vehicle must travel this far after step 10 or be dropped
CROSS_STOP = 2.5  # m short of a crossing pedestrian's path where a yielding vehicle holds its front
CROSS_LEAD = 1.0  # s before a pedestrian steps off the kerb that vehicles start yielding to it
REST_HOLD = (1.5, 5.0)  # s a vehicle started from rest stands at its stop line (at rest at a 1 s init step)


@dataclass(frozen=True)
class Crossing:
    """A pedestrian walking straight from `a` to `b` (m, kerb to kerb across the road) at `speed` m/s,
    leaving `a` at `t0` s (negative: already on its way at the first step)."""

    a: np.ndarray
    b: np.ndarray
    speed: float
    t0: float

    @property
    def t_off(self) -> float:
        return self.t0 + float(np.linalg.norm(self.b - self.a)) / self.speed

    def path(self, num_steps: int, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(T, 2) positions, (T,) headings and (T,) speeds: standing at a, walking, standing at b."""
        span = self.b - self.a
        length = float(np.linalg.norm(span))
        u = span / max(length, 1e-9)
        walked = self.speed * (np.arange(num_steps) * dt - self.t0)
        xy = self.a + np.outer(np.clip(walked, 0.0, length), u)
        speed = np.where((walked > 0) & (walked < length), self.speed, 0.0)
        return xy, np.full(num_steps, math.atan2(u[1], u[0])), speed


def _crossing_s(grid_xy: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Arc length (on the DS grid) where a route's centreline first crosses segment a-b, inf if never."""
    p, r = grid_xy[:-1], np.diff(grid_xy, axis=0)
    q = b - a
    den = r[:, 0] * q[1] - r[:, 1] * q[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((a[0] - p[:, 0]) * q[1] - (a[1] - p[:, 1]) * q[0]) / den
        w = ((a[0] - p[:, 0]) * r[:, 1] - (a[1] - p[:, 1]) * r[:, 0]) / den
    hit = np.flatnonzero((np.abs(den) > 1e-12) & (t >= 0) & (t <= 1) & (w >= 0) & (w <= 1))
    return float((hit[0] + t[hit[0]]) * DS) if len(hit) else math.inf


def _yield_to_pedestrians(now: float, st: np.ndarray, vt: np.ndarray, half: np.ndarray, s_cross: np.ndarray,
                          window: np.ndarray, g_obs: np.ndarray) -> None:
    """Shorten `g_obs` of each vehicle that must hold short of a crossing active `now` (`window`: (K, 2) s,
    from CROSS_LEAD before the pedestrian sets off to its arrival; see the module docstring)."""
    on = (window[:, 0] <= now) & (now <= window[:, 1])
    if not on.any():
        return
    front = st + half
    line = s_cross[:, on]  # (N, K) inf where the route does not cross
    g = line - CROSS_STOP - front[:, None] + 1.0  # the IDM's obstacle gap: the front rests 1 m short of it
    ok = np.isfinite(line) & (front[:, None] < line - 1.0) & (vt[:, None] ** 2 <= 2 * B_HARD * np.maximum(g - 1.0, 0.0))
    np.minimum(g_obs, np.where(ok, g, np.inf).min(1), out=g_obs)


@dataclass
class Route:
    lanes: tuple[int, ...]
    path: Path
    starts: np.ndarray  # (K + 1,) lane start offsets along the route
    prio: np.ndarray  # (K,) lane priority
    grid_xy: np.ndarray  # (G, 2) at s = DS * i
    grid_yaw: np.ndarray  # (G,) unwrapped
    vcap: np.ndarray  # (G,) curve speed limit with braking ahead

    @property
    def length(self) -> float:
        return self.path.length

    def straight_weight(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(w, dw/ds) at arc lengths s: 1 on straight road at least 1 + LANE_OFFSET_RAMP m from any
        curved piece of the route, 0 on and within 1 m of one, a smoothstep between. A lane offset
        scaled by w therefore changes only where the route is straight."""
        s = np.asarray(s, np.float64)
        pieces = self.path.pieces
        curved = [k for k, p in enumerate(pieces) if p.curv != 0.0]
        if not curved:
            return np.ones_like(s), np.zeros_like(s)
        a = self.path.starts[curved]
        b = a + np.array([pieces[k].length for k in curved])
        before, after = a[None, :] - s[:, None], s[:, None] - b[None, :]
        dist = np.maximum(np.maximum(before, after), 0.0)
        k = np.argmin(dist, 1)
        ar = np.arange(len(s))
        d = dist[ar, k]
        slope = np.where(before[ar, k] > 0, -1.0, np.where(after[ar, k] > 0, 1.0, 0.0))
        x = np.clip((d - 1.0) / LANE_OFFSET_RAMP, 0.0, 1.0)
        return x * x * (3 - 2 * x), 6 * x * (1 - x) / LANE_OFFSET_RAMP * slope

    def prio_at(self, s: float) -> int:
        k = int(np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.lanes) - 1))
        later = self.prio[k:]
        ok = later[later >= 0]
        return int(ok[0]) if len(ok) else 0


class TrafficModel:
    """Routes, lane-pair overlaps and route-pair conflict tables of one map (cached)."""

    def __init__(self, m: RoadMap):
        self.map = m
        self.routes: dict[tuple[int, ...], Route] = {}
        self._pairs: dict[tuple, dict | None] = {}
        self._lane_overlaps = None

    # -- routes
    def route(self, lanes: tuple[int, ...]) -> Route:
        r = self.routes.get(lanes)
        if r is None:
            path = Path([p for lane in lanes for p in self.map.lanes[lane].path.pieces])
            starts = np.concatenate([[0.0], np.cumsum([self.map.lanes[lane].path.length for lane in lanes])])
            g = np.arange(0.0, path.length + DS, DS)
            xy, yaw, curv = path.eval(g)
            yaw = np.unwrap(yaw)
            vc = np.sqrt(LAT_ACC / np.maximum(np.abs(curv), 1e-4))
            # v(s)^2 = min over s' >= s of vc(s')^2 + 2 b (s' - s)
            key = vc ** 2 + 2 * B_CURVE * g
            vcap = np.sqrt(np.minimum.accumulate(key[::-1])[::-1] - 2 * B_CURVE * g)
            prio = np.array([self.map.lanes[lane].prio for lane in lanes])
            r = Route(lanes, path, starts, prio, xy, yaw, vcap)
            self.routes[lanes] = r
        return r

    # -- conflicts
    def lane_overlaps(self) -> dict:
        """{(lane_a, lane_b): (s_a, s_b)} where inflated largest boxes on the two lanes touch."""
        if self._lane_overlaps is not None:
            return self._lane_overlaps
        pts, yaw, curv, lane_of, s_of = [], [], [], [], []
        for i, lane in enumerate(self.map.lanes):
            lo, hi = lane.conflict_range or (0.0, lane.path.length)
            lo, hi = max(0.0, lo), min(lane.path.length, hi)
            s = np.linspace(lo, hi, max(2, int(math.ceil((hi - lo) / DS_ZONE)) + 1))
            xy, h, k = lane.path.eval(s)
            pts.append(xy)
            yaw.append(h)
            curv.append(np.abs(k))
            lane_of.append(np.full(len(s), i))
            s_of.append(s)
        pts, yaw, curv, lane_of, s_of = (np.concatenate(x) for x in (pts, yaw, curv, lane_of, s_of))
        # each sample stands for the poses within DS_ZONE / 2 of it: grow its box to cover them
        h = DS_ZONE / 2  # turning by h * curv swings the box ends sideways; the centre moves h^2 curv / 2
        hl = MAX_LEN / 2 + ZONE_INFLATE + h
        hw = MAX_WID / 2 + ZONE_INFLATE + (hl * h + h * h / 2) * curv
        i, j = self_near_pairs(pts, 2 * math.hypot(hl, hw.max()))
        keep = lane_of[i] != lane_of[j]
        i, j = i[keep], j[keep]
        cos, sin = np.cos(yaw), np.sin(yaw)
        d = pts[j] - pts[i]
        hit = box_box_overlap_cs(d[:, 0], d[:, 1], cos[i], sin[i], hl, hw[i], cos[j], sin[j], hl, hw[j])
        i, j = i[hit], j[hit]
        la, lb = lane_of[i], lane_of[j]
        out: dict = {}
        key = la * len(self.map.lanes) + lb
        order = np.argsort(key, kind="stable")
        key, i, j, la, lb = key[order], i[order], j[order], la[order], lb[order]
        cuts = np.flatnonzero(np.diff(key)) + 1
        for seg in np.split(np.arange(len(key)), cuts):
            if not len(seg):
                continue
            a, b = int(la[seg[0]]), int(lb[seg[0]])
            out[a, b] = (s_of[i[seg]], s_of[j[seg]])
            out[b, a] = (s_of[j[seg]], s_of[i[seg]])
        self._lane_overlaps = out
        return out

    def pair(self, ka: tuple[int, ...], kb: tuple[int, ...]) -> list[dict]:
        """Conflict zones of routes a and b (one per cluster), each with its frontier tables."""
        if (ka, kb) in self._pairs:
            return self._pairs[ka, kb]
        ra, rb = self.route(ka), self.route(kb)
        ov = self.lane_overlaps()
        pos_a = {lane: k for k, lane in enumerate(ka)}
        pos_b = {lane: k for k, lane in enumerate(kb)}
        sa, sb = [], []
        for ia, la in enumerate(ka):
            for ib, lb in enumerate(kb):
                if la == lb:
                    continue
                if la in pos_b and pos_b[la] > ib:  # b follows a along b's route
                    continue
                if lb in pos_a and pos_a[lb] > ia:  # a follows b
                    continue
                o = ov.get((la, lb))
                if o is None:
                    continue
                sa.append(ra.starts[ia] + o[0])
                sb.append(rb.starts[ib] + o[1])
        res = []
        if sa:
            sa, sb = np.concatenate(sa), np.concatenate(sb)
            h = DS_ZONE / 2
            for g in _components(sa, sb, 3.0):
                ga, gb = sa[g], sb[g]
                res.append(dict(
                    za=(float(ga.min()) - h, float(ga.max()) + h), zb=(float(gb.min()) - h, float(gb.max()) + h),
                    b_given_a=_frontier(ga, gb, len(ra.grid_yaw)), a_given_b=_frontier(gb, ga, len(rb.grid_yaw)),
                    prio_a=ra.prio_at(ga.min()), prio_b=rb.prio_at(gb.min())))
        self._pairs[ka, kb] = res
        self._pairs[kb, ka] = [dict(za=c["zb"], zb=c["za"], b_given_a=c["a_given_b"], a_given_b=c["b_given_a"],
                                    prio_a=c["prio_b"], prio_b=c["prio_a"]) for c in res]
        return res


def _components(sa: np.ndarray, sb: np.ndarray, gap: float) -> list[np.ndarray]:
    """Split conflict samples into clusters separated by more than `gap` along s_a or s_b."""
    groups = [np.arange(len(sa))]
    for _ in range(2):
        for key in (sa, sb):
            out = []
            for g in groups:
                o = g[np.argsort(key[g], kind="stable")]
                out += np.split(o, np.flatnonzero(np.diff(key[o]) > gap) + 1)
            groups = out
    return groups


def _frontier(s_win: np.ndarray, s_lose: np.ndarray, n: int) -> np.ndarray:
    """f[i]: smallest loser position that may conflict with a winner at or beyond i * DS.

    Zone samples stand for DS_ZONE / 2 either side: a winner sample counts from
    the row where its reach ends, and a loser sample starts that much earlier.
    """
    h = DS_ZONE / 2
    best = np.full(n, np.inf)
    np.minimum.at(best, np.clip(np.floor((s_win + h) / DS).astype(np.int64), 0, n - 1), s_lose - h)
    return np.minimum.accumulate(best[::-1])[::-1]


def _ramp(s: np.ndarray, start: float, length: float, off: float) -> tuple[np.ndarray, np.ndarray]:
    """(offset, its derivative along s) of a smoothstep from 0 at `start` to `off` at `start + length`,
    `off` beyond; zero everywhere when `start` is not finite (no ramp)."""
    if not np.isfinite(start):
        return np.zeros_like(s), np.zeros_like(s)
    x = np.clip((s - start) / length, 0.0, 1.0)
    return off * x * x * (3 - 2 * x), off * 6 * x * (1 - x) / length


# ----------------------------------------------------------------------------- vehicles
@dataclass
class Vehicles:
    """Per-vehicle arrays, in spawn order (nearest to the conflict first)."""

    routes: list[tuple[int, ...]]
    s0: np.ndarray  # m, initial arc length on the route
    v0: np.ndarray  # m/s, initial speed
    v_des: np.ndarray  # m/s, desired speed
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray
    headway: np.ndarray  # s
    min_gap: np.ndarray  # m
    a_max: np.ndarray  # m/s^2
    b_comf: np.ndarray  # m/s^2
    # kerb stops (`plan_kerb_stops`): the vehicle ends its trip parked beside its lane, stopping with its
    # centre at route arc length stop_s after moving kerb_off m to the right over the last ramp_len m
    stop_s: np.ndarray | None = None  # m, inf: drives on to its route's end
    ramp_len: np.ndarray | None = None  # m
    kerb_off: np.ndarray | None = None  # m
    # lane offset (`plan_lane_offsets`): the vehicle drives bias m to the right of the lane centre
    # (negative: left) wherever its route is straight, back on the centre through curves
    bias: np.ndarray | None = None  # m
    # lane change (`plan_lane_changes`): on its route's last lane, which runs straight, the vehicle moves
    # change_off m to the right (negative: left) over change_len m from route arc length change_s, onto
    # the parallel lane change_lane, and keeps to it
    change_s: np.ndarray | None = None  # m, inf: no lane change
    change_len: np.ndarray | None = None  # m
    change_off: np.ndarray | None = None  # m
    change_lane: np.ndarray | None = None  # lane index, -1: none
    # a start from rest (`spawn(rest_front=...)`): the vehicle stands at its stop line until hold_t s, as a
    # driver makes a full stop before pulling into the junction, then gives way as every vehicle does
    hold_t: np.ndarray | None = None  # s, 0: no hold

    def __post_init__(self):
        n = len(self.routes)
        if self.hold_t is None:
            self.hold_t = np.zeros(n)
        if self.bias is None:
            self.bias = np.zeros(n)
        if self.stop_s is None:
            self.stop_s = np.full(n, np.inf)
        if self.ramp_len is None:
            self.ramp_len = np.ones(n)
        if self.kerb_off is None:
            self.kerb_off = np.zeros(n)
        if self.change_s is None:
            self.change_s = np.full(n, np.inf)
        if self.change_len is None:
            self.change_len = np.ones(n)
        if self.change_off is None:
            self.change_off = np.zeros(n)
        if self.change_lane is None:
            self.change_lane = np.full(n, -1, np.int64)

    def __len__(self):
        return len(self.routes)

    def subset(self, keep: np.ndarray) -> "Vehicles":
        idx = np.flatnonzero(keep)
        return Vehicles([self.routes[i] for i in idx], *(getattr(self, f)[idx] for f in (
            "s0", "v0", "v_des", "length", "width", "height", "headway", "min_gap", "a_max", "b_comf",
            "stop_s", "ramp_len", "kerb_off", "bias", "change_s", "change_len", "change_off", "change_lane",
            "hold_t")))

    def kerb_lateral(self, i: int, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset to the right of the lane centre, its derivative along s) of vehicle i's kerb stop at
        route arc lengths s: a smoothstep from 0 to kerb_off over the ramp before stop_s (zero without)."""
        return _ramp(s, self.stop_s[i] - self.ramp_len[i], self.ramp_len[i], self.kerb_off[i])

    def change_lateral(self, i: int, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(offset to the right of the lane centre, its derivative along s) of vehicle i's lane change
        at route arc lengths s: a smoothstep from 0 to change_off over change_len m from change_s, then
        change_off (zero without)."""
        return _ramp(s, self.change_s[i], self.change_len[i], self.change_off[i])

    def lateral(self, i: int, s: np.ndarray, route: Route) -> tuple[np.ndarray, np.ndarray]:
        """Vehicle i's whole offset to the right of its lane centre and its derivative along s: the
        lane offset (on straight road) plus the kerb stop and the lane change. All change only where
        the route is straight, so the path's curvature is d'' there and the lane's own elsewhere."""
        d, dd = self.kerb_lateral(i, s)
        c, dc = self.change_lateral(i, s)
        d, dd = d + c, dd + dc
        if self.bias[i]:
            w, dw = route.straight_weight(s)
            d, dd = d + self.bias[i] * w, dd + self.bias[i] * dw
        return d, dd

    def out_of_lane_s(self) -> np.ndarray:
        """(N,) route s beyond which a vehicle has left its lane for the kerb or for the next lane
        (offset past its width plus the check margins): followers no longer queue behind it. inf
        for those that keep their lane."""
        kerb = np.isfinite(self.stop_s) & (self.kerb_off > 0)
        change = np.isfinite(self.change_s) & (self.change_off != 0)
        off = np.where(kerb, self.kerb_off, np.abs(self.change_off))
        start = np.where(kerb, self.stop_s - self.ramp_len, self.change_s)
        length = np.where(kerb, self.ramp_len, self.change_len)
        frac = np.clip((self.width + 2 * CHECK_MARGIN) / np.maximum(off, 1e-6), 0.0, 1.0)
        # smoothstep^-1 of frac (x = 1/2 - sin(asin(1 - 2 frac) / 3))
        x = 0.5 - np.sin(np.arcsin(1.0 - 2.0 * frac) / 3.0)
        return np.where(kerb | change, start + length * x, np.inf)


def spawn(tm: TrafficModel, rng: np.random.Generator, *, density: float, speed_mean: float,
          speed_std: float, spawn_range: float, headway: float, min_gap: float, a_max: float,
          b_comf: float, max_vehicles: int, rest_front: float = 0.0,
          rest_rng: np.random.Generator | None = None) -> Vehicles:
    """Queue vehicles upstream of each spawn lane's reference point. With `rest_front` > 0, the front vehicle
    of a yielding approach (a lane of negative priority) stands at rest 0.5-2 m short of its stop line with
    that probability, held there for REST_HOLD s (`Vehicles.hold_t`); `rest_rng` draws those choices, so a
    scene without them draws what it drew before."""
    m = tm.map
    by_lane: dict[int, list[list[int]]] = {}
    for r in m.routes:
        for k, lane in enumerate(r):
            by_lane.setdefault(lane, []).append(r[k:])
    rows = []
    for lane, s_ref, weight in m.spawn:
        cands = by_lane.get(lane, [])
        if not cands:
            continue
        d_front = float(rng.uniform(1.0, 15.0))
        hold = 0.0
        if rest_front > 0 and m.lanes[lane].prio < 0 and rest_rng.random() < rest_front:
            d_front, hold = float(rest_rng.uniform(0.5, 2.0)), float(rest_rng.uniform(*REST_HOLD))
        lane_len = m.lanes[lane].path.length
        ahead_speed, ahead_rear = None, None
        while True:
            L = float(rng.uniform(4.0, 5.5))
            s_c = s_ref - d_front - L / 2
            if d_front > spawn_range or s_c < L / 2 + 1.0 or s_c > lane_len:
                break
            route = tuple(cands[int(rng.integers(len(cands)))])
            v_des = float(np.clip(rng.normal(speed_mean, speed_std), 0.4 * speed_mean, 1.6 * speed_mean + 1))
            v = v_des * float(rng.uniform(0.6, 1.0))
            r = tm.route(route)
            v = min(v, float(np.interp(s_c, np.arange(len(r.vcap)) * DS, r.vcap)))
            if m.lanes[lane].prio < 0:  # approaching a junction: able to stop comfortably
                v = min(v, math.sqrt(2 * 2.5 * max(d_front - 1.0, 0.0)) + 1.0)
            if hold > 0:
                v = 0.0
            if ahead_rear is not None:
                gap = ahead_rear - (s_c + L / 2)
                v = min(v, max(0.0, (gap - min_gap) / headway), ahead_speed + 1.0)
            rows.append((d_front, lane, route, s_c, v, v_des, L, float(rng.uniform(1.8, 2.2)),
                         float(rng.uniform(1.4, 1.9)), headway * float(rng.uniform(0.8, 1.25)),
                         min_gap * float(rng.uniform(0.8, 1.25)), a_max * float(rng.uniform(0.8, 1.2)),
                         b_comf * float(rng.uniform(0.8, 1.2)), hold))
            ahead_speed, ahead_rear, hold = v, s_c - L / 2, 0.0
            gap = min_gap + headway * v + float(rng.exponential(25.0 / max(density * weight, 1e-3)))
            d_front += L + gap
    rows.sort(key=lambda r: (r[0], r[1]))
    rows = rows[:max_vehicles]
    if not rows:
        return Vehicles([], *(np.zeros(0) for _ in range(10)))
    cols = list(zip(*rows))
    return Vehicles(list(cols[2]), *(np.array(c, np.float64) for c in cols[3:13]), hold_t=np.array(cols[13]))


# (share, m) of the lengths of vehicles drawn long (vans and pickups, trucks, buses), and their widths: the real
# WOMD candidates longer than 5.5 m (8 % of the 44 dev training scenes', 33 vehicles) have percentiles
# 50 / 75 / 95 of 5.9 / 7.6 / 11.9 m; these bands give 6.1 / 7.9 / 11.9 m
LONG_LENGTH = ((0.60, (5.5, 6.2)), (0.25, (6.2, 9.0)), (0.12, (9.0, 12.5)), (0.03, (12.5, 14.0)))
LONG_WIDTH = (2.0, 2.6)


def draw_banded(rng: np.random.Generator, bands, rest: tuple[float, float]) -> float:
    """A value uniform in one of `bands` ((share, (lo, hi)), ...), each picked with its share, else
    uniform in `rest` (lo, hi): one draw to pick, one for the value."""
    u = float(rng.random())
    for share, band in bands:
        if u < share:
            return float(rng.uniform(*band))
        u -= share
    return float(rng.uniform(*rest))


def plan_long_vehicles(tm: TrafficModel, veh: Vehicles, rng: np.random.Generator, share: float) -> None:
    """Each vehicle becomes a van, a truck or a bus with probability `share` (LONG_LENGTH, LONG_WIDTH); in
    place. It keeps its size where the longer box would touch another vehicle's at its start (with the
    final check's margin) or sweep a curb anywhere along its route from there. The conflict zones stay
    sized for MAX_LEN boxes, so the drive's overlap check (`settle`) drops any pair that still meets."""
    if share <= 0 or not len(veh):
        return
    segs = tm.map.curb_segments()
    routes = [tm.route(r) for r in veh.routes]
    at = [min(int(round(s / DS)), len(r.grid_yaw) - 1) for r, s in zip(routes, veh.s0)]
    xy0 = np.array([r.grid_xy[k] for r, k in zip(routes, at)])[:, None]
    yaw0 = np.array([r.grid_yaw[k] for r, k in zip(routes, at)])[:, None]
    for i in range(len(veh)):
        if rng.random() >= share:
            continue
        L = draw_banded(rng, LONG_LENGTH[:-1], LONG_LENGTH[-1][1])
        W = float(rng.uniform(*LONG_WIDTH))
        r, k = routes[i], at[i]
        if tm.map.curb_hits(r.grid_xy[k:], r.grid_yaw[k:], L / 2 + SWEEP_INFLATE, W / 2 + SWEEP_INFLATE, segs).any():
            continue
        length, width = veh.length.copy(), veh.width.copy()
        length[i], width[i] = L, W
        if overlapping_pairs(xy0, yaw0, length, width, of=i):
            continue
        veh.length[i], veh.width[i] = L, W


LANE_OFFSET_RAMP = 6.0  # m over which a lane offset fades in after a curve and out before one
LANE_OFFSET_CLEAR = 0.25  # m a biased box keeps from its lane's edge


def _offset_room(veh: Vehicles, lane_width: float) -> np.ndarray:
    """(N,) m each vehicle may drive off its lane centre with its box LANE_OFFSET_CLEAR inside the lane."""
    return np.maximum(lane_width / 2 - veh.width / 2 - LANE_OFFSET_CLEAR, 0.0)


def plan_lane_offsets(veh: Vehicles, rng: np.random.Generator, sigma: float, lane_width: float) -> None:
    """Each vehicle drives off its lane centre by N(0, sigma) m (clipped so its box keeps
    LANE_OFFSET_CLEAR from the lane's edges), as logged drivers do; in place."""
    if sigma <= 0:
        return
    room = _offset_room(veh, lane_width)
    veh.bias[:] = np.clip(rng.normal(0.0, sigma, len(veh)), -room, room)


def plan_park_clearance(tm: TrafficModel, veh: Vehicles, rng: np.random.Generator, lane_width: float) -> None:
    """Each vehicle whose route runs along a lane beside a parking strip keeps left of the lane
    centre, away from the parked cars, by U(0.5, 1) x its room (the lane offset's bound), as drivers
    give room to cars parked over the lane edge; in place (it replaces the vehicle's lane offset)."""
    beside = {st.lane for st in tm.map.strips if st.lane >= 0}
    room = _offset_room(veh, lane_width)
    for i, lanes in enumerate(veh.routes):
        if beside.intersection(lanes):
            veh.bias[i] = -room[i] * float(rng.uniform(0.5, 1.0))


KERB_RAMP = (10.0, 16.0)  # m over which a kerb-stopping vehicle moves from its lane into the strip
KERB_REACH = 30.0  # m of strip after the ramp's earliest end where the stop is drawn
KERB_RUNWAY = 12.0  # m a kerb stop lies short of where the vehicle would have got to without it


def plan_kerb_stops(tm: TrafficModel, veh: Vehicles, reach: np.ndarray, rng: np.random.Generator, prob: float,
                    clear: float) -> int:
    """Each vehicle whose route runs along a lane beside a parking strip (before the junction or after
    it) and which drives far enough along it in the episode (`reach`: (N,) route arc length each
    vehicle reached in a drive without stops) ends its trip parked in that strip with probability
    `prob`, as logged drivers pull in at the kerb: the stop is drawn beside the strip, within
    KERB_REACH m of the earliest possible one and at least KERB_RUNWAY m short of `reach` (room to slow
    down); the ramp lies on the lane's straight run, ahead of the vehicle's start; the box keeps `clear`
    m from the kerb. Vehicles drawn are updated in place; returns how many."""
    strips = {st.lane: st for st in tm.map.strips if st.lane >= 0}
    if not strips or prob <= 0:
        return 0
    count = 0
    for i, lanes in enumerate(veh.routes):
        k = next((k for k, lane in enumerate(lanes) if lane in strips), None)
        if k is None or rng.random() >= prob:
            continue
        st = strips[lanes[k]]
        ramp = float(rng.uniform(*KERB_RAMP))
        half = veh.length[i] / 2
        start = tm.route(lanes).starts[k]
        s_a, s_b = sorted((st.lane_s(st.t0), st.lane_s(st.t1)))  # the strip's run along the lane
        lo = max(s_a + 1.0 + ramp, veh.s0[i] - start + 2.0 + ramp)
        hi = min(lo + KERB_REACH, s_b - half - 3.0, reach[i] - start - KERB_RUNWAY)
        if hi <= lo:
            continue
        off = st.half_lane + st.width / 2 + float(rng.uniform(-0.1, 0.1))
        off = _kerb_offset(off, st.half_lane + st.width - clear, ramp, half, veh.width[i] / 2)
        veh.stop_s[i] = start + float(rng.uniform(lo, hi))
        veh.ramp_len[i] = ramp
        veh.kerb_off[i] = off
        veh.bias[i] = 0.0  # the ramp's clearance was worked out from the lane centre
        count += 1
    return count


LANE_CHANGE_RAMP = (25.0, 40.0)  # m over which a vehicle moves onto the parallel lane
LANE_CHANGE_RUNWAY = 5.0  # m the change's DONE point lies short of where the vehicle gets to in the episode
LANE_CHANGE_DONE = 0.6  # share of the ramp the vehicle covers at least: an episode may end mid-change
PARALLEL_TOL = 0.3  # m a point shifted by one lane width may lie from the parallel lane's centre line


def parallel_lane(m: RoadMap, route: Route, s: np.ndarray, off: float, exclude) -> int:
    """The lane whose centre line runs `off` m to the right of the route (negative: left), in its
    direction, at every route arc length of `s`; -1 if there is none."""
    xy, yaw, _ = route.path.eval(s)
    pts = xy + off * np.stack([np.sin(yaw), -np.cos(yaw)], 1)
    for k, lane in enumerate(m.lanes):
        if k in exclude:
            continue
        lxy, lh, _ = lane.path.sample(0.5)
        d = np.linalg.norm(pts[:, None] - lxy[None], axis=-1)
        j = np.argmin(d, 1)
        if (d[np.arange(len(s)), j] < PARALLEL_TOL).all() and (np.cos(lh[j] - yaw) > math.cos(0.05)).all():
            return k
    return -1


def plan_lane_changes(tm: TrafficModel, veh: Vehicles, reach: np.ndarray, rng: np.random.Generator, prob: float,
                      lane_width: float) -> int:
    """Each vehicle whose route's last lane runs straight beside a parallel lane of the same direction,
    over a stretch it drives in the episode (`reach`: (N,) route arc length each vehicle reached in a
    drive without changes), changes onto that lane with probability `prob`, as logged drivers change
    lanes before their goal: the change starts on that last lane, ahead of the vehicle's start, and
    the vehicle covers at least LANE_CHANGE_DONE of it LANE_CHANGE_RUNWAY m short of `reach` (an
    episode may end mid-change, its goal then lying between the lanes, as logged ones do). A kerb-stopping vehicle keeps its lane. Vehicles drawn are
    updated in place (their lane offset is dropped); returns how many."""
    if prob <= 0:
        return 0
    count = 0
    for i, lanes in enumerate(veh.routes):
        if np.isfinite(veh.stop_s[i]) or rng.random() >= prob:
            continue
        r = tm.route(lanes)
        ramp = float(rng.uniform(*LANE_CHANGE_RAMP))
        side = float(rng.choice((-1.0, 1.0)))
        lo = max(r.starts[-2], veh.s0[i] + 2.0)
        hi = min(reach[i], r.length) - LANE_CHANGE_RUNWAY - LANE_CHANGE_DONE * ramp
        if hi <= lo:
            continue
        start = float(rng.uniform(lo, hi))
        stretch = np.linspace(start, min(reach[i] + 2.0, r.length), 12)
        if (r.straight_weight(stretch)[0] < 1.0).any():
            continue
        for off in (side * lane_width, -side * lane_width):
            k = parallel_lane(tm.map, r, stretch, off, set(lanes))
            if k >= 0:
                veh.change_s[i], veh.change_len[i], veh.change_off[i], veh.change_lane[i] = start, ramp, off, k
                veh.bias[i] = 0.0
                count += 1
                break
    return count


def _kerb_offset(want: float, limit: float, ramp: float, hl: float, hw: float) -> float:
    """The largest final offset <= `want` for which the box (half extents hl, hw) never reaches
    further right than `limit` m from the lane centre along the smoothstep ramp: turned by
    atan(d'), its front corner swings out by hl sin + hw cos of that angle."""
    x = np.linspace(0.0, 1.0, 201)
    shape, slope = x * x * (3 - 2 * x), 6 * x * (1 - x) / ramp

    def reach(d: float) -> float:
        ang = np.arctan(d * slope)
        return float(np.max(d * shape + hl * np.sin(ang) + hw * np.cos(ang)))

    if reach(want) <= limit:
        return want
    lo, hi = 0.0, want
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if reach(mid) <= limit else (lo, mid)
    return lo


# ----------------------------------------------------------------------------- drive
@dataclass
class TrafficLog:
    s: np.ndarray  # (N, T) m along the route
    v: np.ndarray  # (N, T) m/s
    xy: np.ndarray  # (N, T, 2)
    yaw: np.ndarray  # (N, T)


def _decide(state, lock, t, live, da, db, sa, sb, va, vb, za1, zb1, pra, prb, room_a, room_b, acc4, vdes4,
            blk_a, blk_b, com_a, com_b, tk_a, tk_b):
    """Order the live conflict pairs: who goes first (1: a, 2: b).

    A vehicle in its zone goes first, then one past its stop line (for a zone
    of that junction). Otherwise the priority road
    goes first unless the minor vehicle clears the zone GAP_ACCEPT seconds
    before the major one arrives; equal priorities go first come first served
    by ticket (the time each vehicle expected to reach its stop line when it
    first came near): one order for all pairs, so no waiting cycles.
    A first-mover that has crawled for 2 s (held up elsewhere) loses its claim,
    which breaks waiting cycles. A decision changes only while neither vehicle
    is in its zone, and only if the new second can still stop comfortably
    (undecided pairs: with hard braking).
    """
    m = len(da)
    dist = np.maximum(np.concatenate([da, db, za1 - sa, zb1 - sb]), 0.0)
    ea, eb, ca, cb = _travel_time(dist, np.concatenate([va, vb, va, vb]), acc4, vdes4).reshape(4, m)
    held_a, held_b = (state == 1) & blk_a, (state == 2) & blk_b
    pa_eff = np.where(held_a, -1, pra)
    pb_eff = np.where(held_b, -1, prb)
    ea = ea + 10.0 * held_a
    eb = eb + 10.0 * held_b
    fcfs = tk_a + 10.0 * held_a <= tk_b + 10.0 * held_b
    a_first = np.where(pa_eff > pb_eff, ~(cb + GAP_ACCEPT < ea),
                       np.where(pa_eff < pb_eff, ca + GAP_ACCEPT < eb, fcfs))
    # physically in the zone beats committed (past the stop line) beats the rules above
    in_a, in_b = da <= 0, db <= 0
    a_first = np.where(com_a & ~com_b, True, np.where(com_b & ~com_a, False, a_first))
    a_first = np.where(in_a & ~in_b, True, np.where(in_b & ~in_a, False, np.where(in_a & in_b, da <= db, a_first)))
    want = np.where(a_first, 1, 2).astype(np.int8)
    new = state.copy()
    und = live & (state == 0)
    if und.any():
        can_b = vb ** 2 <= 2 * B_HARD * np.maximum(room_b - 1.0, 0.0)
        can_a = va ** 2 <= 2 * B_HARD * np.maximum(room_a - 1.0, 0.0)
        w = np.where((want == 1) & ~can_b & can_a, 2, np.where((want == 2) & ~can_a & can_b, 1, want))
        new[und] = w[und]
    flip = live & (state > 0) & (state < 3) & (want != state) & ~com_a & ~com_b & (lock <= t)
    if flip.any():
        comf_b = vb ** 2 <= 2 * 2.5 * np.maximum(room_b - 1.0, 0.0)
        comf_a = va ** 2 <= 2 * 2.5 * np.maximum(room_a - 1.0, 0.0)
        flip &= np.where(want == 1, comf_b, comf_a)
        new[flip] = want[flip]
        lock[flip & (held_a | held_b)] = t + 30  # a broken cycle stays broken for 3 s
    return new


def _travel_time(d, v, a, vmax):
    """s to cover d metres from speed v accelerating at a up to vmax."""
    vmax = np.maximum(vmax, v)
    t_acc = (vmax - v) / a
    d_acc = 0.5 * (v + vmax) * t_acc
    t1 = (np.sqrt(v * v + 2 * a * d) - v) / a
    t2 = t_acc + (d - d_acc) / np.maximum(vmax, 0.1)
    return np.where(d <= d_acc, t1, t2)


@dataclass
class _RouteTables:
    """Per-vehicle look-ups of the routes that `drive` reads every step."""

    routes: list[Route]
    kmax: int  # the most lanes on one route
    bounds: np.ndarray  # (N, kmax + 1) m, route arc length where each lane starts (inf past the last)
    lane_ids: np.ndarray  # (N, kmax) lane of each route position (the last lane repeated)
    off_tab: np.ndarray  # (N, lanes) m, route arc length where each lane starts, NaN off the route
    rlen: np.ndarray  # (N,) m, route lengths
    vcap_all: np.ndarray  # the routes' curve speed caps on the DS grid, back to back
    vcap_off: np.ndarray  # (N,) first entry of each route in vcap_all
    vcap_last: np.ndarray  # (N,) last entry of each route in vcap_all
    stop_s: np.ndarray  # (N,) m, junction entry (stop line), -inf without one
    lim_s: np.ndarray  # (N,) m, end of the first junction lane, -inf without one

    @property
    def ends(self) -> np.ndarray:
        return self.bounds[:, 1:]


def _route_tables(tm: TrafficModel, veh: Vehicles) -> _RouteTables:
    """The route look-ups of the vehicles `veh`."""
    n = len(veh)
    routes = [tm.route(k) for k in veh.routes]
    n_lanes = len(tm.map.lanes)
    kmax = max(len(r.lanes) for r in routes)
    bounds = np.full((n, kmax + 1), np.inf)
    lane_ids = np.zeros((n, kmax), np.int64)
    off_tab = np.full((n, n_lanes), np.nan)
    for i, r in enumerate(routes):
        k = len(r.lanes)
        bounds[i, : k + 1] = r.starts
        lane_ids[i, :k] = r.lanes
        lane_ids[i, k:] = r.lanes[-1]
        off_tab[i, list(r.lanes)] = r.starts[:-1]
    vcap_off = np.concatenate([[0], np.cumsum([len(r.vcap) for r in routes])])[:-1]
    # junction entry (stop line) of each vehicle and the end of its first junction lane: a vehicle that
    # must give way in a zone before that end waits at the stop line rather than inside the junction
    stop_s = np.full(n, -np.inf)
    lim_s = np.full(n, -np.inf)
    for i, r in enumerate(routes):
        jl = np.flatnonzero(r.prio >= 0)
        if len(jl) and jl[0] > 0:
            stop_s[i], lim_s[i] = r.starts[jl[0]], r.starts[jl[0] + 1]
    return _RouteTables(routes, kmax, bounds, lane_ids, off_tab, np.array([r.length for r in routes]),
                        np.concatenate([r.vcap for r in routes]), vcap_off,
                        vcap_off + np.array([len(r.vcap) for r in routes]) - 1, stop_s, lim_s)


@dataclass
class _Conflicts:
    """One entry per conflict zone of each vehicle pair (a, b): the zone tables and the pair's decision."""

    pa: np.ndarray  # (M,) vehicle a
    pb: np.ndarray  # (M,) vehicle b
    flat: np.ndarray  # the frontier tables, back to back: b's (given a's position), then a's, per pair
    tb_off: np.ndarray
    ta_off: np.ndarray
    tb_last: np.ndarray
    ta_last: np.ndarray
    za0: np.ndarray  # m, zone entry and exit along a's route, then b's
    za1: np.ndarray
    zb0: np.ndarray
    zb1: np.ndarray
    pra: np.ndarray  # movement priorities
    prb: np.ndarray
    acc4: np.ndarray  # (4M,) accelerations and desired speeds of a, b, a, b for `_decide`
    vdes4: np.ndarray
    jz_a: np.ndarray  # the zone lies before the end of the vehicle's first junction lane
    jz_b: np.ndarray
    stop_a: np.ndarray  # m, the vehicles' stop lines
    stop_b: np.ndarray
    state: np.ndarray  # (M,) int8: 0 undecided, 1 a first, 2 b first, 3 done
    lock: np.ndarray  # (M,) no re-evaluation before this step


def _conflict_tables(tm: TrafficModel, veh: Vehicles, rt: _RouteTables) -> _Conflicts | None:
    """The conflict zones of every pair of vehicles on different routes; None when there are none."""
    n = len(veh)
    pa, pb, tabs, meta = [], [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            if veh.routes[i] == veh.routes[j]:
                continue
            for c in tm.pair(veh.routes[i], veh.routes[j]):
                pa.append(i)
                pb.append(j)
                tabs.append((c["b_given_a"], c["a_given_b"]))
                meta.append((*c["za"], *c["zb"], c["prio_a"], c["prio_b"]))
    if not pa:
        return None
    pa, pb = np.array(pa, np.int64), np.array(pb, np.int64)
    flat = np.concatenate([x for t in tabs for x in t])
    sizes = np.array([len(x) for t in tabs for x in t])
    offs = np.concatenate([[0], np.cumsum(sizes)])[:-1]
    tb_off, ta_off = offs[0::2], offs[1::2]
    za0, za1, zb0, zb1, pra, prb = np.array(meta).T
    a_max, v_des = veh.a_max, veh.v_des
    return _Conflicts(pa, pb, flat, tb_off, ta_off, tb_off + sizes[0::2] - 1, ta_off + sizes[1::2] - 1,
                      za0, za1, zb0, zb1, pra, prb,
                      np.concatenate([a_max[pa], a_max[pb], a_max[pa], a_max[pb]]),
                      np.concatenate([v_des[pa], v_des[pb], v_des[pa], v_des[pb]]),
                      za0 < rt.lim_s[pa], zb0 < rt.lim_s[pb], rt.stop_s[pa], rt.stop_s[pb],
                      np.zeros(len(pa), np.int8), np.zeros(len(pa), np.int64))


def _leader_gap(rt: _RouteTables, st: np.ndarray, vt: np.ndarray, halfsum: np.ndarray,
                gone_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gap to and speed difference with each vehicle's leader: the nearest vehicle ahead whose lane
    lies on its route (inf gap without one)."""
    ar = np.arange(len(st))
    k = np.minimum((st[:, None] >= rt.ends).sum(1), rt.kmax - 1)
    ls = st - rt.bounds[ar, k]
    pos = rt.off_tab[:, rt.lane_ids[ar, k]] + ls[None, :]
    with np.errstate(invalid="ignore"):
        gap = np.where((pos > st[:, None]) & (st < gone_s)[None, :], pos - st[:, None] - halfsum, np.inf)
    j = np.argmin(gap, 1)
    return gap[ar, j], vt - vt[j]


def _give_way(cf: _Conflicts, t: int, st: np.ndarray, vt: np.ndarray, ticket: np.ndarray, slow: np.ndarray,
              half: np.ndarray, g_obs: np.ndarray, hold_at_stop_line: bool) -> None:
    """Step t of the conflict pairs: decide who goes first (every 0.2 s) and shorten `g_obs` of each
    second vehicle to the frontier the first one leaves free (or its stop line, `hold_at_stop_line`)."""
    pa, pb = cf.pa, cf.pb
    sa, sb, va, vb = st[pa], st[pb], vt[pa], vt[pb]
    room_b = cf.flat[np.minimum(cf.tb_off + (sa / DS).astype(np.int64), cf.tb_last)] - sb  # if a goes first
    room_a = cf.flat[np.minimum(cf.ta_off + (sb / DS).astype(np.int64), cf.ta_last)] - sa
    cf.state[(sa > cf.za1) | (sb > cf.zb1)] = 3
    da, db = cf.za0 - sa, cf.zb0 - sb
    live = (cf.state < 3) & ((da < 30 + 3 * va) | (db < 30 + 3 * vb))
    if t % 2 == 0 and live.any():  # drivers re-assess every 0.2 s
        cf.state = _decide(cf.state, cf.lock, t, live, da, db, sa, sb, va, vb, cf.za1, cf.zb1, cf.pra, cf.prb,
                           room_a, room_b, cf.acc4, cf.vdes4, slow[pa] > 2.0, slow[pb] > 2.0,
                           (da <= 0) | (cf.jz_a & (sa > cf.stop_a + 0.5)),
                           (db <= 0) | (cf.jz_b & (sb > cf.stop_b + 0.5)),
                           ticket[pa] + 1e-6 * pa, ticket[pb] + 1e-6 * pb)
    lose_b, lose_a = cf.state == 1, cf.state == 2
    gb, ga = room_b - 0.3, room_a - 0.3
    if hold_at_stop_line:
        hold_b, hold_a = cf.stop_b - sb - half[pb], cf.stop_a - sa - half[pa]
        ok_b = cf.jz_b & (vb * vb <= 2 * B_HARD * np.maximum(hold_b - 1.0, 0.0))
        ok_a = cf.jz_a & (va * va <= 2 * B_HARD * np.maximum(hold_a - 1.0, 0.0))
        gb = np.where(ok_b, np.minimum(gb, hold_b), gb)
        ga = np.where(ok_a, np.minimum(ga, hold_a), ga)
    np.minimum.at(g_obs, pb[lose_b], gb[lose_b])
    np.minimum.at(g_obs, pa[lose_a], ga[lose_a])


def _acceleration(veh: Vehicles, rt: _RouteTables, st: np.ndarray, vt: np.ndarray, dv: np.ndarray,
                  g_lead: np.ndarray, g_obs: np.ndarray, a_prev: np.ndarray, sqrt_ab: np.ndarray) -> np.ndarray:
    """IDM against the leader and the nearest standing obstacle, capped by the curve speed, with
    jerk limits and the hard bounds."""
    ss_lead = veh.min_gap + np.maximum(0.0, vt * veh.headway + vt * dv / sqrt_ab)
    ss_obs = 1.0 + np.maximum(0.0, 0.5 * vt * veh.headway + vt * vt / sqrt_ab)
    inter = np.maximum((ss_lead / np.maximum(g_lead, 0.05)) ** 2, (ss_obs / np.maximum(g_obs, 0.05)) ** 2)
    a_idm = veh.a_max * (1.0 - (vt / veh.v_des) ** 4 - inter)
    a_curve = 1.5 * (rt.vcap_all[np.minimum(rt.vcap_off + (st / DS).astype(np.int64), rt.vcap_last)] - vt)
    a_t = np.minimum(a_idm, a_curve)
    a = np.minimum(a_t, a_prev + 0.4)  # jerk limit when speeding up
    a = np.where(a_t > -2.0, np.maximum(a, a_prev - 1.0), a)  # soften mild braking onsets
    return np.minimum(np.maximum(a, A_MIN), A_MAX_HARD)


def _poses(routes: list[Route], veh: Vehicles, s: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xy, yaw) of every vehicle at its arc lengths `s`, moved sideways by its lateral plan; the
    speeds `v` of those that move sideways are scaled in place to their path's."""
    n, num_steps = s.shape
    xy = np.empty((n, num_steps, 2))
    yaw = np.empty((n, num_steps))
    for i, r in enumerate(routes):
        g = np.arange(len(r.grid_yaw)) * DS
        xy[i, :, 0] = np.interp(s[i], g, r.grid_xy[:, 0])
        xy[i, :, 1] = np.interp(s[i], g, r.grid_xy[:, 1])
        yaw[i] = np.interp(s[i], g, r.grid_yaw)
        if np.isfinite(veh.stop_s[i]) or np.isfinite(veh.change_s[i]) or veh.bias[i]:
            # kerb ramps, lane changes and lane offsets change only on straight road (`Vehicles.lateral`): the path
            # is the lane offset d(s) to the right, its heading turned by atan(d'), its speed scaled
            # by sqrt(1 + d'^2)
            d, dd = veh.lateral(i, s[i], r)
            xy[i, :, 0] += d * np.sin(yaw[i])
            xy[i, :, 1] -= d * np.cos(yaw[i])
            yaw[i] -= np.arctan(dd)
            v[i] *= np.sqrt(1.0 + dd * dd)
    return xy, yaw


def drive(tm: TrafficModel, veh: Vehicles, num_steps: int, dt: float, hold_at_stop_line: bool = False,
          crossings: tuple[Crossing, ...] = ()) -> TrafficLog:
    """Integrate every vehicle along its route; see the module docstring for the rules.
    `hold_at_stop_line`: a vehicle that must give way waits at its stop line, not at the zone;
    `crossings`: pedestrians the vehicles yield to."""
    n = len(veh)
    rt = _route_tables(tm, veh)
    cf = _conflict_tables(tm, veh, rt)
    half = veh.length / 2
    halfsum = half[:, None] + half[None, :]
    # a kerb-stopping vehicle meets its stop as the IDM's standing obstacle (its centre comes to rest
    # about at stop_s) and stops leading its followers once it is out of their lane
    s_end = np.minimum(rt.rlen, veh.stop_s + half - 1.0)
    gone_s = veh.out_of_lane_s()
    a_max, v_des = veh.a_max, veh.v_des
    sqrt_ab = 2 * np.sqrt(veh.a_max * veh.b_comf)
    s = np.empty((n, num_steps))
    v = np.empty((n, num_steps))
    s[:, 0], v[:, 0] = veh.s0, veh.v0
    a_prev = np.zeros(n)
    slow = np.zeros(n)  # s spent below 1 m/s
    ticket = np.full(n, np.inf)
    if crossings:  # where each route crosses each pedestrian's path, and when each crossing is active
        s_cross = np.array([[_crossing_s(r.grid_xy, c.a, c.b) for c in crossings] for r in rt.routes])
        window = np.array([(c.t0 - CROSS_LEAD, c.t_off) for c in crossings])
    for t in range(num_steps - 1):
        st, vt = s[:, t], v[:, t]
        g_lead, dv = _leader_gap(rt, st, vt, halfsum, gone_s)
        g_obs = s_end - st - half + 2.0  # the route end (or the kerb stop) stands in the way
        to_stop = np.maximum(rt.stop_s - st, 0.0)
        near = np.isinf(ticket) & (to_stop < 30.0 + 3.0 * vt)
        if near.any():
            ticket[near] = t * dt + _travel_time(to_stop[near], vt[near], a_max[near], v_des[near])
        if cf is not None:
            _give_way(cf, t, st, vt, ticket, slow, half, g_obs, hold_at_stop_line)
        if crossings:
            _yield_to_pedestrians(t * dt, st, vt, half, s_cross, window, g_obs)
        a = _acceleration(veh, rt, st, vt, dv, g_lead, g_obs, a_prev, sqrt_ab)
        a = np.where(t * dt < veh.hold_t, np.minimum(a, 0.0), a)  # a start from rest: still at its stop line
        vn = np.maximum(vt + a * dt, 0.0)
        a_prev = (vn - vt) / dt
        v[:, t + 1] = vn
        s[:, t + 1] = np.minimum(st + 0.5 * (vt + vn) * dt, rt.rlen)
        slow = np.where(vn < 1.0, slow + dt, 0.0)
    xy, yaw = _poses(rt.routes, veh, s, v)
    return TrafficLog(s, v, xy, yaw)


def overlapping_pairs(xy, yaw, length, width, margin=CHECK_MARGIN, of: int | None = None) -> list[tuple[int, int, int]]:
    """(step, i, j) with i < j for every pair of boxes that touch (inflated by margin); with `of`, only the
    pairs that include box `of` (one new box against the rest, without re-testing the rest)."""
    n, t = yaw.shape
    if n < 2:
        return []
    if of is None:
        i, j = np.triu_indices(n, 1)
    else:
        other = np.delete(np.arange(n), of)
        i, j = np.minimum(other, of), np.maximum(other, of)
    rad = np.hypot(length / 2 + margin, width / 2 + margin)
    d = np.linalg.norm(xy[i] - xy[j], axis=-1)  # (P, T)
    pi, ti = np.nonzero(d < (rad[i] + rad[j])[:, None])
    if not len(pi):
        return []
    ii, jj = i[pi], j[pi]
    hit = box_box_overlap(xy[ii, ti], yaw[ii, ti], length[ii] / 2 + margin, width[ii] / 2 + margin,
                          xy[jj, ti], yaw[jj, ti], length[jj] / 2 + margin, width[jj] / 2 + margin)
    return sorted(zip(ti[hit].tolist(), ii[hit].tolist(), jj[hit].tolist()))


def settle(tm: TrafficModel, veh: Vehicles, num_steps: int, dt: float, min_keep: int = 2,
           hold_at_stop_line: bool = False, crossings: tuple[Crossing, ...] = ()):
    """Roll out, drop offending vehicles, repeat until no box overlap and everyone moves."""
    dropped = []
    while True:
        ro = drive(tm, veh, num_steps, dt, hold_at_stop_line, crossings)
        bad = np.zeros(len(veh), bool)
        for _, i, j in overlapping_pairs(ro.xy, ro.yaw, veh.length, veh.width):
            if not bad[i] and not bad[j]:
                bad[j] = True  # the later-spawned of the pair
        if not bad.any():
            ref = min(10, num_steps - 1)
            bad = ro.s[:, -1] - ro.s[:, ref] < MIN_MOVE_AFTER_10 * (num_steps - 1 - ref) / 80.0
        if not bad.any():
            return veh, ro, dropped
        if len(veh) - bad.sum() < min_keep:
            return None, None, dropped
        dropped.extend(np.flatnonzero(bad).tolist())
        veh = veh.subset(~bad)
