"""Control of a GoPro on USB through the Open GoPro HTTP API 2.0 (`../shared/reference/
open-gopro-http-openapi.json` is the specification this follows).

    client = GoProClient("C3501324645504")          # http://172.25.104.51:8080, from the serial
    client.connect()                                 # wired USB control, client info, version 2.0, ready
    client.set_resolution("1080"); client.set_fps(30); client.set_lens("linear")
    client.shutter_start(); ...; client.shutter_stop()
    for item in client.media_list(): client.download(item, take_folder)
    client.webcam_start(port=8556)                   # MPEG-TS over UDP to this host, port 8556
    client.events()                                  # "link lost" / "reconnected" ..., with times
    client.close()

- Every request the client can send is in `ENDPOINTS` (and `SETTINGS` for the settings), which a
  test checks against the specification. Commands wait until status 8 (busy) and 10 (encoding) are
  both 0, bounded by `ready_timeout_s`; status queries, keep-alive, shutter stop and the webcam's
  stop / exit / status do not wait.
- A keep-alive goes out every `keep_alive_s` (3 s, as the specification recommends) on the
  client's own thread, which is also the watchdog: `failures_to_drop` consecutive failures (no
  answer, or a 5xx answer) from any request mark the link lost; the thread then runs the connect
  sequence again with a doubling back-off until it succeeds, restarts the webcam if it was
  streaming, and says so in `events()` and to `on_event`. While the link is lost, commands raise
  CameraDisconnected at once.
- Webcam over USB: the specification says to release wired USB control before webcam commands;
  `webcam_start` does so (`release_wired_control=True`).
- `download` writes `<name>.part` beside the target and asks for the rest with a Range header when
  a part is already there, so an interrupted download continues where it stopped; the finished
  file is renamed into place in one step.
- Discovery: `discover_mdns` browses `_gopro-web._tcp.local.` (the instance name is the serial);
  `discover_usb` lists USB devices of GoPro's vendor id 0x2672 with pyusb.

Uses `requests` (one session per thread: the keep-alive never queues behind a long download).
"""
from __future__ import annotations

import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Optional

import requests

from common.files import fsync_dir, fsync_file
from rig.errors import CameraDisconnected, ConfigError, DeviceError, DeviceNotFound

API_VERSION = "2.0"
HTTP_PORT = 8080
DEFAULT_WEBCAM_PORT = 8554
USB_VENDOR_ID = 0x2672
SERVICE_TYPE = "_gopro-web._tcp.local."
URI_SCHEME = "gopro"


class LinkDown(CameraDisconnected):
    """No answer from the camera (or the link is marked lost); `reason` is the short cause."""

    def __init__(self, message: str, reason: str = ""):
        super().__init__(message)
        self.reason = reason or message


# --- the requests ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Endpoint:
    """One request of the API: its path (`{name}` parts filled per request), the query parameters
    it may carry, and whether it waits for the camera to be ready (busy and encoding off)."""

    path: str
    params: tuple[str, ...] = ()
    wait_ready: bool = True


ENDPOINTS: dict[str, Endpoint] = {
    "state": Endpoint("/gopro/camera/state", wait_ready=False),
    "version": Endpoint("/gopro/version", wait_ready=False),
    "info": Endpoint("/gopro/camera/info"),
    "keep_alive": Endpoint("/gopro/camera/keep_alive", wait_ready=False),
    "wired_usb": Endpoint("/gopro/camera/control/wired_usb", ("p",), wait_ready=False),
    "client_info": Endpoint("/gopro/camera/analytics/set_client_info", wait_ready=False),
    "presets": Endpoint("/gopro/camera/presets/get"),
    "preset_load": Endpoint("/gopro/camera/presets/load", ("id",)),
    "preset_group": Endpoint("/gopro/camera/presets/set_group", ("id",)),
    "setting": Endpoint("/gopro/camera/setting", ("setting", "option")),
    "shutter_start": Endpoint("/gopro/camera/shutter/{mode}"),
    "shutter_stop": Endpoint("/gopro/camera/shutter/{mode}", wait_ready=False),
    "webcam_start": Endpoint("/gopro/webcam/start", ("res", "fov", "port", "protocol")),
    "webcam_preview": Endpoint("/gopro/webcam/preview"),
    "webcam_stop": Endpoint("/gopro/webcam/stop", wait_ready=False),
    "webcam_exit": Endpoint("/gopro/webcam/exit", wait_ready=False),
    "webcam_status": Endpoint("/gopro/webcam/status", wait_ready=False),
    "media_list": Endpoint("/gopro/media/list"),
    "last_captured": Endpoint("/gopro/media/last_captured"),
    "download": Endpoint("/videos/DCIM/{directory}/{filename}"),
}


