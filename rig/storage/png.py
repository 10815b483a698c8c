"""Lossless PNG frames, the sequence's compressed image files (`rig record --compress png`).

Written through PyAV's PNG encoder (FFmpeg's: Paeth prediction, zlib level 1, the fastest level
that still finds most of what there is to gain; docs/sequence-format.md has the figures), read with
OpenCV's decoder. 16-bit samples are stored big-endian, as PNG says; both libraries take care of it.
A PNG is whole when it begins with the signature and the header chunk of the camera's size and
format and ends with the IEND chunk: `png_damage` tells a torn or damaged file from the first and
last bytes, without decoding it.
"""
from __future__ import annotations

import contextlib
import os
import struct
import sys
from pathlib import Path
from typing import Optional

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the last chunk of every PNG: length 0, type, CRC
# PNG colour types: 0 greyscale, 2 truecolour (RGB)
_COLOUR_TYPE = {1: 0, 3: 2}
# PyAV pixel formats of the stored image: (channels, bytes per sample) -> format
_PIX_FMT = {(3, 1): "rgb24", (1, 1): "gray", (1, 2): "gray16be"}
PNG_OPTIONS = {"compression_level": "1", "pred": "paeth"}


class PngError(ValueError):
    """A file is not a whole PNG image of the kind the recorder writes."""


class PngEncoder:
    """Encodes one camera's frames to PNG bytes; one per writer thread (a codec context is not
    shared between threads)."""

    def __init__(self, width: int, height: int, channels: int, bytes_per_sample: int):
        import av  # the recorder's only use of PyAV: raw takes never load it

        self._av = av
        self.pix_fmt = _PIX_FMT[(channels, bytes_per_sample)]
        self.width, self.height = width, height

    def encode(self, image: np.ndarray) -> bytes:
        av = self._av
        # a fresh context per frame: FFmpeg's PNG encoder keeps no state between frames, and a
        # context that failed on one frame must not carry anything into the next
        cc = av.CodecContext.create("png", "w")
        cc.width, cc.height, cc.pix_fmt = self.width, self.height, self.pix_fmt
        cc.options = dict(PNG_OPTIONS)
        data = np.ascontiguousarray(image)  # 16-bit: native order in, PyAV writes it big-endian
        frame = av.VideoFrame.from_ndarray(data, format=self.pix_fmt)
        packets = list(cc.encode(frame)) + list(cc.encode(None))
        return b"".join(bytes(p) for p in packets)


@contextlib.contextmanager
def quiet_decoder():
    """Keep libpng's own messages ("libpng error: IDAT: CRC error", written straight to file
    descriptor 2) off stderr while a command checks images: the damage is reported as an error of
    the command's own. For one thread's checks (validate, repair): it silences the whole process."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to keep quiet
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def read_png(path: Path) -> np.ndarray:
    """The image (HxWx3 RGB or HxW, uint8 or uint16) of a PNG written by `PngEncoder`."""
    import cv2

    data = np.fromfile(path, dtype=np.uint8)
    damage = png_damage_bytes(bytes(data[:33]), bytes(data[-12:]) if data.size >= 12 else b"")
    if damage is not None:
        raise PngError(f"{path}: {damage}")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise PngError(f"{path}: damaged PNG (does not decode)")
    return np.ascontiguousarray(img[..., ::-1]) if img.ndim == 3 else img  # OpenCV decodes to BGR


def png_damage_bytes(head: bytes, tail: bytes, width: Optional[int] = None, height: Optional[int] = None,
                     channels: Optional[int] = None, bytes_per_sample: Optional[int] = None) -> Optional[str]:
    """Why a PNG with these first 33 and last 12 bytes is not a whole frame (of the given shape), or None."""
    if not head.startswith(SIGNATURE) or head[12:16] != b"IHDR" or len(head) < 33:
        return "damaged image header (not a PNG)"
    w, h, depth, colour = struct.unpack(">IIBB", head[16:26])
    if width is not None and (w, h) != (width, height):
        return f"damaged image header ({w}x{h}, the camera records {width}x{height})"
    if channels is not None and (depth != 8 * bytes_per_sample or colour != _COLOUR_TYPE[channels]):
        return f"damaged image header (PNG of bit depth {depth}, colour type {colour})"
    if tail != IEND:
        return "torn image (the PNG has no end chunk)"
    return None


def png_damage(path: Path, width: int, height: int, channels: int, bytes_per_sample: int) -> Optional[str]:
    """Why the PNG at `path` is not a whole frame of this shape, or None (reads 45 bytes of it)."""
    with open(path, "rb") as f:
        head = f.read(33)
        size = f.seek(0, 2)
        if size < 33 + 12:
            return "torn image (too short for a PNG)"
        f.seek(size - 12)
        tail = f.read(12)
    return png_damage_bytes(head, tail, width, height, channels, bytes_per_sample)
