"""Road geometry of the procedural scenario generator.

Paths are chains of straight and circular pieces, evaluated exactly (position,
heading, curvature) at any arc length; lanes, curbs and road lines are paths.
The map builders here turn a few random draws into a `RoadMap` (lanes, lane
graph, routes, curbs, road lines, crosswalks, spawn lanes) in a canonical frame
whose origin is the conflict point. They check their own output: every lane is
swept with the largest vehicle box against the curbs, and a builder that cannot
meet that (or the minimum turn radius) raises `GeometryError` so the caller can
draw again. Nothing here knows about vehicles' motion; see traffic.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tg_gpudrive.data.procedural.checks import box_segment_overlap, near_pairs

R_MIN = 6.5  # m, smallest lane radius: curvature 0.154 < 0.25 leaves room for interpolation
MAX_LEN, MAX_WID = 5.5, 2.2  # m, largest vehicle box the lanes must carry
SWEEP_INFLATE = 0.15  # m added to each half extent when sweeping lanes against curbs
POINT_SPACING = 1.0  # m between exported polyline points
# Kerbside parking (junction arms only): a strip between the outer lane and the kerb, as on the urban
# streets of WOMD, where most vehicles of a scene are parked 2-2.5 m from the nearest lane centre.
PARK_WIDTH = (2.3, 2.7)  # m, strip width drawn per kerb side; the widest car (2.2 m) fits with room
PARK_TAPER = 5.0  # m along the arm over which the kerb steps out from the lane edge to the strip
PARK_MIN_CORNER = math.radians(60)  # no strip on a side whose corner is tighter: strips would meet


class GeometryError(RuntimeError):
    """These random draws gave an unusable map; draw again."""


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ----------------------------------------------------------------------------- paths
@dataclass(frozen=True)
class Piece:
    """A straight (curv 0) or circular piece starting at (x, y) with heading h."""

    x: float
    y: float
    h: float
    length: float
    curv: float = 0.0

    def end(self) -> tuple[float, float, float]:
        L, k = self.length, self.curv
        if k == 0.0:
            return self.x + L * math.cos(self.h), self.y + L * math.sin(self.h), self.h
        h1 = self.h + k * L
        return (self.x + (math.sin(h1) - math.sin(self.h)) / k,
                self.y - (math.cos(h1) - math.cos(self.h)) / k, h1)


class Path:
    """G1 chain of pieces; s is arc length from the start."""

    def __init__(self, pieces: list[Piece]):
        self.pieces = [p for p in pieces if p.length > 1e-9]
        if not self.pieces:
            raise GeometryError("empty path")
        self.starts = np.concatenate([[0.0], np.cumsum([p.length for p in self.pieces])])
        self.length = float(self.starts[-1])

    @classmethod
    def chain(cls, x: float, y: float, h: float, spec: list[tuple[float, float]]) -> "Path":
        """Pieces (length, curvature) laid one after another from pose (x, y, h)."""
        pieces = []
        for length, curv in spec:
            if length <= 1e-9:
                continue
            p = Piece(x, y, h, float(length), float(curv))
            pieces.append(p)
            x, y, h = p.end()
        return cls(pieces)

    def __add__(self, other: "Path") -> "Path":
        return Path(self.pieces + other.pieces)

    @property
    def start(self) -> tuple[float, float, float]:
        p = self.pieces[0]
        return p.x, p.y, p.h

    @property
    def end(self) -> tuple[float, float, float]:
        return self.pieces[-1].end()

    def eval(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xy (K, 2), heading (K,), curvature (K,)) at arc lengths s (clipped to the path)."""
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length)
        idx = np.clip(np.searchsorted(self.starts, s, side="right") - 1, 0, len(self.pieces) - 1)
        xy = np.empty((len(s), 2))
        h = np.empty(len(s))
        k = np.empty(len(s))
        for i, p in enumerate(self.pieces):
            m = idx == i
            if not m.any():
                continue
            u = s[m] - self.starts[i]
            k[m] = p.curv
            if p.curv == 0.0:
                h[m] = p.h
                xy[m, 0] = p.x + u * math.cos(p.h)
                xy[m, 1] = p.y + u * math.sin(p.h)
            else:
                hh = p.h + p.curv * u
                h[m] = hh
                xy[m, 0] = p.x + (np.sin(hh) - math.sin(p.h)) / p.curv
                xy[m, 1] = p.y - (np.cos(hh) - math.cos(p.h)) / p.curv
        return xy, h, k

    def sample(self, ds: float = POINT_SPACING):
        """Evenly spaced samples (spacing <= ds) including both ends: (xy, heading, s)."""
        n = max(2, int(math.ceil(self.length / ds)) + 1)
        s = np.linspace(0.0, self.length, n)
        xy, h, _ = self.eval(s)
        return xy, h, s

    def offset(self, d: float) -> "Path":
        """The parallel path d metres to the left (negative: right)."""
        out = []
        for p in self.pieces:
            scale = 1.0 - p.curv * d
            if scale <= 1e-6:
                raise GeometryError("offset beyond a piece's centre of curvature")
            out.append(Piece(p.x - d * math.sin(p.h), p.y + d * math.cos(p.h), p.h,
                             p.length * scale, p.curv / scale))
        return Path(out)

    def reversed(self) -> "Path":
        out = []
        for p in reversed(self.pieces):
            x, y, h = p.end()
            out.append(Piece(x, y, h + math.pi, p.length, -p.curv))
        return Path(out)