# --- settings ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Setting:
    """A camera setting: its id and the option ids of the values we use (names as a user writes them)."""

    id: int
    name: str
    options: dict[str, int]

    def option(self, value: Any) -> int:
        key = str(value).strip().lower().replace(" ", "")
        for name, option in self.options.items():
            if name.replace(" ", "") == key:
                return option
        raise ConfigError(f"{self.name} {value!r} is not one of: {', '.join(self.options)}")

    def name_of(self, option: int) -> str:
        for name, opt in self.options.items():
            if opt == option:
                return name
        return f"option {option}"


RESOLUTION = Setting(2, "video resolution", {"4k": 1, "2.7k": 4, "2.7k 4:3": 6, "1440": 7, "1080": 9, "720": 12,
                                             "4k 4:3": 18, "5.3k": 100})
FPS = Setting(3, "frame rate", {"240": 0, "200": 13, "120": 1, "100": 2, "60": 5, "50": 6, "30": 8, "25": 9, "24": 10})
LENS = Setting(121, "video lens", {"wide": 0, "narrow": 2, "superview": 3, "linear": 4, "max superview": 7,
                                   "linear+horizon leveling": 8, "hyperview": 9, "linear+horizon lock": 10})
HYPERSMOOTH = Setting(135, "hypersmooth", {"off": 0, "low": 1, "high": 2, "boost": 3, "auto boost": 4, "standard": 100})
SETTINGS: dict[int, Setting] = {s.id: s for s in (RESOLUTION, FPS, LENS, HYPERSMOOTH)}

RESOLUTION_SIZES = {"4k": (3840, 2160), "2.7k": (2704, 1520), "2.7k 4:3": (2704, 2028), "1440": (1920, 1440),
                    "1080": (1920, 1080), "720": (1280, 720), "4k 4:3": (4000, 3000), "5.3k": (5312, 2988)}
PRESET_GROUPS = {"video": 1000, "photo": 1001, "timelapse": 1002}
WEBCAM_RESOLUTIONS = {480: 4, 720: 7, 1080: 12}  # lines -> `res` of /gopro/webcam/start
WEBCAM_FOVS = {"wide": 0, "narrow": 2, "superview": 3, "linear": 4}
WEBCAM_STATUS = {0: "off", 1: "idle", 2: "high power preview", 3: "low power preview", 4: "unavailable"}
WEBCAM_ERRORS = {0: "none", 1: "set preset", 2: "set window size", 3: "exec stream", 4: "shutter", 5: "com timeout",
                 6: "invalid param", 7: "unavailable", 8: "exit"}
_SETTING_ERRORS = {1: "setting not available now", 2: "no such setting", 3: "option not available now",
                   4: "no such option"}
STATUS_BUSY, STATUS_ENCODING = 8, 10


def resolution_for_size(width: int, height: int) -> str:
    """The resolution name of a frame size (e.g. 1920x1080 -> '1080'); ConfigError if none matches."""
    for name, size in RESOLUTION_SIZES.items():
        if size == (int(width), int(height)):
            return name
    sizes = ", ".join(f"{w}x{h}" for w, h in RESOLUTION_SIZES.values())
    raise ConfigError(f"a GoPro records {sizes}, not {width}x{height}")


# --- what the camera answers -------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraState:
    status: dict[int, Any]
    settings: dict[int, Any]

    @property
    def busy(self) -> bool:
        return bool(self.status.get(STATUS_BUSY, 0))

    @property
    def encoding(self) -> bool:
        return bool(self.status.get(STATUS_ENCODING, 0))

    @property
    def ready(self) -> bool:
        return not (self.busy or self.encoding)

    @classmethod
    def from_json(cls, data: dict) -> "CameraState":
        def ids(d) -> dict[int, Any]:
            return {int(k): v for k, v in (d or {}).items() if str(k).lstrip("-").isdigit()}

        return cls(ids(data.get("status")), ids(data.get("settings")))


@dataclass(frozen=True)
class CameraInfo:
    model_name: str
    model_number: str
    firmware_version: str
    serial_number: str
    ap_ssid: str = ""
    ap_mac_addr: str = ""


@dataclass(frozen=True)
class Preset:
    id: int
    group: int
    mode: int
    title_id: int
    settings: dict[int, int]
    modified: bool = False


@dataclass(frozen=True)
class WebcamState:
    status: int
    error: int

    @property
    def streaming(self) -> bool:
        return self.status in (2, 3)

    def describe(self) -> str:
        text = WEBCAM_STATUS.get(self.status, f"status {self.status}")
        return text if not self.error else f"{text}, error {self.error} ({WEBCAM_ERRORS.get(self.error, '?')})"


