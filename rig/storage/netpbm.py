"""Binary netpbm images, the sequence's image files: P6 (RGB) and P5 (mono, 8 or 16 bits).

Raw netpbm costs no CPU to write (the disk, not the CPU, is the limit on a small box) and every
image tool reads it. 16-bit samples are big-endian, as the netpbm format says. The reader takes the
files this module writes (one header field per line, no comments), not every netpbm variant.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


class NetpbmError(ValueError):
    """A file is not a whole binary PPM/PGM image of the kind the recorder writes."""


def _header(channels: int, width: int, height: int, bytes_per_sample: int) -> bytes:
    magic = b"P6" if channels == 3 else b"P5"
    maxval = 65535 if bytes_per_sample == 2 else 255
    return b"%s\n%d %d\n%d\n" % (magic, width, height, maxval)


def netpbm_header(width: int, height: int, channels: int, bytes_per_sample: int) -> bytes:
    """The exact header the recorder writes for an image of this shape: a file that does not begin
    with it is damaged (what `read_netpbm` would reject, found without reading the pixels)."""
    return _header(channels, width, height, bytes_per_sample)


def netpbm_suffix(channels: int) -> str:
    return ".ppm" if channels == 3 else ".pgm"


def netpbm_size(width: int, height: int, channels: int, bytes_per_sample: int) -> int:
    """Bytes of the whole file (header and pixels): a file of any other size is torn."""
    return len(_header(channels, width, height, bytes_per_sample)) + width * height * channels * bytes_per_sample


def encode_netpbm(image: np.ndarray) -> tuple[bytes, memoryview]:
    """Header and pixel bytes of a binary PPM/PGM, kept apart so the pixels are written without a copy."""
    if image.dtype == np.uint16:
        data = image.astype(">u2", copy=False)
    elif image.dtype == np.uint8:
        data = image
    else:
        raise ValueError(f"cannot store {image.dtype} images")
    h, w = image.shape[:2]
    header = _header(3 if image.ndim == 3 else 1, w, h, image.dtype.itemsize)
    return header, memoryview(np.ascontiguousarray(data)).cast("B")


def read_netpbm(path: Path) -> np.ndarray:
    """The image (HxWx3 RGB or HxW, uint8 or uint16) of a binary PPM/PGM written by `encode_netpbm`."""
    with open(path, "rb") as f:
        data = f.read()
    parts = data.split(b"\n", 3)
    if len(parts) < 4 or parts[0] not in (b"P5", b"P6"):
        raise NetpbmError(f"{path}: not a binary PPM/PGM image")
    try:
        w, h = (int(x) for x in parts[1].split())
        maxval = int(parts[2])
    except ValueError:
        raise NetpbmError(f"{path}: damaged PPM/PGM header") from None
    if w <= 0 or h <= 0 or maxval not in (255, 65535):
        raise NetpbmError(f"{path}: unsupported PPM/PGM header ({w}x{h}, maxval {maxval})")
    channels = 3 if parts[0] == b"P6" else 1
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    need = w * h * channels * dtype.itemsize
    if len(parts[3]) < need:
        raise NetpbmError(f"{path}: torn image ({len(parts[3])} of {need} bytes)")
    arr = np.frombuffer(parts[3], dtype=dtype, count=w * h * channels)
    arr = arr.reshape((h, w, 3) if channels == 3 else (h, w))
    return arr.astype(np.uint16) if maxval > 255 else arr
