"""The `daemon://` backend: a camera served by a camera daemon on another host (or this one), read over
its control API (rig.daemon.client.RemoteDaemonCamera).

    daemon://HOST:PORT[?token=T]     the daemon's API address
    daemon://RIG/CAMERA[?token=T]    found by mDNS (`_rigcam._tcp.local.`): rig RIG's camera CAMERA

`discover()` lists nothing: looking for daemons takes seconds of mDNS, which `rig discover --network`
spends on purpose; `rig discover` stays quick.
"""
from __future__ import annotations

from urllib.parse import parse_qs, urlsplit

from rig.cameras.base import DeviceInfo
from rig.errors import ConfigError, DeviceNotFound

SCHEME = "daemon"
MDNS_TIMEOUT_S = 3.0


def discover() -> list[DeviceInfo]:
    return []


def _api_url(uri: str) -> tuple[str, str | None]:
    parts = urlsplit(uri)
    token = (parse_qs(parts.query).get("token") or [None])[0]
    if parts.port is not None or (parts.hostname and not parts.path.strip("/")):
        if parts.port is None:
            raise ConfigError(f"{uri}: a daemon address needs its API port (daemon://HOST:PORT)")
        return f"http://{parts.hostname}:{parts.port}", token
    rig, camera = parts.netloc, parts.path.strip("/")
    if not rig or not camera or "/" in camera:
        raise ConfigError(f"{uri}: expected daemon://HOST:PORT or daemon://RIG/CAMERA")
    from rig.daemon.discovery import browse

    for found in browse(MDNS_TIMEOUT_S, rig=rig):
        if found.camera == camera:
            return found.api_url, token
    raise DeviceNotFound(f"{uri}: no daemon of rig {rig!r} serving camera {camera!r} answered on mDNS within {MDNS_TIMEOUT_S:g} s")


def open(uri: str, settings):  # noqa: A001 - the backend contract's name
    from rig.daemon.client import RemoteDaemonCamera

    url, token = _api_url(uri)
    return RemoteDaemonCamera(settings, url, token)
