"""`rig model`: export the Splat-SAP model to ONNX, check ONNX Runtime against torch, benchmark both,
evaluate a model on sequences, and render views from a sequence (ONNX Runtime only, as `rig live`).

torch is imported inside the handlers only: `rig --help` and the live path never load it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

SIZES = ("preview", "paper", "test")
WEIGHTS_HELP = ("the MASt3R checkpoint (MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth from naver/mast3r; "
                "CC BY-NC-SA 4.0, non-commercial: rig never ships it)")


def register(subparsers) -> None:
    p = subparsers.add_parser("model", help="export, check, benchmark, evaluate and render with the Splat-SAP model",
                              description="The Splat-SAP free-viewpoint model: ONNX export, torch-vs-ONNX-Runtime check, per-stage benchmark.")
    sub = p.add_subparsers(dest="model_command", metavar="SUBCOMMAND")
    sub.required = True
    _add_export(sub)
    _add_check(sub)
    _add_bench(sub)
    _add_eval(sub)
    _add_render(sub)


def _add_export(sub) -> None:
    e = sub.add_parser("export", help="export the model to ONNX",
                       description="Export the pipeline to one ONNX file (opset 18+): inputs are the left and right images, "
                                   "their intrinsics and poses, and the target intrinsics and pose; outputs the novel view and its depth.")
    e.add_argument("--backbone", choices=("stereo", "tiny", "oracle", "mast3r"),
                   help="export an untrained model (seeded initialisation) with this point-map backbone: stereo (calibrated "
                        "plane sweep), tiny (two-view ViT), oracle (ground-truth depth as extra inputs) or mast3r (the "
                        "pretrained MASt3R network, its weights from --weights)")
    e.add_argument("--weights", metavar="PATH", help=f"with --backbone mast3r: {WEIGHTS_HELP}")
    e.add_argument("--checkpoint", metavar="CKPT",
                   help="trained weights, e.g. from rig train (default, without --backbone: the shipped model, models/)")
    e.add_argument("--size", choices=SIZES,
                   help="paper: 512x288 / 1024x576 -> 1280x720; preview: half of it; test: 128x64 / 256x144 -> 320x180 "
                        "(default paper; with --checkpoint the checkpoint's own, no weight depends on the sizes)")
    e.add_argument("--fp16", action="store_true", help="also write MODEL.fp16.onnx (learned layers in float16, for GPUs)")
    e.add_argument("--opset", type=int, default=18, help="ONNX opset, 18 or later (default 18)")
    e.add_argument("--shared-data", action="store_true",
                   help="keep the weights of the model and its parts once, in one data file beside it (MODEL.onnx.<digest>.data), "
                        "about a quarter of the bytes; copy the files together (the shipped models are stored so)")
    e.add_argument("-o", "--output", required=True, metavar="model.onnx",
                   help="ONNX file to write; an earlier .onnx export there is replaced (atomically: a failed export leaves it as it was)")
    e.add_argument("--json", action="store_true", help="print one JSON object with the files written")
    e.set_defaults(func=cmd_export)


def _add_check(sub) -> None:
    c = sub.add_parser("check", help="compare ONNX Runtime with torch on the same inputs",
                       description="Run the exported model with ONNX Runtime and the same model in torch on the same inputs "
                                   "and report the largest differences of the image (in [0, 1]) and the depth (metres).")
    c.add_argument("model", metavar="model.onnx")
    c.add_argument("--checkpoint", metavar="CKPT", help="the checkpoint it was exported from, if not at its recorded path")
    c.add_argument("--weights", metavar="PATH", help="the MASt3R weights it was exported with, if not at their recorded path")
    c.add_argument("--snapshot", metavar="DIR", help="inputs from a `rig sim snapshot` folder (default: built-in synthetic inputs)")
    c.add_argument("--left", default="left", help="source camera name in the snapshot (default left)")
    c.add_argument("--right", default="right", help="source camera name in the snapshot (default right)")
    c.add_argument("--target", help="target camera name in the snapshot (default: the middle camera)")
    c.add_argument("--tolerance", type=float, default=1e-3, help="largest accepted image difference (default 1e-3)")
    c.add_argument("--providers", help="comma-separated ONNX Runtime providers (default: best installed)")
    c.add_argument("--device", default="cpu", metavar="cpu|cuda[:N]", help="where the torch reference runs (default cpu)")
    c.add_argument("--json", action="store_true", help="print one JSON object with max_abs_diff_image and max_abs_diff_depth")
    c.set_defaults(func=cmd_check)


def _add_bench(sub) -> None:
    b = sub.add_parser("bench", help="time each stage in torch eager and ONNX Runtime",
                       description="Per-stage milliseconds in the paper's breakdown (point init, affine transform, depth init, depth refine, "
                                   "colour init, Gaussian plane, splatting, total) for torch eager and ONNX Runtime.")
    b.add_argument("--size", default="preview",
                   help="size preset(s), comma-separated: preview, paper, test (default preview; e.g. preview,paper)")
    b.add_argument("--model", metavar="model.onnx", help="benchmark this exported model (default: export one at --size)")
    b.add_argument("--backbone", choices=("stereo", "tiny", "oracle", "mast3r"), default="tiny", help="backbone (default tiny)")
    b.add_argument("--checkpoint", metavar="CKPT", help="trained weights (default: untrained)")
    b.add_argument("--weights", metavar="PATH", help=f"with --backbone mast3r: {WEIGHTS_HELP} (default: random weights, the same arithmetic)")
    b.add_argument("--mast3r-blocks", metavar="ENC,DEC",
                   help="with --backbone mast3r and random weights: encoder and decoder depth (default 24,12, the checkpoint's; "
                        "fewer for a quick CPU run, whose point-init time is then not the model's)")
    b.add_argument("--repeat", type=int, default=5, help="timed runs of each (default 5; medians are reported)")
    b.add_argument("--threads", type=int, help="CPU threads for both torch and ONNX Runtime (default: theirs)")
    b.add_argument("--providers", help="comma-separated ONNX Runtime providers (default: best installed)")
    b.add_argument("--device", default="cpu", metavar="cpu|cuda[:N]", help="torch device (default cpu)")
    b.add_argument("--json", action="store_true", help="print one JSON object: torch_ms, ort_ms (per stage and total), size, speedup")
    b.set_defaults(func=cmd_bench)


def _add_eval(sub) -> None:
    v = sub.add_parser("eval", help="PSNR/SSIM, depth error and scale jitter on sequences with supervision cameras",
                       description="Render every supervision camera of every (or every k-th) frame set from the two sources and report "
                                   "PSNR and SSIM (full image and person mask), stage 1's depth AbsRel against ground truth, split into scale and shape, and "
                                   "the AbsRel of the depth rendered in each supervision camera (simulator takes), and the frame-to-frame jitter of stage 1's scaling S; with the oracle pipeline (same stage-2 "
                                   "weights) and the nearer source image as references. On the person masks also 'vanished': the share of their pixels "
                                   "rendered more than 30 % off in depth or left empty. With several takes, each take's figures and their spread "
                                   "(mean, median, 10th percentile, worst). LPIPS is not reported (it needs pretrained weights).")
    v.add_argument("--model", metavar="MODEL",
                   help="a checkpoint (.pt, e.g. from rig train) or an ONNX export of one (its recorded checkpoint is used)")
    v.add_argument("--backbone", choices=("mast3r",),
                   help="instead of --model: the untrained pipeline on this pretrained backbone (stage 1's S = 1, T = 0: "
                        "MASt3R's own geometry), its weights from --weights")
    v.add_argument("--weights", metavar="PATH", help=f"with --backbone mast3r, or for an export made with them: {WEIGHTS_HELP}")
    v.add_argument("--size", choices=SIZES, default="paper", help="with --backbone: model sizes (default paper)")
    v.add_argument("--sequence", required=True, nargs="+", type=Path, metavar="SEQ",
                   help="sequence folders (a rig sim dataset folder stands for its takes)")
    v.add_argument("--every", type=int, default=1, help="use every k-th frame set (default 1)")
    v.add_argument("--max-sets", type=int, help="at most this many frame sets")
    v.add_argument("--no-references", action="store_true", help="skip the oracle and nearer-source references")
    v.add_argument("--device", metavar="cpu|cuda[:N]", help="where the model runs (default: CUDA when torch sees a GPU, else the CPU)")
    v.add_argument("--json", action="store_true", help="print every figure as one JSON object")
    v.set_defaults(func=cmd_eval)


def _add_render(sub) -> None:
    r = sub.add_parser("render", help="render a novel view (PNG) or a left-to-right sweep (MP4) from a recorded sequence",
                       description="Render the view of a virtual camera from a frame set's two source frames (the cameras with "
                                   "roles left and right) with the ONNX Runtime pipeline, as `rig live` does, without a browser. "
                                   "--view: a PNG at one viewpoint; --orbit: a video sweeping from the left source to the right "
                                   "one over consecutive frame sets.")
    r.add_argument("--model", metavar="M.onnx", help="an exported model (default: the shipped model, models/)")
    r.add_argument("--sequence", required=True, type=Path, metavar="SEQ", help="a sequence folder (rig record, rig sim take)")
    r.add_argument("--set", type=int, default=0, metavar="N", help="the frame set (row of index.jsonl) to render, or where the orbit starts (default 0)")
    what = r.add_mutually_exclusive_group(required=True)
    what.add_argument("--view", metavar="t|CAMERA",
                      help="a number from 0 (the left source) to 1 (the right source) along the arc between them, "
                           "or the name of a calibrated camera of the sequence")
    what.add_argument("--orbit", action="store_true", help="a video: frame i shows set N+i at t = i/(K-1), from left to right")
    r.add_argument("--frames", type=int, metavar="K", help="frames of the orbit (default: every set from --set to the end)")
    r.add_argument("--fps", type=float, help="frame rate of the orbit video (default: the sequence's rate, else 30)")
    r.add_argument("--yaw", type=float, help="orbit about the subject, degrees (positive: towards the right source)")
    r.add_argument("--pitch", type=float, help="orbit up (positive) or down, degrees")
    r.add_argument("--zoom", type=float, help="focal-length multiplier (0.5 to 3)")
    r.add_argument("--providers", help="comma-separated ONNX Runtime providers (default: best installed)")
    r.add_argument("--device", default="cpu", metavar="cpu|cuda[:N]",
                   help="cpu (default): the exported model in ONNX Runtime; cuda: the checkpoint behind it in torch on the GPU "
                        "(the runtime of `rig live --device cuda`, eager)")
    r.add_argument("--size", choices=SIZES, help="with --device cuda: the size preset to render at (default: the model's own)")
    r.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="the image (.png, .jpg) for --view, the video (.mp4, .mkv, .mov) for --orbit; replaced if it exists")
    r.add_argument("--json", action="store_true", help="print one JSON object: output, model, sequence, sets, viewpoints, size, codec, ms")
    r.set_defaults(func=cmd_render)


def _providers(text: str | None) -> list[str] | None:
    return [p.strip() for p in text.split(",") if p.strip()] if text else None


def _status():
    from rig.progress import StatusLine

    return StatusLine()


def cmd_export(args: argparse.Namespace) -> int:
    from inference.errors import InferenceError

    if args.opset < 18:
        raise InferenceError(f"--opset {args.opset}: the pipeline needs opset 18 or later")
    if args.checkpoint and args.weights:
        raise InferenceError("--weights: a checkpoint holds its backbone's weights already; give one of them")
    _check_weights_args(args)
    _check_export_output(args)  # before torch loads (seconds)

    from inference.config import ModelConfig, Sizes
    from inference.export import export_onnx
    from inference.model.checkpoint import checkpoint_record, load_checkpoint
    from inference.model.pipeline import build_model
    from rig.commands._output import emit_json

    status = _status()
    if args.checkpoint is None and args.backbone is None:
        from inference.runtime.shipped import shipped_checkpoint

        args.checkpoint = str(shipped_checkpoint())
    licence = None
    if args.checkpoint:
        model = load_checkpoint(args.checkpoint)
        if args.backbone is not None and model.cfg.backbone.kind != args.backbone:
            raise InferenceError(f"{args.checkpoint}: the checkpoint has the {model.cfg.backbone.kind} backbone, not {args.backbone}")
        weights = checkpoint_record(args.checkpoint)
        trained = True
        if args.size is not None and Sizes.preset(args.size) != model.cfg.sizes:
            # The same weights built at other sizes (none depends on them): e.g. the CPU live model.
            cfg = ModelConfig.from_dict(model.cfg.to_dict())
            cfg.sizes = Sizes.preset(args.size)
            resized = build_model(cfg, seed=None)
            resized.load_state_dict(model.state_dict(), strict=True)
            model = resized.eval()
        if model.cfg.backbone.kind == "mast3r":
            licence = _licence_note(f"{args.checkpoint} holds MASt3R weights")
    elif args.backbone == "mast3r":
        from inference.model.checkpoint import backbone_weights_record, build_with_weights, seed_record

        model, _ = build_with_weights(ModelConfig.for_backbone("mast3r", Sizes.preset(args.size or "paper")), args.weights)
        licence = _licence_note(f"loaded {args.weights}")
        weights = seed_record(0, backbone_weights_record(args.weights))
        trained = False
    else:
        model = build_model(ModelConfig.for_backbone(args.backbone, Sizes.preset(args.size or "paper")))
        weights = None
        trained = False
    status.update(f"exporting {args.output} ...", force=True)
    result = export_onnx(model, args.output, fp16=args.fp16, weights=weights, opset=args.opset, shared_data=args.shared_data)
    status.done()
    files = [str(result.path)] + ([str(result.fp16_path)] if result.fp16_path else [])
    parts = [str(p) for p in result.parts]  # stage 1 and the view of each, for the live path
    info = {
        "files": files,
        "parts": parts,
        "backbone": model.cfg.backbone.kind,
        "sizes": model.cfg.sizes.describe(),
        "opset": result.opset,
        "inputs": list(result.inputs),
        "outputs": ["image", "depth"],
        "weights": "checkpoint" if trained else ("MASt3R backbone from --weights, the rest untrained (seeded initialisation)"
                                                 if args.backbone == "mast3r" else "untrained (seeded initialisation)"),
        "parameters": sum(p.numel() for p in model.parameters()),
    }
    if result.data_files:
        info["data_files"] = [str(p) for p in result.data_files]
    if licence:
        info["licence"] = licence
    if args.json:
        emit_json(info)
    else:
        for f in files + parts + info.get("data_files", []):
            print(f"wrote {f}")
        print(f"backbone {info['backbone']}, sizes {info['sizes']}, opset {info['opset']}, {info['parameters']:,} parameters, weights: {info['weights']}")
        if not trained:
            print("note: the weights are untrained; train a checkpoint and export it with --checkpoint for real output", file=sys.stderr)
    return 0


def _check_weights_args(args: argparse.Namespace) -> None:
    """--backbone mast3r and --weights go together (checked before torch loads)."""
    from inference.errors import InferenceError

    weights = getattr(args, "weights", None)
    if weights is not None and getattr(args, "backbone", None) != "mast3r":
        raise InferenceError("--weights gives the MASt3R backbone's weights: use it with --backbone mast3r")
    if getattr(args, "backbone", None) == "mast3r" and weights is None and not getattr(args, "checkpoint", None):
        raise InferenceError(f"--backbone mast3r needs --weights PATH: {WEIGHTS_HELP}")
    if weights is not None and not Path(weights).is_file():
        raise InferenceError(f"{weights}: no such MASt3R weights file")


def _licence_note(what: str) -> str:
    """Say the MASt3R weights' licence (on stderr) whenever they are loaded; returns the line."""
    from inference.model.mast3r_weights import LICENCE

    line = f"{what}: {LICENCE}"
    print(f"note: {line}", file=sys.stderr)
    return line


