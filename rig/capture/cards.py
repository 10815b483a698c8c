"""The shutters of a take's card-recording cameras (rig.cameras.gopro_card): pressed once the take
runs, released when it ends, every step written to the take's media manifest (rig.storage.media)
before the next one, so that `rig record fetch` knows what the take recorded whatever stops it.

    shutters = CardShutters(session.card_cameras, take)
    shutters.press()          # the card's files before, then the shutter: returns once each encodes
    ...                       # the take
    shutters.release()        # each camera stops and closes its file

A camera that fails to start is an error of the take (`errors`); the others record on.
"""
from __future__ import annotations

from pathlib import Path

from rig.errors import CameraDisconnected, ConfigError, DeviceError
from rig.storage.media import CardCamera, MediaManifest, utc_now


class CardShutters:
    def __init__(self, cameras: dict, take: Path):
        self.cameras = dict(cameras)
        self.manifest = MediaManifest(Path(take))
        self.errors: list[str] = []
        for name, cam in self.cameras.items():
            self.manifest.cameras[name] = CardCamera(name, cam.uri, cam.serial)

    def press(self) -> None:
        for name, cam in self.cameras.items():
            entry = self.manifest.cameras[name]
            try:
                entry.card_before = sorted(m.path for m in cam.media_list())
            except (DeviceError, CameraDisconnected, ConfigError) as exc:
                entry.files = []  # never pressed: it recorded nothing of the take
                entry.problem = f"could not list its card, so its shutter was not pressed: {exc}"
                self.errors.append(f"{name}: {entry.problem}")
                self.manifest.save()
                continue
            self.manifest.save()  # what was on the card before: the take's files are the rest
            try:
                entry.pressed_utc = utc_now()
                entry.pressed_host_ns, entry.encoding_host_ns = cam.press()
            except (DeviceError, CameraDisconnected, ConfigError) as exc:
                entry.problem = f"shutter press failed: {exc}"
                self.errors.append(f"{name}: {entry.problem}")
            self.manifest.save()

    def release(self) -> None:
        for name, cam in self.cameras.items():
            entry = self.manifest.cameras[name]
            if entry.pressed_host_ns is None or entry.released_host_ns is not None:
                continue
            entry.released_utc = utc_now()
            try:
                entry.released_host_ns = cam.release()
            except (DeviceError, CameraDisconnected, ConfigError) as exc:
                entry.released_utc = None
                entry.problem = f"shutter release failed: {exc}"
                self.errors.append(f"{name}: {entry.problem}")
            self.manifest.save()