def line(x, y, h, length) -> Path:
    return Path.chain(x, y, h, [(length, 0.0)])


def fillet(p, h_in, q, h_out, r_cap=math.inf, r_min=R_MIN) -> Path | None:
    """Line from p along h_in, circular arc, line into q along h_out (G1).

    The arc has the largest radius (<= r_cap) whose tangent points stay between
    p and q; None when that radius is below r_min or the lines meet behind p
    or beyond q.
    """
    d1 = np.array([math.cos(h_in), math.sin(h_in)])
    d2 = np.array([math.cos(h_out), math.sin(h_out)])
    pq = np.asarray(q, float) - np.asarray(p, float)
    phi = float(wrap(h_out - h_in))
    if abs(phi) < 1e-6:
        cross = d1[0] * pq[1] - d1[1] * pq[0]
        if abs(cross) < 1e-6 and pq @ d1 > 0:
            return line(p[0], p[1], h_in, float(pq @ d1))
        return None
    det = d1[0] * d2[1] - d1[1] * d2[0]
    t1 = (pq[0] * d2[1] - pq[1] * d2[0]) / det
    t2 = (d1[0] * pq[1] - d1[1] * pq[0]) / det
    if t1 < 0 or t2 < 0:
        return None
    tan_half = math.tan(abs(phi) / 2)
    r = min(min(t1, t2) / tan_half, r_cap)
    if r < r_min:
        return None
    tl = r * tan_half
    return Path.chain(p[0], p[1], h_in, [(t1 - tl, 0.0), (r * abs(phi), math.copysign(1.0 / r, phi)),
                                          (t2 - tl, 0.0)])


# ----------------------------------------------------------------------------- map
@dataclass
class Lane:
    path: Path
    prio: int = -1  # -1: approach lane; >= 0 junction lane, higher goes first at conflicts
    conflict_range: tuple[float, float] | None = None  # s-range sampled for conflicts; None: all
    arms: tuple[int, ...] = ()  # arms whose stop distance to grow if this lane fails a check


@dataclass
class RoadMap:
    lanes: list[Lane] = field(default_factory=list)
    edges: list[tuple[int, int]] = field(default_factory=list)
    curbs: list[Path] = field(default_factory=list)
    lines: list[Path] = field(default_factory=list)
    crosswalks: list[np.ndarray] = field(default_factory=list)
    routes: list[list[int]] = field(default_factory=list)
    spawn: list[tuple[int, float, float]] = field(default_factory=list)  # (lane, s_ref, weight)
    strips: list["ParkingStrip"] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def add_lane(self, path: Path, **kw) -> int:
        self.lanes.append(Lane(path, **kw))
        return len(self.lanes) - 1

    def curb_segments(self) -> np.ndarray:
        """(S, 2, 2) curb segments at the exported point spacing."""
        segs = []
        for c in self.curbs:
            xy = c.sample()[0]
            segs.append(np.stack([xy[:-1], xy[1:]], 1))
        return np.concatenate(segs) if segs else np.zeros((0, 2, 2))

    def offroad_lanes(self) -> list[int]:
        """Lanes along which the largest vehicle box (inflated) would touch a curb."""
        segs = self.curb_segments()
        if not len(segs):
            return []
        pts, hs, lane_of = [], [], []
        for i, lane in enumerate(self.lanes):
            path = lane.path
            if len(path.pieces) == 1 and path.pieces[0].curv == 0.0 and path.length > 40.0:
                # straight approach lanes run parallel to their curbs: check only the ends
                s = np.concatenate([np.arange(0.0, 15.0, 0.5), path.length - np.arange(0.0, 15.0, 0.5)])
                xy, h, _ = path.eval(s)
            else:
                xy, h, _ = path.sample(0.5)
            pts.append(xy)
            hs.append(h)
            lane_of.append(np.full(len(xy), i))
        pts, hs, lane_of = np.concatenate(pts), np.concatenate(hs), np.concatenate(lane_of)
        hit = self.curb_hits(pts, hs, MAX_LEN / 2 + SWEEP_INFLATE, MAX_WID / 2 + SWEEP_INFLATE, segs)
        return sorted(set(lane_of[hit].tolist()))

    def curb_hits(self, xy: np.ndarray, heading: np.ndarray, hl, hw, segs: np.ndarray | None = None) -> np.ndarray:
        """(K,) bool: which boxes (centres xy (K, 2), headings, half extents hl, hw: scalars or (K,))
        touch a curb (`segs`: the curb segments, when the caller has them already)."""
        segs = self.curb_segments() if segs is None else segs
        out = np.zeros(len(xy), bool)
        if not len(segs) or not len(xy):
            return out
        hl, hw = np.broadcast_to(hl, (len(xy),)), np.broadcast_to(hw, (len(xy),))
        seg_half = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1).max() / 2
        ib, js = near_pairs(xy, segs.mean(1), float(np.hypot(hl, hw).max()) + seg_half + 1e-3)
        out[ib[box_segment_overlap(xy[ib], heading[ib], hl[ib], hw[ib], segs[js, 0], segs[js, 1])]] = True
        return out


