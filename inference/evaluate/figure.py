"""A small picture of one evaluated view: the model's render beside the camera's real image.

    path = view_figure(model, data, frame_set_index=7, camera="sup2", path=Path("models/worst-test-take.png"))

Used for the model card's worst test take (benchmarks/model_eval.py --worst-png): two panels,
each the output resized to `width` / 2 pixels wide, labelled, saved as a PNG. Kept small (the
whole of models/ ships with the product): a PNG larger than `max_bytes` is written again with its
colours reduced (fewer bits per channel) until it fits; the returned record says how many bits were kept.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from inference.errors import InferenceError, OutputError
from inference.model.pipeline import SplatSAP
from inference.train.data import FrameSource, Preprocessor


def _panel(image: torch.Tensor, size: tuple[int, int], label: str) -> np.ndarray:
    """(1, 3, H, W) in [0, 1] -> BGR uint8 at `size` (w, h), the label in its top-left corner."""
    rgb = (image[0].permute(1, 2, 0).float().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    bgr = cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), size, interpolation=cv2.INTER_AREA)
    cv2.putText(bgr, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(bgr, label, (5, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return bgr


@torch.no_grad()
def view_figure(model: SplatSAP, source: FrameSource, frame_set_index: int, camera: str, path: Path, width: int = 640,
                caption: str = "", max_bytes: int = 200_000) -> dict:
    """Render `camera` of frame set `frame_set_index` from the two sources and write the render
    beside the camera's image to `path` (PNG, `width` wide). Returns what was written."""
    if camera not in source.supervision:
        raise InferenceError(f"{camera}: not a supervision camera of the data ({', '.join(source.supervision)})")
    device = next(model.parameters()).device
    sizes = model.cfg.sizes
    pre = Preprocessor()
    fs = source.frame_set(frame_set_index)
    L = pre.views(fs, [source.left], sizes.fine).to(device)
    R = pre.views(fs, [source.right], sizes.fine).to(device)
    T = pre.views(fs, [camera], sizes.output).to(device)
    out = model.eval().run(L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses)
    w = width // 2
    h = max(1, round(w * sizes.output[1] / sizes.output[0]))
    left = _panel(out["image"], (w, h), f"render {caption}".strip())
    right = _panel(T.images, (w, h), f"ground truth ({camera})")
    picture = np.hstack([left, right])
    bits = 8
    while True:
        shown = picture if bits == 8 else (picture >> (8 - bits) << (8 - bits)) + (1 << (7 - bits))
        ok, png = cv2.imencode(".png", shown, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise OutputError(f"{path}: could not encode the PNG")
        if len(png) <= max_bytes or bits <= 4:
            break
        bits -= 1
    try:
        Path(path).write_bytes(png.tobytes())
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return {"path": str(path), "bytes": len(png), "size": [2 * w, h], "bits_per_channel": bits, "camera": camera,
            "frame_set_index": frame_set_index, "key": fs.key}