@dataclass(frozen=True)
class MediaItem:
    directory: str
    name: str
    size: Optional[int]
    created: Optional[int]
    modified: Optional[int]

    @property
    def path(self) -> str:
        return f"{self.directory}/{self.name}"


@dataclass(frozen=True)
class LinkEvent:
    kind: str  # "link lost", "reconnected", "webcam restarted"
    time: float  # time.time()
    monotonic: float  # time.monotonic()
    detail: str = ""


@dataclass(frozen=True)
class DiscoveredGoPro:
    serial: str
    address: str
    port: int = HTTP_PORT
    source: str = "mdns"  # "mdns" or "usb"
    name: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def uri(self) -> str:
        return f"{URI_SCHEME}://{self.serial}"

    @property
    def base_url(self) -> str:
        host = f"[{self.address}]" if ":" in self.address else self.address
        return f"http://{host}:{self.port}"


# --- addresses ---------------------------------------------------------------------------------------------
def _check_serial(serial: str) -> str:
    serial = str(serial).strip()
    if not re.fullmatch(r"[A-Za-z0-9]*[0-9]{3}", serial):
        raise ConfigError(f"gopro://{serial}: a GoPro serial is letters and digits ending in three digits "
                          "(e.g. C3501324645504, on the sticker in the battery door)")
    return serial


def usb_address(serial: str) -> str:
    """The camera's USB network address: 172.2X.1YZ.51, XYZ the serial's last three digits."""
    x, y, z = _check_serial(serial)[-3:]
    return f"172.2{x}.1{y}{z}.51"


def usb_base_url(serial: str) -> str:
    return f"http://{usb_address(serial)}:{HTTP_PORT}"