@dataclass(frozen=True)
class ParkingStrip:
    """Kerbside parking along one side of a junction arm, from t0 to t1 m out from the centre.

    Its inner edge (the outer lane's edge) lies at normal offset `side * inner` of the arm, its
    kerb at `side * (inner + width)`; cars parked in it face the traffic of their side. `lane` is
    the outer lane beside it (a straight lane of the arm), `r_stop` the arm's stop-line distance."""

    theta: float  # the arm's outward direction
    side: int  # +1: the inbound side (+normal), -1: the outbound side
    inner: float  # m from the arm's centre line to the strip's inner edge
    width: float  # m
    t0: float
    t1: float
    lane: int
    r_stop: float
    half_lane: float  # m from the lane's centre to the strip's inner edge

    def lane_s(self, t):
        """Arc length along `lane` of the point t m out along the arm."""
        return t - self.r_stop if self.side < 0 else self.t1 - t

    def pose(self, t: float, lateral: float) -> tuple[float, float, float]:
        """(x, y, heading) of a car centred t m out along the arm, `lateral` m from the inner edge."""
        u = np.array([math.cos(self.theta), math.sin(self.theta)])
        n = np.array([-u[1], u[0]])
        xy = t * u + self.side * (self.inner + lateral) * n
        return float(xy[0]), float(xy[1]), float(self.theta + (math.pi if self.side > 0 else 0.0))


# ----------------------------------------------------------------------------- junctions
@dataclass
class Arm:
    theta: float  # outward direction
    n_in: int  # lanes towards the centre (left of the outward direction... on +normal side)
    n_out: int  # lanes away from the centre (on -normal side)
    length: float  # m from the centre to the far end
    major: bool = False  # on the priority road
    r_stop: float = 0.0  # m from the centre to the stop line (junction box boundary)
    park_in: float = 0.0  # m, width of the parking strip on the inbound kerb side (0: none)
    park_out: float = 0.0  # m, the same on the outbound side

    @property
    def u(self):
        return np.array([math.cos(self.theta), math.sin(self.theta)])

    @property
    def n(self):
        return np.array([-math.sin(self.theta), math.cos(self.theta)])

    def point(self, t, off):
        return t * self.u + off * self.n


def _line_t(arm_a: Arm, off_a: float, arm_b: Arm, off_b: float) -> tuple[float, float] | None:
    """Where the lines (off_a on arm a) and (off_b on arm b) cross: (t_a, t_b)."""
    ua, ub = arm_a.u, arm_b.u
    det = ua[0] * ub[1] - ua[1] * ub[0]
    if abs(det) < 1e-9:
        return None
    rhs = off_b * arm_b.n - off_a * arm_a.n  # t_a ua - t_b ub = rhs
    ta = (rhs[0] * (-ub[1]) - rhs[1] * (-ub[0])) / -det
    tb = (ua[0] * rhs[1] - ua[1] * rhs[0]) / -det
    return ta, tb


def _classify(defl: float) -> str:
    if abs(defl) < math.radians(35):
        return "S"
    return "L" if defl > 0 else "R"


def _draw_parking(arms: list[Arm], parking: float, prng: np.random.Generator) -> None:
    """Each kerb side of each arm gets a parking strip with probability `parking` (sides whose
    corner is tighter than PARK_MIN_CORNER excepted). `prng` is the generator's own stream for
    street furniture, so the scene's other draws do not depend on it."""
    na = len(arms)
    for i in range(na):
        a, b = arms[i], arms[(i + 1) % na]
        alpha = float(wrap(b.theta - a.theta)) % (2 * math.pi)
        wide = alpha >= PARK_MIN_CORNER
        if prng.random() < parking and wide:
            a.park_in = float(prng.uniform(*PARK_WIDTH))
        if prng.random() < parking and wide:
            b.park_out = float(prng.uniform(*PARK_WIDTH))


