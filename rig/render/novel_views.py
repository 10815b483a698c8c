"""Novel views of a recorded take in place of its supervision cameras, rendered by the shipped model (the demo's last step).

For a few frame sets spread over the take, every supervision camera is rendered from the two
sources with the ONNX Runtime pipeline (the live path: no torch) and compared with what that camera
really recorded, beside the nearer source's own image (what a viewer sees without a model). Each
view is written as a PNG: the novel view on the left, the real camera on the right.
"""
from __future__ import annotations

import statistics
from pathlib import Path

import cv2
import numpy as np


def render_novel_views(take: Path, out_dir: Path, sets: int = 3, model: Path | None = None) -> dict:
    from inference.metrics import psnr
    from inference.runtime import NovelViewPipeline
    from rig.storage.dataset import Sequence

    seq = Sequence(take)
    left, right = seq.sources()
    sups = seq.supervision
    if not sups:
        return {"skipped": "the rig has no supervision camera to compare a novel view with"}
    pipe = NovelViewPipeline(model)  # None: the shipped model
    names = [left, right] + sups
    complete = seq.complete_sets(names)
    if not complete:
        return {"skipped": "no frame set has every camera"}
    picks = sorted({complete[round(i * (len(complete) - 1) / max(1, sets - 1))] for i in range(min(sets, len(complete)))})
    out_dir.mkdir(parents=True, exist_ok=True)
    size = pipe.sizes.output
    scores, nearer_scores, ms, files = [], [], [], []
    for p in picks:
        s = seq.sample(p, names)
        cams = s.cameras
        for sup in sups:
            view = pipe.render(s.images[left], s.images[right], cams[left], cams[right], cams[sup])
            truth = pipe.prepare.resampler(cams[sup], size).image(s.images[sup])
            nearer = min((left, right), key=lambda c: float(np.linalg.norm(cams[c].center - cams[sup].center)))
            as_is = pipe.prepare.resampler(cams[nearer], size).image(s.images[nearer])
            scores.append(psnr(view.image, truth))
            nearer_scores.append(psnr(as_is, truth))
            ms.append(view.ms)
            pair = np.concatenate([view.image, truth], axis=1)
            path = out_dir / f"set-{s.set:06d}-{sup}.png"
            cv2.imwrite(str(path), cv2.cvtColor((np.clip(pair, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
            files.append(str(path))
    return {"model": str(pipe.path), "views": len(scores), "sets": [int(p) for p in picks], "cameras": sups,
            "psnr": round(statistics.mean(scores), 2), "nearer_source_psnr": round(statistics.mean(nearer_scores), 2),
            "ms_per_view": round(statistics.median(ms), 1), "folder": str(out_dir), "files": files}


def render_strip(take: Path, out_png: Path, ts: tuple[float, ...] = (0.25, 0.5, 0.75), model: Path | None = None) -> dict:
    """One PNG of the take's middle complete set: source left | novel views at `ts` along the arc
    from left to right | source right, all at the model's output size."""
    from inference.runtime import NovelViewPipeline
    from rig.live.viewpoint import arc_camera
    from rig.storage.dataset import Sequence

    seq = Sequence(take)
    left, right = seq.sources()
    pipe = NovelViewPipeline(model)
    complete = seq.complete_sets([left, right])
    s = seq.sample(complete[len(complete) // 2], [left, right])
    cams = s.cameras
    size = pipe.sizes.output
    tiles = [pipe.prepare.resampler(cams[left], size).image(s.images[left])]
    for t in ts:
        view = pipe.render(s.images[left], s.images[right], cams[left], cams[right], arc_camera(cams[left], cams[right], t, size))
        tiles.append(view.image)
    tiles.append(pipe.prepare.resampler(cams[right], size).image(s.images[right]))
    strip = np.concatenate(tiles, axis=1)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_png), cv2.cvtColor((np.clip(strip, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
    return {"file": str(out_png), "set": int(s.set), "t": list(ts)}
