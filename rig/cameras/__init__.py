"""Camera backends, chosen by URI scheme.

Each module in this package that defines `SCHEME` is a backend with `discover()` and
`open(uri, settings)`; adding a backend is adding a module, nothing else changes.
"""
from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

from rig.errors import BackendError

_NOT_BACKENDS = {"base", "pixels", "gopro_http", "gopro_card", "video_reader", "discovery"}  # helpers, not backends


def _backend_modules() -> dict[str, str]:
    found = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name in _NOT_BACKENDS or info.name.startswith("_"):
            continue
        found[info.name] = f"{__name__}.{info.name}"
    return found


def schemes() -> list[str]:
    """URI schemes of all backends (module name = scheme)."""
    return sorted(_backend_modules())


def backend(scheme: str) -> ModuleType:
    modules = _backend_modules()
    if scheme not in modules:
        raise BackendError(f"unknown camera backend '{scheme}' (allowed: {', '.join(sorted(modules))})")
    return importlib.import_module(modules[scheme])


def open_camera(settings):
    """Open the camera a `CameraConfig` names, configured as it says."""
    uri = settings.uri
    if "://" not in uri:
        raise BackendError(f"{uri!r} is not a camera URI (expected scheme://address)")
    return backend(uri.split("://", 1)[0]).open(uri, settings)


def records_to_card(settings) -> bool:
    """True for a camera that records to its own card instead of giving live frames (a GoPro with
    `?record=card`): its backend says so with `records_to_card(uri)`; the session opens it but groups
    no frames of it, and `rig record` brings its video into the take afterwards."""
    uri = settings.uri
    if "://" not in uri:
        return False
    try:
        check = getattr(backend(uri.split("://", 1)[0]), "records_to_card", None)
    except BackendError:
        return False
    return bool(check(uri)) if check is not None else False


def live_cameras(cameras: list, why: str) -> list:
    """The cameras that give live frames (not recording to their cards); ConfigError when there is
    none, `why` saying what needed one."""
    from rig.errors import ConfigError

    live = [c for c in cameras if not records_to_card(c)]
    if not live:
        raise ConfigError(f"every camera of the rig records to its card: {why}")
    return live


def discover_all(errors: list | None = None) -> list:
    """Devices of every backend. A backend that cannot run here (e.g. no Aravis) adds to `errors`."""
    devices = []
    for scheme in schemes():
        try:
            devices.extend(backend(scheme).discover())
        except Exception as exc:  # one broken backend must not hide the others
            if errors is not None:
                errors.append(f"{scheme}: {exc}")
    return devices
