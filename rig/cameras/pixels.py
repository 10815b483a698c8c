"""Pixel-format handling shared by the backends: raw sensor buffers to Frame images.

Bayer data becomes RGB (the Frame keeps the sensor's pixel format name). OpenCV names Bayer
patterns by the 2x2 block starting at pixel (1, 1), GenICam by the block at (0, 0), so GenICam
BayerRG (R at the top-left) is OpenCV's BayerBG.
"""
from __future__ import annotations

import cv2
import numpy as np

_BAYER_TO_RGB = {
    "BayerRG8": cv2.COLOR_BayerBG2RGB,
    "BayerBG8": cv2.COLOR_BayerRG2RGB,
    "BayerGR8": cv2.COLOR_BayerGB2RGB,
    "BayerGB8": cv2.COLOR_BayerGR2RGB,
}

BYTES_PER_PIXEL = {"Mono8": 1, "Mono16": 2, "RGB8": 3, "BayerRG8": 1, "BayerGR8": 1, "BayerGB8": 1, "BayerBG8": 1}


def is_bayer(pixel_format: str) -> bool:
    return pixel_format in _BAYER_TO_RGB


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


def demosaic(raw: np.ndarray, pixel_format: str) -> np.ndarray:
    """Bayer mosaic to RGB, keeping every sensor sample exactly where it was.

    OpenCV treats the outermost rows and columns differently from the interior; a 2-pixel mirror
    border (which keeps the colour phase) gives every pixel the interior treatment, so
    `mosaic(demosaic(raw)) == raw` and a recording can store the mosaic without loss.
    """
    padded = cv2.copyMakeBorder(raw, 2, 2, 2, 2, cv2.BORDER_REFLECT_101)
    return cv2.cvtColor(padded, _BAYER_TO_RGB[pixel_format])[2:-2, 2:-2].copy()


def mosaic(rgb: np.ndarray, pixel_format: str) -> np.ndarray:
    """Sample an RGB image through a Bayer colour filter array (GenICam pattern naming)."""
    pattern = pixel_format[5:7]  # "RG", "GR", "GB", "BG"
    channel = {"R": 0, "G": 1, "B": 2}
    top = pattern
    bottom = {"RG": "GB", "BG": "GR", "GR": "BG", "GB": "RG"}[pattern]
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, channel[top[0]]]
    out[0::2, 1::2] = rgb[0::2, 1::2, channel[top[1]]]
    out[1::2, 0::2] = rgb[1::2, 0::2, channel[bottom[0]]]
    out[1::2, 1::2] = rgb[1::2, 1::2, channel[bottom[1]]]
    return out


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