def build_junction(arms: list[Arm], w: float, allowed, rng, crosswalks: bool, parking: float = 0.0,
                   prng: np.random.Generator | None = None) -> RoadMap:
    """A junction of straight arms meeting at the origin.

    `allowed(a, b)` says whether traffic may go from arm a to arm b. Inbound
    lane k of an arm sits at normal offset +(k + 1/2) w, outbound lane k at
    -(k + 1/2) w (right-hand traffic); k = 0 is next to the centre line.
    `parking` > 0 adds kerbside parking strips (drawn from `prng`, see `_draw_parking`).
    """
    order = np.argsort([wrap(a.theta) for a in arms])
    arms = [arms[i] for i in order]
    na = len(arms)
    if parking > 0:
        _draw_parking(arms, parking, prng)
    # initial stop distances: room for a right-turn radius r_target at every corner
    r_target = float(rng.uniform(8.0, 12.0))
    for a in arms:
        a.r_stop = 0.0
    for i in range(na):
        a, b = arms[i], arms[(i + 1) % na]
        alpha = float(wrap(b.theta - a.theta)) % (2 * math.pi)
        if alpha >= math.pi - 1e-6:
            continue
        tt = _line_t(a, (a.n_in - 0.5) * w, b, -(b.n_out - 0.5) * w)
        need = r_target / math.tan(alpha / 2)
        a.r_stop = max(a.r_stop, tt[0] + need, a.n_in * w + 2)
        b.r_stop = max(b.r_stop, tt[1] + need, b.n_out * w + 2)
    for a in arms:
        a.r_stop = max(a.r_stop, (a.n_in + a.n_out) * w * 0.5 + 4.0) + float(rng.uniform(0.0, 3.0))
    for _ in range(12):
        try:
            m = _junction_try(arms, w, allowed, crosswalks)
        except _Grow as g:
            for i in g.arms:
                arms[i].r_stop += 2.0
            continue
        bad = m.offroad_lanes()
        if not bad:
            m.info["r_stop"] = [a.r_stop for a in arms]
            m.info["arm_angles"] = [float(a.theta) for a in arms]
            return m
        grow = {i for lane in bad for i in m.lanes[lane].arms}
        if not grow:
            raise GeometryError(f"approach lanes {bad} off the road")
        for i in grow:
            arms[i].r_stop += 2.0
    raise GeometryError("junction did not converge")


class _Grow(Exception):
    def __init__(self, arms):
        self.arms = arms


def _junction_try(arms: list[Arm], w: float, allowed, crosswalks: bool) -> RoadMap:
    """One attempt at the junction's map with the arms' current stop distances; raises _Grow naming
    the arms whose stop lines must move out when a turn does not fit."""
    m = RoadMap()
    lane_in, lane_out = _approach_lanes(m, arms, w)
    _junction_movements(m, arms, w, allowed, lane_in, lane_out)
    _junction_curbs(m, arms, w)
    _parking_strips(m, arms, w, lane_in, lane_out)
    _arm_markings(m, arms, w, crosswalks)
    return m


def _approach_lanes(m: RoadMap, arms: list[Arm], w: float) -> tuple[dict, dict]:
    """The straight lanes of every arm, inbound (spawn lanes, ending at the stop line) and outbound
    (starting there): ({(arm, k): lane}, {(arm, k): lane})."""
    lane_in, lane_out = {}, {}
    for i, a in enumerate(arms):
        for k in range(a.n_in):
            p = a.point(a.length, (k + 0.5) * w)
            ln = a.length - a.r_stop
            lane_in[i, k] = m.add_lane(line(p[0], p[1], a.theta + math.pi, ln),
                                       conflict_range=(ln - 12.0, ln))
            m.spawn.append((lane_in[i, k], ln, 1.0))
        for k in range(a.n_out):
            p = a.point(a.r_stop, -(k + 0.5) * w)
            lane_out[i, k] = m.add_lane(line(p[0], p[1], a.theta, a.length - a.r_stop),
                                        conflict_range=(0.0, 12.0))
    return lane_in, lane_out


def _lane_pairs(a: Arm, b: Arm, cls: str, dest: tuple[float, int], s_dests: list) -> list[tuple[int, int]]:
    """(inbound lane of arm a, outbound lane of arm b) pairs of the movement `dest` = (deflection, j)
    from a to b = arms[j], of class `cls` (`_classify`): left turns from the innermost lane, right turns
    from the outermost, straight on lane by lane; two straight-ish destinations (Y) split the lanes."""
    if cls == "L":
        return [(0, 0)]
    if cls == "R":
        return [(a.n_in - 1, b.n_out - 1)]
    if len(s_dests) == 1:
        return [(k, min(k, b.n_out - 1)) for k in range(a.n_in)]
    half = a.n_in / 2
    ks = range(0, max(1, math.ceil(half))) if dest == s_dests[0] else \
        range(min(a.n_in - 1, math.floor(half)), a.n_in)
    ks = list(ks) if a.n_in > 1 else [0]
    return [(k, min(k, b.n_out - 1) if dest == s_dests[0] else
             max(0, b.n_out - a.n_in + k)) for k in ks]


def _junction_movements(m: RoadMap, arms: list[Arm], w: float, allowed, lane_in: dict, lane_out: dict) -> None:
    """The junction lanes of every allowed movement, with their edges and routes."""
    for i, a in enumerate(arms):
        dests = []
        for j, b in enumerate(arms):
            if j == i or not allowed(a, b):
                continue
            defl = float(wrap(b.theta - (a.theta + math.pi)))
            dests.append((defl, j))
        dests.sort(reverse=True)  # leftmost first
        s_dests = [d for d in dests if _classify(d[0]) == "S"]
        for defl, j in dests:
            b = arms[j]
            cls = _classify(defl)
            pairs = _lane_pairs(a, b, cls, (defl, j), s_dests)
            prio = _movement_prio(cls, a.major, any(x.major for x in arms))
            for k, kk in pairs:
                p = a.point(a.r_stop, (k + 0.5) * w)
                q = b.point(b.r_stop, -(kk + 0.5) * w)
                path = fillet(p, a.theta + math.pi, q, b.theta)
                if path is None:
                    raise _Grow([i, j])
                c = m.add_lane(path, prio=prio, arms=(i, j))
                m.edges += [(lane_in[i, k], c), (c, lane_out[j, kk])]
                m.routes.append([lane_in[i, k], c, lane_out[j, kk]])


