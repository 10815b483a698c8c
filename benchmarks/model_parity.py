"""Splat-SAP export parity: ONNX Runtime against torch eager on the same inputs.

    .venv/bin/python benchmarks/model_parity.py [--size test|preview|paper] [--head-std 0 0.01 0.02 0.05] [--json]
    .venv/bin/python benchmarks/model_parity.py --model models/splat-sap-preview.onnx [--seeds 24] [--json]

Exports the tiny-backbone model (untrained, and with its point head's weights drawn at random with
each --head-std, which gives deliberately chaotic point maps: the hardest case for the splatting's
sensitivity to float rounding) and the oracle model, runs both on the synthetic example inputs and
reports the largest and the 99.9th-percentile absolute differences of the image ([0, 1]) and of the
depth (metres), and the fraction of image pixels off by more than 1e-3.

With --model: an exported model (a trained one) against its own weights in torch, as `rig model
check` compares them, on --seeds draws of the synthetic inputs (`rig model check` uses seed 0): two
unrelated source images, where the sources disagree in colour everywhere, so that any swing of a
source's blending weight shows in full.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from inference.config import ModelConfig, Sizes  # noqa: E402
from inference.export import example_arrays, export_onnx  # noqa: E402
from inference.model.pipeline import build_model  # noqa: E402
from inference.runtime import open_session  # noqa: E402


def compare(model, tmp: Path, name: str) -> dict:
    path = tmp / f"{name}.onnx"
    export_onnx(model, path)
    arrays = example_arrays(model)
    with torch.no_grad():
        ref = model(*[torch.from_numpy(arrays[n]) for n in model.input_names])
    out = open_session(path).run(None, {n: arrays[n] for n in model.input_names})
    di = np.abs(out[0] - ref[0].numpy())
    dd = np.abs(out[1] - ref[1].numpy())
    return {
        "model": name,
        "max_abs_diff_image": float(di.max()),
        "p999_abs_diff_image": float(np.quantile(di, 0.999)),
        "image_pixels_over_1e-3": float((di.max(axis=1) > 1e-3).mean()),
        "max_abs_diff_depth": float(dd.max()),
        "p999_abs_diff_depth": float(np.quantile(dd, 0.999)),
    }


def compare_seeds(path: Path, checkpoint: Path | None, seeds: int) -> list[dict]:
    from inference.model.checkpoint import model_from_record
    from inference.runtime import NovelViewPipeline
    from inference.runtime.synthetic import example_inputs

    pipe = NovelViewPipeline(path, providers=["CPUExecutionProvider"])
    cfg = pipe.info.config
    model = model_from_record(cfg, pipe.info.weights, checkpoint, None)
    rows = []
    for seed in range(seeds):
        feeds = {n: a for n, a in example_inputs(cfg.sizes, pipe.info.needs_depth, seed=seed).arrays.items() if n in pipe.info.inputs}
        image, depth = pipe.run(feeds)
        with torch.no_grad():
            ref_image, ref_depth = model(*[torch.from_numpy(feeds[n]) for n in model.input_names])
        di = np.abs(image - ref_image.numpy())
        rows.append({"seed": seed, "max_abs_diff_image": float(di.max()), "image_pixels_over_1e-3": int((di.max(axis=1) > 1e-3).sum()),
                     "max_abs_diff_depth": float(np.abs(depth - ref_depth.numpy()).max())})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="test", choices=["test", "preview", "paper"])
    ap.add_argument("--head-std", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.05])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--model", type=Path, help="an exported model (.onnx) to compare with its weights in torch")
    ap.add_argument("--checkpoint", type=Path, help="with --model: the checkpoint it was exported from (default: the one it records)")
    ap.add_argument("--seeds", type=int, default=24, help="with --model: draws of the synthetic inputs (default 24)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.model is not None:
        rows = compare_seeds(args.model, args.checkpoint, args.seeds)
        worst = max(rows, key=lambda r: r["max_abs_diff_image"])
        if args.json:
            print(json.dumps({"model": str(args.model), "seeds": rows, "worst": worst}))
        else:
            for r in rows:
                print(f"seed {r['seed']:>3}  image max {r['max_abs_diff_image']:.2e} ({r['image_pixels_over_1e-3']} pixels > 1e-3)  "
                      f"depth max {r['max_abs_diff_depth']:.2e} m")
            print(f"worst: seed {worst['seed']}, image {worst['max_abs_diff_image']:.2e}")
        return 0
    sizes = Sizes.preset(args.size)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for std in args.head_std:
            model = build_model(ModelConfig.for_backbone("tiny", sizes))
            if std > 0:
                torch.manual_seed(1)
                torch.nn.init.normal_(model.point_init.head.weight, std=std)
            rows.append(compare(model, Path(tmp), f"tiny head_std={std:g}"))
        rows.append(compare(build_model(ModelConfig.for_backbone("oracle", sizes)), Path(tmp), "oracle"))
    if args.json:
        print(json.dumps({"size": sizes.describe(), "runs": rows}))
    else:
        for r in rows:
            print(f"{r['model']:<22} image max {r['max_abs_diff_image']:.2e} (99.9 % {r['p999_abs_diff_image']:.1e}, "
                  f"{100 * r['image_pixels_over_1e-3']:.3f} % of pixels > 1e-3)  depth max {r['max_abs_diff_depth']:.2e} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
