"""How far ONNX Runtime's CPU kernels round from float64, beside torch's float32, per operator.

    .venv/bin/python benchmarks/onnx_op_precision.py [--json]

Each row: one operator at a size the Splat-SAP pipeline uses, on random inputs; the largest
absolute error against the same function in float64, divided by the largest |output|, for
torch float32, ONNX Runtime as exported, and ONNX Runtime after inference.onnx_precision's rewrite
(which the exporter applies). A kernel that rounds worse than torch shows as an ORT/torch ratio
well above 1; reductions over long axes are where it does (docs/model.md, "Parity").
"""
from __future__ import annotations

import argparse
import io
import json
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import onnx  # noqa: E402
import onnxruntime as ort  # noqa: E402
import torch  # noqa: E402

from inference import onnx_precision  # noqa: E402


class Fn(torch.nn.Module):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def forward(self, *args):
        return self.fn(*args)


def cases():
    g = torch.Generator().manual_seed(0)
    feat = torch.randn(2, 32, 72, 128, generator=g) * 2 + 1
    small = torch.randn(1, 64, 36, 64, generator=g)
    grid = torch.rand(1, 36, 64, 2, generator=g) * 2 - 1
    yield "conv 3x3, 64 channels", torch.nn.Conv2d(64, 64, 3, padding=1), (small,)
    yield "GroupNorm(4, 32), 72x128", torch.nn.GroupNorm(4, 32), (feat,)
    yield "sum over H, W (72x128)", Fn(lambda a: a.sum(dim=(2, 3))), (feat,)
    yield "mean over H, W (72x128)", Fn(lambda a: a.mean(dim=(2, 3))), (feat,)
    yield "sum over channels (32)", Fn(lambda a: a.sum(dim=1)), (feat,)
    yield "sum of everything (590k)", Fn(lambda a: a.sum()), (feat,)
    yield "softmax over 48", Fn(lambda a: torch.softmax(a * 5, dim=1)), (torch.randn(2, 48, 36, 64, generator=g),)
    yield "sigmoid", Fn(torch.sigmoid), (small * 4,)
    yield "tanh", Fn(torch.tanh), (small,)
    yield "grid_sample (bilinear)", Fn(lambda a, b: torch.nn.functional.grid_sample(a, b, align_corners=False)), (small, grid)
    yield "matmul 256x128x256", Fn(lambda a, b: a @ b), (torch.randn(256, 128, generator=g), torch.randn(128, 256, generator=g))


def onnx_of(module, args) -> onnx.ModelProto:
    f = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module, args, f, dynamo=False, opset_version=18)
    return onnx.load_from_string(f.getvalue())


def ort_run(model: onnx.ModelProto, args) -> np.ndarray:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    s = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
    return s.run(None, {i.name: a.numpy() for i, a in zip(s.get_inputs(), args)})[0]


def measure(name, module, args) -> dict:
    module = module.eval()
    with torch.no_grad():
        ref = module.double()(*[a.double() for a in args]).numpy()
        module.float()
        t32 = module(*args).double().numpy()
    plain = onnx_of(module, args)
    rewritten = onnx.ModelProto()
    rewritten.CopyFrom(plain)
    n = onnx_precision.rewrite(rewritten)
    scale = float(np.abs(ref).max())
    err = lambda y: float(np.abs(np.asarray(y, np.float64) - ref).max() / scale)  # noqa: E731
    row = {"op": name, "torch": err(t32), "ort": err(ort_run(plain, args)), "ort_rewritten": err(ort_run(rewritten, args)), "nodes_rewritten": n}
    row["ort_over_torch"] = row["ort"] / max(row["torch"], 1e-30)
    row["rewritten_over_torch"] = row["ort_rewritten"] / max(row["torch"], 1e-30)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = [measure(*case) for case in cases()]
    if args.json:
        print(json.dumps(rows))
        return 0
    print(f"{'operator':28s} {'torch f32':>10s} {'ORT':>10s} {'ORT/torch':>9s} {'rewritten':>10s} {'/torch':>7s}")
    for r in rows:
        print(f"{r['op']:28s} {r['torch']:10.2e} {r['ort']:10.2e} {r['ort_over_torch']:9.1f} {r['ort_rewritten']:10.2e} {r['rewritten_over_torch']:7.1f}")
    print("errors: max |y - y_float64| / max |y_float64|, random inputs, one thread")
    return 0


if __name__ == "__main__":
    sys.exit(main())
