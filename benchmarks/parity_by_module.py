"""Where an export's ONNX Runtime output leaves torch's: stage 1 module by module, and the float32 noise
floor the whole model has in torch itself.

    .venv/bin/python benchmarks/parity_by_module.py [--model M.onnx] [--seed 0] [--checkpoint CKPT] [--json]

For every torch module of stage 1 whose output the exported stage-1 part also computes (matched by the
exporter's name scopes and the tensor's shape), the largest difference of ONNX Runtime from torch
float32 beside torch float32's own from torch float64: a module where the first is many times the second
rounds differently in ONNX Runtime. Then the whole model's image in torch float32 against float64 and
between one and two threads: what float32 alone moves the image by, the floor any parity bar sits on.
Inputs: the synthetic inputs `rig model check` uses (seed 0 is its own draw).
"""
from __future__ import annotations

import argparse
import ast
import copy
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import onnx  # noqa: E402
import onnxruntime as ort  # noqa: E402
import torch  # noqa: E402

from inference.model.checkpoint import model_from_record  # noqa: E402
from inference.runtime.shipped import MODELS, NAME  # noqa: E402
from inference.runtime.split import SplitPipeline  # noqa: E402
from inference.runtime.synthetic import example_inputs  # noqa: E402

STAGE1_INPUTS = ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose")


def module_outputs(model, args) -> dict[str, np.ndarray]:
    """The first tensor each named module returns (tuple outputs as NAME[i]) in one stage-1 run."""
    found: dict[str, np.ndarray] = {}

    def hook(name):
        def keep(_mod, _inp, out):
            items = [(name, out)] if torch.is_tensor(out) else [(f"{name}[{i}]", o) for i, o in enumerate(out)] if isinstance(out, (tuple, list)) else []
            for key, t in items:
                if torch.is_tensor(t) and key not in found:
                    found[key] = t.detach().double().numpy()
        return keep

    handles = [m.register_forward_hook(hook(n)) for n, m in model.named_modules() if n]
    try:
        with torch.no_grad():
            model.run_stage1(*args)
    finally:
        for h in handles:
            h.remove()
    return found


def ort_values(stage1_path: Path, feeds: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """Every float tensor the stage-1 graph computes, by name, and the name scopes of the node making it."""
    proto = onnx.load(str(stage1_path))
    inferred = {v.name: v for v in onnx.shape_inference.infer_shapes(proto).graph.value_info}
    scopes = {}
    for node in proto.graph.node:
        scope = [p.value for p in node.metadata_props if p.key == "pkg.torch.onnx.name_scopes"]
        for out in node.output:
            if scope:
                scopes[out] = ast.literal_eval(scope[0])
    have = {o.name for o in proto.graph.output}
    for name in scopes:
        if name in inferred and name not in have and inferred[name].type.tensor_type.elem_type == onnx.TensorProto.FLOAT:
            proto.graph.output.append(inferred[name])
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(proto.SerializeToString(), options, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    values = dict(zip(names, session.run(None, {i.name: feeds[i.name] for i in session.get_inputs()})))
    return values, scopes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=MODELS / f"{NAME}.onnx",
                    help="an exported model (.onnx; its stage-1 part is read beside it; default: the shipped one)")
    ap.add_argument("--checkpoint", type=Path, help="the checkpoint it was exported from (default: the one it records)")
    ap.add_argument("--seed", type=int, default=0, help="draw of the synthetic inputs (0: rig model check's)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    torch.set_num_threads(1)
    pipe = SplitPipeline(args.model, providers=["CPUExecutionProvider"], threads=1)
    model = model_from_record(pipe.info.config, pipe.info.weights, args.checkpoint, None).eval()
    feeds = dict(example_inputs(pipe.sizes, False, seed=args.seed).arrays)
    t32 = [torch.from_numpy(feeds[n]) for n in STAGE1_INPUTS]
    wide = copy.deepcopy(model).double()
    ref32 = module_outputs(model, t32)
    ref64 = module_outputs(wide, [a.double() for a in t32])
    values, scopes = ort_values(pipe.stage1_path, feeds)

    rows = []
    for name, want in ref32.items():
        base = name.split("[")[0]
        best = None
        for out, scope in scopes.items():
            got = values.get(out)
            if got is not None and base in scope[:-1] and got.shape == want.shape:
                d = float(np.abs(got - want).max())
                best = d if best is None else min(best, d)
        if best is not None and name in ref64:
            rows.append({"module": name, "ort_vs_torch32": best, "torch32_vs_torch64": float(np.abs(want - ref64[name]).max()),
                         "largest": float(np.abs(want).max()), "shape": list(want.shape)})

    whole = [torch.from_numpy(feeds[n]) for n in model.input_names]
    images = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        with torch.no_grad():
            images[threads] = model(*whole)[0].double()
    with torch.no_grad():
        image64 = wide(*[a.double() for a in whole])[0]
    ort_image = torch.from_numpy(pipe.view(pipe.stage1(feeds), feeds, feeds["target_K"], feeds["target_pose"])[0]).double()
    floor = {"image_ort_vs_torch32": float((ort_image - images[1]).abs().max()),
             "image_ort_vs_torch64": float((ort_image - image64).abs().max()),
             "image_torch32_vs_torch64": float((images[1] - image64).abs().max()),
             "image_torch32_one_vs_two_threads": float((images[1] - images[2]).abs().max())}
    if args.json:
        print(json.dumps({"model": str(args.model), "seed": args.seed, "modules": rows, **floor}))
        return 0
    print(f"{args.model}, synthetic inputs seed {args.seed}: stage 1 module by module (largest |difference|)")
    print(f"{'module':<52} {'ORT - t32':>10} {'t32 - t64':>10} {'ratio':>6} {'largest':>9}")
    for r in rows:
        ratio = r["ort_vs_torch32"] / max(r["torch32_vs_torch64"], 1e-12)
        print(f"{r['module']:<52} {r['ort_vs_torch32']:10.2e} {r['torch32_vs_torch64']:10.2e} {ratio:6.1f} {r['largest']:9.2e}")
    print("the whole image: " + ", ".join(f"{k[6:].replace('_', ' ')} {v:.2e}" for k, v in floor.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
