"""`rig train`: train Splat-SAP on recorded or simulated sequences (both stages; self-supervised, or stage 1 also on ground-truth depth with --recipe supervised).

Data-parallel: `rig train --nproc N ...` starts N processes on this machine through torchrun
(gloo on CPU, NCCL on GPUs). For several machines run torchrun yourself on each, e.g.
    torchrun --nnodes 2 --node-rank 0 --nproc-per-node 4 --rdzv-backend c10d \\
        --rdzv-endpoint HOST:29500 -m rig train DATA -o OUT
(docs/training.md). Every process reads the same sequences; process 0 writes the output folder.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

from rig.errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("train", help="train the model on recorded or simulated sequences",
                       description="Train Splat-SAP (stage 1: backbone + affine transform, self-supervised or, with --recipe supervised, also on simulator takes' ground-truth depth; stage 2: "
                                   "depth refinement, colour blending, Gaussian plane) on one or more sequences.")
    p.add_argument("sequences", nargs="+", type=Path,
                   help="sequence folders (from rig record or rig sim dataset); a data-set folder stands for all its takes")
    p.add_argument("-o", "--out", required=True, type=Path, help="output folder (new or empty, or the run to continue with --resume; Ctrl-C or SIGTERM end the step under way and write the checkpoint)")
    p.add_argument("--config", type=Path, help="training configuration (JSON, the keys of inference.train.config.TrainConfig)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    p.add_argument("--init", type=Path, metavar="CKPT",
                   help="start a new run (its own schedule) from the weights of a checkpoint of the same model configuration (settings no weight's shape depends on, such as depth init's z-buffer, depth refinement's search or stage 1's scale search, may differ)")
    p.add_argument("--recipe", choices=("self-supervised", "supervised"),
                   help="what stage 1 learns from (default self-supervised: images and calibration, any take); supervised: "
                        "also the takes' ground-truth depth (simulator takes only), then stage 2 as before; fine-tune the result "
                        "on real takes with --init CKPT and the self-supervised recipe (docs/training.md, Recipes)")
    p.add_argument("--size", choices=("paper", "preview", "test"), help="model sizes (default preview)")
    p.add_argument("--backbone", choices=("stereo", "tiny", "mast3r"),
                   help="point-map backbone (default stereo); mast3r: the pretrained MASt3R network, its weights from --weights, "
                        "frozen unless --train-backbone")
    p.add_argument("--weights", type=Path, metavar="PATH",
                   help="with --backbone mast3r: the MASt3R checkpoint (MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth from "
                        "naver/mast3r; CC BY-NC-SA 4.0, non-commercial: rig never ships it)")
    p.add_argument("--train-backbone", action="store_true",
                   help="fine-tune a pretrained backbone (mast3r) in stage 1 instead of keeping it frozen")
    p.add_argument("--stage1-steps", type=int, help="stage-1 steps")
    p.add_argument("--stage2-steps", type=int, help="stage-2 steps")
    p.add_argument("--batch", type=int, help="frame sets per step in both stages (global batch)")
    p.add_argument("--eval-every", type=int, help="steps between evaluations (sample PNG, loss curve)")
    p.add_argument("--seed", type=int, help="seed of the initial weights and the batch order")
    p.add_argument("--stop-after", type=int, help="train this many more steps, write the checkpoint and stop (continue with --resume)")
    p.add_argument("--nproc", type=int, default=1, help="data-parallel processes on this machine (torchrun; default 1)")
    p.add_argument("--threads", type=int, help="torch threads per process (default: cores / processes)")
    p.add_argument("--device", metavar="cpu|cuda[:N]",
                   help="where the model trains (default: CUDA when torch sees a GPU, else the CPU); --resume may change it")
    p.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                   help="fp32 (default) or bf16: the forward passes under bfloat16 autocast (weights, gradients and optimiser state stay fp32)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="DataLoader processes that build batches ahead of the model (default: 0 on the CPU, where they would take the "
                        "model's cores; 4 on CUDA, at most cores - 1); batches land in pinned memory on CUDA")
    p.add_argument("--cache-mb", type=float, metavar="MB",
                   help="decoded and resampled views kept in memory per process, so each frame is decoded once per run "
                        "(default 2048; 0 turns it off)")
    p.add_argument("--checkpoint-minutes", type=float, metavar="M",
                   help="also write the checkpoint every M minutes of wall clock (a run cut off loses at most that; fractions allowed)")
    p.add_argument("--max-minutes", type=float, metavar="M",
                   help="stop cleanly with a checkpoint after M minutes of training (continue with --resume; fractions allowed)")
    p.add_argument("--json", action="store_true", help="print a summary as one JSON object at the end")
    p.set_defaults(func=cmd_train)


def build_config(args: argparse.Namespace):
    from inference.config import ModelConfig, Sizes
    from inference.train.config import TrainConfig

    if args.config is not None:
        try:
            cfg = TrainConfig.from_dict(json.loads(args.config.read_text()))
        except OSError as exc:
            raise ConfigError(f"{args.config}: cannot read ({exc.strerror})") from None
        except ValueError as exc:
            raise ConfigError(f"{args.config}: not valid JSON ({exc})") from None
    elif args.resume and (args.out / "train.json").is_file():
        try:
            cfg = TrainConfig.from_dict(json.loads((args.out / "train.json").read_text())["config"], saved=True)
        except (OSError, ValueError, KeyError, TypeError):
            raise ConfigError(f"{args.out / 'train.json'}: not a readable training record; pass --config") from None
    else:
        cfg = TrainConfig()
    if args.backbone:
        sizes = Sizes.preset(args.size) if args.size else cfg.model.sizes
        cfg.model = ModelConfig.for_backbone(args.backbone, sizes)
    elif args.size:
        cfg.model.sizes = Sizes.preset(args.size)  # the rest of a --config file's model section holds
    for flag, (section, key) in {"stage1_steps": ("stage1", "steps"), "stage2_steps": ("stage2", "steps")}.items():
        if getattr(args, flag) is not None:
            setattr(getattr(cfg, section), key, getattr(args, flag))
    if args.batch is not None:
        cfg.stage1.batch = cfg.stage2.batch = args.batch
    if args.eval_every is not None:
        cfg.eval_every = args.eval_every
    if args.seed is not None:
        cfg.seed = args.seed
    if args.train_backbone:
        cfg.train_backbone = True
    if getattr(args, "recipe", None) is not None:
        cfg.recipe = args.recipe
    cfg.check()
    return cfg


def _relaunch(args: argparse.Namespace) -> int:
    """Run this command again under torchrun with --nproc processes."""
    argv = list(sys.argv[1:]) if sys.argv and Path(sys.argv[0]).name in ("rig", "__main__.py") else None
    if argv is None or "train" not in argv:
        raise ConfigError("--nproc needs the rig command line; run torchrun -m rig train ... yourself")
    rest, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a == "--nproc":
            skip = True
            continue
        if a.startswith("--nproc="):
            continue
        rest.append(a)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={args.nproc}", "-m", "rig", *rest]
    return subprocess.call(cmd)


def _check_options(args: argparse.Namespace):
    """The options against each other and the output folder (a new run needs a new or empty one, a
    resumed run its checkpoint); the training configuration and the output folder."""
    from rig.commands._paths import output_folder

    if args.stop_after is not None and args.stop_after < 1:
        raise ConfigError(f"--stop-after must be at least 1, got {args.stop_after}")
    if args.nproc < 1:
        raise ConfigError(f"--nproc must be at least 1, got {args.nproc}")
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be at least 1, got {args.threads}")
    if args.workers is not None and args.workers < 0:
        raise ConfigError(f"--workers must be at least 0, got {args.workers}")
    for flag, value in (("--cache-mb", args.cache_mb), ("--checkpoint-minutes", args.checkpoint_minutes), ("--max-minutes", args.max_minutes)):
        if value is not None and not (math.isfinite(value) and (value >= 0 if flag == "--cache-mb" else value > 0)):
            raise ConfigError(f"{flag} must be a number {'>= 0' if flag == '--cache-mb' else '> 0'}, got {value:g}")
    cfg = build_config(args)
    out = output_folder(args.out)
    from inference.train.run import elastic_restart

    if int(os.environ.get("RANK", "0")) > 0 or elastic_restart(out):
        # under torchrun only rank 0 writes the folder (the others may see it fill on a shared disk);
        # a worker torchrun started again continues its run (inference/train/run.py)
        return cfg, out
    if not args.resume and out.exists() and ((out / "checkpoint.pt").exists() or (out / "metrics.jsonl").exists()):
        if not (out / "checkpoint.pt").exists():
            raise ConfigError(f"{out}: holds a training run that stopped before its first checkpoint (nothing trained was "
                              "kept); remove the folder to start it again, or choose a new folder")
        raise ConfigError(f"{out}: already holds a training run; pass --resume to continue it, or choose a new folder")
    if not args.resume and out.is_dir() and any(out.iterdir()):
        # a model.pt, a recorded take, anything else: a new run writes only into a new or empty folder
        raise ConfigError(f"{out}: is not empty (it holds {next(iter(sorted(out.iterdir()))).name}); "
                          "a new run needs a new or empty folder (nothing was written)")
    if args.init is not None and args.resume:
        raise ConfigError("--init starts a new run from a checkpoint's weights; --resume continues a run: give one of them")
    if args.init is not None and not args.init.is_file():
        raise ConfigError(f"{args.init}: no such checkpoint")
    if args.resume and not (out / "checkpoint.pt").is_file():
        stopped = (out / "metrics.jsonl").exists()
        raise ConfigError(f"{out / 'checkpoint.pt'}: no checkpoint to resume from"
                          + ("; the run stopped before its first one (nothing trained was kept): remove the folder to start "
                             "it again" if stopped else ""))
    pretrained = cfg.model.backbone.kind == "mast3r"
    if args.weights is not None:
        if not pretrained:
            raise ConfigError("--weights gives the MASt3R backbone's weights: use it with --backbone mast3r")
        if args.resume or args.init is not None:
            raise ConfigError("--weights starts a new run's backbone; --resume and --init take the weights from their checkpoint")
        if not args.weights.is_file():
            raise ConfigError(f"{args.weights}: no such MASt3R weights file")
    elif pretrained and not args.resume and args.init is None:
        raise ConfigError("--backbone mast3r needs --weights PATH (the MASt3R checkpoint MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth; "
                          "rig never ships it)")
    return cfg, out


def cmd_train(args: argparse.Namespace) -> int:
    from rig.commands._output import emit_json
    from rig.storage.dataset import TrainingSet, expand_sequences
    from rig.storage.validate import check_whole

    # Everything a user can get wrong is checked before torch loads and before any work.
    cfg, out = _check_options(args)
    data = TrainingSet(expand_sequences(args.sequences))
    check_whole(data.roots)  # a damaged take is one line before the output folder is written
    if cfg.supervised:
        from inference.train.depth_supervision import truth_missing

        missing = data.without_ground_truth()
        if missing:
            raise ConfigError(truth_missing(missing[0]))
    if args.nproc > 1 and "WORLD_SIZE" not in os.environ:
        return _relaunch(args)

    from inference.train.run import RunOptions, rank, train

    opts = RunOptions(resume=args.resume, init=args.init, weights=args.weights, device=args.device, precision=args.precision,
                      workers=args.workers, cache_mb=args.cache_mb, threads=args.threads, stop_after=args.stop_after,
                      max_minutes=args.max_minutes, checkpoint_minutes=args.checkpoint_minutes)
    bar = None
    if rank() == 0 and not args.json:
        from rig.progress import ProgressBar

        bar = ProgressBar("training")
    try:
        summary = train(cfg, data, out, opts, progress=None if bar is None else lambda step, total, metrics: bar.update(step, total))
    finally:
        if bar is not None:
            bar.close()
    if rank() == 0:
        if args.json:
            emit_json(summary)
        else:
            last = summary["last"]
            rate = f", {summary['steps_per_s']:.3g} steps/s on {summary['device']['device']}" if summary.get("steps_per_s") else ""
            print(f"trained {summary['steps']} steps ({summary['steps_this_run']} in {summary['wall_s']} s{rate}) -> {out}"
                  + (f" (last: stage {last['stage']}, loss {last['loss']:.4f}, psnr {last['psnr']:.2f} dB)" if last else ""))
            if summary["steps"] < cfg.total_steps:
                print(f"stopped at step {summary['steps']} of {cfg.total_steps}; continue with: rig train ... -o {out} --resume")
            else:
                print(f"next: rig model export --checkpoint {out / 'model.pt'} -o model.onnx")
    return 0

