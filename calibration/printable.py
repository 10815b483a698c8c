"""A printable board image at true size: the PNG carries its resolution, so printing at 100% gives the
square size the board file says."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from calibration.boards import BoardSpec
from calibration.camera import CalibrationError
from common.files import atomic_write_bytes

MAX_PIXELS = 400_000_000


def board_image(board: BoardSpec, dpi: float) -> np.ndarray:
    if not 10 <= dpi <= 2400:
        raise CalibrationError(f"--dpi must be between 10 and 2400, got {dpi}")
    ppm = dpi / 0.0254
    w_m, h_m = board.size_m
    m = board.margin_m
    if (w_m + 2 * m) * (h_m + 2 * m) * ppm * ppm > MAX_PIXELS:
        raise CalibrationError(f"a {w_m:.2f} x {h_m:.2f} m board at {dpi:g} dpi is too large an image; lower --dpi")
    return board.image(ppm)


def _png_with_dpi(png: bytes, dpi: float) -> bytes:
    """Insert a pHYs chunk (pixels per metre) after IHDR."""
    ppm = int(round(dpi / 0.0254))
    data = struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", len(data)) + b"pHYs" + data + struct.pack(">I", zlib.crc32(b"pHYs" + data) & 0xFFFFFFFF)
    ihdr_end = 8 + 4 + 4 + 13 + 4  # signature, length, type, IHDR data, CRC
    return png[:ihdr_end] + chunk + png[ihdr_end:]


def write_board(board: BoardSpec, path: str | Path, dpi: float = 300.0) -> dict:
    """Render the board to `path` (PNG) at `dpi`; returns its pixel and printed size."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise CalibrationError(f"{path}: the board is written as PNG; name the file *.png")
    img = board_image(board, dpi)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise CalibrationError(f"{path}: could not encode the board image")
    atomic_write_bytes(path, _png_with_dpi(buf.tobytes(), dpi), make_parents=True)
    h, w = img.shape[:2]
    return {
        "path": str(path),
        "width_px": w,
        "height_px": h,
        "dpi": dpi,
        "width_mm": round(w / dpi * 25.4, 2),
        "height_mm": round(h / dpi * 25.4, 2),
        "square_mm": round(board.square_size * 1000, 3),
    }
