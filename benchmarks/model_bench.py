"""Splat-SAP speed: per-stage milliseconds of torch eager and ONNX Runtime, in the paper's breakdown.

    .venv/bin/python benchmarks/model_bench.py [--size preview|paper|test ...] [--repeat 5] [--threads N]
                                               [--providers CUDAExecutionProvider] [--device cuda] [--json]

For each size the untrained model (or --checkpoint) is exported to ONNX in a temp folder and both
run on the same synthetic inputs, alternating, medians reported; ONNX Runtime's per-stage figures
come from its profiler (see inference/benchmark.py). On a GPU machine pass
`--providers CUDAExecutionProvider` or `TensorrtExecutionProvider` (and `--device cuda` for torch)
and compare with the paper's 280 ms total on an RTX 3090, printed beside.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.benchmark import format_table, run_benchmark  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", nargs="+", default=["preview"], choices=["preview", "paper", "test"])
    ap.add_argument("--backbone", default="tiny", choices=["tiny", "oracle"])
    ap.add_argument("--checkpoint")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int)
    ap.add_argument("--providers", help="comma-separated ONNX Runtime providers (default: best installed)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", action="store_true", help="one JSON object: {'runs': [...]} with one result per size")
    args = ap.parse_args()
    providers = [p for p in args.providers.split(",") if p] if args.providers else None
    runs = []
    for size in args.size:
        r = run_benchmark(size=size, backbone=args.backbone, providers=providers, repeat=args.repeat, threads=args.threads,
                          device=args.device, checkpoint=args.checkpoint, progress=lambda t: print(t, file=sys.stderr))
        runs.append(r)
        if not args.json:
            print(format_table(r))
            print(f"torch totals {r['torch_total_runs_ms']} ms, ORT totals {r['ort_total_runs_ms']} ms\n")
    if args.json:
        print(json.dumps({"runs": runs}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
