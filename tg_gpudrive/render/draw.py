"""Drawing: top-down pictures of one world of a `Simulator` (matplotlib Agg, no display).

    frame = render_frame(sim, world=0)                  # (H, W, 3) uint8 of the current state
    r = FrameRenderer(sim, world=0); r.draw(trails)     # one figure reused for many frames

What is drawn: road edges (dark), lane centrelines (light, dashed), road lines,
crosswalks and speed bumps (hatched polygons), driveways (faint polygons),
stop signs (red octagons), traffic-signal states at their stop points;
agents present and not removed as oriented boxes with a heading arrow
(controlled vehicles blue, replayed vehicles grey, pedestrians green, cyclists
purple, others brown; controlled non-vehicles get a blue outline); agents that
collided this episode outlined red, off-road orange; goals of controlled agents
(star plus a thin line to the agent); trails of past positions.

This module only reads the simulator's torch views (one world's host copy per
frame) and its Model's scenes; it never writes engine state, never steps the
simulator and writes no files (record.py does). It is for looking at single
worlds (~0.1 s a frame), not for logging thousands of them.
"""

from __future__ import annotations

import numpy as np
# Figure + the Agg canvas directly, never pyplot: no display, no global figure state, the user's backend untouched
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from tg_gpudrive.enums import AgentType, RoadType, TrafficLightState

# ------------------------------------------------------------------ palette
BACKGROUND = "#f4f3ef"
ROAD_EDGE = "#2e2e2e"
LANE = "#b4b4b4"
ROAD_LINE = "#c9a227"
CROSSWALK = "#6f6f6f"
SPEED_BUMP = "#d98c1f"
DRIVEWAY = "#e4e1d8"
STOP_SIGN = "#c8102e"
CONTROLLED = "#1f6fd1"
REPLAYED = "#9a9a9a"
PEDESTRIAN = "#2ca02c"
CYCLIST = "#9b59b6"
OTHER = "#8c564b"
COLLIDED = "#e8000b"  # outline of agents that collided this episode
OFFROAD = "#ff8c00"  # outline of agents that left the road this episode
GOAL = "#1f6fd1"
TYPE_COLOUR = {int(AgentType.PEDESTRIAN): PEDESTRIAN, int(AgentType.CYCLIST): CYCLIST,
               int(AgentType.OTHER): OTHER}
SIGNAL_COLOUR = {  # TrafficLightState -> colour; UNKNOWN signals are not drawn
    TrafficLightState.ARROW_STOP: "#e8000b", TrafficLightState.STOP: "#e8000b",
    TrafficLightState.FLASHING_STOP: "#e8000b", TrafficLightState.ARROW_CAUTION: "#f2c500",
    TrafficLightState.CAUTION: "#f2c500", TrafficLightState.FLASHING_CAUTION: "#f2c500",
    TrafficLightState.ARROW_GO: "#17b31a", TrafficLightState.GO: "#17b31a",
}

HIGHLIGHT = ("controlled", "all", "none")  # whose collisions / off-road events get outlined
FITS = ("scene", "controlled")  # what a fixed view fits: every slotted agent, or the controlled ones only
DEFAULT_VIEW_RADIUS = 40.0  # m, half the shorter side of an agent-centred view
DPI = 100


def rgba(colour: str, alpha: float = 1.0) -> np.ndarray:
    return np.array(to_rgba(colour, alpha))


def _darker(colour: np.ndarray, f: float = 0.6) -> np.ndarray:
    out = colour.copy()
    out[..., :3] *= f
    return out


