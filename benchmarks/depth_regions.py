"""Which part of the scene's stage-1 depth costs a trained model its image, and how much.

The oracle pipeline with the model's own stage-2 weights (`rig model eval`'s oracle reference)
renders every supervision camera from the sources' depth given to it. Fed the model's stage-1
depth it measures what that depth costs; fed ground truth in one region of the sources and the
model's depth elsewhere, it measures what that region's error costs. Regions of each source, at the
coarse size (simulator takes: they carry depth and person masks):

- `people`: the person masks;
- `both see`: the rest of the scene that the other source sees too (what the stereo match covers);
- `one sees`: the rest, seen by this source alone (beyond the other's view, or hidden from it).

Also each region's share of the pixels and the stage-1 depth AbsRel there. The oracle backbone
makes every point fully opaque and places it on its own pixel's ray, so "model depth everywhere"
differs from the model itself by its opacities and its translation T; both rows are printed.

    .venv/bin/python benchmarks/depth_regions.py --model models/splat-sap-preview.pt --data HELDOUT [--every 3] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

REGIONS = ("people", "both see", "one sees")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True, help="a checkpoint (rig train's model.pt)")
    ap.add_argument("--data", type=Path, required=True, help="sequences with ground-truth depth and person masks (rig sim dataset)")
    ap.add_argument("--every", type=int, default=3, help="use every k-th frame set")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import numpy as np
    import torch

    from inference.evaluate.model_eval import oracle_twin
    from inference.train.depth_figures import stage1_depths
    from inference.metrics import covisibility, psnr
    from inference.model.checkpoint import load_checkpoint
    from inference.runtime.preprocess import pinhole
    from inference.train.data import Preprocessor
    from inference.train.stages import stage1_forward
    from rig.storage.dataset import TrainingSet, expand_sequences

    torch.set_num_threads(max(1, args.threads))
    try:
        model = load_checkpoint(args.model).eval()
        data = TrainingSet(expand_sequences([args.data]))
    except Exception as exc:  # noqa: BLE001 - a bad path or file gets one line
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if model.cfg.backbone.kind == "oracle":
        print("error: an oracle model has no stage-1 depth of its own", file=sys.stderr)
        return 2
    sizes = model.cfg.sizes
    twin = oracle_twin(model)
    pre = Preprocessor()
    feeds = ["model depth everywhere"] + [f"truth on {r}" for r in REGIONS] + ["truth everywhere"]
    scores: dict[str, list[tuple[float, float | None]]] = {n: [] for n in ["model itself"] + feeds}
    share: dict[str, list[float]] = {r: [] for r in REGIONS}
    absrel: dict[str, list[float]] = {r: [] for r in REGIONS}
    started = time.monotonic()
    picks = range(0, len(data), max(1, args.every))
    src = (data.left, data.right)
    with torch.no_grad():
        for i in picks:
            fs = data.frame_set(i, with_truth=True)
            if any(fs.depth.get(c) is None or fs.masks.get(c) is None for c in src):
                print(f"error: {args.data}: frame set {i} has no ground-truth depth or person masks (simulator takes have them)", file=sys.stderr)
                return 2
            L = pre.views(fs, [data.left], sizes.fine)
            R = pre.views(fs, [data.right], sizes.fine)
            *_, affine = stage1_forward(model, L, R)
            ours = stage1_depths(affine, L, R, data)
            gt = {c: pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse) for c in src}
            cams = {c: pinhole(fs.cameras[c], sizes.coarse) for c in src}
            region = {}
            for c, other in ((data.left, data.right), (data.right, data.left)):
                person = pre.depth(fs.masks[c].astype(np.float32), fs.cameras[c], sizes.coarse) > 0.5
                seen = covisibility(cams[c], gt[c], [(cams[other], gt[other])])
                has = gt[c] > 0
                region[c] = {"people": person & has, "both see": ~person & seen & has, "one sees": ~person & ~seen & has}
                for r, sel in region[c].items():
                    share[r].append(float(sel.sum() / has.sum()))
                    if sel.any():
                        absrel[r].append(float(np.mean(np.abs(ours[c][sel] / gt[c][sel] - 1.0))))
            depth_of = {"model depth everywhere": ours, "truth everywhere": gt}
            for r in REGIONS:
                depth_of[f"truth on {r}"] = {c: np.where(region[c][r], gt[c], ours[c]) for c in src}
            for sup in data.supervision:
                T = pre.views(fs, [sup], sizes.output)
                mask = pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.output) > 0.5
                truth = T.images[0].permute(1, 2, 0).numpy()
                args_ = (L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses)

                def add(name, image):
                    img = image[0].permute(1, 2, 0).numpy()
                    scores[name].append((psnr(img, truth), psnr(img, truth, mask) if mask.any() else None))

                add("model itself", model.run(*args_)["image"])
                for name in feeds:
                    d = [torch.from_numpy(np.ascontiguousarray(depth_of[name][c], dtype=np.float32))[None, None] for c in src]
                    add(name, twin.run(*args_, *d)["image"])
    result = {
        "model": str(args.model), "data": str(args.data), "frame_sets": len(picks), "views": len(scores["model itself"]),
        "seconds": round(time.monotonic() - started, 1),
        "regions": {r: {"share": round(float(np.mean(share[r])), 4), "absrel": round(float(np.mean(absrel[r])), 4) if absrel[r] else None} for r in REGIONS},
        "psnr": {n: {"all": round(float(np.mean([a for a, _ in v])), 2),
                     "person": round(float(np.mean([p for _, p in v if p is not None])), 2) if any(p is not None for _, p in v) else None}
                 for n, v in scores.items()},
    }
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    print(f"{args.model} on {args.data}: {len(picks)} frame sets, {result['views']} supervision views")
    print(f"{'source region':14s} {'pixels':>7s} {'stage-1 AbsRel':>15s}")
    for r, v in result["regions"].items():
        a = f"{100 * v['absrel']:14.2f}%" if v["absrel"] is not None else "            n/a"
        print(f"{r:14s} {100 * v['share']:6.1f}% {a}")
    print(f"\n{'rendered by':34s} {'PSNR dB':>8s} {'person':>8s}")
    for n, v in result["psnr"].items():
        label = n if n == "model itself" else f"oracle, {n}"
        person = f"{v['person']:8.2f}" if v["person"] is not None else "     n/a"
        print(f"{label:34s} {v['all']:8.2f} {person}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
