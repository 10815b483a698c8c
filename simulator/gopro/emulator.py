"""An emulated GoPro on USB: the Open GoPro HTTP API on loopback, the webcam's MPEG-TS stream over
UDP, media files recorded on the shutter, and a zeroconf advertisement.

    with GoProEmulator("C3501324645504", render, width=640, height=360, fps=30) as cam:
        cam.url                        # http://127.0.0.1:<port>, what a client talks to
        cam.inject_http_errors(3)      # the next three requests answer 500
        cam.drop_link(2.0)             # HTTP stalls and the UDP stream goes silent for 2 s
        cam.recordings                 # ground truth of every video: frame k shows t0 + k / fps

Behaviour, as the specification describes a camera:
- shutter start: encoding (status 10) from then on, busy (status 8) for `busy_s`; in a photo
  preset a JPEG and a short encoding pulse (`photo_s`). Shutter stop: encoding off, busy until the
  MP4 is closed, then it is in the media list.
- a setting or preset change makes the camera busy for `busy_s`; changes are refused (403) while
  encoding, for options the other settings rule out, and for video settings outside video presets.
- webcam start streams MPEG-TS over UDP to the requesting host at the requested port (default
  8554) at `fps`, of the frames `render(t)` returns (`width` x `height`); stop leaves the webcam
  idle, exit turns it off.
- keep-alive: once a client has taken wired control or sent a keep-alive, a lapse of
  `keep_alive_timeout_s` without a keep-alive makes the camera give up the client, as it does when
  the keep-alive timer runs out: wired control is released (status 116 = 0) and the webcam stops
  (status off, error 5 "Com timeout"); `events` records it.

`render(t)` gets times from `clock` (default time.monotonic); the default picture is
`pattern.time_code_pattern` (a colour of the serial's, the time written along the top).
`media_render(t)` (default: `render`) draws the photos and videos written to the card: a video
started at `clock()` = t0 shows `media_render(t0 + k / fps)` in frame k (`recordings` keeps t0).
With `stream_on_clock`, the webcam stream is on `clock` too: frame k shows `render(t0 + k / fps)`,
t0 being `clock()` when the stream's schedule began (`stream_t0`), as a camera stamps a frame when
it exposes it, not when its encoder gets round to it; without, `render(k / fps)`. A camera does not
drop frames because its host is busy: frames the emulator makes late (up to `STREAM_LATE_S`) are
sent late, in a burst, not skipped.
Timers (busy, keep-alive, faults) run on the host monotonic clock.
"""
from __future__ import annotations

import re
import shutil
import tempfile
import threading
import time
import zlib
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from simulator.errors import SimulatorError
from simulator.gopro import camera_state as cs
from simulator.gopro.advertise import Advertisement
from simulator.gopro.camera_state import CameraState, Refusal
from simulator.gopro.faults import Faults
from simulator.gopro.http_app import HttpServer, create_app, query_of
from simulator.gopro.media import MediaFile, MediaStore, Recording, VideoWriter, write_photo
from simulator.gopro.pattern import time_code_pattern

DEFAULT_WEBCAM_PORT = 8554
STREAM_LATE_S = 1.0  # how far behind its schedule the emulator's stream may fall before it skips frames
_SERIAL = re.compile(r"[A-Za-z0-9]*[0-9]{3}")


def usb_address(serial: str) -> str:
    """The camera's address on its USB network: 172.2X.1YZ.51, XYZ the serial's last three digits."""
    x, y, z = serial[-3:]
    return f"172.2{x}.1{y}{z}.51"


@dataclass(frozen=True)
class RequestRecord:
    """One request as the camera received it."""

    time: float  # host monotonic seconds
    method: str
    path: str
    query: dict[str, str]
    range: Optional[str]
    client: str


@dataclass(frozen=True)
class EmulatorEvent:
    time: float  # host monotonic seconds
    kind: str  # "keep-alive lapsed", "link dropped", "link back", "recording failed"
    detail: str = ""


