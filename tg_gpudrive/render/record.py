"""Recording: stepping an episode, capturing one world's frames and writing GIF / MP4 / PNG.

    rec = EpisodeRecorder(sim, world=0)                 # one figure reused for every frame
    rec.capture()                                       # after reset and after each step
    rec.save("episode.gif")                             # .gif, .mp4 or .png (last frame)
    frames = render_episode(sim, policy, steps, out="episode.gif")

The pictures themselves come from draw.py. `render_episode` is the only place
here that steps the simulator (it resets it first); the recorder and the
writers only read it. MP4 needs ffmpeg: imageio-ffmpeg when installed, else an
ffmpeg on PATH through matplotlib (`mp4_backend` says which, `check_mp4` fails
early with what to install).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from matplotlib import animation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image
from tqdm import tqdm

from tg_gpudrive.render.draw import (BACKGROUND, COLLIDED, CONTROLLED, CYCLIST, DPI, OFFROAD, OTHER, PEDESTRIAN,
                                     REPLAYED, ROAD_EDGE, STOP_SIGN, FrameRenderer, as_numpy, rgba)


class EpisodeRecorder:
    """Frames of one world: call `capture()` after `reset()` and after each `step()`.

    Keeps a trail of past positions per agent (the last `trail_length` steps,
    all when None); a new episode (auto-reset, or the world's step going back)
    starts the trails afresh. With `auto_reset` on, the step that ends an
    episode already shows the world after its reset (the engine keeps no final
    positions): `render_episode` stops before that frame, or run the engine
    with `auto_reset: false` to see the final state. `capture(draw=False)`
    only extends the trails. `seconds` accumulates drawing time, so
    `seconds_per_frame` is the cost of a frame.
    """

    def __init__(self, sim, world: int = 0, *, trail_length: int | None = None, **render_kw):
        self.sim, self.world, self.render_kw = sim, int(world), render_kw
        self.trail_length = trail_length
        self.frames: list[np.ndarray] = []
        self.trails: dict[int, list[np.ndarray]] = {}
        self.seconds = 0.0
        self._renderer: FrameRenderer | None = None
        self._last_step = -1

    @property
    def renderer(self) -> FrameRenderer:
        # a new batch of scenes (sim.set_scenes) invalidates the road layer and the per-agent colours
        if self._renderer is None or self._renderer.model is not self.sim.model:
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = FrameRenderer(self.sim, self.world, **self.render_kw)
            self.trails = {}
        return self._renderer

    def _record_positions(self) -> None:
        sim, w = self.sim, self.world
        step = int(sim.world_step[w])
        if int(sim.world_reset[w]) != 0 or step < self._last_step:
            self.trails = {}
        self._last_step = step
        shown = (as_numpy(sim.present[w]) != 0) & (as_numpy(sim.removed[w]) == 0) & (as_numpy(sim.slot_valid[w]) != 0)
        pos = as_numpy(sim.pos[w])
        for a in np.nonzero(shown)[0]:
            tr = self.trails.setdefault(int(a), [])
            tr.append(pos[a].astype(np.float64))
            if self.trail_length is not None and len(tr) > self.trail_length:
                del tr[: len(tr) - self.trail_length]

    def capture(self, draw: bool = True) -> np.ndarray | None:
        renderer = self.renderer
        self._record_positions()
        if not draw:
            return None
        t0 = time.perf_counter()
        frame = renderer.draw({a: np.asarray(tr) for a, tr in self.trails.items()})
        self.seconds += time.perf_counter() - t0
        self.frames.append(frame)
        return frame

    @property
    def seconds_per_frame(self) -> float:
        return self.seconds / max(len(self.frames), 1)

    def save(self, path: str | Path, fps: float = 10, frame: int = -1) -> Path:
        """Write .gif / .mp4 (all frames) or .png (frame `frame`, default the last)."""
        path = Path(path)
        ext = path.suffix.lower()
        if ext not in (".gif", ".mp4", ".png"):
            raise ValueError(f"{path}: expected a .gif, .mp4 or .png file name")
        if not self.frames:
            if ext != ".png":
                raise ValueError("nothing to save: no frames captured")
            self.capture()  # a .png of the current state
        path.parent.mkdir(parents=True, exist_ok=True)
        if ext == ".png":
            Image.fromarray(self.frames[frame]).save(path)
        elif ext == ".gif":
            save_gif(self.frames, path, fps)
        else:
            save_mp4(self.frames, path, fps)
        return path

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def save_gif(frames: list[np.ndarray], path: str | Path, fps: float = 10) -> None:
    """Looping GIF. Note: GIF writers merge consecutive identical frames (the step counter keeps ours distinct)."""
    # one shared adaptive palette (no per-frame colour flicker, a smaller file), made from a few frames plus
    # swatches of the key colours so that an outline appearing late in the episode keeps its colour
    keys = np.array([rgba(c)[:3] * 255 for c in (COLLIDED, OFFROAD, CONTROLLED, REPLAYED, PEDESTRIAN, CYCLIST,
                                                   OTHER, STOP_SIGN, ROAD_EDGE, BACKGROUND)], np.uint8)
    w = frames[0].shape[1]
    swatch = np.repeat(np.repeat(keys[None], 8, 0), -(-w // len(keys)), 1)[:, :w]
    sample = np.concatenate([frames[i][::2] for i in sorted({0, len(frames) // 2, len(frames) - 1})]
                            + [swatch] * 40)
    pal = Image.fromarray(sample).quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    ims = [Image.fromarray(f).quantize(palette=pal, dither=Image.Dither.NONE) for f in frames]
    ims[0].save(path, save_all=True, append_images=ims[1:], duration=max(int(round(1000 / fps)), 20), loop=0)


def mp4_backend() -> str | None:
    """How .mp4 would be written: "imageio" (imageio-ffmpeg installed), "matplotlib" (ffmpeg on PATH) or None."""
    try:  # optional: imageio-ffmpeg is not in the render extra
        import imageio_ffmpeg  # noqa: F401

        return "imageio"
    except ImportError:
        pass
    return "matplotlib" if animation.writers.is_available("ffmpeg") else None


def check_mp4() -> None:
    """Raise a RuntimeError telling the user what to do when no .mp4 writer is available."""
    if mp4_backend() is None:
        raise RuntimeError("writing .mp4 needs ffmpeg (pip install imageio-ffmpeg, or put an ffmpeg on PATH); "
                           "save a .gif instead")


def save_mp4(frames: list[np.ndarray], path: str | Path, fps: float = 10) -> None:
    """H.264 MP4 through imageio's ffmpeg plugin, else matplotlib's FFMpegWriter (needs ffmpeg on PATH)."""
    check_mp4()
    h, w = frames[0].shape[:2]
    if mp4_backend() == "imageio":
        import imageio.v2 as iio  # present when imageio-ffmpeg is (mp4_backend)

        with iio.get_writer(path, fps=fps, codec="libx264", quality=7, macro_block_size=2,
                            pixelformat="yuv420p") as wr:
            for f in frames:
                wr.append_data(f[: h - h % 2, : w - w % 2])  # yuv420p wants even sides
        return
    fig = Figure(figsize=(w / DPI, h / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    im = ax.imshow(frames[0], interpolation="none")
    writer = animation.FFMpegWriter(fps=fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p"])
    with writer.saving(fig, str(path), dpi=DPI):
        for f in frames:
            im.set_data(f)
            writer.grab_frame()


def render_episode(sim, policy: Callable, steps: int | None = None, world: int = 0, out: str | Path | None = None,
                   *, fps: float = 10, reset: bool = True, stop_at_end: bool = True, progress: bool = False,
                   seed: int | None = None, **kw) -> list[np.ndarray]:
    """Reset `sim`, record world `world` under `policy(sim)` for `steps` steps; optionally save to `out`.

    Returns the frames, the reset state first. `steps` defaults to one episode.
    With `stop_at_end` (default) recording stops when the world's episode ends
    (all its controlled agents done, or the log ran out): with the engine's
    `auto_reset` on, the frame of that step would show the world reset, so it
    is left out; with `auto_reset: false` the final state is the last frame.
    Other keywords go to `EpisodeRecorder` / `render_frame`. For a .png `out`
    without auto-reset only the last frame is drawn (and returned). `seed` seeds torch's generator
    first, which trained policies sample from (as `run_rollout` and `record_episodes` do): the same
    seed draws the same episode.
    """
    if seed is not None:
        torch.manual_seed(seed)
    if out is not None and Path(out).suffix.lower() == ".mp4":
        check_mp4()  # fail before the episode, not after it
    if steps is None:
        steps = sim.episode_length
    if reset:
        sim.reset()
    rec = EpisodeRecorder(sim, world, **kw)
    # a .png needs only the last frame; without auto-reset the final state stays to be drawn at the end
    lazy = out is not None and Path(out).suffix.lower() == ".png" and not getattr(sim.cfg, "auto_reset", True)
    bar = None
    if progress:
        bar = tqdm(total=steps, desc="render", unit="step", leave=False)
    try:
        rec.capture(draw=not lazy)
        for _ in range(steps):
            policy(sim)
            sim.step()
            if bar is not None:
                bar.update(1)
            if stop_at_end and int(sim.world_reset[world]) != 0:
                break
            rec.capture(draw=not lazy)
            if stop_at_end and int(sim.world_ended[world]) != 0:
                break
    finally:
        if bar is not None:
            bar.close()
    if lazy:
        rec.frames.append(rec.renderer.draw({a: np.asarray(tr) for a, tr in rec.trails.items()}))
    if out is not None:
        rec.save(out, fps=fps)
    rec.close()
    return rec.frames
