"""How much depth a plane-sweep volume coarser than the coarse size loses on its way up to it.

The stereo backbone matches at a quarter of the size it reads its images at: at a quarter of stage
1's coarse size (64x36 at the preview size) by default, where a cell is 4x4 coarse pixels and a
person a few cells wide; at half of it with `backbone.stereo_input_scale` 2 (`--cell 2`). This takes each source's ground-truth
depth at the coarse size (simulator takes: they carry depth and person masks), pools its inverse
to the volume's cells (what a perfect volume could hold) and brings it back up:

- `bilinear`: bilinear upsampling (what the backbone does);
- `nearest`: each pixel takes its own cell's value;
- `best of 3x3`: each pixel takes whichever of its cell's 3x3 neighbours is nearest the truth (what
  an edge-aware upsampling, RAFT's convex one say, would reach if it picked perfectly).

AbsRel over every pixel with depth and over the person masks, both sources of every `--every`-th
frame set.

    .venv/bin/python benchmarks/depth_upsampling.py --data HELDOUT [--every 3] [--size preview] [--cell 4|2] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="sequences with ground-truth depth (rig sim dataset)")
    ap.add_argument("--every", type=int, default=3, help="use every k-th frame set")
    ap.add_argument("--size", default="preview", help="size preset whose coarse size is used (preview, paper)")
    ap.add_argument("--cell", type=int, choices=(1, 2, 4), default=4,
                    help="coarse pixels per volume cell: 4 / backbone.stereo_input_scale (default 4)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import numpy as np
    import torch
    import torch.nn.functional as F

    from inference.config import Sizes
    from inference.train.data import Preprocessor
    from rig.storage.dataset import TrainingSet, expand_sequences

    torch.set_num_threads(2)
    coarse = Sizes.preset(args.size).coarse
    cw, ch = coarse
    cell = args.cell
    if cw % cell or ch % cell:
        print(f"error: the coarse size {cw}x{ch} is not a multiple of {cell}", file=sys.stderr)
        return 2
    try:
        data = TrainingSet(expand_sequences([args.data]))
    except Exception as exc:  # noqa: BLE001 - a bad folder gets one line
        print(f"error: {args.data}: {exc}", file=sys.stderr)
        return 2
    pre = Preprocessor()
    names = ["bilinear", "nearest", "best of 3x3"]
    errs = {n: ([], []) for n in names}
    started = time.monotonic()
    sets = range(0, len(data), max(1, args.every))
    for i in sets:
        fs = data.frame_set(i, with_truth=True)
        if any(fs.depth.get(c) is None or fs.masks.get(c) is None for c in (data.left, data.right)):
            print(f"error: {args.data}: frame set {i} has no ground-truth depth or person masks (simulator takes have them)", file=sys.stderr)
            return 2
        for cam in (data.left, data.right):
            gt = pre.depth(fs.depth[cam], fs.cameras[cam], coarse)
            person = pre.depth(fs.masks[cam].astype(np.float32), fs.cameras[cam], coarse) > 0.5
            ok = gt > 0
            inv = torch.from_numpy(np.where(ok, 1.0 / np.maximum(gt, 1e-6), 0.0).astype(np.float32))[None, None]
            pooled = F.avg_pool2d(inv, cell)
            padded = F.pad(pooled, (1, 1, 1, 1), mode="replicate")
            h, w = pooled.shape[-2:]
            near = torch.cat([padded[:, :, dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], dim=1)
            near = F.interpolate(near, scale_factor=cell, mode="nearest")[0].numpy()  # (9, H, W)
            out = {
                "bilinear": F.interpolate(pooled, scale_factor=cell, mode="bilinear", align_corners=False)[0, 0].numpy(),
                "nearest": near[4],
            }
            rel_all = np.abs(1.0 / np.maximum(near, 1e-6) - gt[None]) / np.maximum(gt, 1e-6)[None]
            best = rel_all.min(axis=0)
            for n in names:
                e = best if n == "best of 3x3" else np.abs(1.0 / np.maximum(out[n], 1e-6) - gt) / np.maximum(gt, 1e-6)
                errs[n][0].append(float(e[ok].mean()))
                if (ok & person).any():
                    errs[n][1].append(float(e[ok & person].mean()))
    result = {
        "data": str(args.data), "coarse": f"{cw}x{ch}", "volume": f"{cw // cell}x{ch // cell}", "frame_sets": len(sets),
        "seconds": round(time.monotonic() - started, 1),
        "absrel": {n: {"all": float(np.mean(a)), "person": float(np.mean(p)) if p else None} for n, (a, p) in errs.items()},
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"{args.data}: {len(sets)} frame sets, depth at {cw}x{ch} pooled to {cw // cell}x{ch // cell} and upsampled again")
    print(f"{'':14s} {'AbsRel':>8s} {'person':>8s}")
    for n, v in result["absrel"].items():
        person = f"{100 * v['person']:7.2f}%" if v["person"] is not None else "     n/a"
        print(f"{n:14s} {100 * v['all']:7.2f}% {person}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
