"""The model's figures on held-out simulator takes, beside the untrained model and the references.

Renders `--takes` takes from a data-set seed that no training take uses (take i of seed K has seed
K * 1000 + i; training data sets use seed 0 by default), or reads `--data DIR`, then runs the
evaluation of `rig model eval` for:
- the trained model (`--model`, default the shipped models/splat-sap-preview.pt);
- the untrained model of the same configuration (seeded initial weights);
and prints PSNR/SSIM (full image and person mask), stage-1 depth AbsRel and scale jitter for each,
with the references each run carries: the oracle pipeline with that model's stage-2 weights (for the
untrained model: the oracle pipeline with untrained stage 2) and the nearer source image.

    .venv/bin/python benchmarks/model_eval.py [--model M.pt] [--takes 3] [--seconds 1] [--fps 5] [--seed 1] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
DEFAULT_MODEL = REPO / "models" / "splat-sap-preview.pt"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--data", type=Path, help="held-out takes already rendered (default: render them)")
    ap.add_argument("--takes", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--fps", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1, help="data-set seed of the held-out takes (default 1)")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    from inference.evaluate.model_eval import depth_lines, evaluate
    from inference.model.checkpoint import load_checkpoint
    from inference.model.pipeline import build_model
    from rig.storage.dataset import TrainingSet, expand_sequences
    from simulator.takes import write_dataset

    trained = load_checkpoint(args.model)
    untrained = build_model(trained.cfg, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = args.data
        if data_dir is None:
            data_dir = Path(tmp) / "held-out"
            write_dataset(data_dir, args.takes, args.seconds, seed=args.seed, fps=args.fps, size=(640, 360))
        data = TrainingSet(expand_sequences([data_dir]))
        results = {}
        for name, model in (("trained", trained), ("untrained", untrained)):
            t0 = time.monotonic()
            results[name] = evaluate(model, data, every=args.every)
            results[name]["wall_s"] = round(time.monotonic() - t0, 1)
    report = {"model": str(args.model), "held_out": {"seed": args.seed, "takes": args.takes, "seconds": args.seconds, "fps": args.fps},
              **results}
    if args.json:
        print(json.dumps(report))
        return 0
    t, u = results["trained"], results["untrained"]
    print(f"held-out: {args.takes} takes of data-set seed {args.seed}, {t['sets']} frame sets x {len(t['supervision'])} supervision cameras")
    rows = [("trained model", t), ("untrained model", u),
            ("oracle, trained stage 2", t["references"].get("oracle")), ("oracle, untrained stage 2", u["references"].get("oracle")),
            ("nearer source", t["references"].get("nearest_source"))]
    print(f"{'':28s} {'PSNR':>7s} {'SSIM':>6s} {'PSNR mask':>10s} {'SSIM mask':>10s}")
    for name, r in rows:
        if not r:
            continue
        o = r["overall"]
        f = lambda v, fmt: (fmt % v) if v is not None else "-"
        print(f"{name:28s} {f(o['psnr'], '%7.2f'):>7s} {f(o['ssim'], '%6.3f'):>6s} {f(o['psnr_mask'], '%10.2f'):>10s} {f(o['ssim_mask'], '%10.3f'):>10s}")
    for name, r in (("trained", t), ("untrained", u)):
        for line in depth_lines(r):
            print(f"{name}: {line.strip()}")
    print("per camera (trained): " + ", ".join(f"{c} {v['psnr']:.2f} dB" for c, v in t["cameras"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