# --- the client --------------------------------------------------------------------------------------------
class GoProClient:
    """One camera over HTTP. Thread-safe; `connect()` starts the keep-alive / watchdog thread."""

    def __init__(self, serial: str, *, base_url: Optional[str] = None, timeout_s: float = 5.0,
                 keep_alive_s: float = 3.0, ready_timeout_s: float = 10.0, poll_s: float = 0.1,
                 failures_to_drop: int = 3, reconnect_backoff_s: tuple[float, float] = (0.25, 5.0),
                 on_event: Optional[Callable[[LinkEvent], None]] = None, watchdog: bool = True):
        self.serial = _check_serial(serial)
        self.base_url = (base_url or usb_base_url(self.serial)).rstrip("/")
        self.timeout_s = float(timeout_s)
        self.keep_alive_s = float(keep_alive_s)
        self.ready_timeout_s = float(ready_timeout_s)
        self.poll_s = float(poll_s)
        self.failures_to_drop = max(1, int(failures_to_drop))
        self.reconnect_backoff_s = (float(reconnect_backoff_s[0]), float(reconnect_backoff_s[1]))
        self.on_event = on_event
        self.use_watchdog = watchdog
        self._lock = threading.RLock()
        self._local = threading.local()
        self._sessions: list[requests.Session] = []
        self._events: list[LinkEvent] = []
        self._failures = 0
        self._link_up = False
        self._down_since = 0.0
        self._connected = False
        self._webcam: Optional[dict[str, Any]] = None  # what webcam_start asked for, restored after a reconnect
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    @property
    def uri(self) -> str:
        return f"{URI_SCHEME}://{self.serial}"

    # --- lifecycle ---------------------------------------------------------------------------------------
    def connect(self) -> "GoProClient":
        """Take wired USB control, introduce the client, check the API version, wait until ready,
        then keep the link alive. Raises DeviceNotFound when nothing answers."""
        try:
            self._connect_sequence(internal=True)
        except LinkDown as exc:
            raise DeviceNotFound(f"{self.uri}: no answer at {self.base_url} ({exc.reason}); is the camera on and "
                                 "plugged in by USB?") from None
        with self._lock:
            self._link_up, self._failures, self._connected = True, 0, True
        if self.use_watchdog and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._watch, name=f"gopro-{self.serial}-keepalive", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the keep-alive (the camera keeps its state); safe to call twice."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(self.timeout_s + 2)
        self._thread = None
        with self._lock:
            self._connected = False
            sessions, self._sessions = self._sessions, []
        for s in sessions:
            s.close()

    def __enter__(self) -> "GoProClient":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    def _connect_sequence(self, internal: bool = False) -> None:
        self._get("wired_usb", params={"p": 1}, internal=internal)
        self._get("client_info", internal=internal)
        version = self._json(self._get("version", internal=internal)).get("version")
        if str(version) != API_VERSION:
            raise DeviceError(f"{self.uri}: the camera speaks Open GoPro {version}; this client needs {API_VERSION} "
                              "(update the camera's firmware)")
        self.wait_ready(internal=internal)

    # --- link state and events ---------------------------------------------------------------------------
    @property
    def link_up(self) -> bool:
        with self._lock:
            return self._link_up

    def events(self) -> list[LinkEvent]:
        with self._lock:
            return list(self._events)

    def wait_event(self, kind: str, timeout: float, after: int = 0) -> Optional[LinkEvent]:
        """The first event of `kind` among events()[after:], waiting up to `timeout` seconds for it."""
        deadline = time.monotonic() + timeout
        while True:
            for event in self.events()[after:]:
                if event.kind == kind:
                    return event
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.02)

    def _event(self, kind: str, detail: str = "") -> None:
        event = LinkEvent(kind, time.time(), time.monotonic(), detail)
        with self._lock:
            self._events.append(event)
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:  # noqa: BLE001 - a listener's bug must not stop the watchdog
                pass

    def _failed(self, reason: str) -> None:
        lost = False
        with self._lock:
            self._failures += 1
            if self._link_up and self._connected and self._failures >= self.failures_to_drop:
                self._link_up, self._down_since, lost = False, time.monotonic(), True
        if lost:
            self._event("link lost", reason)
            self._wake.set()

    def _succeeded(self) -> None:
        with self._lock:
            self._failures = 0

    # --- requests ----------------------------------------------------------------------------------------
    def _session(self) -> requests.Session:
        session = getattr(self._local, "session", None)
        if session is None:
            session = requests.Session()
            self._local.session = session
            with self._lock:
                self._sessions.append(session)
        return session

    def _get(self, name: str, *, params: Optional[dict] = None, path: Optional[dict] = None,
             headers: Optional[dict] = None, stream: bool = False, internal: bool = False,
             timeout: Optional[float] = None) -> requests.Response:
        endpoint = ENDPOINTS[name]
        with self._lock:
            down = self._connected and not self._link_up
            since = self._down_since
        if down and not internal:
            raise LinkDown(f"{self.uri}: link to the camera lost {time.monotonic() - since:.1f} s ago; reconnecting",
                           "link lost")
        if endpoint.wait_ready:
            self.wait_ready(internal=internal)
        url = self.base_url + endpoint.path.format(**(path or {}))
        try:
            response = self._session().get(url, params=params, headers=headers, stream=stream,
                                           timeout=timeout or self.timeout_s)
        except requests.RequestException as exc:
            reason = _short(exc)
            self._failed(f"{endpoint.path}: {reason}")
            raise LinkDown(f"{self.uri}: no answer to {endpoint.path} ({reason})", reason) from None
        if response.status_code >= 500:
            reason = f"HTTP {response.status_code}"
            response.close()
            self._failed(f"{endpoint.path}: {reason}")
            raise DeviceError(f"{self.uri}: {endpoint.path} failed on the camera ({reason})")
        self._succeeded()
        return response

    def _json(self, response: requests.Response) -> dict:
        if response.status_code == 204 or not response.content:
            return {}
        try:
            data = response.json()
        except ValueError:
            raise DeviceError(f"{self.uri}: {response.request.path_url} answered something that is not JSON") from None
        return data if isinstance(data, dict) else {}

    def _command(self, name: str, what: str, **kw) -> dict:
        response = self._get(name, **kw)
        if response.status_code >= 400:
            raise DeviceError(f"{self.uri}: the camera refused {what} (HTTP {response.status_code})")
        return self._json(response)

    # --- state and info ----------------------------------------------------------------------------------
    def state(self, *, internal: bool = False) -> CameraState:
        return CameraState.from_json(self._json(self._get("state", internal=internal)))

    def wait_ready(self, timeout: Optional[float] = None, *, internal: bool = False) -> CameraState:
        """Wait until status 8 (busy) and 10 (encoding) are both 0; DeviceError after `timeout`."""
        limit = self.ready_timeout_s if timeout is None else timeout
        deadline = time.monotonic() + limit
        while True:
            state = self.state(internal=internal)
            if state.ready:
                return state
            if time.monotonic() >= deadline:
                what = " and ".join(w for w, on in (("busy", state.busy), ("encoding", state.encoding)) if on)
                hint = " (stop the recording first)" if state.encoding else ""
                raise DeviceError(f"{self.uri}: camera still {what} after {limit:g} s{hint}")
            time.sleep(self.poll_s)

    def info(self) -> CameraInfo:
        data = self._command("info", "the hardware info request")
        return CameraInfo(model_name=str(data.get("model_name", "")), model_number=str(data.get("model_number", "")),
                          firmware_version=str(data.get("firmware_version", "")),
                          serial_number=str(data.get("serial_number", "")), ap_ssid=str(data.get("ap_ssid", "")),
                          ap_mac_addr=str(data.get("ap_mac_addr", "")))

    def keep_alive(self) -> None:
        self._command("keep_alive", "the keep-alive")

    # --- presets and settings ----------------------------------------------------------------------------
    def presets(self) -> list[Preset]:
        data = self._command("presets", "the preset list")
        found = []
        for group in data.get("presetGroupArray", []):
            for p in group.get("presetArray", []):
                settings = {int(s["id"]): int(s["value"]) for s in p.get("settingArray", []) if "id" in s and "value" in s}
                found.append(Preset(int(p["id"]), int(group.get("id", 0)), int(p.get("mode", -1)),
                                    int(p.get("titleId", -1)), settings, bool(p.get("isModified", False))))
        return found

    def load_preset(self, preset_id: int) -> None:
        self._command("preset_load", f"preset {preset_id} (not available now?)", params={"id": int(preset_id)})

    def load_preset_group(self, group: str | int) -> None:
        if isinstance(group, str):
            if group.lower() not in PRESET_GROUPS:
                raise ConfigError(f"preset group {group!r} is not one of: {', '.join(PRESET_GROUPS)}")
            group = PRESET_GROUPS[group.lower()]
        self._command("preset_group", f"preset group {group}", params={"id": int(group)})

    def get_setting(self, setting: Setting | int) -> int:
        sid = setting.id if isinstance(setting, Setting) else int(setting)
        response = self._get("setting", params={"setting": sid})
        data = self._json(response)
        if response.status_code >= 400 or "option" not in data:
            raise DeviceError(f"{self.uri}: the camera does not report setting {sid} (HTTP {response.status_code})")
        return int(data["option"])

    def set_setting(self, setting: Setting | int, option: int) -> None:
        """Set a setting to an option id; a refusal (403) is a one-line DeviceError naming both and
        what the camera allows now."""
        known = setting if isinstance(setting, Setting) else SETTINGS.get(int(setting))
        sid = known.id if known else int(setting)
        response = self._get("setting", params={"setting": sid, "option": int(option)})
        if response.status_code == 403:
            raise DeviceError(self._refusal(known, sid, int(option), self._json(response)))
        if response.status_code >= 400:
            raise DeviceError(f"{self.uri}: setting {sid} = option {option} failed (HTTP {response.status_code})")

    def _refusal(self, known: Optional[Setting], sid: int, option: int, body: dict) -> str:
        what = f"{known.name} (setting {sid})" if known else f"setting {sid}"
        value = f"{known.name_of(option)} (option {option})" if known else f"option {option}"
        reason = _SETTING_ERRORS.get(body.get("error"), "refused")
        allowed = [f"{o.get('display_name', '?')} ({o.get('id')})" for o in body.get("supported_options") or []
                   if isinstance(o, dict)]
        tail = f"; allowed now: {', '.join(allowed)}" if allowed else ""
        return f"{self.uri}: the camera refused {what} = {value}: {reason}{tail}"

    def set_resolution(self, name: str) -> None:
        self.set_setting(RESOLUTION, RESOLUTION.option(name))

    def set_fps(self, fps: float | int | str) -> None:
        value = fps if isinstance(fps, str) else f"{float(fps):g}"
        self.set_setting(FPS, FPS.option(value))

    def set_lens(self, name: str) -> None:
        self.set_setting(LENS, LENS.option(name))

    def set_hypersmooth(self, name: str) -> None:
        self.set_setting(HYPERSMOOTH, HYPERSMOOTH.option(name))

    # --- shutter -----------------------------------------------------------------------------------------
    def shutter_start(self) -> None:
        self._command("shutter_start", "shutter start", path={"mode": "start"})

    def shutter_stop(self) -> None:
        self._command("shutter_stop", "shutter stop", path={"mode": "stop"})

    # --- webcam ------------------------------------------------------------------------------------------
    def webcam_start(self, port: int = DEFAULT_WEBCAM_PORT, resolution: Optional[int] = 1080,
                     fov: Optional[str] = "wide", *, release_wired_control: bool = True) -> WebcamState:
        """Stream MPEG-TS over UDP to this host at `port` (one port per camera keeps streams apart)."""
        if not 1 <= int(port) <= 65535:
            raise ConfigError(f"{self.uri}: webcam port {port} is not a UDP port (1-65535)")
        params: dict[str, Any] = {"port": int(port), "protocol": "TS"}
        if resolution is not None:
            if int(resolution) not in WEBCAM_RESOLUTIONS:
                raise ConfigError(f"{self.uri}: webcam resolution {resolution} is not one of: "
                                  f"{', '.join(map(str, WEBCAM_RESOLUTIONS))}")
            params["res"] = WEBCAM_RESOLUTIONS[int(resolution)]
        if fov is not None:
            if str(fov).lower() not in WEBCAM_FOVS:
                raise ConfigError(f"{self.uri}: webcam field of view {fov!r} is not one of: {', '.join(WEBCAM_FOVS)}")
            params["fov"] = WEBCAM_FOVS[str(fov).lower()]
        wanted = {"port": int(port), "resolution": resolution, "fov": fov, "release_wired_control": release_wired_control}
        state = self._start_webcam(params, release_wired_control)
        with self._lock:
            self._webcam = wanted
        return state

    def _start_webcam(self, params: dict, release_wired_control: bool, internal: bool = False) -> WebcamState:
        if release_wired_control:
            self._get("wired_usb", params={"p": 0}, internal=internal)
        response = self._get("webcam_start", params=params, internal=internal)
        if response.status_code >= 400:
            raise DeviceError(f"{self.uri}: the camera refused to start the webcam (HTTP {response.status_code})")
        state = self._webcam_state(response)
        if state.error:
            raise DeviceError(f"{self.uri}: webcam start failed: {state.describe()}")
        return state

    def webcam_stop(self) -> WebcamState:
        with self._lock:
            self._webcam = None
        return self._webcam_state(self._get("webcam_stop"))

    def webcam_exit(self) -> WebcamState:
        with self._lock:
            self._webcam = None
        return self._webcam_state(self._get("webcam_exit"))

    def webcam_status(self, *, internal: bool = False) -> WebcamState:
        return self._webcam_state(self._get("webcam_status", internal=internal))

    def _webcam_state(self, response: requests.Response) -> WebcamState:
        data = self._json(response)
        return WebcamState(int(data.get("status", 4)), int(data.get("error", 0)))

    # --- media -------------------------------------------------------------------------------------------
    def media_list(self) -> list[MediaItem]:
        data = self._command("media_list", "the media list")
        items = []
        for folder in data.get("media", []):
            directory = str(folder.get("d", ""))
            for f in folder.get("fs", []):
                items.append(MediaItem(directory, str(f.get("n", "")), _int(f.get("s")), _int(f.get("cre")),
                                       _int(f.get("mod"))))
        return items

    def last_captured(self) -> Optional[MediaItem]:
        """The last medium captured (None when there is none); size and times are unknown here."""
        data = self._command("last_captured", "the last captured media request")
        if not data.get("file"):
            return None
        return MediaItem(str(data.get("folder", "")), str(data["file"]), None, None, None)

    def download(self, media: MediaItem | str, folder: str | os.PathLike, *, chunk_size: int = 64 * 1024) -> Path:
        """Download a medium ('100GOPRO/GH010001.MP4' or a MediaItem) into `folder`; resumes a partial
        download (`<name>.part`) with an HTTP Range request; returns the finished file."""
        directory, name, expected = _media_parts(media)
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        final = folder / name
        part = folder / f"{name}.part"
        if final.exists() and not part.exists() and (expected is None or final.stat().st_size == expected):
            return final
        offset = part.stat().st_size if part.exists() else 0
        if expected is not None and offset > expected:
            offset = 0
        total = self._fetch(directory, name, part, offset, chunk_size)
        size = part.stat().st_size
        if size != total or (expected is not None and size != expected):
            raise DeviceError(f"{self.uri}: {directory}/{name} arrived with {size} bytes, expected "
                              f"{expected if expected is not None else total}")
        fsync_file(part)
        os.replace(part, final)
        fsync_dir(folder)
        return final

    def _fetch(self, directory: str, name: str, part: Path, offset: int, chunk_size: int) -> int:
        """Append the rest of the file to `part` from `offset`; the file's full size."""
        headers = {"Range": f"bytes={offset}-"} if offset else None
        response = self._get("download", path={"directory": directory, "filename": name}, headers=headers, stream=True)
        with response:
            if response.status_code == 404:
                raise DeviceError(f"{self.uri}: no media {directory}/{name} on the camera")
            if response.status_code == 416:  # the part already holds the whole file (or more)
                total = _content_range_total(response.headers.get("Content-Range"))
                if total is not None and total == offset:
                    return total
                part.unlink(missing_ok=True)
                return self._fetch(directory, name, part, 0, chunk_size)
            if response.status_code == 206:
                first, total = _content_range(response.headers.get("Content-Range"))
                if first != offset or total is None:
                    raise DeviceError(f"{self.uri}: {directory}/{name}: asked for bytes from {offset}, "
                                      f"got {response.headers.get('Content-Range')!r}")
            elif response.status_code == 200:
                offset = 0  # the whole file: start over
                total = _int(response.headers.get("Content-Length"))
            else:
                raise DeviceError(f"{self.uri}: download of {directory}/{name} failed (HTTP {response.status_code})")
            written = offset
            with open(part, "r+b" if offset and part.exists() else "wb") as f:
                f.seek(offset)
                f.truncate()
                try:
                    for chunk in response.iter_content(chunk_size):
                        f.write(chunk)
                        written += len(chunk)
                except requests.RequestException as exc:
                    reason = _short(exc)
                    self._failed(f"download {directory}/{name}: {reason}")
                    f.flush()
                    of = f" of {total}" if total is not None else ""
                    raise LinkDown(f"{self.uri}: download of {directory}/{name} stopped at {written}{of} bytes "
                                   f"({reason}); download again to resume", reason) from None
            return total if total is not None else written

    # --- the keep-alive / watchdog thread ----------------------------------------------------------------
    def _watch(self) -> None:
        backoff = self.reconnect_backoff_s[0]
        next_beat = time.monotonic() + self.keep_alive_s
        while not self._stop.is_set():
            if self.link_up:
                self._wake.wait(max(0.0, next_beat - time.monotonic()))
                self._wake.clear()
                if self._stop.is_set() or not self.link_up:
                    continue
                next_beat = time.monotonic() + self.keep_alive_s
                try:
                    self._get("keep_alive", internal=True, timeout=min(self.timeout_s, max(self.keep_alive_s, 0.5)))
                    self._check_webcam()
                except DeviceError:
                    pass  # counted by _get; the link is marked lost after enough of them
                backoff = self.reconnect_backoff_s[0]
            else:
                try:
                    self._connect_sequence(internal=True)
                except DeviceError:
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.reconnect_backoff_s[1])
                    continue
                with self._lock:
                    self._link_up, self._failures = True, 0
                    down_for = time.monotonic() - self._down_since
                self._event("reconnected", f"after {down_for:.1f} s")
                next_beat = time.monotonic() + self.keep_alive_s
                try:
                    self._check_webcam()
                except DeviceError:
                    pass

    def _check_webcam(self) -> None:
        """Restart the webcam when it should stream and does not (the camera gave it up)."""
        with self._lock:
            wanted = dict(self._webcam) if self._webcam else None
        if wanted is None:
            return
        state = self.webcam_status(internal=True)
        if state.streaming:
            return
        params: dict[str, Any] = {"port": wanted["port"], "protocol": "TS"}
        if wanted["resolution"] is not None:
            params["res"] = WEBCAM_RESOLUTIONS[int(wanted["resolution"])]
        if wanted["fov"] is not None:
            params["fov"] = WEBCAM_FOVS[str(wanted["fov"]).lower()]
        self.wait_ready(internal=True)
        self._start_webcam(params, wanted["release_wired_control"], internal=True)
        self._event("webcam restarted", f"it was {state.describe()}")


