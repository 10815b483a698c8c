"""The emulated camera's SD card: `DCIM/100GOPRO/` in a folder, the media list in the specification's
shape, and the writers of real media files.

A video is an H.264 MP4 (PyAV) of the frames `render(t)` shows at t = t0 + k / fps for every frame
period k of the encoding interval, so each frame's scene time is known exactly; it is written
frame by frame while the camera encodes (`VideoWriter`), and appears in the list once finished,
as on a camera, where a file shows up when the encoder has closed it. Names follow the camera's
scheme: `GH01nnnn.MP4` (H.264 video, chapter 01) and `GOPRnnnn.JPG`, nnnn the media id.

Media list entries carry the specification's fields n, cre, mod, s, glrv and ls, as strings (the
specification notes that the camera sends every value as a string).
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

DIRECTORY = "100GOPRO"
Render = Callable[[float], np.ndarray]


@dataclass(frozen=True)
class MediaFile:
    directory: str
    name: str
    size: int
    created: int  # seconds since the epoch
    modified: int

    @property
    def path(self) -> str:
        return f"{self.directory}/{self.name}"

    def to_json(self) -> dict:
        return {"n": self.name, "cre": str(self.created), "mod": str(self.modified), "s": str(self.size),
                "glrv": "0", "ls": "-1"}


@dataclass(frozen=True)
class Recording:
    """Ground truth of a recorded video: frame k shows scene time t0 + k / fps."""

    file: MediaFile
    t0: float
    fps: float
    frames: int
    width: int
    height: int

    def frame_time(self, k: int) -> float:
        return self.t0 + k / self.fps


class MediaStore:
    """The card: files under `root/DCIM/100GOPRO`, numbered from 1."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.folder = self.root / "DCIM" / DIRECTORY
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._files: list[MediaFile] = []
        self._next_id = 1
        self.list_id = str(int(time.time() * 1e6))  # the media list's session identifier

    def new_name(self, photo: bool) -> str:
        with self._lock:
            media_id = self._next_id
            self._next_id += 1
        return f"GOPR{media_id:04d}.JPG" if photo else f"GH01{media_id:04d}.MP4"

    def add(self, name: str, created: float) -> MediaFile:
        path = self.folder / name
        st = path.stat()
        media = MediaFile(DIRECTORY, name, st.st_size, int(created), int(st.st_mtime))
        with self._lock:
            self._files.append(media)
        return media

    def files(self) -> list[MediaFile]:
        with self._lock:
            return list(self._files)

    def last(self) -> Optional[MediaFile]:
        with self._lock:
            return self._files[-1] if self._files else None

    def find(self, directory: str, name: str) -> Optional[Path]:
        """The file of a listed medium (None for anything else: no path tricks reach the disk)."""
        with self._lock:
            if any(m.directory == directory and m.name == name for m in self._files):
                return self.folder / name
        return None

    def list_json(self) -> dict:
        files = self.files()
        media = [{"d": DIRECTORY, "fs": [m.to_json() for m in files]}] if files else []
        return {"id": self.list_id, "media": media}

    def free_kb(self) -> int:
        try:
            st = os.statvfs(self.root)
            return int(st.f_bavail * st.f_frsize // 1024)
        except OSError:
            return 0


def _fit(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[1] != width or image.shape[0] != height:
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image[:, :, :3], dtype=np.uint8)


def write_photo(path: Path, image: np.ndarray) -> None:
    tmp = path.with_name(f".{path.stem}.part.jpg")  # cv2 picks the format by the suffix
    if not cv2.imwrite(str(tmp), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90]):
        raise OSError(f"could not write {path}")
    os.replace(tmp, path)


class VideoWriter:
    """Encodes the frames of one recording into an MP4 while the camera encodes.

    `run()` (on its own thread) renders frame k, the instant t0 + k / fps, once its frame period is
    over (at t0 + (k + 1) / fps, as a camera encodes a frame once it is exposed: a picture of what
    lights up or goes dark during the exposure needs to know it), so the work is spread over the
    recording; `finish(t1)` fixes the frame count (the frame periods that began before t1, at least
    one) and returns once the file is closed.
    """

    def __init__(self, path: Path, render: Render, t0: float, fps: float, width: int, height: int,
                 clock: Callable[[], float], bit_rate: int = 2_000_000):
        self.path, self.render, self.t0, self.fps = path, render, t0, fps
        self.width, self.height = width - width % 2, height - height % 2  # 4:2:0 needs even sizes
        self.clock = clock
        self.bit_rate = bit_rate
        self.frames = 0
        self.error: Optional[BaseException] = None
        self._end: Optional[int] = None
        self._wake = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"gopro-encode-{path.name}", daemon=True)

    def start(self) -> "VideoWriter":
        self._thread.start()
        return self

    def finish(self, t1: float, timeout: Optional[float] = None) -> bool:
        self._end = max(1, int(np.ceil((t1 - self.t0) * self.fps - 1e-9)))
        self._wake.set()
        return self._done.wait(timeout)

    def _run(self) -> None:
        import av

        tmp = self.path.with_name(f".{self.path.name}.part")
        try:
            rate = Fraction(self.fps).limit_denominator(1001)
            with av.open(str(tmp), mode="w", format="mp4") as container:
                stream = container.add_stream("libx264", rate=rate)
                stream.width, stream.height, stream.pix_fmt = self.width, self.height, "yuv420p"
                stream.bit_rate = self.bit_rate
                stream.options = {"preset": "ultrafast", "tune": "zerolatency"}
                stream.time_base = 1 / rate
                k = 0
                while self._end is None or k < self._end:
                    exposed = self.t0 + (k + 1) / self.fps  # the end of frame k's exposure
                    if self._end is None and self.clock() < exposed:
                        self._wake.wait(min(0.05, max(0.0, exposed - self.clock())))
                        continue
                    image = _fit(self.render(self.t0 + k / self.fps), self.width, self.height)
                    frame = av.VideoFrame.from_ndarray(image, format="rgb24")
                    frame.pts = k
                    for packet in stream.encode(frame):
                        container.mux(packet)
                    k += 1
                    self.frames = k
                for packet in stream.encode(None):
                    container.mux(packet)
            os.replace(tmp, self.path)
        except BaseException as exc:  # noqa: BLE001 - reported by the emulator (the file is then absent)
            self.error = exc
            tmp.unlink(missing_ok=True)
        finally:
            self._done.set()