def _check_export_output(args: argparse.Namespace) -> None:
    """Before the (slow) export: the output must be writable, and only a model may be replaced.

    An exported model is regenerable (the same checkpoint and options export it again), so a user
    re-running `rig model export -o model.onnx` expects it replaced, as a compiler's `-o`; the export
    writes atomically, so a failed export never leaves a torn model. What is not regenerable is
    refused: any name not ending in .onnx (a mistyped `-o calib.json`: the export would refuse it
    too, but only after building the model), and the checkpoint the model is exported from."""
    from rig.commands._paths import output_file
    from rig.errors import ConfigError

    out = output_file(args.output)
    if out.suffix != ".onnx":
        raise ConfigError(f"{out}: the output file name must end in .onnx (nothing was written)")
    for path in (out, out.with_name(out.stem + ".fp16.onnx")) if args.fp16 else (out,):
        if args.checkpoint and path.exists() and Path(args.checkpoint).exists() and path.samefile(args.checkpoint):
            raise ConfigError(f"{path}: is the checkpoint being exported; choose another output (nothing was overwritten)")
    _check_replaced_are_exports(out, args.fp16)


def _check_replaced_are_exports(out: Path, fp16: bool) -> None:
    """Each file the export would write over (the model, its parts, the fp16 copies) must be an
    earlier export (Splat-SAP metadata) or empty: a file of the same name that is anything else (a
    foreign ONNX model, data the user keeps) is not regenerable and is refused."""
    from inference.errors import InferenceError
    from inference.runtime.metadata import read_file_metadata
    from inference.runtime.split import PARTS, UNSCALED_PART, part_path
    from rig.errors import ConfigError

    models = (out, out.with_name(out.stem + ".fp16.onnx")) if fp16 else (out,)
    for model in models:
        for path in (model, *(part_path(model, p) for p in PARTS + (UNSCALED_PART,))):
            if not path.is_file() or path.stat().st_size == 0:
                continue
            try:
                exported = read_file_metadata(path).get("splat_sap.format") is not None
            except InferenceError:
                exported = False
            if not exported:
                raise ConfigError(f"{path}: exists and is not a model rig model export wrote; choose another output name "
                                  "or move it away (nothing was overwritten)")