# --- helpers -----------------------------------------------------------------------------------------------
def _int(value) -> Optional[int]:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def _short(exc: BaseException) -> str:
    """A requests error in a few words (its own text nests urllib3's several levels deep)."""
    text = str(exc).lower()
    if isinstance(exc, requests.Timeout) or "timed out" in text:
        return "timed out"
    if isinstance(exc, requests.exceptions.ChunkedEncodingError) or "incompleteread" in text:
        return "connection broken mid-transfer"
    if "refused" in text:
        return "connection refused"
    if "aborted" in text or "reset" in text or "remotedisconnected" in text:
        return "connection closed by the camera"
    if "no route" in text or "unreachable" in text:
        return "no route to the camera"
    return type(exc).__name__


def _media_parts(media: MediaItem | str) -> tuple[str, str, Optional[int]]:
    if isinstance(media, MediaItem):
        directory, name, size = media.directory, media.name, media.size
    else:
        directory, _, name = str(media).strip("/").rpartition("/")
        size = None
    ok = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
    if not (ok.fullmatch(directory) and ok.fullmatch(name)) or ".." in (directory, name):
        raise ConfigError(f"{media!r} is not a camera media path such as 100GOPRO/GH010001.MP4")
    return directory, name, size


def _content_range(header: Optional[str]) -> tuple[Optional[int], Optional[int]]:
    m = re.fullmatch(r"\s*bytes\s+(\d+)-(\d+)/(\d+|\*)\s*", header or "")
    if not m:
        return None, None
    return int(m.group(1)), (int(m.group(3)) if m.group(3) != "*" else None)


