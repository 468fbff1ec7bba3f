"""Save a PNG grid with one procedural scene of each type.

    python scripts/procedural_gallery.py out.png [--seed 0] [--extent 60] [--density 1.0]
        [--knobs parking=0.8,stop_lines=0.5,kerb_stops=0.5,lane_offset=0.4]

Curbs black, lane centrelines thin blue, lane dividers dashed olive,
crosswalks green; each vehicle's trajectory is a coloured line with its box
drawn at the first step (filled) and the last step (outline). `--knobs` takes
generator knobs as a scene spec does (`procedural:all[...]`); parked cars are
drawn grey, and a kerb stop's final box thick black.
"""

from __future__ import annotations

import argparse
import dataclasses

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tg_gpudrive.data.procedural import SCENARIO_TYPES, ProceduralParams, generate_scene  # noqa: E402
from tg_gpudrive.data.sources import resolve_scenes  # noqa: E402
from tg_gpudrive.enums import RoadType  # noqa: E402


def box_corners(c, yaw, length, width):
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-u[1], u[0]])
    hl, hw = length / 2, width / 2
    return np.array([c + hl * u + hw * v, c - hl * u + hw * v, c - hl * u - hw * v, c + hl * u - hw * v,
                     c + hl * u + hw * v])


def draw(ax, scene, extent):
    style = {RoadType.ROAD_EDGE: dict(color="k", lw=1.2), RoadType.LANE: dict(color="#7a9cc6", lw=0.5),
             RoadType.ROAD_LINE: dict(color="#b5a642", lw=0.6, ls="--"),
             RoadType.CROSSWALK: dict(color="#3a9a3a", lw=0.8)}
    for kind, pts in scene.polylines():
        ax.plot(pts[:, 0], pts[:, 1], **style.get(RoadType(kind), dict(color="grey", lw=0.5)))
    movers = scene.num_agents - scene.metadata.get("num_parked", 0)
    kerb = set(scene.metadata.get("kerb_stops", []))
    colors = plt.cm.tab20(np.linspace(0, 1, max(movers, 2)))
    for i in range(scene.num_agents):
        xy = scene.log_pos[i]
        first = box_corners(xy[0], scene.log_yaw[i, 0], scene.length[i], scene.width[i])
        if i >= movers:  # parked
            ax.fill(first[:, 0], first[:, 1], color="0.6")
            continue
        ax.plot(xy[:, 0], xy[:, 1], color=colors[i], lw=1.5)
        last = box_corners(xy[-1], scene.log_yaw[i, -1], scene.length[i], scene.width[i])
        ax.fill(first[:, 0], first[:, 1], color=colors[i], alpha=0.8)
        ax.plot(last[:, 0], last[:, 1], color="k" if i in kerb else colors[i], lw=2.5 if i in kerb else 1.0)
    ax.plot(*scene.metadata["conflict_point"], "r+", ms=10)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    parked = scene.num_agents - movers
    ax.set_title(f"{scene.metadata['scenario_type']} seed {scene.metadata['seed']}: {movers} vehicles"
                 + (f", {parked} parked, {len(kerb)} kerb stops" if parked else ""), fontsize=10)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="PNG path")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--extent", type=float, default=60.0, help="half width of each panel, m")
    ap.add_argument("--density", type=float, default=1.0)
    ap.add_argument("--knobs", default="", help="generator knobs as in a scene spec, e.g. parking=0.8,kerb_stops=0.5")
    args = ap.parse_args(argv)
    params = ProceduralParams(density=args.density)
    if args.knobs:  # the scene spec's parser: an unknown knob is a one-line error
        params = dataclasses.replace(resolve_scenes(f"procedural:all[{args.knobs}]", n=1).params, density=args.density)
    fig, axs = plt.subplots(2, 3, figsize=(18, 12))
    for ax, kind in zip(axs.ravel(), SCENARIO_TYPES):
        draw(ax, generate_scene(kind, args.seed, params), args.extent)
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
