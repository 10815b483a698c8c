"""The Frame and FrameSet types that travel from camera backends through sync to every consumer."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterator, Optional

import numpy as np

PIXEL_FORMATS = ("Mono8", "Mono16", "RGB8", "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8")


def monotonic_ns() -> int:
    """Host timestamps: the monotonic clock, in nanoseconds."""
    return time.monotonic_ns()


@dataclass
class Frame:
    """One image from one camera.

    `image` is HxW (mono) or HxWx3 RGB; Bayer sensor data is converted to RGB by the backend and
    `pixel_format` then records what the sensor delivered. `device_ts_ns` is the camera's own clock;
    `host_ts_ns` is host monotonic time when the frame reached the host. `trigger_index` is set by
    sync once the frame has been assigned to a trigger pulse.
    """

    image: np.ndarray
    camera: str
    frame_id: int
    device_ts_ns: int
    host_ts_ns: int
    pixel_format: str = "Mono8"
    exposure_us: Optional[float] = None
    trigger_index: Optional[int] = None
    sim_time_s: Optional[float] = None  # simulated cameras only: the scene time the image shows (ground truth)

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def meta(self) -> dict:
        """The frame's metadata as a JSON-ready dict (no pixels)."""
        return {
            "camera": self.camera,
            "frame_id": int(self.frame_id),
            "device_ts_ns": int(self.device_ts_ns),
            "host_ts_ns": int(self.host_ts_ns),
            "pixel_format": self.pixel_format,
            "exposure_us": self.exposure_us,
            "trigger_index": self.trigger_index,
            "sim_time_s": self.sim_time_s,
        }


@dataclass
class FrameSet:
    """One instant: a Frame per camera, or None where that camera's frame is missing (a marked gap)."""

    index: int
    frames: dict[str, Optional[Frame]] = field(default_factory=dict)
    host_ts_ns: Optional[int] = None
    trigger_index: Optional[int] = None  # the trigger pulse (counted from 0 in its train), when triggered
    train: int = 0  # which pulse train of the session (a new one after the trigger board came back)

    @property
    def cameras(self) -> list[str]:
        return list(self.frames)

    @property
    def complete(self) -> bool:
        return all(f is not None for f in self.frames.values())

    @property
    def missing(self) -> list[str]:
        return [name for name, f in self.frames.items() if f is None]

    def __getitem__(self, camera: str) -> Optional[Frame]:
        return self.frames[camera]

    def __iter__(self) -> Iterator[Frame]:
        return (f for f in self.frames.values() if f is not None)

    def skew_ns(self) -> int:
        """Spread of host timestamps across the present frames."""
        ts = [f.host_ts_ns for f in self]
        return (max(ts) - min(ts)) if len(ts) > 1 else 0
