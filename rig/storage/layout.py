"""The recorded sequence folder: its file names and `sequence.json`, what was recorded.

Layout (documented for users in docs/sequence-format.md):

    SEQ/sequence.json        what was recorded: cameras, sizes, pixel formats, rate, start time
    SEQ/rig.toml             copy of the rig configuration
    SEQ/calibration.json     copy of the rig calibration (when the rig has one)
    SEQ/index.jsonl          one row per FrameSet, appended and flushed as sets land (rig/storage/index.py)
    SEQ/frames/CAM/NNNNNNNN.ppm|pgm   one binary netpbm image per frame (rig/storage/netpbm.py)
    SEQ/frames/CAM/NNNNNNNN.png       or, for a camera recorded with --compress png, one lossless PNG (rig/storage/png.py)
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from common.bayer import demosaic, mosaic
from rig.errors import RigError
from rig.storage.netpbm import NetpbmError, netpbm_header, netpbm_size, netpbm_suffix, read_netpbm
from rig.storage.png import PngError, png_damage, read_png

FORMAT_VERSION = 1
INDEX = "index.jsonl"
META = "sequence.json"
FRAMES = "frames"
CONFIG_COPY = "rig.toml"
CALIBRATION_COPY = "calibration.json"
CODECS = ("raw", "png")  # how a camera's frames are stored: uncompressed netpbm, or lossless PNG
FLASHES = "flashes.jsonl"  # the trigger board's LED flashes during the take (rig record align reads them)


class ImageError(ValueError):
    """A frame file is not a whole image of the kind the recorder writes (netpbm or PNG)."""


class SequenceError(RigError):
    """A sequence folder is missing, damaged or does not have what was asked of it."""

    exit_code = 2


def stored_layout(pixel_format: str) -> tuple[int, int]:
    """(channels, bytes per sample) of the stored image for a sensor pixel format.

    Bayer sensors are stored as their mosaic (one sample per pixel, a third of RGB's bytes): the
    backend's demosaic keeps every sample, so re-mosaicking the Frame recovers the sensor data
    exactly and the reader's demosaic gives back the very same RGB image.
    """
    if pixel_format in ("Mono8", "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8"):
        return 1, 1
    if pixel_format == "Mono16":
        return 1, 2
    return 3, 1  # RGB8


@dataclass
class CameraEntry:
    name: str
    role: str
    width: int
    height: int
    pixel_format: str  # what the sensor delivered
    channels: int  # as stored: 3 (RGB) or 1
    bytes_per_sample: int
    codec: str = "raw"  # raw (netpbm) or png; sequence.json names it only for png (a raw take reads as before)
    trigger: Optional[str] = None  # hardware, software or free, as recorded (None: a take from before it was kept)

    @property
    def frame_bytes(self) -> Optional[int]:
        """Size of each of this camera's image files (None for PNG: it varies with the content)."""
        if self.codec == "png":
            return None
        return netpbm_size(self.width, self.height, self.channels, self.bytes_per_sample)

    @property
    def raw_bytes(self) -> int:
        """Bytes of one frame's samples as stored uncompressed."""
        return self.width * self.height * self.channels * self.bytes_per_sample

    @property
    def suffix(self) -> str:
        return ".png" if self.codec == "png" else netpbm_suffix(self.channels)

    def damage(self, path: Path) -> Optional[str]:
        """Why the image file at `path` is not a whole frame of this camera, or None; from its size and
        first and last bytes, without decoding it. Raises FileNotFoundError / OSError as `open` does."""
        if self.codec == "png":
            return png_damage(path, self.width, self.height, self.channels, self.bytes_per_sample)
        size = path.stat().st_size
        if size != self.frame_bytes:
            return f"torn image ({size} of {self.frame_bytes} bytes)"
        header = netpbm_header(self.width, self.height, self.channels, self.bytes_per_sample)
        with open(path, "rb") as f:
            if f.read(len(header)) != header:
                return "damaged image header"
        return None

    def read(self, path: Path) -> np.ndarray:
        """The stored image (before `decoded`) of a frame file; ImageError when it is damaged."""
        if path.suffix != self.suffix:
            raise ImageError(f"{path}: not a {self.suffix} image (the camera is recorded as {self.codec})")
        return read_image_file(path)

    @property
    def bayer(self) -> bool:
        return self.pixel_format.startswith("Bayer")

    def stored(self, image: np.ndarray) -> np.ndarray:
        """What is written for a Frame image of this camera."""
        if self.bayer:
            return mosaic(image, self.pixel_format)
        return image

    def decoded(self, stored: np.ndarray) -> np.ndarray:
        """The Frame image back from what was stored."""
        if self.bayer:
            return demosaic(stored, self.pixel_format)
        return stored


def read_image_file(path: Path) -> np.ndarray:
    """The stored image of a frame file, netpbm or PNG by its name (ImageError when damaged)."""
    try:
        return read_png(path) if path.suffix == ".png" else read_netpbm(path)
    except (NetpbmError, PngError) as exc:
        raise ImageError(str(exc)) from None


@dataclass
class SequenceMeta:
    """The content of `sequence.json`."""

    cameras: list[CameraEntry]
    rig: str = ""
    rate_hz: Optional[float] = None
    created: str = ""
    extra: dict[str, Any] = field(default_factory=dict)  # e.g. "simulator": the ground truth of a simulator take

    def to_dict(self) -> dict[str, Any]:
        d = {"version": FORMAT_VERSION, "rig": self.rig, "rate_hz": self.rate_hz, "created": self.created,
             "cameras": [{k: v for k, v in c.__dict__.items() if not (k == "codec" and v == "raw") and not (k == "trigger" and v is None)}
                         for c in self.cameras]}
        d.update(self.extra)
        return d

    @classmethod
    def load(cls, root: Path) -> "SequenceMeta":
        path = root / META
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise SequenceError(f"{root}: not a sequence ({META} missing)") from None
        except NotADirectoryError:
            raise SequenceError(f"{root}: is a file, not a sequence folder") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise SequenceError(f"{path}: corrupt ({exc})") from None
        if not isinstance(d, dict):
            raise SequenceError(f"{path}: corrupt (not a JSON object)")
        if d.get("version") != FORMAT_VERSION:
            raise SequenceError(f"{path}: unsupported sequence version {d.get('version')!r}")
        try:
            cams = [CameraEntry(**c) for c in d["cameras"]]
        except (KeyError, TypeError) as exc:
            raise SequenceError(f"{path}: malformed camera list ({exc})") from None
        for c in cams:
            if c.codec not in CODECS:
                raise SequenceError(f"{path}: camera '{c.name}' stored as {c.codec!r}, which this version cannot read (knows {', '.join(CODECS)})")
        extra = {k: v for k, v in d.items() if k not in ("version", "rig", "rate_hz", "created", "cameras")}
        return cls(cams, d.get("rig", ""), d.get("rate_hz"), d.get("created", ""), extra)

    def camera(self, name: str) -> CameraEntry:
        for c in self.cameras:
            if c.name == name:
                return c
        raise SequenceError(f"no camera '{name}' in this sequence (have: {', '.join(c.name for c in self.cameras)})")
