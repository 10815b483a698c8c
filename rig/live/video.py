"""Video files of rendered views (PyAV): H.264 where the installed FFmpeg has an encoder for it,
else MPEG-4 part 2, in an MP4 container."""
from __future__ import annotations

from fractions import Fraction
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from rig.errors import RigError

CODECS = (("libx264", "H.264"), ("h264", "H.264"), ("mpeg4", "MPEG-4 part 2"))


def video_codec() -> tuple[str, str]:
    """(encoder, format name): H.264 where this PyAV/FFmpeg build has an encoder for it, else MPEG-4."""
    import av

    for name, label in CODECS:
        try:
            av.codec.Codec(name, "w")
            return name, label
        except Exception:  # PyAV raises its own UnknownCodecError (and older versions ValueError)
            continue
    raise RigError("this PyAV/FFmpeg build has no H.264 or MPEG-4 encoder")


class VideoWriter:
    """Frames (RGB uint8, all the same size) to an MP4 file: at `fps`, or at the times given to
    `write` (a live output arrives at the model's rate, not the cameras')."""

    def __init__(self, path: str | Path, fps: float = 30.0):
        import av

        self.path = Path(path)
        self.fps = fps
        try:
            self._container = av.open(str(self.path), mode="w")
        except (OSError, av.error.FFmpegError) as exc:
            raise RigError(f"{self.path}: cannot write a video there ({exc})") from None
        self.codec, self.codec_label = video_codec()
        self._stream = None
        self._t0: Optional[float] = None
        self._last_pts = -1
        self.frames = 0

    def write(self, rgb: np.ndarray, t_s: Optional[float] = None) -> None:
        """Append a frame; `t_s`: when it happened (seconds, any origin), else one period after the last."""
        import av

        if self._stream is None:
            h, w = rgb.shape[:2]
            self._stream = self._container.add_stream(self.codec, rate=Fraction(self.fps).limit_denominator(1001))
            self._stream.width, self._stream.height = w - w % 2, h - h % 2  # 4:2:0 needs even sizes
            self._stream.pix_fmt = "yuv420p"
            self._stream.codec_context.time_base = Fraction(1, 1000)
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[: self._stream.height, : self._stream.width]), format="rgb24")
        if t_s is None:
            pts = self._last_pts + max(1, round(1000 / self.fps))
        else:
            self._t0 = t_s if self._t0 is None else self._t0
            pts = max(self._last_pts + 1, round((t_s - self._t0) * 1000))
        frame.pts, frame.time_base = pts, Fraction(1, 1000)
        self._last_pts = pts
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        if self._stream is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
        self._container.close()


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> VideoWriter:
    """RGB uint8 frames (one size) to a video file at `fps`, atomically (a failure leaves nothing
    at `path`); returns the closed writer (its `frames`, `codec`, `codec_label`)."""
    from common.files import atomic_path

    with atomic_path(Path(path)) as tmp:
        writer = VideoWriter(tmp, fps)
        try:
            for rgb in frames:
                writer.write(rgb)
        finally:
            writer.close()
    writer.path = Path(path)
    return writer


def read_frame_count(path: str | Path) -> Optional[int]:
    """How many frames a video file holds (decoded, not the container's claim)."""
    import av

    with av.open(str(path)) as c:
        return sum(1 for _ in c.decode(video=0))