def _content_range_total(header: Optional[str]) -> Optional[int]:
    m = re.fullmatch(r"\s*bytes\s+\*/(\d+)\s*", header or "")
    return int(m.group(1)) if m else None


# --- discovery ---------------------------------------------------------------------------------------------
def discover_mdns(timeout: float = 3.0, interfaces: Optional[Iterable[str]] = None,
                  quiet_s: float = 0.5) -> list[DiscoveredGoPro]:
    """GoPros announcing `_gopro-web._tcp.local.` (sorted by serial). Returns after `timeout`, or
    once one was found and no new one appeared for `quiet_s`. `interfaces`: addresses to browse on
    (e.g. ["127.0.0.1"]); default: every interface."""
    from zeroconf import InterfaceChoice, IPVersion, ServiceBrowser, ServiceInfo, ServiceStateChange, Zeroconf

    start = time.monotonic()
    deadline = start + max(0.0, timeout)
    lock, changed = threading.Lock(), threading.Event()
    pending: set[str] = set()
    found: dict[str, DiscoveredGoPro] = {}
    last_new = [start]

    def on_change(zeroconf, service_type, name, state_change):
        with lock:
            if state_change is ServiceStateChange.Removed:
                pending.discard(name)
                found.pop(name, None)
            elif name not in found:
                if name not in pending:
                    last_new[0] = time.monotonic()
                pending.add(name)
        changed.set()

    zc = Zeroconf(interfaces=list(interfaces) if interfaces is not None else InterfaceChoice.All)
    try:
        browser = ServiceBrowser(zc, SERVICE_TYPE, handlers=[on_change])
        try:
            while True:
                with lock:
                    todo = sorted(pending)
                for name in todo:
                    info = ServiceInfo(SERVICE_TYPE, name)
                    wait_ms = int(max(0.0, min(1.0, deadline - time.monotonic())) * 1000)
                    if not info.request(zc, wait_ms) and time.monotonic() < deadline:
                        continue
                    addresses = info.parsed_addresses(IPVersion.V4Only) or info.parsed_addresses()
                    serial = name[: -len(SERVICE_TYPE) - 1] if name.endswith("." + SERVICE_TYPE) else name
                    with lock:
                        pending.discard(name)
                        if addresses and info.port:
                            found[name] = DiscoveredGoPro(serial, addresses[0], int(info.port), "mdns", name)
                now = time.monotonic()
                with lock:
                    quiet = found and not pending and now - last_new[0] >= quiet_s
                if now >= deadline or quiet:
                    break
                changed.clear()
                changed.wait(min(0.05, max(0.0, deadline - now)))
        finally:
            browser.cancel()
    finally:
        zc.close()
    return sorted(found.values(), key=lambda d: (d.serial, d.address, d.port))


