"""The emulated GoPro's picture when no scene is given: moving bars in a colour of its own (two
cameras never look alike) with the frame's time in milliseconds written as 32 black/white blocks
along the top, so a decoded frame says which instant it shows (`read_time_code`)."""
from __future__ import annotations

import zlib
from typing import Callable, Optional

import cv2
import numpy as np

CODE_BITS = 32


def time_code_pattern(width: int, height: int, seed: str | int = 0) -> Callable[[float], np.ndarray]:
    key = zlib.crc32(str(seed).encode()) if not isinstance(seed, int) else seed
    # a saturated colour of a hue of its own: two cameras' pictures differ even after lossy coding
    hue = np.uint8(key % 180)
    tint = cv2.cvtColor(np.array([[[hue, 220, 210]]], np.uint8), cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32)
    period = 96
    xx = np.arange(width + period, dtype=np.float32)
    bars = np.where((xx % period) < period / 2, 1.0, 0.45)[None, :, None]
    yy = np.linspace(0.7, 1.0, height, dtype=np.float32)[:, None, None]
    base = np.clip(bars * yy * tint, 0, 255).astype(np.uint8)  # (height, width + period, 3)
    block = max(1, width // CODE_BITS)
    band = max(2, min(height // 8, block))

    def render(t: float) -> np.ndarray:
        shift = int(t * 120.0) % period
        image = np.ascontiguousarray(base[:, shift:shift + width])
        code = int(round(t * 1000.0)) & 0xFFFFFFFF
        for bit in range(CODE_BITS):
            x0 = bit * block
            if x0 >= width:
                break
            image[:band, x0:x0 + block] = 255 if (code >> (CODE_BITS - 1 - bit)) & 1 else 0
        return image

    return render


def read_time_code(image: np.ndarray) -> Optional[int]:
    """The millisecond code a `time_code_pattern` frame carries (after lossy coding: blocks read by their
    mean brightness); None when the frame is too small to hold it."""
    height, width = image.shape[:2]
    block = max(1, width // CODE_BITS)
    band = max(2, min(height // 8, block))
    if block * CODE_BITS > width or band < 2:
        return None
    gray = image[:band].astype(np.float32)
    gray = gray.mean(axis=2) if gray.ndim == 3 else gray
    y0, y1 = band // 4, max(band // 4 + 1, band - band // 4)  # the middle of each block: away from coding blur
    code = 0
    for bit in range(CODE_BITS):
        x0 = bit * block + block // 4
        x1 = max(x0 + 1, (bit + 1) * block - block // 4)
        code = (code << 1) | int(gray[y0:y1, x0:x1].mean() > 127)
    return code
