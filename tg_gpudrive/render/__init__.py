"""Top-down pictures and videos of one world of a `Simulator` (matplotlib Agg, no display).

    frame = render_frame(sim, world=0)                  # (H, W, 3) uint8 of the current state
    rec = EpisodeRecorder(sim, world=0)                 # one figure reused for every frame
    rec.capture()                                       # after reset and after each step
    rec.save("episode.gif")                             # .gif, .mp4 or .png (last frame)
    frames = render_episode(sim, policy, steps, out="episode.gif")

    draw.py    the picture: palette, FrameRenderer (road layer once, agents per frame), render_frame
    record.py  the episode: EpisodeRecorder (frames and trails), render_episode, GIF / MP4 / PNG writers

Needs the render extra (matplotlib, Pillow; imageio-ffmpeg or an ffmpeg on PATH for .mp4). Nothing
here writes engine state; only `render_episode` steps the simulator.
"""

from tg_gpudrive.render.draw import (BACKGROUND, COLLIDED, CONTROLLED, CROSSWALK, CYCLIST, DEFAULT_VIEW_RADIUS,
                                     DRIVEWAY, GOAL, HIGHLIGHT, LANE, OFFROAD, OTHER, PEDESTRIAN, REPLAYED,
                                     ROAD_EDGE, ROAD_LINE, SIGNAL_COLOUR, SPEED_BUMP, STOP_SIGN, TYPE_COLOUR,
                                     FrameRenderer, render_frame, rgba)
from tg_gpudrive.render.record import EpisodeRecorder, check_mp4, mp4_backend, render_episode, save_gif, save_mp4

__all__ = ["BACKGROUND", "COLLIDED", "CONTROLLED", "CROSSWALK", "CYCLIST", "DEFAULT_VIEW_RADIUS", "DRIVEWAY", "GOAL",
           "HIGHLIGHT", "LANE", "OFFROAD", "OTHER", "PEDESTRIAN", "REPLAYED", "ROAD_EDGE", "ROAD_LINE",
           "SIGNAL_COLOUR", "SPEED_BUMP", "STOP_SIGN", "TYPE_COLOUR", "EpisodeRecorder", "FrameRenderer",
           "check_mp4", "mp4_backend", "render_episode", "render_frame", "rgba", "save_gif", "save_mp4"]
