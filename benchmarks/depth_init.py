"""Depth initialisation's z-buffers on ground-truth points: how well each puts the target's depth.

Stage 2 refines the initial depth within +-6 % (Stage2Config.search_range), so the initial depth
splatted into a supervision camera must lie within that of the truth. This feeds each source's
ground-truth depth (at the coarse size, through the oracle backbone: no learned weight is involved)
into depth initialisation at every supervision camera of every `--every`-th frame set of `--data`
(simulator takes: they carry ground-truth depth and person masks) and compares the result with the
camera's own ground-truth depth at the fine size:

- AbsRel over all pixels and over the person mask;
- the share of pixels within 2 % of the truth, and the share further off than 6 % (beyond what
  stage 2 can refine).

One line per configuration: "occlusion" (the default) and "reference" (the z-buffer of models saved
before it) at splat radius 1 and 2.

    .venv/bin/python benchmarks/depth_init.py --data HELDOUT [--every 2] [--size preview] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CONFIGS = {
    "occlusion r2 (default)": {"zbuffer": "occlusion", "radius": 2},
    "occlusion r1": {"zbuffer": "occlusion", "radius": 1},
    "reference r1 (saved before)": {"zbuffer": "reference", "radius": 1},
    "reference r2": {"zbuffer": "reference", "radius": 2},
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="sequences with ground-truth depth (rig sim dataset)")
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--size", default="preview")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import numpy as np
    import torch

    from inference.config import ModelConfig, Sizes
    from inference.config import DepthInitConfig
    from inference.model.depth_init import DepthInit
    from inference.model.geometry import relative_pose, resize_intrinsics
    from inference.model.pipeline import build_model
    from inference.train.data import Preprocessor
    from rig.storage.dataset import TrainingSet, expand_sequences

    data = TrainingSet(expand_sequences([args.data]))
    model = build_model(ModelConfig.for_backbone("oracle", Sizes.preset(args.size)), seed=0)
    sizes = model.cfg.sizes
    pre = Preprocessor()
    layers = {name: DepthInit(DepthInitConfig(**kw), sizes.fine) for name, kw in CONFIGS.items()}
    scores = {name: {"absrel": [], "absrel_person": [], "within_2": [], "beyond_6": []} for name in CONFIGS}
    start = time.perf_counter()
    for index in range(0, len(data), args.every):
        fs = data.frame_set(index, with_truth=True)
        L = pre.views(fs, [data.left], sizes.fine)
        R = pre.views(fs, [data.right], sizes.fine)
        depth = [torch.from_numpy(pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse))[None, None] for c in (data.left, data.right)]
        stage1 = None  # the points and opacities depth init reads: the same for every target, so computed once
        for sup in data.supervision:
            T = pre.views(fs, [sup], sizes.output)
            truth = torch.from_numpy(pre.depth(fs.depth[sup], fs.cameras[sup], sizes.fine))
            person = torch.from_numpy(pre.depth(fs.masks[sup].astype(np.float32), fs.cameras[sup], sizes.fine) > 0.5) if fs.masks.get(sup) is not None else None
            with torch.no_grad():
                if stage1 is None:
                    stage1 = list(model.run(L.images, R.images, L.K, R.K, L.poses, R.poses, T.K, T.poses, *depth)["stage1"].values())
                to_target = relative_pose(T.poses, L.poses)
                target_K = resize_intrinsics(T.K, sizes.output, sizes.fine)
                for name, layer in layers.items():
                    got = layer(*stage1, to_target, target_K).depth[0, 0]
                    ok = truth > 0
                    rel = (got - truth).abs() / truth.clamp(min=1e-6)
                    s = scores[name]
                    s["absrel"].append(float(rel[ok].mean()))
                    if person is not None and bool((person & ok).any()):
                        s["absrel_person"].append(float(rel[person & ok].mean()))
                    s["within_2"].append(float((rel[ok] <= 0.02).float().mean()))
                    s["beyond_6"].append(float((rel[ok] > 0.06).float().mean()))
    seconds = time.perf_counter() - start
    result = {name: {k: round(100 * float(np.mean(v)), 2) if v else None for k, v in s.items()} for name, s in scores.items()}
    if args.json:
        print(json.dumps({"data": str(args.data), "every": args.every, "views": len(scores[next(iter(scores))]["absrel"]), "percent": result}))
        return 0
    print(f"{args.data}: {len(scores[next(iter(scores))]['absrel'])} supervision views, {seconds:.0f} s (figures in %)")
    print(f"{'configuration':30s} {'AbsRel':>7s} {'person':>7s} {'<=2 %':>7s} {'>6 %':>7s}")
    for name, r in result.items():
        print(f"{name:30s} {r['absrel']:7.2f} {r['absrel_person'] if r['absrel_person'] is not None else float('nan'):7.2f} {r['within_2']:7.2f} {r['beyond_6']:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
