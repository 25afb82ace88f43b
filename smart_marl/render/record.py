"""Recording episodes: RGB frames -> GIF or MP4, and the logged scene as an animation.

Stage: rendering, at the end of the data flow. :class:`EpisodeRecorder` takes the images that
:class:`~smart_marl.render.bev.BevRenderer` (or anything else) makes; :func:`render_log_replay`
renders a scene's log frame by frame. imageio (GIF through Pillow) and imageio-ffmpeg (MP4; its
wheel ships the ffmpeg binary) are imported when a file is written.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..scenario import Scenario
from .bev import BevRenderer

FRAME_FPS = 10.0
"""Frames per second of an animation with one image per 0.1 s frame (real time)."""
TOKEN_STEP_FPS = 2.0
"""Frames per second of an animation with one image per 0.5 s token step (real time)."""

_FORMATS = {".gif": "gif", ".mp4": "mp4"}


class EpisodeRecorder:
    """Collects RGB frames and writes them as a GIF or an MP4, chosen by the path's extension.

    ``fps`` is the playback rate: :data:`FRAME_FPS` (10) for one image per 0.1 s frame,
    :data:`TOKEN_STEP_FPS` (2) for one image per 0.5 s token step, or anything else. Frames are
    kept in memory until :meth:`write` (600x600 RGB is ~1 MB a frame). MP4s are H.264 through the
    ffmpeg binary that the ``imageio-ffmpeg`` wheel ships; odd image sizes are padded to even.
    """

    def __init__(self, path: str | os.PathLike, fps: float = FRAME_FPS):
        self.path = Path(path)
        ext = self.path.suffix.lower()
        if ext not in _FORMATS:
            raise ValueError(f"EpisodeRecorder: cannot write {self.path}: unknown extension {ext or '(none)'!r}; "
                             f"use one of {', '.join(_FORMATS)}")
        if not fps > 0:
            raise ValueError(f"EpisodeRecorder: fps must be positive, got {fps}")
        self.format = _FORMATS[ext]
        self.fps = float(fps)
        self.frames: list[np.ndarray] = []

    def add(self, frame: np.ndarray) -> None:
        """Append one ``[H, W, 3] uint8`` image (all frames must share a size)."""
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] not in (3, 4) or frame.dtype != np.uint8:
            raise ValueError(f"EpisodeRecorder: a frame must be [H, W, 3] uint8, got {frame.shape} {frame.dtype}")
        if self.frames and frame.shape[:2] != self.frames[0].shape[:2]:
            raise ValueError(f"EpisodeRecorder: frame size {frame.shape[:2]} differs from the first {self.frames[0].shape[:2]}")
        self.frames.append(np.ascontiguousarray(frame[..., :3]))

    def extend(self, frames: Sequence[np.ndarray]) -> None:
        for frame in frames:
            self.add(frame)

    def __len__(self) -> int:
        return len(self.frames)

    def write(self) -> Path:
        """Write the file (creating its folder) and return its path."""
        if not self.frames:
            raise ValueError(f"EpisodeRecorder: no frames to write to {self.path}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.format == "gif":
            import imageio.v3 as iio

            # Pillow stores durations in ms; loop=0 repeats forever.
            iio.imwrite(self.path, np.stack(self.frames), extension=".gif", duration=1000.0 / self.fps, loop=0)
        else:
            import imageio_ffmpeg

            h, w = self.frames[0].shape[:2]
            ph, pw = h + h % 2, w + w % 2
            writer = imageio_ffmpeg.write_frames(str(self.path), (pw, ph), fps=self.fps, codec="libx264",
                                                 pix_fmt_out="yuv420p", macro_block_size=1, quality=7,
                                                 ffmpeg_log_level="error")
            writer.send(None)
            try:
                for frame in self.frames:
                    if (ph, pw) != (h, w):
                        frame = np.pad(frame, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
                    writer.send(np.ascontiguousarray(frame))
            finally:
                writer.close()
        return self.path


def render_log_replay(scenario: Scenario, path: str | os.PathLike, fps: float = FRAME_FPS, every: int = 1,
                      history_frames: int = 10, **renderer_kw) -> Path:
    """Write the logged scene as an animation (GIF or MP4 by extension): every ``every``-th frame
    from the first to the last, at ``fps``. Returns the path."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    renderer = BevRenderer(scenario, **renderer_kw)
    recorder = EpisodeRecorder(path, fps=fps)
    for f in range(0, scenario.num_frames, every):
        recorder.add(renderer.render_logged(f, history_frames=history_frames))
    renderer.close()
    return recorder.write()