def _snapshot_inputs(folder: str, left: str, right: str, target: str | None):
    import cv2
    import numpy as np

    from calibration.camera import RigCalibration
    from inference.errors import InferenceError

    d = Path(folder)
    if not d.is_dir():
        raise InferenceError(f"{d}: no such snapshot folder")
    calib = RigCalibration.load(d / "cameras.json")
    names = calib.names
    if target is None:
        others = [n for n in names if n not in (left, right)]
        if not others:
            raise InferenceError(f"{d}: no camera besides {left} and {right} to use as the target (pass --target)")
        target = others[len(others) // 2]
    frames = {}
    for name in (left, right):
        if name not in calib:
            raise InferenceError(f"{d}: no camera '{name}' in cameras.json (have: {', '.join(names)})")
        img = cv2.imread(str(d / f"{name}.png"), cv2.IMREAD_COLOR)
        if img is None:
            raise InferenceError(f"{d / (name + '.png')}: missing or unreadable")
        depth_path = d / f"{name}.depth.npy"
        depth = np.load(depth_path) if depth_path.is_file() else None
        frames[name] = (cv2.cvtColor(img, cv2.COLOR_BGR2RGB), depth)
    if target not in calib:
        raise InferenceError(f"{d}: no camera '{target}' in cameras.json (have: {', '.join(names)})")
    return calib[left], calib[right], calib[target], frames[left], frames[right]


def cmd_check(args: argparse.Namespace) -> int:
    import math

    from rig.errors import ConfigError

    if not (math.isfinite(args.tolerance) and args.tolerance >= 0):  # before torch loads
        raise ConfigError(f"--tolerance must be a number >= 0 (an image difference, in [0, 1]), got {args.tolerance:g}")
    import numpy as np
    import torch

    from inference.device import describe, resolve_device
    from inference.errors import InferenceError
    from inference.model.checkpoint import model_from_record
    from inference.runtime import NovelViewPipeline
    from inference.runtime.synthetic import example_inputs
    from rig.commands._output import emit_json

    device = resolve_device(args.device)
    pipe = NovelViewPipeline(args.model, providers=_providers(args.providers))
    cfg = pipe.info.config
    if pipe.info.precision != "fp32":
        raise InferenceError(f"{args.model}: check the fp32 model; the {pipe.info.precision} variant differs from torch by its precision")
    if args.weights is not None and not Path(args.weights).is_file():
        raise InferenceError(f"{args.weights}: no such MASt3R weights file")
    model = model_from_record(cfg, pipe.info.weights, args.checkpoint, args.weights)
    if cfg.backbone.kind == "mast3r":
        _licence_note(f"{args.model} runs MASt3R weights")
    if args.snapshot:
        lc, rc, tc, (limg, ldep), (rimg, rdep) = _snapshot_inputs(args.snapshot, args.left, args.right, args.target)
        if pipe.info.needs_depth and (ldep is None or rdep is None):
            raise InferenceError(f"{args.snapshot}: the oracle model needs {args.left}.depth.npy and {args.right}.depth.npy")
        feeds = pipe.prepare(limg, rimg, lc, rc, tc, ldep, rdep)
        source = f"snapshot {args.snapshot} ({args.left}, {args.right} -> {tc.name})"
    else:
        feeds = {n: a for n, a in example_inputs(cfg.sizes, pipe.info.needs_depth).arrays.items() if n in pipe.info.inputs}
        source = "synthetic inputs"
    image, depth = pipe.run(feeds)
    model = model.to(device)
    with torch.no_grad():
        ref_image, ref_depth = model(*[torch.from_numpy(feeds[n]).to(device) for n in model.input_names])
    diff_image = float(np.abs(image - ref_image.cpu().numpy()).max())
    diff_depth = float(np.abs(depth - ref_depth.cpu().numpy()).max())
    ok = diff_image <= args.tolerance
    info = {
        "model": args.model,
        "inputs": source,
        "providers": pipe.providers,
        "torch_device": describe(device),
        "max_abs_diff_image": diff_image,
        "max_abs_diff_depth": diff_depth,
        "tolerance": args.tolerance,
        "ok": ok,
    }
    if args.json:
        emit_json(info)
    else:
        print(f"{args.model} on {source}, providers {', '.join(pipe.providers)}, torch on {device}")
        print(f"max |ORT - torch|: image {diff_image:.3g} (tolerance {args.tolerance:g}), depth {diff_depth:.3g} m")
        print("OK" if ok else "MISMATCH")
    return 0 if ok else 1


def cmd_bench(args: argparse.Namespace) -> int:
    from inference.benchmark import format_table, run_benchmark
    from inference.device import resolve_device
    from inference.errors import InferenceError
    from rig.commands._output import emit_json

    device = resolve_device(args.device)  # --device cuda without a GPU: one line, before any export

    sizes = [x.strip() for x in args.size.split(",") if x.strip()]
    bad = [x for x in sizes if x not in SIZES]
    if bad or not sizes:
        raise InferenceError(f"--size {args.size}: unknown size {', '.join(bad) or '(none)'} (allowed: {', '.join(SIZES)})")
    if args.model:
        sizes = sizes[:1]  # the model's own sizes
    blocks = None
    if args.mast3r_blocks is not None:
        try:
            blocks = tuple(int(v) for v in args.mast3r_blocks.split(","))
        except ValueError:
            blocks = ()
        if len(blocks) != 2 or blocks[0] < 1 or blocks[1] < 2:
            raise InferenceError(f"--mast3r-blocks {args.mast3r_blocks}: give ENC,DEC with ENC >= 1 and DEC >= 2 (the checkpoint's: 24,12)")
        if args.backbone != "mast3r" or args.weights or args.checkpoint or args.model:
            raise InferenceError("--mast3r-blocks reduces the random-weight MASt3R backbone: use it with --backbone mast3r alone")
    if args.weights is not None:
        if args.backbone != "mast3r" or args.checkpoint or args.model:
            raise InferenceError("--weights gives the MASt3R backbone's weights: use it with --backbone mast3r (no --checkpoint, --model)")
        if not Path(args.weights).is_file():
            raise InferenceError(f"{args.weights}: no such MASt3R weights file")
        _licence_note(f"loading {args.weights}")
    status = _status()
    runs = []
    for size in sizes:
        runs.append(
            run_benchmark(
                size=size,
                backbone=args.backbone,
                providers=_providers(args.providers),
                repeat=args.repeat,
                threads=args.threads,
                device=str(device),
                checkpoint=args.checkpoint,
                model_path=args.model,
                weights=args.weights,
                mast3r_blocks=blocks,
                progress=lambda text, size=size: status.update(f"{size}: {text}", force=True),
            )
        )
    status.done()
    if args.weights is None and (args.model or args.checkpoint) and runs[0].get("backbone") == "mast3r":
        _licence_note(f"{args.model or args.checkpoint} runs MASt3R weights")
    if args.json:
        # The first size's figures at the top level; every size's under "runs".
        emit_json({**runs[0], "runs": runs} if len(runs) > 1 else runs[0])
    else:
        print("\n\n".join(format_table(r) for r in runs))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from rig.commands._output import emit_json
    from rig.errors import ConfigError
    from rig.storage.dataset import TrainingSet, expand_sequences

    if args.every < 1:
        raise ConfigError(f"--every must be at least 1, got {args.every}")
    if args.max_sets is not None and args.max_sets < 1:
        raise ConfigError(f"--max-sets must be at least 1, got {args.max_sets}")
    if (args.model is None) == (args.backbone is None):
        raise ConfigError("give --model MODEL, or --backbone mast3r --weights PATH (the untrained pipeline on MASt3R)")
    if args.backbone is not None and args.weights is None:
        raise ConfigError(f"--backbone mast3r needs --weights PATH: {WEIGHTS_HELP}")
    if args.weights is not None and not Path(args.weights).is_file():
        raise ConfigError(f"{args.weights}: no such MASt3R weights file")
    model_path = Path(args.model) if args.model else None
    if model_path is not None and not model_path.is_file():
        raise ConfigError(f"{model_path}: no such model")
    sequences = expand_sequences(args.sequence)
    data = TrainingSet(sequences)  # before the model loads: a take that cannot be evaluated costs nothing
    if len(data) == 0:
        raise ConfigError(f"--sequence {', '.join(data.roots)}: no frame set to evaluate (none has both sources and the "
                          "supervision cameras)")

    from inference.device import describe, resolve_device
    from inference.evaluate.load import model_to_evaluate
    from inference.evaluate.model_eval import depth_lines, evaluate, spread_lines, take_lines, vanished_lines

    device = resolve_device(args.device)  # --device cuda without a GPU: one line, exit 2
    model = model_to_evaluate(model_path, weights=args.weights, size=args.size)
    if model.cfg.backbone.kind == "mast3r":
        _licence_note(f"{model_path} runs MASt3R weights" if args.model else f"loaded {args.weights}")
    if model_path is None:
        model_path = Path(args.weights)
    from rig.progress import ProgressBar

    with ProgressBar("evaluating") as bar:
        result = evaluate(model, data, every=args.every, max_sets=args.max_sets, references=not args.no_references,
                          progress=None if args.json else bar.update, device=device)
    result["model"] = str(model_path)
    result["sequences"] = data.roots
    result["device"] = describe(device)
    if args.json:
        emit_json(result)
        return 0
    print(f"{result['sets']} frame sets x {len(result['supervision'])} supervision cameras ({', '.join(result['supervision'])}), on {device}")
    rows = [("model", result)] + [(name, ref) for name, ref in result["references"].items()]
    print(f"{'':16s} {'PSNR':>7s} {'SSIM':>6s} {'PSNR mask':>10s} {'SSIM mask':>10s}")
    for name, r in rows:
        o = r.get("overall", {})
        fmt = lambda v, f: (f % v) if v is not None else "-"
        print(f"{name:16s} {fmt(o.get('psnr'), '%7.2f'):>7s} {fmt(o.get('ssim'), '%6.3f'):>6s} "
              f"{fmt(o.get('psnr_mask'), '%10.2f'):>10s} {fmt(o.get('ssim_mask'), '%10.3f'):>10s}")
    for line in depth_lines(result) + vanished_lines(result):
        print(line)
    if len(result.get("takes") or {}) > 1:  # per take and the spread over takes (docs/training.md, "Evaluation")
        print()
        print("\n".join(take_lines(result)))
        print()
        print("\n".join(spread_lines(result)))
    return 0


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")


def cmd_render(args: argparse.Namespace) -> int:
    from rig.commands._output import emit_json
    from rig.commands._paths import output_file
    from rig.errors import ConfigError
    from rig.live.app import parse_device
    from rig.render.take import Steer, open_renderer, open_take, plan_views, render_take, summary

    out = output_file(args.output)
    suffixes = VIDEO_SUFFIXES if args.orbit else IMAGE_SUFFIXES
    if out.suffix.lower() not in suffixes:
        raise ConfigError(f"{out}: {'--orbit writes a video' if args.orbit else '--view writes an image'}; "
                          f"the output file name must end in {', '.join(suffixes)} (nothing was written)")
    if args.set < 0:
        raise ConfigError(f"--set must be 0 or more, got {args.set}")
    for flag, value in (("--frames", args.frames), ("--fps", args.fps)):
        if value is not None and not args.orbit:
            raise ConfigError(f"{flag} is for --orbit (a video); --view renders one image")
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    if args.fps is not None and not 0 < args.fps <= 1000:
        raise ConfigError(f"--fps must be between 0 and 1000, got {args.fps:g}")

    take = open_take(args.sequence)
    plan = plan_views(take, args.set, Steer(args.yaw, args.pitch, args.zoom),
                      view=None if args.orbit else args.view, frames=args.frames)
    renderer = open_renderer(args.model, parse_device(args.device), _providers(args.providers), args.size)
    status = _status()
    done = render_take(take, plan, renderer, out, fps=args.fps, progress=lambda text: status.update(text, force=True))
    status.done()
    info = summary(take, plan, renderer, out, done)
    size, positions = done.size, plan.positions
    if args.json:
        emit_json(info)
    elif args.orbit:
        print(f"wrote {out}: {done.frames} frames at {done.fps:g} fps, {size[0]}x{size[1]}, {done.codec_label} ({done.codec}); "
              f"sets {positions[0]} to {positions[-1]}, left to right; model {info['model_ms_median']} ms per frame (median)")
    else:
        vp = plan.viewpoints[0]
        print(f"wrote {out}: {size[0]}x{size[1]}, set {positions[0]}, view {vp.label()}; model {info['model_ms_median']} ms")
    return 0