@dataclass(frozen=True)
class WebcamInfo:
    status: int
    error: int
    host: Optional[str]
    port: Optional[int]
    resolution: Optional[int]
    fov: Optional[int]
    frames_sent: int


class GoProEmulator:
    """One emulated camera; `start()` / `stop()` or a `with` block."""

    def __init__(self, serial: str, render: Optional[Callable[[float], np.ndarray]] = None, width: int = 1920,
                 height: int = 1080, fps: float = 30.0, host: str = "127.0.0.1", http_port: int = 0,
                 advertise: bool = True, *, media_dir: Optional[str | Path] = None,
                 media_size: Optional[tuple[int, int]] = None, keep_alive_timeout_s: Optional[float] = 10.0,
                 busy_s: float = 0.2, photo_s: float = 0.5, stream_codec: str = "h264",
                 download_bytes_per_s: Optional[float] = None, clock: Callable[[], float] = time.monotonic,
                 media_render: Optional[Callable[[float], np.ndarray]] = None, stream_on_clock: bool = False):
        if not isinstance(serial, str) or not _SERIAL.fullmatch(serial):
            raise SimulatorError(f"GoPro emulator: serial {serial!r} must be letters and digits ending in three digits "
                                 "(e.g. C3501324645504): the USB address comes from them")
        if width < 16 or height < 16 or fps <= 0:
            raise SimulatorError(f"GoPro emulator: need a frame of at least 16x16 and fps > 0, got {width}x{height} at {fps}")
        self.serial = serial
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.render = render or time_code_pattern(self.width, self.height, seed=serial)
        self.media_render = media_render or self.render
        self.host = host
        self.http_port = int(http_port)
        self.advertise = advertise
        self.media_size = tuple(media_size) if media_size else (self.width, self.height)
        self.keep_alive_timeout_s = keep_alive_timeout_s
        self.busy_s, self.photo_s = float(busy_s), float(photo_s)
        self.stream_codec = stream_codec
        self._frames_sent_before = 0
        self.download_bytes_per_s = download_bytes_per_s
        self.clock = clock
        self.stream_on_clock = bool(stream_on_clock)
        self._stream_t0: Optional[float] = None

        self.state = CameraState(self.width, self.height, self.fps)
        self.faults = Faults(time.monotonic)
        self.requests: deque[RequestRecord] = deque(maxlen=20_000)
        self.events: list[EmulatorEvent] = []
        self.recordings: list[Recording] = []
        self._media_dir_arg = Path(media_dir) if media_dir else None
        self._media_dir: Optional[Path] = None
        self.media: MediaStore = None  # type: ignore[assignment] - made by start()
        self._lock = threading.RLock()
        self._server: Optional[HttpServer] = None
        self._advert: Optional[Advertisement] = None
        self._writer: Optional[VideoWriter] = None
        self._writer_name = ""
        self._writer_created = 0.0
        self._finishing: list[threading.Thread] = []
        self._photo_ends = 0.0
        self._streamer = None
        self._webcam_target: tuple[Optional[str], Optional[int], Optional[int], Optional[int]] = (None, None, None, None)
        self._keep_alive_armed = False
        self._last_keep_alive = 0.0
        self._link_was_down = False
        self._stop = threading.Event()
        self._monitor: Optional[threading.Thread] = None

    # --- lifecycle -------------------------------------------------------------------------------------------
    def start(self) -> "GoProEmulator":
        if self._server is not None:
            return self
        self._media_dir = self._media_dir_arg or Path(tempfile.mkdtemp(prefix=f"gopro-{self.serial}-"))
        self.media = MediaStore(self._media_dir)
        self._server = HttpServer(create_app(self), self.host, self.http_port, name=f"gopro-{self.serial}-http").start()
        self._stop.clear()
        self._monitor = threading.Thread(target=self._watch, name=f"gopro-{self.serial}-monitor", daemon=True)
        self._monitor.start()
        if self.advertise:
            self._advert = Advertisement(self.serial, self.host, self._server.port).start()
        return self

    def stop(self) -> None:
        if self._server is None:
            return
        if self.state.encoding:
            self.shutter_stop()
        self._stop_stream()
        self._stop.set()
        if self._monitor is not None:
            self._monitor.join(2)
        for t in list(self._finishing):
            t.join(30)
        if self._advert is not None:
            self._advert.close()
            self._advert = None
        self._server.stop()
        self._server = None
        if self._media_dir_arg is None and self._media_dir is not None:
            shutil.rmtree(self._media_dir, ignore_errors=True)

    def __enter__(self) -> "GoProEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def port(self) -> int:
        if self._server is None:
            raise SimulatorError("GoPro emulator: not started")
        return self._server.port

    @property
    def url(self) -> str:
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(self.host, self.host)
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}"

    @property
    def usb_address(self) -> str:
        return usb_address(self.serial)

    @property
    def media_dir(self) -> Optional[Path]:
        """The card's folder (files under DCIM/100GOPRO)."""
        return self._media_dir

    def wait_advertised(self, timeout: float = 10.0) -> bool:
        """Block until the zeroconf announcement is out (False if not within `timeout`)."""
        if self._advert is None:
            raise SimulatorError("GoPro emulator: not advertising (advertise=False or not started)")
        return self._advert.wait(timeout)

    # --- fault injection -------------------------------------------------------------------------------------
    def inject_http_errors(self, count: Optional[int] = None, *, seconds: Optional[float] = None, status: int = 500) -> None:
        """The next `count` requests, or every request for `seconds`, answer `status` instead."""
        try:
            self.faults.inject_http_errors(count, seconds, status)
        except ValueError as exc:
            raise SimulatorError(f"GoPro emulator: {exc}") from None

    def drop_link(self, seconds: float) -> None:
        """The USB link dies for `seconds`: HTTP requests stall (answered once it is back, if the client
        still waits), downloads stall, the UDP stream goes silent."""
        self.faults.drop_link(seconds)
        self._event("link dropped", f"{seconds:g} s")
        with self._lock:
            streamer = self._streamer
        if streamer is not None:
            streamer.silence(seconds)

    def cut_next_download(self, after_bytes: int) -> None:
        """The next media download sends `after_bytes` bytes, then the connection closes."""
        self.faults.cut_next_download(after_bytes)

    def hold_busy(self, seconds: float) -> None:
        """Status 8 (busy) stays on for `seconds`, as while the camera formats its card."""
        self.state.busy_for(seconds)

    async def _link_hold(self) -> bool:
        import asyncio

        while (wait := self.faults.link_down_for()) > 0:
            await asyncio.sleep(min(wait, 0.05))
        return True

    # --- what routes call ------------------------------------------------------------------------------------
    def _log_request(self, scope) -> None:
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        client = scope.get("client") or ("", 0)
        self.requests.append(RequestRecord(time.monotonic(), scope.get("method", ""), scope.get("path", ""),
                                           query_of(scope), headers.get("range"), str(client[0])))

    def _event(self, kind: str, detail: str = "") -> None:
        with self._lock:
            self.events.append(EmulatorEvent(time.monotonic(), kind, detail))

    def info(self) -> dict:
        digest = f"{zlib.crc32(self.serial.encode()):08x}"
        return {"model_number": cs.MODEL_NUMBER, "model_name": cs.MODEL_NAME, "firmware_version": cs.FIRMWARE_VERSION,
                "serial_number": self.serial, "ap_mac_addr": f"0657{digest}", "ap_ssid": f"GP{self.serial[-8:]}"}

    def keep_alive(self) -> None:
        with self._lock:
            self._keep_alive_armed = True
            self._last_keep_alive = time.monotonic()

    def set_wired_control(self, enabled: bool) -> None:
        with self._lock:
            self.state.wired_control = enabled
            if enabled:
                self._keep_alive_armed = True
                self._last_keep_alive = time.monotonic()

    def load_preset(self, preset_id: int) -> bool:
        if self.state.load_preset(preset_id):
            self.state.busy_for(self.busy_s)
            return True
        return False

    def load_preset_group(self, group: int) -> bool:
        if self.state.load_group(group):
            self.state.busy_for(self.busy_s)
            return True
        return False

    def set_setting(self, setting_id: int, option: int) -> Optional[Refusal]:
        refusal = self.state.set_setting(setting_id, option)
        if refusal is None:
            self.state.busy_for(self.busy_s)
        return refusal

    def shutter_start(self) -> None:
        with self._lock, self.state.lock:
            if self.state.encoding:
                return
            now = self.clock()
            if self.state.in_photo_mode:
                name = self.media.new_name(photo=True)
                image = self.media_render(now)
                write_photo(self.media.folder / name, np.asarray(image)[:, :, :3])
                self.media.add(name, time.time())
                self.state.photos += 1
                self.state.encoding_since = time.monotonic()
                self._photo_ends = time.monotonic() + self.photo_s
                return
            name = self.media.new_name(photo=False)
            fps = self.state.frame_rate
            self._writer = VideoWriter(self.media.folder / name, self.media_render, now, fps, *self.media_size,
                                       clock=self.clock).start()
            self._writer_name = name
            self._writer_created = time.time()
            self.state.encoding_since = time.monotonic()
            self.state.busy_for(self.busy_s)

    def shutter_stop(self) -> None:
        with self._lock, self.state.lock:
            writer = self._writer
            if writer is None:
                return  # not recording video (a photo's encoding ends by itself)
            t1 = self.clock()
            self._writer = None
            self.state.encoding_since = None
            self.state.busy_holds += 1
            name, created = self._writer_name, self._writer_created

        def finish():
            try:
                writer.finish(t1)
                if writer.error is None:
                    media = self.media.add(name, created)
                    with self._lock:
                        self.recordings.append(Recording(media, writer.t0, writer.fps, writer.frames,
                                                         writer.width, writer.height))
                    with self.state.lock:
                        self.state.videos += 1
                else:
                    self._event("recording failed", f"{name}: {writer.error}")
            finally:
                with self.state.lock:
                    self.state.busy_holds -= 1
                self.state.busy_for(self.busy_s)

        thread = threading.Thread(target=finish, name=f"gopro-{self.serial}-finish", daemon=True)
        self._finishing = [t for t in self._finishing if t.is_alive()] + [thread]
        thread.start()

    def last_media(self) -> Optional[MediaFile]:
        return self.media.last()

    # --- webcam ----------------------------------------------------------------------------------------------
    def _webcam_body(self) -> dict:
        return {"status": self.state.webcam_status, "error": self.state.webcam_error}

    def webcam_start(self, client_host: str, *, res: Optional[int], fov: Optional[int], port: Optional[int],
                     protocol: Optional[str]) -> tuple[int, dict]:
        if protocol is not None and protocol.upper() == "RTSP":
            return 501, {}  # this emulator streams MPEG-TS over UDP only
        with self._lock, self.state.lock:
            bad = ((protocol is not None and protocol.upper() != "TS") or (res is not None and res not in cs.WEBCAM_RESOLUTIONS)
                   or (fov is not None and fov not in cs.WEBCAM_FOVS) or (port is not None and not 1 <= port <= 65535))
            if bad:
                self.state.webcam_error = cs.WEBCAM_ERR_INVALID_PARAM
                return 200, self._webcam_body()
            if self.state.encoding:
                self.state.webcam_error = cs.WEBCAM_ERR_SHUTTER
                return 200, self._webcam_body()
            port = port or DEFAULT_WEBCAM_PORT
            self._start_stream(client_host, port)
            self._webcam_target = (client_host, port, res or 12, fov or 0)
            self.state.webcam_status, self.state.webcam_error = cs.WEBCAM_HIGH_POWER, cs.WEBCAM_OK
            return 200, self._webcam_body()

    def webcam_preview(self, client_host: str) -> dict:
        with self._lock, self.state.lock:
            host, port, res, fov = self._webcam_target
            if self.state.encoding:
                self.state.webcam_error = cs.WEBCAM_ERR_SHUTTER
                return self._webcam_body()
            self._start_stream(host or client_host, port or DEFAULT_WEBCAM_PORT)
            self._webcam_target = (host or client_host, port or DEFAULT_WEBCAM_PORT, res or 12, fov or 0)
            self.state.webcam_status, self.state.webcam_error = cs.WEBCAM_LOW_POWER, cs.WEBCAM_OK
            return self._webcam_body()

    def webcam_stop(self) -> dict:
        with self._lock, self.state.lock:
            self._stop_stream()
            if self.state.webcam_status != cs.WEBCAM_OFF:
                self.state.webcam_status = cs.WEBCAM_IDLE
            self.state.webcam_error = cs.WEBCAM_OK
            return self._webcam_body()

    def webcam_exit(self) -> dict:
        with self._lock, self.state.lock:
            self._stop_stream()
            self.state.webcam_status, self.state.webcam_error = cs.WEBCAM_OFF, cs.WEBCAM_OK
            return self._webcam_body()

    def webcam_status(self) -> dict:
        with self.state.lock:
            return self._webcam_body()

    @property
    def webcam(self) -> WebcamInfo:
        with self._lock:
            host, port, res, fov = self._webcam_target
            streamer = self._streamer
            return WebcamInfo(self.state.webcam_status, self.state.webcam_error, host, port, res, fov,
                              int(streamer.frames_sent) if streamer is not None else self._frames_sent_before)

    def _start_stream(self, host: str, port: int) -> None:
        from simulator.video_stream import UdpTsStreamer

        self._stop_stream()
        streamer = UdpTsStreamer(self.render, self.width, self.height, self.fps, host, port, self.stream_codec,
                                 clock=self.clock if self.stream_on_clock else None, late_s=STREAM_LATE_S)
        streamer.start()
        self._stream_t0 = streamer.t0
        if (down := self.faults.link_down_for()) > 0:
            streamer.silence(down)
        self._streamer = streamer

    @property
    def stream_t0(self) -> Optional[float]:
        """The instant frame 0 of the current (or last) webcam stream shows: `clock()` when its
        schedule began with `stream_on_clock`, else 0.0; None before any stream."""
        return self._stream_t0

    def _stop_stream(self) -> None:
        with self._lock:
            streamer, self._streamer = self._streamer, None
        if streamer is not None:
            streamer.stop()
            self._frames_sent_before = int(streamer.frames_sent)  # what the last stream sent, once stopped

    # --- timers ----------------------------------------------------------------------------------------------
    def _watch(self) -> None:
        """Photo encoding pulses, the keep-alive timer and the link's comings and goings."""
        while not self._stop.wait(0.02):
            now = time.monotonic()
            with self._lock, self.state.lock:
                if self._photo_ends and now >= self._photo_ends:
                    self._photo_ends = 0.0
                    self.state.encoding_since = None
                    self.state.busy_for(self.busy_s)
                timeout = self.keep_alive_timeout_s
                lapsed = (timeout is not None and self._keep_alive_armed and now - self._last_keep_alive > timeout)
                if lapsed:
                    self._keep_alive_armed = False
                    self.state.wired_control = False
                    if self.state.streaming or self._streamer is not None:
                        self._stop_stream()
                        self.state.webcam_status, self.state.webcam_error = cs.WEBCAM_OFF, cs.WEBCAM_ERR_COM_TIMEOUT
                    self.events.append(EmulatorEvent(now, "keep-alive lapsed",
                                                     f"no keep-alive for {now - self._last_keep_alive:.1f} s"))
                down = self.faults.link_down_for() > 0
                if self._link_was_down and not down:
                    self.events.append(EmulatorEvent(now, "link back"))
                self._link_was_down = down
