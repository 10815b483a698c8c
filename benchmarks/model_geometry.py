"""Splat-SAP geometry without training, on simulator frame sets (the pipeline's accuracy figures).

    .venv/bin/python benchmarks/model_geometry.py [--size preview|paper] [--seeds 0 1] [--times 1.0 2.5] [--json]

For each scene seed and time, the six-camera simulator rig is rendered at the output size (with its
lens distortion); the sources are 'left' and 'right', each supervision camera is a target. With the
oracle backbone in metric scale and the affine transform bypassed it reports (inference/geometry_eval.py):
the fraction of covisible target pixels whose splatted initial depth is within 2 % of the truth,
the PSNR of the colour warped from the sources with that depth on those pixels, and the PSNR of the
renderer fed the target's ground-truth depth and colours. Acceptance: >= 95 %, >= 25 dB, >= 30 dB.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from inference.config import Sizes  # noqa: E402
from inference.evaluate.geometry import View, evaluate_geometry, target_views  # noqa: E402
from simulator.render import render  # noqa: E402
from simulator.rig import virtual_rig  # noqa: E402
from simulator.scene import Scene  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="preview", choices=["preview", "paper", "test"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--times", type=float, nargs="+", default=[1.0, 2.5])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sizes = Sizes.preset(args.size)
    rig = virtual_rig(6, *sizes.output)
    rows = []
    start = time.perf_counter()
    for seed in args.seeds:
        scene = Scene(seed=seed)
        for t in args.times:
            def view(cam):
                r = render(scene, cam, t)
                return View(cam, r.rgb, r.depth)

            left, right = view(rig["left"]), view(rig["right"])
            for name in rig.names:
                if name in ("left", "right"):
                    continue
                fig = evaluate_geometry(sizes, left, right, *[view(c) for c in target_views(rig[name], sizes)])
                rows.append({"seed": seed, "t": t, "target": name, **fig.to_dict()})
                if not args.json:
                    print(f"seed {seed} t {t:4.1f} {name}: depth within 2 % {100 * fig.depth_within_2pct:5.1f} % "
                          f"(covisible {100 * fig.covisible_fraction:4.1f} %), warped colour {fig.colour_psnr_db:5.2f} dB, "
                          f"GT Gaussian plane render {fig.render_psnr_db:5.2f} dB")
    summary = {
        "size": sizes.describe(),
        "views": len(rows),
        "depth_within_2pct_min": min(r["depth_within_2pct"] for r in rows),
        "depth_within_2pct_median": statistics.median(r["depth_within_2pct"] for r in rows),
        "colour_psnr_db_min": min(r["colour_psnr_db"] for r in rows),
        "render_psnr_db_min": min(r["render_psnr_db"] for r in rows),
        "seconds": round(time.perf_counter() - start, 1),
    }
    summary["pass"] = summary["depth_within_2pct_min"] >= 0.95 and summary["colour_psnr_db_min"] >= 25 and summary["render_psnr_db_min"] >= 30
    if args.json:
        print(json.dumps({"summary": summary, "views": rows}))
    else:
        print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
