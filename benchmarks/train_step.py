"""Milliseconds per training step of each stage (forward + backward + optimiser), torch.

Renders a short simulator take (six cameras) into a temporary folder, then times `--steps` steps
of stage 1 and of stage 2 at each size preset asked for, after `--warmup` untimed steps, with the
batch and supervision cameras per step of the default training configuration (or the flags).
Data loading is part of a step, as in `rig train`. Runs on CUDA when torch sees a GPU (`--device`).

Besides, per stage: the milliseconds a step's batch takes to build on the CPU (reading and decoding
the frames, resampling them, the MVS depth from its cache) with the view cache cold (every frame
decoded, as before the cache) and warm (every frame decoded once per run), over the same steps.

    .venv/bin/python benchmarks/train_step.py [--sizes preview paper] [--steps 5] [--device cpu|cuda]
        [--precision fp32|bf16] [--workers N] [--json]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["preview", "paper"], choices=["test", "preview", "paper"])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--batch", type=int, help="frame sets per step (default: the training config's)")
    ap.add_argument("--threads", type=int)
    ap.add_argument("--device", help="cpu or cuda[:N] (default: CUDA when torch sees a GPU)")
    ap.add_argument("--precision", choices=["fp32", "bf16"], default="fp32")
    ap.add_argument("--workers", type=int, default=0, help="DataLoader processes building batches (default 0)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    import torch

    from inference.config import ModelConfig, Sizes
    from inference.device import resolve_device
    from inference.train.config import TrainConfig
    from inference.train.trainer import DEFAULT_CACHE_MB, BatchMaker, Trainer
    from rig.storage.dataset import TrainingSet
    from simulator.takes import write_take

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        take = write_take(Path(tmp) / "take", seed=4242, seconds=0.4, fps=10, size=(1280, 720))["out"]
        data = TrainingSet([take])
        for preset in args.sizes:
            cfg = TrainConfig()
            cfg.model = ModelConfig.for_backbone("stereo", Sizes.preset(preset))
            if args.batch:
                cfg.stage1.batch = cfg.stage2.batch = args.batch
            n = args.warmup + args.steps
            cfg.stage1.steps = cfg.stage2.steps = n
            cfg.eval_every = cfg.checkpoint_every = 10 ** 6
            trainer = Trainer(cfg, data, Path(tmp) / f"run-{preset}", device=device, precision=args.precision, workers=args.workers)
            times = {1: [], 2: []}

            def progress(step, total, metrics):
                times[metrics["stage"]].append(metrics["step_s"])

            trainer.progress = progress
            trainer.run()
            load = {}
            for stage, sched in ((1, cfg.stage1), (2, cfg.stage2)):
                steps = [trainer._draw(stage, k, sched) for k in range(n)]
                # The MVS depth cache is warm from the run above in both: what differs is the frames.
                cold = BatchMaker(cfg, data, trainer.out, 0, mvs=True)
                warm = BatchMaker(cfg, data, trainer.out, int(DEFAULT_CACHE_MB * 2**20), mvs=True)
                for items in steps:  # a run that has drawn these sets before (each frame decoded once)
                    warm(items, stage)
                load[stage] = {}
                for name, maker in (("cold", cold), ("warm", warm)):
                    ts = []
                    for items in steps[args.warmup:]:
                        t0 = time.perf_counter()
                        maker(items, stage)
                        ts.append(time.perf_counter() - t0)
                    load[stage][name] = round(1000 * statistics.median(ts), 1)
            for stage in (1, 2):
                t = times[stage][args.warmup:]
                results.append({"size": preset, "sizes": Sizes.preset(preset).describe(), "stage": stage,
                                "batch": getattr(cfg, f"stage{stage}").batch,
                                "views": getattr(cfg, f"stage{stage}").views or cfg.supervision_per_step,
                                "ms_median": round(1000 * statistics.median(t), 1), "ms_min": round(1000 * min(t), 1),
                                "steps": len(t), "device": str(device), "precision": args.precision, "workers": args.workers,
                                "load_ms_cold_cache": load[stage]["cold"], "load_ms_warm_cache": load[stage]["warm"],
                                "threads": torch.get_num_threads()})
    if args.json:
        print(json.dumps(results))
    else:
        for r in results:
            print(f"{r['size']:8s} stage {r['stage']}: {r['ms_median']:8.1f} ms/step median ({r['ms_min']:.1f} min) over {r['steps']} steps, "
                  f"batch {r['batch']} x {r['views']} supervision views, {r['device']} {r['precision']}, {r['threads']} threads; "
                  f"batch building {r['load_ms_cold_cache']:.1f} ms decoding every frame, {r['load_ms_warm_cache']:.1f} ms from the view cache")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
