"""`gopro://SERIAL[@HOST:PORT]?record=card`: a GoPro that records the take to its own card.

Such a camera gives no live frames. Opening it takes wired USB control (rig.cameras.gopro_http),
waits until it is ready and sets the video preset group, the resolution of the configured
`width` x `height` (a recording size: 5.3K, 4K, 2.7K, 1080, ...) and the frame rate `fps` (24, 25,
30, 50, 60, 100, 120, 200 or 240); a setting the camera refuses is a one-line error before the take.
`rig record` then presses the shutter once the take runs (`press`: it returns when the camera says it
encodes) and releases it when the take ends (`release`: it returns once the camera has closed the
file); rig.capture.cards does that, and rig.capture.fetch downloads what the camera recorded into the
take. The session opens it with the other cameras but leaves it out of the frame grouping.
"""
from __future__ import annotations

import time

from rig.cameras.base import Camera, raise_problems
from rig.cameras.gopro_http import FPS, RESOLUTION_SIZES, GoProClient, MediaItem, resolution_for_size
from rig.errors import CameraDisconnected, ConfigError, DeviceError
from sync.frames import monotonic_ns

ENCODING_TIMEOUT_S = 5.0  # from the shutter press until the camera says it encodes
CLOSE_TIMEOUT_S = 60.0  # from the shutter release until the camera has closed the file (long takes take a while)


def card_problems(settings) -> list[str]:
    """What keeps these settings from recording to a GoPro's card (gopro.problems asks)."""
    out = []
    if settings.trigger != "free":
        out.append('a GoPro cannot be triggered; set trigger = "free" (its video is aligned afterwards: rig record align)')
    if (settings.width, settings.height) not in RESOLUTION_SIZES.values():
        sizes = ", ".join(f"{w}x{h}" for w, h in RESOLUTION_SIZES.values())
        out.append(f"a GoPro records {sizes} to its card; got {settings.width}x{settings.height}")
    if f"{float(settings.fps):g}" not in FPS.options:
        out.append(f"a GoPro records at {', '.join(sorted(FPS.options, key=float))} fps; got {settings.fps:g}")
    return out


class GoProCardCamera(Camera):
    records_to_card = True  # the session opens it but groups no frames of it

    def __init__(self, uri: str, settings, client: GoProClient):
        """`client`: not yet connected, for the camera the URI names (rig.cameras.gopro opens it so)."""
        super().__init__(uri, settings)
        raise_problems(settings, uri, card_problems(settings))
        self.client = client
        self.serial = self.client.serial
        self.pressed = False
        self.client.connect()
        try:
            self.client.load_preset_group("video")
            self.client.set_resolution(resolution_for_size(settings.width, settings.height))
            self.client.set_fps(settings.fps)
        except BaseException:
            self.client.close()
            raise

    # --- the card ------------------------------------------------------------------------------------
    def media_list(self) -> list[MediaItem]:
        return self.client.media_list()

    def press(self) -> tuple[int, int]:
        """Start recording: (host monotonic ns when the shutter was pressed, when the camera said it
        encodes). DeviceError when it does not start within ENCODING_TIMEOUT_S."""
        self.client.wait_ready()
        pressed = monotonic_ns()
        self.client.shutter_start()
        self.pressed = True
        deadline = time.monotonic() + ENCODING_TIMEOUT_S
        while not self.client.state().encoding:
            if time.monotonic() >= deadline:
                raise DeviceError(f"{self.name} ({self.uri}): pressed the shutter, but the camera did not start "
                                  f"recording within {ENCODING_TIMEOUT_S:g} s (card full or missing?)")
            time.sleep(self.client.poll_s)
        return pressed, monotonic_ns()

    def release(self) -> int:
        """Stop recording and wait until the camera has closed the file: host monotonic ns of the release."""
        released = monotonic_ns()
        self.client.shutter_stop()
        self.pressed = False
        self.client.wait_ready(timeout=CLOSE_TIMEOUT_S)
        return released

    # --- the camera contract: no live frames -----------------------------------------------------------
    def start(self) -> None:
        pass  # recording is the shutter's business (press / release)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        """Releases the shutter if it is still pressed (a take that ended by an error), then lets go."""
        if self.pressed:
            try:
                self.release()
            except (DeviceError, CameraDisconnected):
                pass  # the camera is gone: it stops by itself when its battery or card runs out
        self.client.close()

    def _read_frame(self, timeout: float):
        raise ConfigError(f"{self.name} ({self.uri}): records to its card and has no live frames "
                          "(`rig record` downloads its video into the take; drop ?record=card for webcam frames)")

    def software_trigger(self) -> None:
        raise ConfigError(f"{self.name} ({self.uri}): a GoPro cannot be triggered")

