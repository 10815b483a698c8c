"""Simulated network video streams: what a GoPro's webcam mode, an IP camera or an MJPEG webcam sends.

    streamer = UdpTsStreamer(render, 1280, 720, 30.0, "127.0.0.1", 8554)   # MPEG-TS over UDP
    streamer.start(); ...; streamer.silence(2.0); ...; streamer.stop()
    server = MjpegHttpServer(render, 640, 360, 15.0); server.start(); server.url   # multipart MJPEG

`render(t)` gives the frame (HxWx3 uint8 RGB) of the instant `t`: `t0` plus the seconds since the
stream started. To put the stream on another clock's timeline (the simulated scene's), pass `clock`:
`t0` is then that clock's reading at the stream's start, taken by the streaming thread itself, so
frame k shows exactly the instant it was exposed over, however late the thread got going. Frames go out in real
time on an absolute schedule (frame k at start + k / fps, so the rate never drifts); a frame whose
time has passed while the previous one was made is skipped, as a camera that cannot keep up drops
frames. An emulated camera that only falls behind because its host is busy (a real one would not)
passes `late_s`: frames up to that late are still made and sent, in a burst, as a link that
delivers late does. Each frame's presentation time is its index in 1/fps units, so a receiver recovers when it
was taken.
"""
from __future__ import annotations

import socket
import threading
import time
from fractions import Fraction
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable, Optional

import cv2
import numpy as np

Render = Callable[[float], np.ndarray]
TS_PACKET = 188 * 7  # bytes per UDP datagram: seven MPEG-TS packets, as cameras and FFmpeg send them


class UdpTsStreamer:
    """MPEG-TS (H.264, or another codec PyAV has) over UDP to host:port, in real time."""

    def __init__(self, render: Render, width: int, height: int, fps: float, host: str = "127.0.0.1",
                 port: int = 8554, codec: str = "h264", *, t0: float = 0.0, bitrate: int = 4_000_000,
                 clock: Optional[Callable[[], float]] = None, late_s: Optional[float] = None):
        if not (width > 0 and height > 0 and width % 2 == 0 and height % 2 == 0):
            raise ValueError(f"stream size must be positive and even, got {width}x{height}")
        if not 0 < fps <= 240:
            raise ValueError(f"stream rate must be between 0 and 240 fps, got {fps}")
        if not 1 <= int(port) <= 65535:
            raise ValueError(f"UDP port must be 1-65535, got {port}")
        self.render, self.width, self.height, self.fps = render, int(width), int(height), float(fps)
        self.host, self.port, self.codec, self.t0, self.bitrate = host, int(port), codec, float(t0), int(bitrate)
        self.clock = clock
        self.late_s = 1.0 / self.fps if late_s is None else float(late_s)
        self.frames_sent = 0
        self.frames_skipped = 0
        self.started_at: Optional[float] = None  # time.monotonic() of frame 0
        self._silent_until = 0.0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self.error: Optional[str] = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> "UdpTsStreamer":
        if self.running:
            return self
        self._stop.clear()
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(ready,), name=f"ts-stream-{self.port}", daemon=True)
        self._thread.start()
        ready.wait(5.0)
        if self.error:
            raise RuntimeError(self.error)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._thread = None

    def silence(self, seconds: float) -> None:
        """Send nothing for `seconds` (a link that drops); frames of that time are lost."""
        self._silent_until = max(self._silent_until, time.monotonic() + float(seconds))

    def _open(self):
        import av

        container = av.open(f"udp://{self.host}:{self.port}?pkt_size={TS_PACKET}", mode="w", format="mpegts")
        names = [self.codec, "libx264", "mpeg2video"] if self.codec in ("h264", "libx264") else [self.codec, "mpeg2video"]
        for name in names:
            try:
                stream = container.add_stream(name, rate=Fraction(self.fps).limit_denominator(1001))
                break
            except (ValueError, av.error.FFmpegError):  # a codec this build of FFmpeg lacks: the next one
                continue
        else:
            container.close()
            raise RuntimeError(f"none of the codecs {', '.join(names)} is available to PyAV")
        stream.width, stream.height, stream.pix_fmt = self.width, self.height, "yuv420p"
        stream.bit_rate = self.bitrate
        stream.codec_context.time_base = Fraction(1, 1) / stream.codec_context.framerate
        gop = max(1, int(round(self.fps / 2)))  # a key frame twice a second: a receiver that joins or loses packets recovers fast
        stream.codec_context.gop_size = gop
        if stream.codec_context.name == "libx264":
            stream.codec_context.options = {"preset": "ultrafast", "tune": "zerolatency"}
        return container, stream

    def _run(self, ready: threading.Event) -> None:
        import av

        try:
            container, stream = self._open()
        except Exception as exc:  # noqa: BLE001 - reported by start()
            self.error = f"cannot stream to udp://{self.host}:{self.port}: {exc}"
            ready.set()
            return
        self.started_at = time.monotonic()
        if self.clock is not None:  # the schedule's origin on that clock: frame k covers t0 + [k, k + 1] / fps
            self.t0 = float(self.clock())
        ready.set()
        k = 0
        key_next = False
        try:
            while not self._stop.is_set():
                due = self.started_at + (k + 1) / self.fps  # frame k is read out once its time is over
                wait = due - time.monotonic()
                if wait > 0 and self._stop.wait(wait):
                    break
                if time.monotonic() - due > self.late_s:  # this frame's time has passed: skip it
                    self.frames_skipped += 1
                    k += 1
                    continue
                if time.monotonic() < self._silent_until:
                    k += 1
                    key_next = True  # the receiver lost the reference frames: start again from a key frame
                    continue
                frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(self.render(self.t0 + k / self.fps)), format="rgb24")
                frame.pts = k
                if key_next:
                    frame.pict_type = av.video.frame.PictureType.I
                    key_next = False
                for packet in stream.encode(frame):
                    container.mux(packet)
                self.frames_sent += 1
                k += 1
        except Exception as exc:  # noqa: BLE001 - the stream ends; say why
            self.error = f"udp://{self.host}:{self.port}: stream stopped: {exc}"
        finally:
            try:
                container.close()
            except Exception:  # noqa: BLE001 - closing a broken stream
                pass


