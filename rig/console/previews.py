"""Preview images of the newest frames: JPEG at the viewer's size, a histogram, clipped pixels marked.

Encoded on the server's threads at the rate each viewer asks for, from a reference to the newest
frame (rig.console.rigstate): never on the capture path.
"""
from __future__ import annotations

import cv2
import numpy as np

HIST_BINS = 32
CLIPPED = 250  # an 8-bit value at or above this counts as clipped (the overlay paints it red)
MAX_WIDTH = 960


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) of uint8 or uint16 -> (H, W, 3) uint8."""
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img


def preview(image: np.ndarray, width: int = 320, overlay: bool = False, quality: int = 75) -> tuple[bytes, dict]:
    """(JPEG bytes, {"histogram": [HIST_BINS fractions of the luma], "clipped": fraction of clipped pixels})."""
    rgb = to_rgb8(image)
    h, w = rgb.shape[:2]
    width = max(16, min(int(width), MAX_WIDTH, w))
    small = cv2.resize(rgb, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA) if width < w else rgb
    luma = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    hist = np.bincount((luma >> 3).ravel(), minlength=HIST_BINS).astype(np.float64)
    clipped_mask = small.max(axis=2) >= CLIPPED
    stats = {"histogram": [round(float(v), 5) for v in hist / max(1.0, hist.sum())],
             "clipped": round(float(clipped_mask.mean()), 5)}
    if overlay and clipped_mask.any():
        small = small.copy()
        small[clipped_mask] = (255, 0, 64)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), stats