def _junction_curbs(m: RoadMap, arms: list[Arm], w: float) -> None:
    """One curb per corner between consecutive arms; where an arm side has a parking strip, the kerb
    runs at the strip's outer edge and steps in to the lane edge over PARK_TAPER before the corner."""
    na = len(arms)
    for i in range(na):
        a, b = arms[i], arms[(i + 1) % na]
        alpha = float(wrap(b.theta - a.theta)) % (2 * math.pi)
        head = _kerb_run(a, a.n_in * w, a.park_in, +1)
        tail = _kerb_run(b, b.n_out * w, b.park_out, -1).reversed()
        if abs(alpha - math.pi) < 1e-6:
            m.curbs.append(head + _segment(head.end[:2], tail.start[:2]) + tail)
            continue
        if alpha > math.pi:
            raise GeometryError("reflex corner between arms")
        p = a.point(a.r_stop, (a.n_in - 0.5) * w)
        q = b.point(b.r_stop, -(b.n_out - 0.5) * w)
        turn = fillet(p, a.theta + math.pi, q, b.theta)
        if turn is None:
            raise _Grow([i, (i + 1) % na])
        curb = turn.offset(-w / 2)
        m.curbs.append(head + curb + tail)  # the runs end where the corner's kerb starts and ends


def _parking_strips(m: RoadMap, arms: list[Arm], w: float, lane_in: dict, lane_out: dict) -> None:
    """A ParkingStrip for every arm side drawn with one (`_draw_parking`), beside its outer lane."""
    for i, a in enumerate(arms):
        for side, inner, width, lane in ((+1, a.n_in * w, a.park_in, lane_in.get((i, a.n_in - 1), -1)),
                                         (-1, a.n_out * w, a.park_out, lane_out.get((i, a.n_out - 1), -1))):
            if width > 0:
                m.strips.append(ParkingStrip(float(a.theta), side, inner, width, a.r_stop + PARK_TAPER, a.length,
                                             lane, a.r_stop, w / 2))


def _arm_markings(m: RoadMap, arms: list[Arm], w: float, crosswalks: bool) -> None:
    """Road lines along the arms and, with `crosswalks`, a crosswalk at each stop line."""
    for a in arms:
        ln = a.length - a.r_stop
        offs = ([0.0] if a.n_in and a.n_out else []) + [k * w for k in range(1, a.n_in)] + \
            [-k * w for k in range(1, a.n_out)]
        for off in offs:
            p = a.point(a.r_stop, off)
            m.lines.append(line(p[0], p[1], a.theta, ln))
        if crosswalks:
            t0, t1 = a.r_stop + 1.0, a.r_stop + 4.0
            lo, hi = -a.n_out * w, a.n_in * w
            m.crosswalks.append(np.array([a.point(t0, lo), a.point(t0, hi), a.point(t1, hi),
                                          a.point(t1, lo), a.point(t0, lo)]))


def _segment(p, q) -> Path:
    p, q = np.asarray(p, float), np.asarray(q, float)
    d = q - p
    return line(p[0], p[1], math.atan2(d[1], d[0]), float(np.linalg.norm(d)))


def _kerb_run(a: Arm, edge: float, park: float, side: int) -> Path:
    """The kerb along one side of arm `a`, from its far end in to the stop line: at the lane edge
    (normal offset side * edge), or with a parking strip of width `park` at side * (edge + park)
    until PARK_TAPER before the stop line, then stepping in to the lane edge."""
    far = a.point(a.length, side * (edge + park))
    stop = a.point(a.r_stop, side * edge)
    if park <= 0:
        return _segment(far, stop)
    knee = a.point(a.r_stop + PARK_TAPER, side * (edge + park))
    return _segment(far, knee) + _segment(knee, stop)


def _movement_prio(cls: str, from_major: bool, has_major: bool) -> int:
    """Who goes first at a conflict: the priority road (its left turns after its
    straight and right movements), then the minor road; a junction without a
    priority road is all-way first come first served."""
    if from_major:
        return 2 if cls in "SR" else 1
    return 0 if has_major else 1


# ----------------------------------------------------------------------------- the six maps
def _rot(rng) -> float:
    return float(rng.uniform(-math.pi, math.pi))


