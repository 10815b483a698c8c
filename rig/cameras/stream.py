"""`stream://URL`: a network camera's video stream, decoded with FFmpeg (rig.cameras.video_reader).

    stream://rtsp://192.168.1.20:554/stream1       RTSP (over TCP)
    stream://udp://127.0.0.1:5000                  MPEG-TS over UDP, received on this host's port 5000
    stream://http://192.168.1.21/video.mjpg        HTTP multipart MJPEG

A network camera free-runs (trigger = "free"): its frames carry the stream's presentation time as
device time and their arrival as host time; frames are converted to the configured pixel format
(RGB8 or Mono8) and size. Network streams are configured, not found: `discover()` lists none.
"""
from __future__ import annotations

from urllib.parse import urlsplit

from rig.cameras.base import DeviceInfo, free_running_problems, raise_problems
from rig.cameras.video_reader import ReaderCamera, VideoReader
from rig.errors import ConfigError

SCHEME = "stream"
INNER = {"rtsp": "rtsp", "rtsps": "rtsp", "udp": "mpegts", "rtp": None, "srt": "mpegts", "tcp": "mpegts",
         "http": None, "https": None}  # inner scheme -> FFmpeg demuxer (None: FFmpeg finds it)
STALL_S = 2.0


def discover() -> list[DeviceInfo]:
    return []


def open(uri: str, settings) -> "StreamCamera":  # noqa: A001 - the backend contract's name
    return StreamCamera(uri, settings)


def inner_url(uri: str) -> tuple[str, str]:
    """(the stream's own URL, its scheme) from stream://URL."""
    inner = uri[len(SCHEME) + 3:] if uri.startswith(f"{SCHEME}://") else ""
    parts = urlsplit(inner)
    if parts.scheme not in INNER or not parts.netloc:
        raise ConfigError(f"{uri}: a stream URI is stream://URL with URL one of {', '.join(f'{s}://...' for s in INNER)}, "
                          "e.g. stream://udp://127.0.0.1:5000 or stream://rtsp://CAMERA/stream1")
    return inner, parts.scheme


def problems(uri: str, settings) -> list[str]:
    """What keeps these settings from working with a network stream (`rig config check` and opening ask)."""
    out = []
    try:
        inner_url(uri)
    except ConfigError as exc:
        out.append(str(exc))
    out += free_running_problems("a network stream", settings)
    return out


class StreamCamera(ReaderCamera):
    def __init__(self, uri: str, settings):
        super().__init__(uri, settings)
        raise_problems(settings, uri, problems(uri, settings))
        self.url, scheme = inner_url(uri)
        options = {}
        url = self.url
        if scheme == "rtsp":
            options["rtsp_transport"] = "tcp"  # no lost packets: a whole frame or none
        elif scheme == "udp":
            sep = "&" if "?" in url else "?"
            url = f"{url}{sep}overrun_nonfatal=1&fifo_size=65536"
        fmt = "mpjpeg" if scheme in ("http", "https") and urlsplit(self.url).path.endswith((".mjpg", ".mjpeg")) else INNER[scheme]
        self.reader = VideoReader(url, settings.name, format=fmt, options=options, stall_s=STALL_S,
                                  pixel_format=settings.pixel_format, size=(settings.width, settings.height))
        self._started = False

    def reconnect(self) -> bool:
        self.reader.reopen()
        return True

    def software_trigger(self) -> None:
        raise ConfigError(f"{self.name} ({self.uri}): a network stream cannot be triggered")