def _box_corners(pos: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(n, 4, 2) corners of oriented boxes."""
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], np.float64)  # (4, 2) signs
    lx = local[None, :, 0] * hl[:, None]
    ly = local[None, :, 1] * hw[:, None]
    x = pos[:, None, 0] + c[:, None] * lx - s[:, None] * ly
    y = pos[:, None, 1] + s[:, None] * lx + c[:, None] * ly
    return np.stack([x, y], -1)


def _arrow_heads(pos: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(n, 3, 2) triangles inside the front of each box, pointing along the heading."""
    c, s = np.cos(yaw), np.sin(yaw)
    tip = length / 2
    back = tip - np.minimum(0.45 * length, 1.8)
    half = 0.32 * width
    lx = np.stack([tip, back, back], 1)
    ly = np.stack([np.zeros_like(half), half, -half], 1)
    x = pos[:, None, 0] + c[:, None] * lx - s[:, None] * ly
    y = pos[:, None, 1] + s[:, None] * lx + c[:, None] * ly
    return np.stack([x, y], -1)


def _nice_length(span: float) -> float:
    """A round scale-bar length near a fifth of `span` metres."""
    target = span / 5
    for v in (1, 2, 5, 10, 20, 25, 50, 100, 200, 500, 1000):
        if v >= target * 0.7:
            return float(v)
    return 1000.0


def as_numpy(t) -> np.ndarray:
    """A host NumPy copy of a torch view."""
    return t.detach().cpu().numpy()


class FrameRenderer:
    """One figure for one world of `sim`: static road artists built once, agents redrawn per frame.

    `draw(trails)` returns an (H, W, 3) uint8 frame of the simulator's current
    state (keywords as `render_frame`'s). A fixed view (the default: all the scene's agents and controlled
    goals with a margin; or around `center_point`) caches the road layer as a bitmap and only blits the
    moving artists over it; an agent-centred view redraws everything.
    """

    def __init__(self, sim, world: int = 0, *, size: tuple[int, int] | int = (640, 640),
                 center_agent: int | None = None, view_radius: float | None = None, show_goals: bool = True,
                 title: str | None = None, legend: bool | None = None, highlight: str = "controlled",
                 fit: str = "scene", trail_ticks: int = 0, center_point: tuple[float, float] | None = None):
        if highlight not in HIGHLIGHT:
            raise ValueError(f"highlight: expected one of {', '.join(HIGHLIGHT)}, got {highlight!r}")
        if not 0 <= int(world) < sim.num_worlds:
            raise ValueError(f"world {world} out of range [0, {sim.num_worlds})")
        if isinstance(size, (int, np.integer)):
            size = (int(size), int(size))
        w_px, h_px = (int(v) for v in size)
        if w_px < 32 or h_px < 32:
            raise ValueError(f"size: need at least 32x32 pixels, got {w_px}x{h_px}")
        if center_agent is not None and not 0 <= int(center_agent) < sim.max_agents:
            raise ValueError(f"center_agent {center_agent} out of range [0, {sim.max_agents})")
        if view_radius is not None and not view_radius > 0:
            raise ValueError(f"view_radius must be positive, got {view_radius}")
        if fit not in FITS:
            raise ValueError(f"fit: expected one of {', '.join(FITS)}, got {fit!r}")
        self.fit = fit
        if int(trail_ticks) < 0:
            raise ValueError(f"trail_ticks: expected a number of steps >= 0, got {trail_ticks}")
        self.trail_ticks = int(trail_ticks)
        self.sim, self.world, self.size = sim, int(world), (w_px, h_px)
        self.center_agent = None if center_agent is None else int(center_agent)
        self.center_point = None if center_point is None else tuple(float(v) for v in center_point)
        self.view_radius = view_radius
        self.show_goals, self.title, self.highlight = show_goals, title, highlight
        self.model = sim.model
        self.scene = sim.model.scenes[self.world]
        self.scale = min(w_px, h_px) / 640.0  # fonts and line widths follow the picture size
        legend = (w_px >= 400 and h_px >= 300) if legend is None else bool(legend)

        # fixed per loaded batch: host copies once
        w = self.world
        self.slot_valid = as_numpy(sim.slot_valid[w]).astype(bool)
        self.controlled = as_numpy(sim.integrated[w]).astype(bool)
        self.agent_type = as_numpy(sim.agent_type[w]).astype(np.int64)
        self.length = as_numpy(sim.length[w]).astype(np.float64)
        self.width = as_numpy(sim.width[w]).astype(np.float64)
        self.goal = as_numpy(sim.goal[w]).astype(np.float64)
        face = np.tile(rgba(REPLAYED), (sim.max_agents, 1))
        face[self.controlled] = rgba(CONTROLLED)
        for t, col in TYPE_COLOUR.items():
            face[self.agent_type == t] = rgba(col)
        self.face = face
        self.edge = _darker(face)
        ctrl_other = self.controlled & (self.agent_type != int(AgentType.VEHICLE))
        self.edge[ctrl_other] = rgba(CONTROLLED)

        self.fig = Figure(figsize=(w_px / DPI, h_px / DPI), dpi=DPI, facecolor=BACKGROUND)
        self.canvas = FigureCanvasAgg(self.fig)
        self._legend_ncol = 6 if w_px >= 560 else 4
        self._legend_fs = 7.2 * max(self.scale, 0.8)
        rows = -(-12 // self._legend_ncol)  # 12 legend entries
        strip = int(round(rows * self._legend_fs * DPI / 72 * 1.5 + 8)) if legend else 0
        self.ax = self.fig.add_axes((0, strip / h_px, 1, 1 - strip / h_px))
        self.ax.set_facecolor(BACKGROUND)
        self.ax.set_axis_off()
        self.ax_px = (w_px, h_px - strip)
        self.fixed = self.center_agent is None
        if self.fixed:
            xlim, ylim = self._fit_view() if self.center_point is None else self._limits(
                *self.center_point, self.view_radius or DEFAULT_VIEW_RADIUS)
            self.ax.set_xlim(*xlim)
            self.ax.set_ylim(*ylim)
        self._add_roads()
        self._add_dynamic()
        if legend:
            self._add_legend(strip / h_px)
        self._background = None

    # ------------------------------------------------------------ geometry
    def _limits(self, cx: float, cy: float, half_short: float):
        aw, ah = self.ax_px
        if aw >= ah:
            hy, hx = half_short, half_short * aw / ah
        else:
            hx, hy = half_short, half_short * ah / aw
        return (cx - hx, cx + hx), (cy - hy, cy + hy)

    def _fit_view(self):
        """Limits around every logged position of the slotted agents, controlled goals and current positions
        (fit "controlled": of the controlled agents only)."""
        sc, w = self.scene, self.world
        idx = self.model.slot_agent[w]
        keep = idx >= 0
        only = self.fit == "controlled" and bool((self.controlled & keep).any())  # else the whole scene
        if only:
            keep &= self.controlled
        idx = idx[keep]
        init = min(self.model.init_step, sc.num_steps - 1)
        valid = sc.log_valid[idx, init:]
        pts = [sc.log_pos[idx, init:][valid].reshape(-1, 2)]
        pts.append(self.goal[self.controlled & self.slot_valid])
        present = as_numpy(self.sim.present[w]).astype(bool)
        if only:
            present &= self.controlled
        pts.append(as_numpy(self.sim.pos[w])[present])
        pts = np.concatenate([p.astype(np.float64).reshape(-1, 2) for p in pts])
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts) == 0:
            pts = sc.road_points.astype(np.float64) if len(sc.road_points) else np.zeros((1, 2))
        lo, hi = pts.min(0), pts.max(0)
        centre = (lo + hi) / 2
        if self.view_radius is not None:
            return self._limits(centre[0], centre[1], self.view_radius)
        half = (hi - lo) / 2 * 1.08 + 12.0  # margin: a car length or two beyond the outermost agent
        aw, ah = self.ax_px
        half_short = max(half[0] * min(1.0, ah / aw), half[1] * min(1.0, aw / ah), 15.0)
        return self._limits(centre[0], centre[1], half_short)

    # --------------------------------------------------------------- roads
    def _add_roads(self) -> None:
        ax, sc, k = self.ax, self.scene, max(self.scale, 0.5)
        lines = {t: [] for t in (RoadType.LANE, RoadType.ROAD_LINE, RoadType.ROAD_EDGE)}
        polys = {t: [] for t in (RoadType.CROSSWALK, RoadType.SPEED_BUMP, RoadType.DRIVEWAY)}
        stops = []
        if self.fixed:  # skip what lies far outside the picture (WOMD maps reach well beyond the agents)
            (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
            pad = 0.1 * max(x1 - x0, y1 - y0)
            box = (x0 - pad, x1 + pad, y0 - pad, y1 + pad)
        for t, pts in sc.polylines():
            if self.fixed:
                if (pts[:, 0].max() < box[0] or pts[:, 0].min() > box[1] or pts[:, 1].max() < box[2]
                        or pts[:, 1].min() > box[3]):
                    continue
            if t in lines and len(pts) >= 2:
                lines[t].append(pts)
            elif t in polys and len(pts) >= 3:
                polys[t].append(pts)
            elif t == RoadType.STOP_SIGN:
                stops.append(pts.mean(0))
            elif len(pts) >= 2:  # polygons with too few points, unknown kinds: plain thin lines
                lines[RoadType.ROAD_LINE].append(pts)
        if polys[RoadType.DRIVEWAY]:
            ax.add_collection(PolyCollection(polys[RoadType.DRIVEWAY], facecolors=DRIVEWAY, edgecolors="none",
                                             zorder=0.5))
        ax.add_collection(LineCollection(lines[RoadType.LANE], colors=LANE, linewidths=0.9 * k,
                                         linestyles=(0, (5, 4)), zorder=1))
        ax.add_collection(LineCollection(lines[RoadType.ROAD_LINE], colors=ROAD_LINE, linewidths=0.9 * k,
                                         zorder=1.2))
        ax.add_collection(LineCollection(lines[RoadType.ROAD_EDGE], colors=ROAD_EDGE, linewidths=1.6 * k,
                                         capstyle="round", zorder=1.5))
        for kind, col in ((RoadType.CROSSWALK, CROSSWALK), (RoadType.SPEED_BUMP, SPEED_BUMP)):
            if polys[kind]:
                pc = PolyCollection(polys[kind], facecolors="none", edgecolors=col, linewidths=0.7 * k,
                                    hatch="////", zorder=1.3)
                ax.add_collection(pc)
        if stops:
            s = np.array(stops)
            ax.plot(s[:, 0], s[:, 1], linestyle="none", marker="8", markersize=7 * k, markerfacecolor=STOP_SIGN,
                    markeredgecolor="white", markeredgewidth=0.8 * k, zorder=2)

    # -------------------------------------------------------------- agents
    def _add_dynamic(self) -> None:
        ax, k = self.ax, max(self.scale, 0.5)
        self.trail_lc = LineCollection([], linewidths=1.4 * k, alpha=0.55, capstyle="round", zorder=3)
        self.goal_lc = LineCollection([], colors=GOAL, linewidths=0.7 * k, linestyles=(0, (2, 2)), alpha=0.6,
                                      zorder=3.5)
        self.goal_pts = Line2D([], [], linestyle="none", marker="*", markersize=9 * k, markerfacecolor=GOAL,
                               markeredgecolor="white", markeredgewidth=0.6 * k, zorder=4)
        self.signals = ax.scatter([], [], s=(6 * k) ** 2, edgecolors="white", linewidths=0.6 * k, zorder=2.5)
        self.ticks = ax.scatter([], [], s=(4.0 * max(k, 0.8)) ** 2, edgecolors="white", linewidths=0.5, zorder=3.2)
        self.boxes = PolyCollection([], zorder=5)
        self.heads = PolyCollection([], facecolors=(1, 1, 1, 0.85), edgecolors="none", zorder=6)
        self.text = ax.text(0.012, 0.988, "", transform=ax.transAxes, ha="left", va="top",
                            fontsize=8.5 * max(k, 0.8),
                            family="monospace", zorder=10,
                            bbox=dict(boxstyle="round,pad=0.3", facecolor="white", edgecolor="#cccccc", alpha=0.85))
        for a in (self.trail_lc, self.goal_lc, self.boxes, self.heads):
            ax.add_collection(a)
        ax.add_line(self.goal_pts)
        self.dynamic = [self.signals, self.ticks, self.trail_lc, self.goal_lc, self.goal_pts, self.boxes, self.heads,
                        self.text]
        self._add_scale_bar()

    def _add_scale_bar(self) -> None:
        # the view's width in metres is fixed (a centred view moves but keeps its radius)
        if self.fixed:
            x0, x1 = self.ax.get_xlim()
        else:
            x0, x1 = self._limits(0.0, 0.0, self.view_radius or DEFAULT_VIEW_RADIUS)[0]
        L = _nice_length(x1 - x0)
        bar = AnchoredSizeBar(self.ax.transData, L, f"{L:g} m", "lower left", pad=0.4, borderpad=0.6, sep=3,
                              color="#333333", frameon=True, size_vertical=0,
                              fontproperties={"size": 7.5 * max(self.scale, 0.8)})
        bar.patch.set(facecolor="white", edgecolor="#cccccc", alpha=0.85, linewidth=0.6)
        bar.size_bar.get_children()[0].set_linewidth(2.2 * max(self.scale, 0.5))
        bar.set_zorder(9)
        self.ax.add_artist(bar)

    def _add_legend(self, strip_frac: float) -> None:
        handles = legend_handles()
        self.fig.legend([h for h, _ in handles], [n for _, n in handles], loc="center",
                        bbox_to_anchor=(0.5, strip_frac / 2), ncol=self._legend_ncol, fontsize=self._legend_fs,
                        frameon=False, handlelength=2.0, handleheight=0.9, columnspacing=1.1, labelspacing=0.3,
                        borderaxespad=0.0, handletextpad=0.5)

    # --------------------------------------------------------------- frame
    def _update(self, trails: dict | None) -> None:
        sim, w, k = self.sim, self.world, self.scale
        pos = as_numpy(sim.pos[w]).astype(np.float64)
        yaw = as_numpy(sim.yaw[w]).astype(np.float64)
        shown = as_numpy(sim.present[w]).astype(bool) & ~as_numpy(sim.removed[w]).astype(bool) & self.slot_valid
        hit = (as_numpy(sim.ep_collided[w]) != 0) | (as_numpy(sim.collided[w]) != 0)
        off = (as_numpy(sim.ep_offroad[w]) != 0) | (as_numpy(sim.offroad[w]) != 0)
        marked = {"controlled": self.controlled, "all": self.slot_valid, "none": np.zeros_like(shown)}[self.highlight]
        step = int(sim.world_step[w])

        if self.center_agent is not None:
            c = pos[self.center_agent]
            (x0, x1), (y0, y1) = self._limits(c[0], c[1], self.view_radius or DEFAULT_VIEW_RADIUS)
            self.ax.set_xlim(x0, x1)
            self.ax.set_ylim(y0, y1)

        ids = np.nonzero(shown)[0]
        # draw highlighted agents last so their outlines are not hidden by neighbours
        ids = ids[np.argsort(((hit | off) & marked)[ids], kind="stable")]
        edge, lw = self.edge[ids].copy(), np.full(len(ids), 0.6 * k)
        hl_off, hl_hit = (off & marked)[ids], (hit & marked)[ids]
        edge[hl_off] = rgba(OFFROAD)
        edge[hl_hit] = rgba(COLLIDED)  # a collision outranks off-road
        lw[hl_off | hl_hit] = 2.2 * max(k, 0.8)  # stays visible in small pictures
        self.boxes.set_verts(_box_corners(pos[ids], yaw[ids], self.length[ids], self.width[ids]))
        self.boxes.set_facecolors(self.face[ids])
        self.boxes.set_edgecolors(edge)
        self.boxes.set_linewidths(lw)
        self.heads.set_verts(_arrow_heads(pos[ids], yaw[ids], self.length[ids], self.width[ids]))

        if self.show_goals:
            g = ids[self.controlled[ids]]
            self.goal_pts.set_data(self.goal[g, 0], self.goal[g, 1])
            self.goal_lc.set_segments(np.stack([pos[g], self.goal[g]], 1) if len(g) else [])
        else:
            self.goal_pts.set_data([], [])
            self.goal_lc.set_segments([])

        segs, cols, ticks, tick_cols = [], [], [], []
        for a, tr in (trails or {}).items():
            tr = np.asarray(tr, np.float64).reshape(-1, 2)
            if len(tr) >= 2 and 0 <= int(a) < len(self.face):
                segs.append(tr)
                cols.append(self.face[int(a)])
                if self.trail_ticks:
                    t = tr[self.trail_ticks::self.trail_ticks]
                    ticks.append(t)
                    tick_cols += [self.face[int(a)]] * len(t)
        self.trail_lc.set_segments(segs)
        self.trail_lc.set_color(cols if cols else "none")
        self.ticks.set_offsets(np.concatenate(ticks) if ticks else np.zeros((0, 2)))
        self.ticks.set_facecolors(tick_cols if tick_cols else "none")

        sc = self.scene
        if len(sc.tl_lane) and sc.tl_state is not None and 0 <= step < len(sc.tl_state):
            st = sc.tl_state[step]
            keep = np.array([int(s) in SIGNAL_COLOUR for s in st], bool)
            self.signals.set_offsets(sc.tl_stop_point[keep] if keep.any() else np.zeros((0, 2)))
            self.signals.set_facecolors([SIGNAL_COLOUR[TrafficLightState(int(s))] for s in st[keep]])
        else:
            self.signals.set_offsets(np.zeros((0, 2)))

        if self.title is not None:
            self.text.set_text(self.title)
        else:
            kind = sc.metadata.get("scenario_type")
            n = max(int(46 * self.size[0] / 640), 16)
            name = sc.scene_id if len(sc.scene_id) <= n else sc.scene_id[: n - 3] + "..."
            ctrl = self.controlled & self.slot_valid
            head = f"{name}" + (f" ({kind})" if kind and kind not in sc.scene_id else "")
            self.text.set_text(
                f"{head}\nworld {w}  step {step:>2}  t={step * sc.dt:4.1f}s\n"
                f"controlled {int(ctrl.sum())}: collided {int((hit & ctrl).sum())}  "
                f"off-road {int((off & ctrl).sum())}  goal {int((as_numpy(sim.ep_goal[w]) != 0)[ctrl].sum())}")

    def draw(self, trails: dict | None = None) -> np.ndarray:
        """(H, W, 3) uint8 picture of the current state; `trails`: {agent slot: (k, 2) past positions}."""
        self._update(trails)
        canvas = self.canvas
        if self.fixed:
            if self._background is None:
                for a in self.dynamic:
                    a.set_visible(False)
                canvas.draw()
                self._background = canvas.copy_from_bbox(self.fig.bbox)
                for a in self.dynamic:
                    a.set_visible(True)
            canvas.restore_region(self._background)
            for a in self.dynamic:
                self.ax.draw_artist(a)
        else:
            canvas.draw()
        img = np.asarray(canvas.buffer_rgba())[..., :3]
        w_px, h_px = self.size
        if img.shape[:2] != (h_px, w_px):  # figure size rounding: pad / crop to the exact request
            out = np.empty((h_px, w_px, 3), np.uint8)
            out[:] = np.array(rgba(BACKGROUND)[:3] * 255, np.uint8)
            hh, ww = min(h_px, img.shape[0]), min(w_px, img.shape[1])
            out[:hh, :ww] = img[:hh, :ww]
            return out
        return img.copy()

    def close(self) -> None:
        self.fig.clear()
        self._background = None


def legend_handles() -> list[tuple[object, str]]:
    """(matplotlib handle, name) of everything a frame draws: the legend of frames and of the report's grid."""
    box = lambda face, edge, lw=0.6: Patch(facecolor=face, edgecolor=edge, linewidth=lw)  # noqa: E731
    return [
        (box(CONTROLLED, _darker(rgba(CONTROLLED))), "controlled"),
        (box(REPLAYED, _darker(rgba(REPLAYED))), "log replay"),
        (box(PEDESTRIAN, _darker(rgba(PEDESTRIAN))), "pedestrian"),
        (box(CYCLIST, _darker(rgba(CYCLIST))), "cyclist"),
        (box("white", COLLIDED, 2.0), "collided"),
        (box("white", OFFROAD, 2.0), "off-road"),
        (Line2D([], [], color=GOAL, marker="*", markersize=8, linestyle=(0, (2, 2)), lw=0.8), "goal"),
        (Line2D([], [], color=CONTROLLED, alpha=0.55, lw=1.6), "trail"),
        (Line2D([], [], color=ROAD_EDGE, lw=1.6), "road edge"),
        (Line2D([], [], color=LANE, lw=1.0, linestyle=(0, (5, 4))), "lane centre"),
        (Line2D([], [], color=ROAD_LINE, lw=1.0), "road line"),
        (Patch(facecolor="none", edgecolor=CROSSWALK, hatch="////", linewidth=0.7), "crosswalk"),
    ]


def render_frame(sim, world: int = 0, *, size: tuple[int, int] | int = (640, 640), center_agent: int | None = None,
                 view_radius: float | None = None, trails: dict | None = None, show_goals: bool = True,
                 title: str | None = None, legend: bool | None = None,
                 highlight: str = "controlled", fit: str = "scene", trail_ticks: int = 0,
                 center_point: tuple[float, float] | None = None) -> np.ndarray:
    """Top-down picture of world `world`'s current state: (H, W, 3) uint8, `size` = (width, height) pixels.

    `center_agent` (a slot index of that world) centres the view on that agent
    with half-side `view_radius` (default 40 m); otherwise the view fits the
    scene's agents and controlled goals with a margin (or, with only
    `view_radius`, their centre); `center_point` (x, y) in m, without `center_agent`, holds the view
    still there with half-side `view_radius` (an agent's place after it has left). `trails` maps agent
    slots to (k, 2) past positions. `legend` (default: when the picture is at least 400x300) adds a
    colour key below the map. `highlight` says whose collisions and off-road
    events are outlined: "controlled" (default; logged parked cars are often
    "off-road" in WOMD), "all" or "none". `fit` "controlled" fits the view to
    the controlled agents' paths and goals only (a zoom on the interaction in
    a long scene). `trail_ticks` > 0 dots every trail each that many points from its first one, so
    equal spacing in time shows speed and who was where when (with `EpisodeRecorder`'s whole trails, the
    default, that is every that many steps of the agent's episode; a `trail_length` cut moves the dots).
    Builds a figure per call; `EpisodeRecorder` reuses one.
    """
    r = FrameRenderer(sim, world, size=size, center_agent=center_agent, view_radius=view_radius,
                      show_goals=show_goals, title=title, legend=legend, highlight=highlight, fit=fit,
                      trail_ticks=trail_ticks, center_point=center_point)
    try:
        return r.draw(trails)
    finally:
        r.close()