class MjpegHttpServer:
    """`multipart/x-mixed-replace` MJPEG over HTTP at `url` (path /video.mjpg), any number of
    clients, in real time; the stdlib HTTP server is enough for a test stream."""

    PATH = "/video.mjpg"

    def __init__(self, render: Render, width: int, height: int, fps: float, host: str = "127.0.0.1", port: int = 0,
                 *, t0: float = 0.0, quality: int = 85):
        self.render, self.width, self.height, self.fps = render, int(width), int(height), float(fps)
        self.t0, self.quality = float(t0), int(quality)
        self._host, self._port = host, int(port)
        self._server: Optional[ThreadingHTTPServer] = None
        self._thread: Optional[threading.Thread] = None
        self._frame: tuple[int, bytes] = (-1, b"")
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self.started_at: Optional[float] = None

    @property
    def url(self) -> str:
        if self._server is None:
            raise RuntimeError("the MJPEG server is not started")
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}{self.PATH}"

    def start(self) -> "MjpegHttpServer":
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet
                pass

            def do_GET(self) -> None:
                if self.path.split("?")[0] != owner.PATH:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.send_header("Cache-Control", "no-cache")
                self.end_headers()
                last = -1
                try:
                    while not owner._stop.is_set():
                        with owner._cv:
                            owner._cv.wait_for(lambda: owner._frame[0] != last or owner._stop.is_set(), timeout=1.0)
                            last, jpeg = owner._frame
                        if not jpeg:
                            continue
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                         + str(len(jpeg)).encode() + b"\r\n\r\n" + jpeg + b"\r\n")
                        self.wfile.flush()
                except (BrokenPipeError, ConnectionResetError, socket.timeout):
                    pass

        self._server = ThreadingHTTPServer((self._host, self._port), Handler)
        self._server.daemon_threads = True
        self._stop.clear()
        threading.Thread(target=self._server.serve_forever, name="mjpeg-http", daemon=True).start()
        self._thread = threading.Thread(target=self._produce, name="mjpeg-frames", daemon=True)
        self._thread.start()
        return self

    def _produce(self) -> None:
        self.started_at = time.monotonic()
        k = 0
        while not self._stop.is_set():
            due = self.started_at + (k + 1) / self.fps
            wait = due - time.monotonic()
            if wait > 0 and self._stop.wait(wait):
                break
            rgb = self.render(self.t0 + k / self.fps)
            ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, self.quality])
            with self._cv:
                self._frame = (k, jpeg.tobytes() if ok else b"")
                self._cv.notify_all()
            k += 1

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        if self._thread is not None:
            self._thread.join(5.0)
        self._thread = None
