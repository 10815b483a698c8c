"""The Bayer colour filter array: RGB through the filter (mosaic) and back (demosaic).

A pattern is named by the top row of its 2x2 block at pixel (0, 0), as GenICam names pixel formats:
"RG" (= BayerRG8) has R at the top-left, G beside it, and G, B in the row below. OpenCV names its
conversions by the block at pixel (1, 1) instead, so GenICam BayerRG is OpenCV's BayerBG.

The demosaic keeps every sensor sample exactly where it was: `mosaic(demosaic(raw)) == raw`. So a
recording stores the mosaic (exactly what the sensor sent, a third of RGB's bytes) and a reader's
demosaic of it is the very same RGB image the live Frame had (docs/sequence-format.md). OpenCV's
bilinear demosaic keeps the samples of interior pixels but fills the outermost rows and columns
from their neighbours; a 2-pixel mirror border (an even width keeps the colour phase) gives every
pixel the interior treatment.
"""
from __future__ import annotations

import cv2
import numpy as np

PATTERNS = ("RG", "GR", "GB", "BG")

# pattern (block at (0, 0)) -> OpenCV conversion (named by the block at (1, 1))
_TO_RGB = {"RG": cv2.COLOR_BayerBG2RGB, "BG": cv2.COLOR_BayerRG2RGB, "GR": cv2.COLOR_BayerGB2RGB, "GB": cv2.COLOR_BayerGR2RGB}
_BOTTOM_ROW = {"RG": "GB", "BG": "GR", "GR": "BG", "GB": "RG"}
_CHANNEL = {"R": 0, "G": 1, "B": 2}
_BORDER = 2  # even: the mirrored border continues the colour phase


def bayer_pattern(name: str) -> str:
    """The pattern of a name: a pattern itself ("RG") or an 8-bit GenICam Bayer pixel format
    ("BayerRG8"). Anything else is a ValueError."""
    if name in PATTERNS:
        return name
    if isinstance(name, str) and name.startswith("Bayer") and name.endswith("8") and name[5:7] in PATTERNS and len(name) == 8:
        return name[5:7]
    raise ValueError(f"{name!r} is not a Bayer pattern (allowed: {', '.join(PATTERNS)} or BayerRG8, BayerGR8, BayerGB8, BayerBG8)")


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """One sample per pixel, of the colour the filter above it passes: HxWx3 RGB -> HxW."""
    pattern = bayer_pattern(pattern)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"mosaic needs an HxWx3 RGB image, got shape {rgb.shape}")
    top, bottom = pattern, _BOTTOM_ROW[pattern]
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, _CHANNEL[top[0]]]
    out[0::2, 1::2] = rgb[0::2, 1::2, _CHANNEL[top[1]]]
    out[1::2, 0::2] = rgb[1::2, 0::2, _CHANNEL[bottom[0]]]
    out[1::2, 1::2] = rgb[1::2, 1::2, _CHANNEL[bottom[1]]]
    return out


def demosaic(raw: np.ndarray, pattern: str) -> np.ndarray:
    """HxW mosaic (uint8 or uint16) -> HxWx3 RGB by bilinear interpolation, every sample kept."""
    pattern = bayer_pattern(pattern)
    if raw.ndim != 2 or raw.shape[0] < 2 or raw.shape[1] < 2:
        raise ValueError(f"demosaic needs an HxW mosaic of at least 2x2, got shape {raw.shape}")
    if raw.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"demosaic needs uint8 or uint16 samples, got {raw.dtype}")
    b = _BORDER
    padded = cv2.copyMakeBorder(np.ascontiguousarray(raw), b, b, b, b, cv2.BORDER_REFLECT_101)
    return np.ascontiguousarray(cv2.cvtColor(padded, _TO_RGB[pattern])[b:-b, b:-b])