def discover_usb(backend=None) -> list[DiscoveredGoPro]:
    """GoPros on USB (vendor id 0x2672), by pyusb; [] when there is no USB or no libusb backend.
    The address comes from the USB serial string (the camera's serial), empty when it cannot be read
    (permissions). `backend`: a pyusb backend (default: the one pyusb finds)."""
    try:
        import usb.core
        import usb.util
    except ImportError:
        return []
    try:
        devices = list(usb.core.find(find_all=True, idVendor=USB_VENDOR_ID, backend=backend) or [])
    except (usb.core.NoBackendError, usb.core.USBError, ValueError, OSError):
        return []
    found = []
    for dev in devices:
        serial = _usb_string(dev, "iSerialNumber")
        product = _usb_string(dev, "iProduct")
        try:
            address = usb_address(serial) if serial else ""
        except ConfigError:
            address = ""
        found.append(DiscoveredGoPro(serial, address, HTTP_PORT, "usb", product,
                                     {"usb_bus": getattr(dev, "bus", None), "usb_address": getattr(dev, "address", None),
                                      "product_id": f"{int(getattr(dev, 'idProduct', 0)):04x}"}))
    return sorted(found, key=lambda d: (d.serial, str(d.extra.get("usb_bus")), str(d.extra.get("usb_address"))))


def _usb_string(dev, attribute: str) -> str:
    import usb.util

    try:
        index = getattr(dev, attribute, 0)
        return usb.util.get_string(dev, index).strip() if index else ""
    except Exception:  # noqa: BLE001 - no permission, no language ids, a device gone: unknown
        return ""

