"""Renderer: frame size and content, episodes, GIF / PNG files, the CLI command, highlights."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from conftest import WOMD_FILES
from tg_gpudrive import render
from tg_gpudrive.config import EngineConfig
from tg_gpudrive.data.womd.gpudrive_json import load_gpudrive_json
from tg_gpudrive.render import EpisodeRecorder, render_episode, render_frame
from tg_gpudrive.agents.builtin import expert_policy
from tg_gpudrive.scene import make_scene
from tg_gpudrive.engine.simulator import Simulator
from tg_gpudrive.enums import AgentType, RoadType


def _rgb(colour: str) -> np.ndarray:
    return np.round(render.rgba(colour)[:3] * 255).astype(np.uint8)


BG, RED, BLUE = _rgb(render.BACKGROUND), _rgb(render.COLLIDED), _rgb(render.CONTROLLED)


@pytest.fixture(scope="module")
def womd_sim():
    sim = Simulator([load_gpudrive_json(WOMD_FILES[0])], EngineConfig())
    sim.reset()
    return sim


def _colour_count(img: np.ndarray) -> int:
    return len(np.unique(img.reshape(-1, 3), axis=0))


def _has_colour(img: np.ndarray, rgb: np.ndarray, tol: int = 12) -> int:
    return int((np.abs(img.astype(int) - rgb.astype(int)).max(-1) <= tol).sum())


@pytest.mark.parametrize("size", [(640, 640), (320, 240)])
def test_frame_size_and_content(womd_sim, size):
    img = render_frame(womd_sim, size=size)
    assert img.shape == (size[1], size[0], 3) and img.dtype == np.uint8
    assert _colour_count(img) > 50
    not_bg = (np.abs(img.astype(int) - BG.astype(int)).max(-1) > 10).mean()
    assert 0.03 < not_bg < 0.9
    # controlled vehicles are drawn in their colour
    assert _has_colour(img, BLUE) > 20


def test_center_agent_and_trails_change_the_view(womd_sim):
    default = render_frame(womd_sim, size=(320, 320))
    a = int(np.nonzero(womd_sim.integrated[0].numpy())[0][0])
    centred = render_frame(womd_sim, size=(320, 320), center_agent=a, view_radius=20.0)
    assert centred.shape == default.shape
    assert np.abs(centred.astype(int) - default.astype(int)).sum(-1).astype(bool).mean() > 0.1
    p = womd_sim.pos[0, a].numpy().astype(float)
    trail = {a: np.stack([p - [30.0, 30.0], p - [15.0, 5.0], p])}
    assert not np.array_equal(render_frame(womd_sim, size=(320, 320), trails=trail), default)
    with pytest.raises(ValueError):
        render_frame(womd_sim, center_agent=10_000)


def test_episode_gif_and_png(womd_sim, tmp_path):
    frames = render_episode(womd_sim, expert_policy, 12, out=tmp_path / "ep.gif", size=(256, 256))
    assert len(frames) == 13
    assert all(f.shape == (256, 256, 3) for f in frames)
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).sum() > 0
    with Image.open(tmp_path / "ep.gif") as gif:
        assert gif.n_frames == 13 and gif.size == (256, 256)
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "ep.gif", index=None).shape[0] == 13

    rec = EpisodeRecorder(womd_sim, size=(200, 150))
    womd_sim.reset()
    rec.capture()
    expert_policy(womd_sim)
    womd_sim.step()
    rec.capture()
    assert set(rec.trails) and all(len(t) == 2 for t in rec.trails.values())
    rec.save(tmp_path / "a" / "frame.png")
    with Image.open(tmp_path / "a" / "frame.png") as im:
        assert im.size == (200, 150)
        assert np.array_equal(np.asarray(im.convert("RGB")), rec.frames[-1])
    rec.save(tmp_path / "first.png", frame=0)
    with pytest.raises(ValueError, match="gif"):
        rec.save(tmp_path / "x.avi")
    if render.mp4_backend() is None:
        with pytest.raises(RuntimeError, match="gif"):
            rec.save(tmp_path / "x.mp4")
    rec.close()


def test_episode_stops_at_its_end():
    """Without auto-reset the final state is the last frame; with it, the reset state is left out."""
    t = 30
    x = np.linspace(0, 20, t)
    pos = np.stack([np.stack([x, np.zeros(t)], -1)], 0)
    scene = make_scene(pos, np.zeros((1, t)), roads=[(RoadType.ROAD_EDGE, [[-10, -5], [40, -5]]),
                                                    (RoadType.ROAD_EDGE, [[-10, 5], [40, 5]])])
    for auto in (True, False):
        sim = Simulator([scene], EngineConfig(replay_infeasible=False, auto_reset=auto))
        frames = render_episode(sim, expert_policy, 100, size=(128, 128), legend=False)
        assert len(frames) <= sim.episode_length + 1
        assert int(sim.world_ended[0]) == 1
        # the car drove away from its start: the last frame is not the reset state
        assert not np.array_equal(frames[-1], frames[0])


def _two_car_sim(overlap: bool):
    t = 20
    x = np.linspace(0.0, 10.0, t)
    dy = 1.0 if overlap else 6.0  # boxes are 4.5 x 2 m: 1 m apart laterally they overlap
    pos = np.stack([np.stack([x, np.zeros(t)], -1), np.stack([x, np.full(t, dy)], -1)])
    roads = [(RoadType.ROAD_EDGE, [[-20, -8], [40, -8]]), (RoadType.ROAD_EDGE, [[-20, 14], [40, 14]]),
             (RoadType.LANE, [[-20, 0], [40, 0]])]
    scene = make_scene(pos, np.zeros((2, t)), roads=roads, agent_type=AgentType.VEHICLE)
    sim = Simulator([scene], EngineConfig(replay_infeasible=False, init_steps=2))
    sim.reset()
    expert_policy(sim)
    sim.step()
    return sim


def test_collided_agents_are_highlighted():
    sim = _two_car_sim(overlap=True)
    assert int(sim.ep_collided[0].sum()) == 2
    img = render_frame(sim, size=(320, 320), legend=False, title="")
    assert _has_colour(img, RED) > 20
    assert _has_colour(render_frame(sim, size=(320, 320), legend=False, title="", highlight="none"), RED) == 0
    calm = _two_car_sim(overlap=False)
    assert int(calm.ep_collided[0].sum()) == 0
    assert _has_colour(render_frame(calm, size=(320, 320), legend=False, title=""), RED) == 0


def test_procedural_scene_renders():
    procedural = pytest.importorskip("tg_gpudrive.data.procedural")
    sim = Simulator([procedural.generate_scene("roundabout", 0)], EngineConfig())
    sim.reset()
    img = render_frame(sim, size=(300, 300))
    assert img.shape == (300, 300, 3) and _colour_count(img) > 30


def test_cli_render(tmp_path, capsys):
    from tg_gpudrive.cli import main

    gif = tmp_path / "ep.gif"
    assert main(["render", "--scenes", str(WOMD_FILES[0]), "--steps", "3", "--size", "160x120",
                 "--out", str(gif)]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == 4 and im.size == (160, 120)
    png = tmp_path / "frame.png"
    assert main(["render", "--scenes", str(WOMD_FILES[0]), "--steps", "2", "--size", "128", "--policy", "constant",
                 "--center-agent", "0", "--out", str(png)]) == 0
    with Image.open(png) as im:
        assert im.size == (128, 128)
    assert main(["render", "--policy", str(tmp_path / "missing.pt"), "--out", str(gif)]) == 2
    assert "checkpoint" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path / "ep.avi")]) == 2


def test_fit_controlled_zooms_on_the_controlled_cars():
    """fit="controlled" frames the controlled car's path and goal, not a replayed car 300 m away; a bad
    fit is a one-line error."""
    from tg_gpudrive.render.draw import FrameRenderer

    t = 20
    near = np.stack([np.linspace(0.0, 20.0, t), np.zeros(t)], -1)
    far = np.stack([np.linspace(300.0, 310.0, t), np.zeros(t)], -1)
    scene = make_scene(np.stack([near, far]), np.zeros((2, t)), agent_type=AgentType.VEHICLE)
    sim = Simulator([scene], EngineConfig(replay_infeasible=False, init_steps=2), "cpu", controlled=[np.array([True, False])])
    sim.reset()
    spans = {}
    for fit in ("scene", "controlled"):
        r = FrameRenderer(sim, size=(200, 200), legend=False, fit=fit)
        (x0, x1), (y0, y1) = r.ax.get_xlim(), r.ax.get_ylim()
        spans[fit] = (x0, x1)
        r.close()
    assert spans["scene"][0] < 0 and spans["scene"][1] > 310
    assert spans["controlled"][0] < 0 < 20 < spans["controlled"][1] < 100
    with pytest.raises(ValueError, match="fit"):
        FrameRenderer(sim, size=(200, 200), fit="nope")


def test_trail_ticks_mark_every_nth_recorded_position(womd_sim):
    """A dot every `trail_ticks` recorded steps from a trail's start, in the trail's colour; none when 0."""
    from tg_gpudrive.render.draw import FrameRenderer

    a = int(np.nonzero(womd_sim.integrated[0].numpy())[0][0])
    p = womd_sim.pos[0, a].numpy().astype(float)
    trail = {a: p + np.arange(25, dtype=float)[:, None] * [1.0, 0.5]}  # 25 steps along a line
    r = FrameRenderer(womd_sim, 0, size=(320, 320), trail_ticks=10)
    try:
        ticked = r.draw(trail)
        np.testing.assert_allclose(r.ticks.get_offsets(), trail[a][[10, 20]])  # steps 10 and 20, not 0
        np.testing.assert_allclose(r.ticks.get_facecolors()[:, :3], np.tile(np.asarray(r.face[a])[:3], (2, 1)))
    finally:
        r.close()
    plain = render_frame(womd_sim, size=(320, 320), trails=trail)
    assert not np.array_equal(ticked, plain)
    r = FrameRenderer(womd_sim, 0, size=(320, 320))
    try:
        r.draw(trail)
        assert len(r.ticks.get_offsets()) == 0
    finally:
        r.close()
    with pytest.raises(ValueError, match="trail_ticks"):
        FrameRenderer(womd_sim, 0, trail_ticks=-1)

