"""Frames from a compressed video stream: a GoPro's webcam stream (MPEG-TS over UDP), a network
camera (RTSP, UDP MPEG-TS, HTTP MJPEG).

A thread opens the stream with PyAV (FFmpeg), decodes it and hands each frame over with two times:
its host arrival (monotonic ns, when it was decoded) and its device time, the stream's own
presentation time (pts x time base), which a free-running camera stamps when it takes the frame. The
hand-over keeps the newest frames (a bounded queue: a slow consumer loses the oldest, counted as
dropped, never an unbounded backlog). A stream that goes silent for `stall_s` ends the thread; reads
then raise CameraDisconnected until `reopen()` succeeds.

PyAV rather than OpenCV's VideoCapture: it gives each frame's pts in the stream's time base, and a
read timeout on a UDP socket that sends nothing.
"""
from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from rig.cameras.base import Camera
from rig.errors import CameraDisconnected, CameraTimeout
from sync.frames import Frame, monotonic_ns


@dataclass
class ReaderStats:
    decoded: int = 0
    dropped: int = 0  # decoded frames the consumer never took (the queue was full)
    opened: int = 0
    errors: int = 0


class VideoReader:
    QUEUE_FRAMES = 8

    def __init__(self, url: str, camera: str, *, format: Optional[str] = None, options: Optional[dict] = None,
                 stall_s: float = 2.0, open_s: float = 5.0, pixel_format: str = "RGB8",
                 size: Optional[tuple[int, int]] = None):
        self.url, self.camera, self.format = url, camera, format
        self.options = dict(options or {})
        self.stall_s, self.open_s = float(stall_s), float(open_s)
        self.pixel_format, self.size = pixel_format, size
        self.stats = ReaderStats()
        self.problem: Optional[str] = None  # why the stream ended
        self._queue: queue.Queue = queue.Queue(maxsize=self.QUEUE_FRAMES)
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._opened = threading.Event()
        # Frame ids: the frame's place in the stream (pts x frame rate), so that frames the stream
        # lost show as gaps; when a stream starts again (its pts back at 0, or a reopen) they go
        # on from the last one handed over.
        self._id_base = 0
        self._last_id = 0

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, wait_s: float = 0.0) -> None:
        """Open the stream in the reader thread; with `wait_s`, wait that long for it to open."""
        if self.alive:
            return
        self._stop.clear()
        self._opened.clear()
        self.problem = None
        self._thread = threading.Thread(target=self._run, name=f"video-{self.camera}", daemon=True)
        self._thread.start()
        if wait_s > 0:
            self._opened.wait(wait_s)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(self.stall_s + self.open_s + 1)
        self._thread = None

    def reopen(self) -> None:
        self.stop()
        while not self._queue.empty():
            self._queue.get_nowait()
        self.start()

    def read(self, timeout: float) -> Frame:
        """The next frame; CameraTimeout when none came within `timeout`, CameraDisconnected once
        the stream has ended (silent for `stall_s`, or closed)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self._queue.get(timeout=min(0.05, max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                if not self.alive and self._queue.empty():
                    raise CameraDisconnected(f"{self.camera}: {self.problem or 'the stream is closed'}") from None
                if time.monotonic() >= deadline:
                    raise CameraTimeout(f"{self.camera}: no frame within {timeout:.3f} s from {self.url}") from None

    # --- the thread ---------------------------------------------------------------------------------
    def _run(self) -> None:
        import av

        try:
            container = av.open(self.url, format=self.format, options=self.options, timeout=(self.open_s, self.stall_s))
        except Exception as exc:  # noqa: BLE001 - FFmpeg's errors are many; all of them end this stream
            self.problem = f"cannot open {self.url}: {exc}"
            self.stats.errors += 1
            return
        self.stats.opened += 1
        self._opened.set()
        try:
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            rate = stream.average_rate or stream.guessed_rate
            first_id = prev = None
            for frame in container.decode(stream):
                host_ns = monotonic_ns()
                if self._stop.is_set():
                    break
                if frame.pts is None:
                    continue
                seconds = float(frame.pts * frame.time_base)
                index = int(round(seconds * float(rate))) if rate else self.stats.decoded
                if first_id is None or index <= prev:  # the first frame, or the sender started its stream again
                    self._id_base, first_id = self._last_id, index
                prev = index
                frame_id = self._id_base + 1 + index - first_id
                self._hand_over(self._convert(frame), frame_id, int(round(seconds * 1e9)), host_ns)
            else:
                self.problem = f"the stream {self.url} ended"
        except Exception as exc:  # noqa: BLE001 - a read timeout (silent stream) or a broken one
            self.problem = f"the stream stopped ({type(exc).__name__}: {exc})"
            self.stats.errors += 1
        finally:
            try:
                container.close()
            except Exception:  # noqa: BLE001 - closing what already broke
                pass

    def _convert(self, frame) -> np.ndarray:
        if self.size is not None and (frame.width, frame.height) != self.size:
            frame = frame.reformat(width=self.size[0], height=self.size[1])
        if self.pixel_format == "Mono8":
            return frame.to_ndarray(format="gray")
        return frame.to_ndarray(format="rgb24")

    def _hand_over(self, image: np.ndarray, frame_id: int, device_ns: int, host_ns: int) -> None:
        self.stats.decoded += 1
        self._last_id = frame_id
        frame = Frame(image=image, camera=self.camera, frame_id=frame_id, device_ts_ns=device_ns,
                      host_ts_ns=host_ns, pixel_format=self.pixel_format)
        while True:
            try:
                self._queue.put_nowait(frame)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()  # the oldest goes: the consumer wants the newest
                    self.stats.dropped += 1
                except queue.Empty:
                    pass




class ReaderCamera(Camera):
    """A free-running camera whose frames come from a VideoReader (`self.reader`, set by the
    subclass): stream:// and uvc://. `_before_start()` is the subclass's device set-up."""

    reader: VideoReader
    _started = False

    def _before_start(self) -> None:
        pass

    def start(self) -> None:
        if not self._started:
            self._before_start()
            self.reader.start()
            self._started = True

    def stop(self) -> None:
        if self._started:
            self.reader.stop()
            self._started = False

    def close(self) -> None:
        self.stop()

    def _read_frame(self, timeout: float) -> Frame:
        frame = self.reader.read(timeout)
        self.stats.extra["stream_dropped"] = self.reader.stats.dropped
        return frame