def map_dual_lane(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    rho = _rot(rng)
    phi = float(rng.uniform(math.radians(70), math.radians(110)))
    n = 2
    arms = [Arm(rho + d, n, n, scale * float(rng.uniform(100, 140))) for d in (0, phi, math.pi, phi + math.pi)]
    m = build_junction(arms, w, lambda a, b: True, rng, crosswalks, parking, prng)
    m.info.update(lanes_per_direction=n, crossing_angle_deg=math.degrees(phi))
    return m


def map_dense(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    rho = _rot(rng)
    phi = float(rng.uniform(math.radians(75), math.radians(105)))
    na = lanes if lanes else int(rng.integers(3, 5))
    nb = lanes if lanes else int(rng.integers(3, 5))
    arms = [Arm(rho + d, n, n, scale * float(rng.uniform(100, 140)))
            for d, n in ((0, na), (phi, nb), (math.pi, na), (phi + math.pi, nb))]
    m = build_junction(arms, w, lambda a, b: True, rng, crosswalks, parking, prng)
    m.info.update(lanes_per_direction=[na, nb], crossing_angle_deg=math.degrees(phi))
    return m


def map_t_junction(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    rho = _rot(rng)
    nm = lanes if lanes else int(rng.integers(1, 3))
    ns = lanes if lanes else int(rng.integers(1, 3))
    psi = float(rng.uniform(math.radians(65), math.radians(115)))
    arms = [Arm(rho, nm, nm, scale * float(rng.uniform(100, 140)), major=True),
            Arm(rho + math.pi, nm, nm, scale * float(rng.uniform(100, 140)), major=True),
            Arm(rho + math.pi + psi, ns, ns, scale * float(rng.uniform(100, 140)))]
    m = build_junction(arms, w, lambda a, b: True, rng, crosswalks, parking, prng)
    m.info.update(lanes_per_direction=[nm, ns], stem_angle_deg=math.degrees(psi))
    return m


def map_y_junction(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    rho = _rot(rng)
    n = lanes if lanes else int(rng.integers(1, 3))
    bl = float(rng.uniform(math.radians(22), math.radians(40)))
    br = float(rng.uniform(math.radians(22), math.radians(40)))
    arms = [Arm(rho - math.pi / 2, n, n, scale * float(rng.uniform(100, 140)), major=True),
            Arm(rho + math.pi / 2 + bl, n, n, scale * float(rng.uniform(100, 140))),
            Arm(rho + math.pi / 2 - br, n, n, scale * float(rng.uniform(100, 140)))]
    stem = arms[0]
    # no branch-to-branch movements
    m = build_junction(arms, w, lambda a, b: a is stem or b is stem, rng, crosswalks, parking, prng)
    m.info.update(lanes_per_direction=n, branch_angles_deg=[math.degrees(bl), math.degrees(br)])
    return m


def map_roundabout(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    # no kerbside parking on roundabouts: `parking` and `prng` are unused
    rho = _rot(rng)
    na = int(rng.choice([3, 4, 4, 5]))
    rc = float(rng.uniform(16.0, 20.0) if na == 5 else rng.uniform(12.5, 19.0))
    jitter = {3: 12.0, 4: 9.0, 5: 5.0}[na]
    thetas = [rho + 2 * math.pi * k / na + math.radians(float(rng.uniform(-jitter, jitter)))
              for k in range(na)]
    lengths = [scale * float(rng.uniform(100, 140)) for _ in range(na)]
    re0 = float(rng.uniform(10.0, 16.0))
    for attempt in range(6):
        re = max(R_MIN + 3.0, re0 - 1.5 * attempt)
        try:
            m = _roundabout_try(thetas, lengths, rc, re, re, w)
        except GeometryError:
            continue
        bad = m.offroad_lanes()
        if not bad:
            m.info.update(num_arms=na, ring_radius=rc, entry_radius=re, arm_angles=thetas)
            return m
        re0 += 3.0  # tight entries cut the island: try wider ones
    raise GeometryError("roundabout did not fit")


def _roundabout_try(thetas, lengths, rc, re, rx, w) -> RoadMap:
    """The roundabout's map: ring radius `rc`, entry and exit radii `re`, `rx`, arms at `thetas`;
    raises GeometryError when the arms do not fit."""
    m = RoadMap()
    arm_data, nodes = _roundabout_arms(thetas, rc, re, rx, w)
    gaps = _order_ring_nodes(nodes, rc)
    ring, seg_of_start, seg_of_end = _ring_lanes(m, nodes, gaps, rc)
    lanes = _roundabout_arm_lanes(m, thetas, lengths, arm_data, rc, re, rx, w, seg_of_start, seg_of_end)
    _roundabout_routes(m, nodes, ring, *lanes)
    for lid in ring:
        m.spawn.append((lid, m.lanes[lid].path.length, 0.35))
    _roundabout_curbs(m, thetas, lengths, arm_data, rc, re, rx, w)
    for i, th in enumerate(thetas):
        u, n, te, tx = arm_data[i][:4]
        t0 = max(te, tx)
        m.lines.append(line(t0 * u[0], t0 * u[1], th, lengths[i] - t0))
    return m


def _roundabout_arms(thetas, rc, re, rx, w) -> tuple[list[tuple], list[tuple]]:
    """Per arm (u, n, te, tx, ce, cx, psi_e, psi_x): its direction and normal, how far out its entry
    and exit arcs leave the arm, their centres and the ring angles where they meet the ring; and the
    ring nodes (angle, "e" or "x", arm) in arm order."""
    nodes = []  # (angle, kind, arm)
    arm_data = []
    for i, th in enumerate(thetas):
        u = np.array([math.cos(th), math.sin(th)])
        n = np.array([-math.sin(th), math.cos(th)])
        te = math.sqrt((rc + re) ** 2 - (w / 2 + re) ** 2)
        tx = math.sqrt((rc + rx) ** 2 - (w / 2 + rx) ** 2)
        ce = (w / 2 + re) * n + te * u
        cx = -(w / 2 + rx) * n + tx * u
        psi_e = math.atan2(ce[1], ce[0])
        psi_x = math.atan2(cx[1], cx[0])
        arm_data.append((u, n, te, tx, ce, cx, psi_e, psi_x))
        nodes += [(psi_x, "x", i), (psi_e, "e", i)]
    return arm_data, nodes


def _order_ring_nodes(nodes: list[tuple], rc: float) -> np.ndarray:
    """Sorts `nodes` counter-clockwise from the first exit and returns the angular gaps between
    consecutive ones; raises GeometryError when they are too close or do not alternate exit, entry."""
    base = nodes[0][0]
    nodes.sort(key=lambda t: (t[0] - base) % (2 * math.pi))
    ang = np.array([(t[0] - base) % (2 * math.pi) for t in nodes])
    gaps = np.diff(np.concatenate([ang, [2 * math.pi]]))
    if (gaps * rc < 4.0).any() or [t[1] for t in nodes] != ["x", "e"] * (len(nodes) // 2):
        raise GeometryError("roundabout arms too close")
    return gaps


def _ring_lanes(m: RoadMap, nodes: list[tuple], gaps: np.ndarray, rc: float) -> tuple[list[int], dict, dict]:
    """The ring's lane segments between consecutive nodes, joined in a loop: (their lanes in ring order,
    {(kind, arm): segment starting at that node}, {(kind, arm): segment ending there})."""
    seg_of_start, seg_of_end = {}, {}
    for k, (psi, kind, arm) in enumerate(nodes):
        x0, y0 = rc * math.cos(psi), rc * math.sin(psi)
        lid = m.add_lane(Path.chain(x0, y0, psi + math.pi / 2, [(rc * gaps[k], 1.0 / rc)]), prio=2)
        seg_of_start[kind, arm] = lid
        nxt = nodes[(k + 1) % len(nodes)]
        seg_of_end[nxt[1], nxt[2]] = lid
    ring = [seg_of_start[t[1], t[2]] for t in nodes]
    for k in range(len(ring)):
        m.edges.append((ring[k], ring[(k + 1) % len(ring)]))
    return ring, seg_of_start, seg_of_end


def _roundabout_arm_lanes(m: RoadMap, thetas, lengths, arm_data, rc, re, rx, w, seg_of_start: dict,
                          seg_of_end: dict) -> tuple[dict, dict, dict, dict]:
    """Each arm's inbound lane, entry arc onto the ring, exit arc off it and outbound lane, joined to the
    ring: ({arm: lane} inbound, entry arcs, exit arcs, outbound)."""
    lane_in, lane_out, conn_e, conn_x = {}, {}, {}, {}
    for i, th in enumerate(thetas):
        u, n, te, tx, ce, cx, psi_e, psi_x = arm_data[i]
        L = lengths[i]
        p = L * u + (w / 2) * n
        lane_in[i] = m.add_lane(line(p[0], p[1], th + math.pi, L - te), conflict_range=(L - te - 12, L - te))
        m.spawn.append((lane_in[i], L - te, 1.0))
        dh_e = float(wrap(psi_e + math.pi / 2 - (th + math.pi)))
        pe = te * u + (w / 2) * n
        conn_e[i] = m.add_lane(Path.chain(pe[0], pe[1], th + math.pi, [(re * abs(dh_e), -1.0 / re)]), prio=0)
        jx = rc * np.array([math.cos(psi_x), math.sin(psi_x)])
        dh_x = float(wrap(th - (psi_x + math.pi / 2)))
        conn_x[i] = m.add_lane(Path.chain(jx[0], jx[1], psi_x + math.pi / 2, [(rx * abs(dh_x), -1.0 / rx)]),
                               prio=2)
        px = tx * u - (w / 2) * n
        lane_out[i] = m.add_lane(line(px[0], px[1], th, L - tx), conflict_range=(0.0, 12.0))
        if dh_e > 0 or dh_x > 0:
            raise GeometryError("roundabout entry not a right turn")
        m.edges += [(lane_in[i], conn_e[i]), (conn_e[i], seg_of_start["e", i]),
                    (seg_of_end["x", i], conn_x[i]), (conn_x[i], lane_out[i])]
    return lane_in, conn_e, conn_x, lane_out


def _roundabout_routes(m: RoadMap, nodes: list[tuple], ring: list[int], lane_in: dict, conn_e: dict,
                       conn_x: dict, lane_out: dict) -> None:
    """Routes from every arm to every other arm, counter-clockwise around the ring."""
    na = len(lane_in)
    k_of = {(t[1], t[2]): k for k, t in enumerate(nodes)}
    for i in range(na):
        for j in range(na):
            if i == j:
                continue
            k = k_of["e", i]
            segs = []
            while True:
                segs.append(ring[k])
                k = (k + 1) % len(ring)
                if nodes[k][1] == "x" and nodes[k][2] == j:
                    break
            m.routes.append([lane_in[i], conn_e[i]] + segs + [conn_x[j], lane_out[j]])


def _roundabout_curbs(m: RoadMap, thetas, lengths, arm_data, rc, re, rx, w) -> None:
    """The island's curb, and one outer curb per corner between consecutive arms."""
    na = len(thetas)
    ri, ro = rc - w / 2, rc + w / 2
    m.curbs.append(Path.chain(ri, 0.0, math.pi / 2, [(2 * math.pi * ri, 1.0 / ri)]))
    for i in range(na):
        j = (i + 1) % na
        u, n, te, _, ce, _, psi_e, _ = arm_data[i]
        uj, nj, _, txj, _, cxj, _, psi_xj = arm_data[j]
        p = lengths[i] * u + w * n
        dh_e = float(wrap(psi_e + math.pi / 2 - (thetas[i] + math.pi)))
        dh_x = float(wrap(thetas[j] - (psi_xj + math.pi / 2)))
        sweep = (psi_xj - psi_e) % (2 * math.pi)
        rcurb_e, rcurb_x = re - w / 2, rx - w / 2
        m.curbs.append(Path.chain(p[0], p[1], thetas[i] + math.pi, [
            (lengths[i] - te, 0.0), (rcurb_e * abs(dh_e), -1.0 / rcurb_e), (ro * sweep, 1.0 / ro),
            (rcurb_x * abs(dh_x), -1.0 / rcurb_x), (lengths[j] - txj, 0.0)]))


def map_merge(rng, w, scale, lanes, crosswalks, parking=0.0, prng=None) -> RoadMap:
    # no kerbside parking on merges: `parking` and `prng` are unused
    n = lanes if lanes else int(rng.integers(1, 4))
    gamma = float(rng.uniform(math.radians(8), math.radians(18)))
    r_ramp = float(rng.uniform(60, 120))
    l_acc = float(rng.uniform(20, 50))
    l_tap = float(rng.uniform(30, 50))
    l_up = scale * float(rng.uniform(130, 170))
    l_down = scale * float(rng.uniform(120, 160))
    l_rs = scale * float(rng.uniform(70, 100))
    # canonical frame: traffic along +x, left curb y = 0; conflict point at the taper middle
    x_tip = -(l_acc + l_tap / 2)
    y_a = -(n + 0.5) * w
    x_m = x_tip + l_acc + l_tap
    x_end = x_m + l_down
    x0 = x_tip - l_up
    m = RoadMap()
    main = []
    for k in range(n - 1):
        y = -(k + 0.5) * w
        main.append(m.add_lane(line(x0, y, 0.0, x_end - x0), prio=2,
                               conflict_range=(x_tip - x0, x_m - x0 + 12)))
        m.routes.append([main[-1]])
        m.spawn.append((main[-1], -x0 - 20.0, 0.6))
    yr = -(n - 0.5) * w
    right_up = m.add_lane(line(x0, yr, 0.0, x_m - x0), prio=2, conflict_range=(x_tip - x0, x_m - x0))
    right_down = m.add_lane(line(x_m, yr, 0.0, l_down), prio=2, conflict_range=(0.0, 12.0))
    cx, cy = x_tip, y_a - r_ramp
    sx, sy = cx - r_ramp * math.sin(gamma), cy + r_ramp * math.cos(gamma)
    ramp_path = Path.chain(sx - l_rs * math.cos(gamma), sy - l_rs * math.sin(gamma), gamma,
                           [(l_rs, 0.0), (r_ramp * gamma, -1.0 / r_ramp), (l_acc, 0.0)])
    ramp = m.add_lane(ramp_path, conflict_range=(ramp_path.length - 12.0, ramp_path.length))
    phi = 2 * math.atan(w / l_tap)
    r_s = l_tap / (2 * math.sin(phi))
    taper = m.add_lane(Path.chain(x_tip + l_acc, y_a, 0.0, [(r_s * phi, 1.0 / r_s), (r_s * phi, -1.0 / r_s)]),
                       prio=0)
    m.edges += [(right_up, right_down), (ramp, taper), (taper, right_down)]
    m.routes += [[right_up, right_down], [ramp, taper, right_down]]
    m.spawn += [(right_up, x_tip + l_acc - x0, 1.0), (ramp, ramp_path.length, 1.2)]
    # curbs: left edge, the gore (main right edge then back down the ramp's left edge), ramp right edge
    m.curbs.append(line(x0, 0.0, 0.0, x_end - x0))
    ramp_in = Path(ramp_path.pieces[:2])
    m.curbs.append(line(x0, -n * w, 0.0, x_tip - x0) + ramp_in.offset(w / 2).reversed())
    m.curbs.append(ramp_path.offset(-w / 2) + m.lanes[taper].path.offset(-w / 2)
                   + line(x_m, -n * w, 0.0, l_down))
    for k in range(1, n):
        m.lines.append(line(x0, -k * w, 0.0, x_end - x0))
    m.lines.append(line(x_tip, -n * w, 0.0, l_acc))
    bad = m.offroad_lanes()
    if bad:
        raise GeometryError(f"merge lanes {bad} off the road")
    m.info.update(main_lanes=n, ramp_angle_deg=math.degrees(gamma), accel_lane=l_acc, taper=l_tap)
    m.info["frame_offset"] = [0.0, -n * w]  # the conflict point, subtracted at export
    m.info["frame_rotation"] = _rot(rng)
    return m
