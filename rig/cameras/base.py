"""The camera contract every backend implements.

A backend is one module in `rig/cameras/` that defines `SCHEME`, `discover()` and `open(uri, settings)`.
`open` returns a configured `Camera`; the caller then `start()`s it, pulls Frames with `get_frame()`,
fires `software_trigger()` when the camera is in software-trigger mode, and `stop()`s / `close()`s it.
"""
from __future__ import annotations

import abc
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Optional

from sync.frames import Frame

if TYPE_CHECKING:  # annotations only: rig.config imports the camera backends to check a camera's settings
    from rig.config import CameraConfig


@dataclass
class DeviceInfo:
    """A device found by a backend's `discover()`."""

    uri: str
    backend: str
    model: str = ""
    serial: str = ""
    vendor: str = ""
    address: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class CameraStats:
    """Counters a camera keeps while streaming."""

    delivered: int = 0  # frames handed to the caller
    dropped: int = 0  # frames the camera produced but the host never received (gaps in frame ids)
    incomplete: int = 0  # buffers that arrived damaged and were discarded
    timeouts: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.update(d.pop("extra"))
        return d


def free_running_problems(kind: str, settings) -> list[str]:
    """What a camera that cannot be triggered and delivers decoded RGB (a GoPro, a webcam, a network
    stream: `kind`) cannot take from its settings."""
    out = []
    if settings.trigger != "free":
        out.append(f'{kind} cannot be triggered; set trigger = "free" (the take is aligned afterwards: rig record align)')
    if settings.pixel_format not in ("RGB8", "Mono8"):
        out.append(f"pixel_format must be RGB8 or Mono8 for {kind}, got {settings.pixel_format}")
    return out


def raise_problems(settings, uri: str, problems: list[str]) -> None:
    """Open-time form of a backend's `problems(uri, settings)` (the same checks `rig config check`
    makes): the first problem, as one line naming the camera."""
    from rig.errors import ConfigError

    if problems:
        raise ConfigError(f"{settings.name} ({uri}): {problems[0]}")


class Camera(abc.ABC):
    """One open camera. Use as a context manager to be sure it is closed."""

    def __init__(self, uri: str, settings: CameraConfig):
        self.uri = uri
        self.settings = settings
        self.name = settings.name
        self.stats = CameraStats()
        self._last_frame_id: Optional[int] = None
        self._last_unwrapped = 0

    # lifecycle -----------------------------------------------------------------------------------
    def prepare(self) -> None:
        """Slow work before acquisition (a sim camera pre-renders its loop); the session prepares
        every camera before it starts any, so that they start within moments of each other."""

    @abc.abstractmethod
    def start(self) -> None:
        """Begin acquisition (in trigger modes the camera then waits for triggers)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """End acquisition; frames already delivered stay valid."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device. Safe to call twice."""

    def reconnect(self) -> bool:
        """After get_frame reported CameraDisconnected: try once to get the device back and
        acquiring with the same settings (the session calls it about once a second). True when it
        is back. Backends that cannot tell keep the default: the camera stays lost."""
        return False

    # exposure and gain while acquiring -----------------------------------------------------------
    def controls(self) -> dict[str, Any]:
        """What the camera reports it exposes and amplifies with now, and what it accepts:
        {"exposure_us": float | None, "gain": float | None, "ranges": {"exposure_us": [lo, hi], "gain": [lo, hi]},
        "live": bool}. `live` False: the backend takes them only when it opens (`set_controls` refuses)."""
        return {"exposure_us": self.settings.exposure_us, "gain": self.settings.gain, "ranges": {}, "live": False}

    def set_controls(self, exposure_us: Optional[float] = None, gain: Optional[float] = None) -> dict[str, Any]:
        """Set the exposure (microseconds) and/or the gain (dB) while acquiring, then read back what
        the camera reports (`controls()`): a camera may round or clamp a value, and the caller shows
        what it got, not what it asked for. A value outside `ranges` raises ConfigError, and nothing
        changes; a backend that takes them only when it opens raises DeviceError."""
        from rig.errors import DeviceError

        raise DeviceError(f"{self.name}: this camera takes its exposure and gain only when it opens; change them in the rig's config")

    # frames --------------------------------------------------------------------------------------
    def get_frame(self, timeout: float = 1.0) -> Frame:
        """The next frame; raises CameraTimeout or CameraDisconnected. Counts gaps in frame ids."""
        frame = self._read_frame(timeout)
        frame.frame_id = self._account(frame.frame_id)
        return frame

    @abc.abstractmethod
    def _read_frame(self, timeout: float) -> Frame:
        """Backend part of get_frame: wait for and decode the next frame."""

    @abc.abstractmethod
    def software_trigger(self) -> None:
        """Fire one software trigger (trigger = "software")."""

    def hardware_trigger(self, pulse_index: int, time_ns: int) -> None:
        """An edge on the hardware trigger input. Real cameras get it by wire; emulated ones here."""
        raise NotImplementedError(f"{self.uri}: no emulated trigger input on this backend")

    # bookkeeping shared by all backends ----------------------------------------------------------
    FRAME_ID_MODULUS: Optional[int] = None  # wrap of the device's frame counter, None = no wrap

    def _account(self, device_id: int) -> int:
        """Unwrap the device's frame counter and count gaps in it (dropped frames).

        Returns the unwrapped id, which keeps increasing across wraps of a short device counter.
        """
        last_raw = self._last_frame_id
        if last_raw is None:
            unwrapped = device_id
        else:
            step = device_id - last_raw
            if self.FRAME_ID_MODULUS and step <= 0:
                step += self.FRAME_ID_MODULUS - 1  # GigE Vision ids skip 0 when they wrap
            if step > 1:
                self.stats.dropped += step - 1
            unwrapped = self._last_unwrapped + step
        self._last_frame_id = device_id
        self._last_unwrapped = unwrapped
        self.stats.delivered += 1
        return unwrapped

    def __enter__(self) -> "Camera":
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.stop()
        finally:
            self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} {self.uri}>"


def check_control(name: str, key: str, value: Any, bounds: tuple[float, float]) -> float:
    """`value` for control `key` of camera `name` as a float within `bounds`, else one ConfigError line."""
    import math

    from rig.errors import ConfigError

    lo, hi = bounds
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{name}: {key} must be a number from {lo:g} to {hi:g}, got {value!r}")
    if not lo <= float(value) <= hi:
        raise ConfigError(f"{name}: {key} {float(value):g} is outside what the camera takes ({lo:g} to {hi:g})")
    return float(value)
