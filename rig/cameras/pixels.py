"""Pixel-format handling shared by the backends: raw sensor buffers to Frame images.

Bayer data becomes RGB (the Frame keeps the sensor's pixel format name) through common.bayer, the
one mosaic/demosaic of the project: its demosaic keeps every sensor sample, so a recording can store
the mosaic and read back the identical RGB. `mosaic` and `demosaic` here are that module's functions
(they take a Bayer pixel format such as "BayerRG8" as well as a bare pattern).
"""
from __future__ import annotations

import cv2
import numpy as np

from common.bayer import demosaic, mosaic

BAYER_FORMATS = ("BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8")
BYTES_PER_PIXEL = {"Mono8": 1, "Mono16": 2, "RGB8": 3, "BayerRG8": 1, "BayerGR8": 1, "BayerGB8": 1, "BayerBG8": 1}

__all__ = ["BAYER_FORMATS", "BYTES_PER_PIXEL", "buffer_to_image", "demosaic", "from_rgb", "is_bayer", "mosaic", "rgb8"]


def is_bayer(pixel_format: str) -> bool:
    return pixel_format in BAYER_FORMATS


def buffer_to_image(data, width: int, height: int, pixel_format: str, copy: bool = True) -> np.ndarray:
    """Decode a raw buffer (bytes-like) into a Frame image.

    With copy=False the image may share memory with `data` (read-only): use it when `data` is an
    immutable bytes object that nothing will reuse.
    """
    keep = (lambda a: a.copy()) if copy else (lambda a: a)
    bpp = BYTES_PER_PIXEL[pixel_format]
    need = width * height * bpp
    arr = np.frombuffer(data, dtype=np.uint8, count=need)
    if pixel_format == "Mono16":
        return keep(arr.view("<u2").reshape(height, width))
    if pixel_format == "RGB8":
        return keep(arr.reshape(height, width, 3))
    mono = arr.reshape(height, width)
    if is_bayer(pixel_format):
        return demosaic(mono, pixel_format)
    return keep(mono)


def rgb8(image: np.ndarray) -> np.ndarray:
    """A frame's image as RGB uint8, what the model takes: mono repeated, 16-bit shifted down."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return image


def from_rgb(rgb: np.ndarray, pixel_format: str) -> np.ndarray:
    """What a sensor with this pixel format would deliver for an RGB uint8 scene image (before decoding)."""
    if pixel_format == "RGB8":
        return rgb
    if is_bayer(pixel_format):
        return mosaic(rgb, pixel_format)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if pixel_format == "Mono16":
        return grey.astype(np.uint16) * 257
    return grey
