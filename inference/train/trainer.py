"""The training loop: both stages, checkpoints with resume, metrics log, sample and loss-curve PNGs.

Output folder:
    checkpoint.pt    the latest state (model, optimiser, step, training config): `--resume` reads it;
                     it is also a model checkpoint (`rig model export --checkpoint`)
    model.pt         the trained model once both stages are done
    train.json       the training config and the sequences
    metrics.jsonl    one JSON line per step (and per evaluation, "eval": true)
    mvs-depth/       stage 1's multi-view stereo depth of the sources, one file per frame set (a cache)
    samples/step-NNNNNN.png   at each evaluation: renders of held-out sets beside their truth
    loss.png         the loss curves, redrawn at each evaluation

Batches are drawn from a generator seeded by (seed, stage, step), so a resumed run sees the batches
the uninterrupted one would have seen and continues the same loss curve. With torch.distributed
initialised (torchrun), every process draws the same global batch and computes its share; DDP
averages the gradients, so N processes step as one process on the whole batch would.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from common.files import atomic_path, atomic_write_json
from inference.errors import InferenceError, OutputError
from inference.config import GROWN_FROM_ZERO, ModelConfig, weight_differences
from inference.model.checkpoint import FORMAT, VERSION, load_weights, read_checkpoint
from inference.model.pipeline import SplatSAP, build_model
from inference.train.config import PRETRAINED_BACKBONES, StageSchedule, TrainConfig
from inference.train.data import CachedViews, FrameSource, Preprocessor, stack_views
from inference.train.plots import save_loss_curve, save_samples
from inference.train.depth_supervision import TruthDepth, truth_missing
from inference.train.multiview_depth import source_depths
from inference.train.stages import Batch, SourceDepth, Stage1Loss, Stage2Loss, TrainingDiverged, ViewTruth

CHECKPOINT = "checkpoint.pt"
FINAL = "model.pt"
METRICS = "metrics.jsonl"
MVS_CACHE = "mvs-depth"
SNAPSHOTS = "snapshots"
PRECISIONS = ("fp32", "bf16")
DEFAULT_CACHE_MB = 2048.0
Progress = Callable[[int, int, dict], None]


def _rank_world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


class BatchMaker:
    """Builds a step's batch on the CPU from (frame-set index, supervision cameras) items: views
    from the run's view cache, stage 1's multi-view stereo depth from the output folder's cache.
    Picklable: DataLoader workers each build batches with their own copy (and their own cache)."""

    def __init__(self, cfg: TrainConfig, source: FrameSource, out: Path, cache_bytes: int, mvs: bool, truth: bool = False):
        self.cfg = cfg
        self.source = source
        self.out = out
        self.mvs = mvs
        self.truth = truth  # the supervised recipe: the sources' ground-truth depth in stage 1's batches
        self.views = CachedViews(source, Preprocessor(), cache_bytes)
        # Ground-truth depth of both sources at the coarse size per frame set: rendering the truth of
        # a set costs about as much as decoding it (every camera is rendered), and a run draws each
        # set many times. Two float maps and four masks per set (about 0.4 MB at the preview size).
        self._truth: dict[int, tuple[torch.Tensor, ...]] = {}

    def __call__(self, items: list[tuple[int, list[str]]], stage: int) -> Batch:
        s, src, views = self.cfg.model.sizes, self.source, self.views.views
        lefts, rights, targets, fines, depths = [], [], [], [], []
        trains_stage1 = stage == 1 or self.cfg.stage2_trains_stage1 > 0
        want_depth = self.mvs and trains_stage1 and self.cfg.mvs_depth > 0
        want_truth = self.truth and trains_stage1
        truths = []
        for index, sup in items:
            lefts.append(views(index, [src.left], s.fine))
            rights.append(views(index, [src.right], s.fine))
            targets.append(views(index, sup, s.coarse if stage == 1 else s.output))
            if stage == 2:
                fines.append(views(index, sup, s.fine))
            if want_depth:
                depths.append(self._source_depth(index))
            if want_truth:
                truths.append(self._truth_depth(index))
        source_depth = SourceDepth(*(torch.stack([d[k] for d in depths]) for k in range(4))) if depths else None
        truth_depth = TruthDepth(*(torch.stack([d[k] for d in truths]) for k in range(6))) if truths else None
        view_truth = None
        if stage == 2 and self.truth and (self.cfg.view_depth > 0 or self.cfg.render_person > 0):
            per_view = [t for index, sup in items for t in self._view_truth(index, sup)]
            view_truth = ViewTruth(*(torch.stack([v[k] for v in per_view]) for k in range(3)))
        return Batch(stack_views(lefts), stack_views(rights), stack_views(targets),
                     stack_views(fines) if fines else None, len(items[0][1]), source_depth, truth_depth, view_truth)

    def _view_truth(self, index: int, cameras: list[str]) -> list[tuple[torch.Tensor, ...]]:
        """Ground-truth depth of supervision views at the fine size, as `_truth_depth` resamples the
        sources' (depth, where it holds, person mask), in the order of `cameras`. Not cached: four
        views' truth at the fine size is about 2 MB a set, and rendering it costs a few per cent of
        a step."""
        fs = self.source.frame_set(index, with_truth=True)
        return [self._camera_truth(fs, index, cam, self.cfg.model.sizes.fine) for cam in cameras]

    def _camera_truth(self, fs, index: int, cam: str, size: tuple[int, int]) -> tuple[torch.Tensor, ...]:
        """One camera's ground-truth depth at `size` (nearest, onto its pinhole image), where it holds, and its person mask."""
        depth = fs.depth.get(cam)
        if depth is None:
            raise InferenceError(truth_missing(fs.key or f"frame set {index}"))
        z = torch.from_numpy(np.ascontiguousarray(self.views.pre.depth(depth, fs.cameras[cam], size), dtype=np.float32))
        mask = fs.masks.get(cam)
        person = (torch.from_numpy(self.views.pre.depth(mask.astype(np.float32), fs.cameras[cam], size) > 0.5) if mask is not None
                  else torch.zeros_like(z, dtype=torch.bool))
        return z, z > 0, person

    def _truth_depth(self, index: int) -> tuple[torch.Tensor, ...]:
        """Ground-truth depth of both sources at the coarse size, resampled onto their pinhole images
        as `rig model eval` resamples it (nearest), where it holds and their person masks (the
        TruthDepth fields: left depth, valid, person, then the right's)."""
        hit = self._truth.get(index)
        if hit is not None:
            return hit
        src, coarse = self.source, self.cfg.model.sizes.coarse
        fs = src.frame_set(index, with_truth=True)
        out = []
        for cam in (src.left, src.right):
            out += self._camera_truth(fs, index, cam, coarse)
        self._truth[index] = tuple(out)
        return self._truth[index]

    def _source_depth(self, index: int) -> tuple[torch.Tensor, ...]:
        """Multi-view stereo depth of both sources at the coarse size (depth, mask, depth, mask), from
        the cache in the output folder when this frame set's images and cameras were seen before."""
        src, coarse = self.source, self.cfg.model.sizes.coarse
        names = [src.left, src.right] + list(src.supervision)
        views = self.views.views(index, names, coarse)
        digest = hashlib.blake2b(digest_size=16)
        for t in (views.images, views.K, views.poses):
            digest.update(t.numpy().tobytes())
        digest.update(json.dumps([asdict(self.cfg.mvs), self.cfg.mvs_neighbours]).encode())
        path = self.out / MVS_CACHE / f"{digest.hexdigest()}.pt"
        if path.is_file():
            try:
                # map_location: a cache written by a GPU run (CPU tensors, but say so) read anywhere
                return tuple(torch.load(path, map_location="cpu", weights_only=True))
            except Exception:  # a torn or foreign file: compute it again
                pass
        out = source_depths(views, list(range(2, len(names))), self.cfg.mvs_neighbours, self.cfg.mvs)
        try:
            with atomic_path(path, make_parents=True) as tmp:
                torch.save(out, tmp)
        except OSError:
            pass  # the cache only saves time
        return tuple(out)


class _StepBatches(torch.utils.data.Dataset):
    """The batches of a run of steps, for a DataLoader: item i is the batch of the i-th step."""

    def __init__(self, maker: BatchMaker, steps: list[list[tuple[int, list[str]]]], stage: int):
        self.maker, self.steps, self.stage = maker, steps, stage

    def __len__(self) -> int:
        return len(self.steps)

    def __getitem__(self, i: int) -> Batch:
        return self.maker(self.steps[i], self.stage)


class Trainer:
    def __init__(self, cfg: TrainConfig, data: FrameSource, out_dir: str | os.PathLike, *, resume: bool = False,
                 eval_data: Optional[FrameSource] = None, progress: Optional[Progress] = None,
                 describe: Optional[dict] = None, init: Optional[str | os.PathLike] = None,
                 backbone_weights: Optional[str | os.PathLike] = None, device: Optional[torch.device] = None,
                 precision: str = "fp32", workers: int = 0, cache_mb: float = DEFAULT_CACHE_MB):
        """`device`: where the model trains (None: CUDA when torch sees a GPU, else the CPU; with
        torchrun a CUDA device is the process's LOCAL_RANK GPU). `precision` "bf16" runs the forward
        passes under autocast (weights, gradients and optimiser state stay fp32). `workers`:
        DataLoader processes building batches (0: in this process). `cache_mb`: decoded, resampled
        views kept per process."""
        cfg.check()
        if precision not in PRECISIONS:
            raise InferenceError(f"precision {precision!r}: give one of {', '.join(PRECISIONS)}")
        if not isinstance(workers, int) or workers < 0:
            raise InferenceError(f"workers must be an integer >= 0, got {workers!r}")
        self.cfg = cfg
        self.data = data
        self.eval_data = eval_data or data
        self.out = Path(out_dir)
        self.progress = progress
        self.rank, self.world = _rank_world()
        if device is None:
            device = torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
        if device.type == "cuda":
            # One GPU per process: torchrun's LOCAL_RANK picks it (a lone process keeps the index given).
            index = int(os.environ["LOCAL_RANK"]) if "LOCAL_RANK" in os.environ and self.world > 1 else (device.index or 0)
            device = torch.device("cuda", index)
            torch.cuda.set_device(device)
        self.device = device
        self.precision = precision
        self.workers = workers
        self.pre = Preprocessor()
        if len(data) == 0:
            raise InferenceError("no frame set has every camera the training needs")
        if cfg.supervised:
            # A recorded take has no ground-truth depth: refused before anything is written (a
            # FrameSource that cannot say is refused at its first batch without truth).
            for seq in getattr(data, "sequences", ()):
                if hasattr(seq, "has_ground_truth") and not seq.has_ground_truth():
                    raise InferenceError(truth_missing(str(getattr(seq, "root", seq))))
        if not data.supervision:
            raise InferenceError("training needs supervision cameras besides the two sources")
        self.train_index = list(range(0, len(data), cfg.frame_stride))
        self.step = 0
        self.model = build_model(cfg.model, seed=cfg.seed).train()
        self._optim_state = None
        if resume:
            if self.rank == 0:
                self._load(self.out / CHECKPOINT)
            if self.world > 1:  # the other processes take rank 0's state (their hosts need no copy of the folder)
                self._share_state()
        else:
            if self.rank == 0:
                _check_fresh(self.out)
            if init is not None:
                self._init_from(Path(init))
            elif backbone_weights is not None:
                # A fresh run on a pretrained backbone: its weights from the user's file (a
                # resumed or --init run has them in its checkpoint).
                from inference.model.checkpoint import load_backbone_weights

                load_backbone_weights(self.model, backbone_weights)
            elif cfg.model.backbone.kind in PRETRAINED_BACKBONES:
                raise InferenceError(f"the {cfg.model.backbone.kind} backbone is pretrained: give its weights (--weights PATH)")
        self.model.to(self.device)
        cache_bytes = int(cache_mb * 2**20)
        self.batches = BatchMaker(cfg, data, self.out, cache_bytes, mvs=True, truth=cfg.supervised)
        self._eval_batches = self.batches if self.eval_data is data else BatchMaker(cfg, self.eval_data, self.out, cache_bytes, mvs=False)
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "samples").mkdir(exist_ok=True)
            if not resume:
                atomic_write_json(self.out / "train.json", {"config": cfg.to_dict(), **(describe or {})})
            else:
                self._record_config()
            self._trim_metrics()

    # -- state ------------------------------------------------------------------------------------

    def _share_state(self) -> None:
        """Rank 0's resumed weights, step and optimiser state, to every process."""
        import torch.distributed as dist

        state = [{"state_dict": self.model.state_dict(), "step": self.step, "optimizer": self._optim_state}] if self.rank == 0 else [None]
        dist.broadcast_object_list(state, src=0)
        if self.rank != 0:
            self.model.load_state_dict(state[0]["state_dict"])
            self.step, self._optim_state = int(state[0]["step"]), state[0]["optimizer"]

    def _load(self, path: Path) -> None:
        if not path.is_file():
            raise InferenceError(f"{path}: no checkpoint to resume from")
        data = read_checkpoint(path)
        if "train" not in data:
            raise InferenceError(f"{path}: not a training checkpoint (a finished model; start a new run from scratch)")
        saved = TrainConfig.from_dict(data["train"]["config"], saved=True)
        if saved.model.to_dict() != self.cfg.model.to_dict():
            raise InferenceError(f"{path}: the checkpoint's model configuration differs from this run's (train it with its own config, or start a new folder)")
        load_weights(self.model, data.get("state_dict"), path)
        self.step = int(data["train"]["step"])
        self._optim_state = data["train"].get("optimizer")
        self._check_stage(path, saved.stage1.steps)

    def _check_stage(self, path: Path, saved_stage1: int) -> None:
        """A resumed run continues the stage its checkpoint's optimiser belongs to: a new stage-1
        length (--stage1-steps) may end stage 1 at the checkpoint or later, never move the run
        into the other stage half way (stage 1's optimiser on stage 2's parameters, or back)."""
        step, new_stage1 = self.step, self.cfg.stage1.steps
        if self._optim_state is None or step == 0 or new_stage1 == saved_stage1:
            return
        saved_stage = 1 if step <= saved_stage1 else 2
        resumed_stage = 1 if step < new_stage1 else (2 if step > new_stage1 else None)  # None: stage 2 starts afresh
        if resumed_stage is None and saved_stage == 1:
            return
        if saved_stage == 1 and resumed_stage == 2:
            raise InferenceError(f"{path}: the run is at step {step}, in stage 1; --stage1-steps {new_stage1} would put it half way "
                                 f"through stage 2: give --stage1-steps {step} to end stage 1 here, or more to continue it")
        if saved_stage == 2:
            raise InferenceError(f"{path}: the run is at step {step}, in stage 2 (stage 1 ended at step {saved_stage1}); "
                                 f"stage 1's length cannot change now: give --stage1-steps {saved_stage1}")

    def _init_from(self, path: Path) -> None:
        """Start this run's schedule from the weights of an earlier run (fine-tuning, a longer schedule)."""
        data = read_checkpoint(path)
        try:
            # A checkpoint written before a key was added computes what its value in SAVED_BEFORE does.
            saved = ModelConfig.from_dict(data.get("config"), saved=True)
        except (InferenceError, TypeError, ValueError, AttributeError):
            saved = None
        # Settings no weight depends on (config.WEIGHT_FREE) may differ: the run fine-tunes to its own.
        # A module the checkpoint lacks (config.GROWN_FROM_ZERO, e.g. the stereo cascade) starts at zero.
        differs = weight_differences(saved, self.cfg.model) if saved is not None else ["model"]
        grown = [GROWN_FROM_ZERO[d] for d in differs if d in GROWN_FROM_ZERO and not _config_value(saved, d)]
        if saved is None or len(grown) != len(differs):
            raise InferenceError(f"{path}: the checkpoint's model configuration differs from this run's (--size, --backbone, --config)")
        missing, unexpected = load_weights(self.model, data.get("state_dict"), path, strict=not grown)
        if unexpected or any(not k.startswith(tuple(grown)) for k in missing):
            raise InferenceError(f"{path}: the checkpoint's weights do not fit this run's model")

    def _save(self, path: Path, optimizer: Optional[torch.optim.Optimizer], final: bool = False) -> None:
        if self.rank != 0:
            return
        meta = {"steps": self.step, "device": str(self.device), "stage1_steps": self.cfg.stage1.steps, "stage2_steps": self.cfg.stage2.steps}
        state = {k: v.cpu() for k, v in self.model.state_dict().items()}
        broken = next((k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())), None)
        if broken is not None:  # never written over the last good checkpoint
            raise TrainingDiverged(f"training diverged at step {self.step}: the weights ({broken}) are no longer finite numbers "
                                   f"(a learning rate too high?); {path.name} was not written, the last one saved is kept")
        data = {"format": FORMAT, "version": VERSION, "config": self.cfg.model.to_dict(),
                "state_dict": state, "meta": meta}
        if not final:
            data["train"] = {"config": self.cfg.to_dict(), "step": self.step,
                             "optimizer": optimizer.state_dict() if optimizer is not None else None}
        try:
            with atomic_path(path, make_parents=True) as tmp:
                torch.save(data, tmp)
        except OSError as exc:
            raise OutputError(f"{path}: cannot write the checkpoint ({exc.strerror or exc})") from None

    def _record_config(self) -> None:
        """On resume: train.json's config becomes this run's (a flag such as --stage1-steps may have
        changed the schedule), so that the next --resume, which reads it, continues the same one."""
        path = self.out / "train.json"
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            record = None
        if not isinstance(record, dict):
            record = {}
        if record.get("config") != self.cfg.to_dict():
            record["config"] = self.cfg.to_dict()
            atomic_write_json(path, record)

    def _trim_metrics(self) -> None:
        """On resume: drop lines logged after the checkpoint (they will be logged again)."""
        path = self.out / METRICS
        if not path.exists():
            return
        keep = []
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if rec.get("step", 0) <= self.step:
                keep.append(line)
        with atomic_path(path) as tmp:
            Path(tmp).write_text("".join(k + "\n" for k in keep))

    def _log(self, rec: dict) -> None:
        if self.rank != 0:
            return
        try:
            with open(self.out / METRICS, "a") as f:
                f.write(json.dumps(rec) + "\n")
        except OSError as exc:
            raise OutputError(f"{self.out / METRICS}: cannot write ({exc.strerror})") from None

    # -- batches ----------------------------------------------------------------------------------

    def _draw(self, stage: int, step: int, sched: StageSchedule) -> list[tuple[int, list[str]]]:
        """The global batch of a step: (frame-set index, supervision cameras) per item."""
        rng = np.random.default_rng([self.cfg.seed, stage, step])
        sets = rng.choice(len(self.train_index), size=sched.batch, replace=len(self.train_index) < sched.batch)
        k = min(sched.views or self.cfg.supervision_per_step, len(self.data.supervision))
        return [(self.train_index[int(s)], [self.data.supervision[int(j)] for j in rng.choice(len(self.data.supervision), k, replace=False)]) for s in sets]

    def _batch(self, source: FrameSource, items: list[tuple[int, list[str]]], stage: int) -> Batch:
        """A batch on the model's device (evaluation; training steps come through `_loader`)."""
        maker = self.batches if source is self.data else self._eval_batches
        return maker(items, stage).to(self.device)

    # -- loop -------------------------------------------------------------------------------------

    def _lr(self, sched: StageSchedule, k: int) -> float:
        if k < sched.warmup:
            return sched.lr * (k + 1) / sched.warmup
        t = (k - sched.warmup) / max(1, sched.steps - sched.warmup)
        return sched.lr * (sched.final_lr + (1 - sched.final_lr) * 0.5 * (1 + math.cos(math.pi * min(1.0, t))))

    def _stage_module(self, stage: int):
        """The loss module of `stage` and its optimiser's parameter groups, each with its `lr_factor`."""
        m = self.model
        first = [m.point_init, m.affine_transform] if self.cfg.backbone_trainable else [m.affine_transform]
        for p in m.parameters():
            p.requires_grad_(False)
        if stage == 1:
            # A pretrained backbone (MASt3R) stays frozen unless train_backbone (--train-backbone).
            groups = [(first, 1.0)]
        else:
            rest = [mod for mod in m.children() if all(mod is not f for f in (m.point_init, m.affine_transform))]
            groups = [(rest, 1.0)]
            if self.cfg.stage2_trains_stage1 > 0:
                groups.append((first, float(self.cfg.stage2_trains_stage1)))
        names = {id(p): n for n, p in m.named_parameters()}
        param_groups = []
        for mods, factor in groups:
            by_factor: dict[float, list] = {}  # one optimiser group per learning-rate factor (TrainConfig.lr_factors)
            for p in (p for mod in mods for p in mod.parameters()):
                p.requires_grad_(True)
                by_factor.setdefault(factor * self.cfg.lr_factor(names[id(p)]), []).append(p)
            param_groups += [{"params": ps, "lr_factor": f} for f, ps in by_factor.items()]
        w = self.cfg.loss
        truth = self.cfg.depth_supervision if self.cfg.supervised else None
        module = (Stage1Loss(m, w, self.cfg.point_radius, self.cfg.render_scales, self.cfg.plane_render, self.cfg.mvs_depth, truth,
                             self.cfg.stage1_render) if stage == 1
                  else Stage2Loss(m, w, self.cfg.mvs_depth if self.cfg.stage2_trains_stage1 > 0 else 0.0,
                                  truth if self.cfg.stage2_trains_stage1 > 0 else None,
                                  self.cfg.view_depth if self.cfg.supervised else 0.0, self.cfg.depth_supervision.person,
                                  self.cfg.render_person if self.cfg.supervised else 0.0))
        if self.world > 1:
            module = DistributedDataParallel(module, device_ids=[self.device.index] if self.device.type == "cuda" else None)
        return module, param_groups

    def run(self, stop_after: Optional[int] = None, max_minutes: Optional[float] = None,
            checkpoint_minutes: Optional[float] = None) -> dict:
        """Train to the end of the schedule, or `stop_after` more steps, or until `max_minutes` of
        wall clock have passed (then checkpoint and return). `checkpoint_minutes`: also write the
        checkpoint whenever that long has passed since the last one (a run cut off loses at most that).
        Ctrl-C or SIGTERM (one process, main thread) ends the step under way, writes the checkpoint and
        raises KeyboardInterrupt: nothing trained is lost; a second one stops at once."""
        for name, v in (("max_minutes", max_minutes), ("checkpoint_minutes", checkpoint_minutes)):
            if v is not None and not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise InferenceError(f"{name} must be a number > 0, got {v!r}")
        with _StopRequests(self.world == 1) as stop:
            return self._run(stop_after, stop, max_minutes, checkpoint_minutes)

    def _autocast(self):
        """bf16 autocast for the forward passes (`precision`), on the model's device kind."""
        return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16")

    def _loader(self, stage: int, steps: list[list[tuple[int, list[str]]]]):
        """The batches of `steps` on the model's device, built ahead by `workers` processes (pinned
        memory on CUDA, so the copy overlaps the step under way) or here, one at a time."""
        cuda = self.device.type == "cuda"
        if self.workers == 0:
            for items in steps:
                yield self.batches(items, stage).to(self.device)
            return
        loader = torch.utils.data.DataLoader(_StepBatches(self.batches, steps, stage), batch_size=None, shuffle=False,
                                             num_workers=self.workers, pin_memory=cuda, prefetch_factor=2)
        for batch in loader:
            yield batch.to(self.device, non_blocking=cuda)

    def _run(self, stop_after: Optional[int], stop: "_StopRequests", max_minutes: Optional[float] = None,
             checkpoint_minutes: Optional[float] = None) -> dict:
        cfg = self.cfg
        total = cfg.total_steps
        stop_at = total if stop_after is None else min(total, self.step + stop_after)
        started = time.monotonic()
        deadline = None if max_minutes is None else started + 60.0 * max_minutes
        saved_at = started
        first_step = self.step
        last = {}
        timed_out = False
        for stage, sched, offset in ((1, cfg.stage1, 0), (2, cfg.stage2, cfg.stage1.steps)):
            if self.step >= offset + sched.steps or sched.steps == 0:
                continue
            module, groups = self._stage_module(stage)
            params = [p for g in groups for p in g["params"]]
            optimizer = self._stage_optimizer(groups, sched, offset)
            end = min(offset + sched.steps, stop_at)
            steps = [self._draw(stage, k, sched)[self.rank::self.world] for k in range(self.step - offset, end - offset)]
            t_stage, n_stage = time.perf_counter(), 0
            t0 = time.perf_counter()
            for batch in self._loader(stage, steps):
                metrics, gnorm = self._train_step(stage, module, optimizer, params, sched, batch, self.step - offset)
                n_stage += 1
                now = time.perf_counter()
                # step_s: this step, loading included (the time since the previous step ended);
                # steps_per_s: the stage's mean rate in this run, evaluations and checkpoints included.
                last = {"step": self.step, "stage": stage, "lr": optimizer.param_groups[0]["lr"], **metrics,
                        "grad_norm": gnorm, "step_s": round(now - t0, 4),
                        "steps_per_s": round(n_stage / max(now - t_stage, 1e-9), 4)}
                self._log(last)
                if self.progress is not None and self.rank == 0:
                    self.progress(self.step, total, last)
                end_of_stage = self.step == offset + sched.steps
                if self.step % cfg.eval_every == 0 or end_of_stage:
                    self.evaluate(stage)
                wall = time.monotonic()
                timed_out = self._past_deadline(deadline, wall, stop_at)
                on_clock = checkpoint_minutes is not None and wall - saved_at >= 60.0 * checkpoint_minutes
                if (self.step % cfg.checkpoint_every == 0 or self.step % cfg.eval_every == 0 or end_of_stage
                        or self.step == stop_at or stop.requested or timed_out or on_clock):
                    self._save(self.out / CHECKPOINT, optimizer)
                    saved_at = time.monotonic()
                if cfg.snapshot_every and self.step % cfg.snapshot_every == 0:
                    # the weights alone (a model checkpoint), kept for a validation curve measured apart
                    self._save(self.out / SNAPSHOTS / f"step-{self.step:06d}.pt", None, final=True)
                if stop.requested:
                    raise KeyboardInterrupt
                if timed_out:
                    break
                t0 = time.perf_counter()
            if self.step >= stop_at or timed_out:
                break
        if self.step >= total:
            self._save(self.out / FINAL, None, final=True)
        if self.world > 1:
            dist.barrier()
        wall_s = time.monotonic() - started
        done = self.step - first_step
        return {"steps": self.step, "steps_this_run": done, "wall_s": round(wall_s, 1),
                "steps_per_s": round(done / wall_s, 4) if wall_s > 0 else None, "stopped_by": "max_minutes" if timed_out else None,
                "device": str(self.device), "precision": self.precision, "workers": self.workers,
                "last": last, "out": str(self.out)}

    def _stage_optimizer(self, groups: list[dict], sched, offset: int) -> torch.optim.Optimizer:
        """The stage's AdamW, with the checkpoint's state when the run resumes inside the stage."""
        optimizer = torch.optim.AdamW(groups, lr=sched.lr, weight_decay=1e-4)
        if self._optim_state is not None and self.step > offset:
            # Read onto the CPU (a checkpoint from a GPU opens anywhere); load_state_dict moves
            # each state tensor onto its parameter's device, this run's.
            optimizer.load_state_dict(self._optim_state)
        self._optim_state = None
        self.optimizer = optimizer  # the stage's, for inspection (tests, tools)
        return optimizer

    def _train_step(self, stage: int, module, optimizer, params: list, sched, batch, k: int) -> tuple[dict, float]:
        """One optimiser step at the stage's step k: (the metrics averaged over the ranks, the gradient norm)."""
        for g in optimizer.param_groups:
            g["lr"] = self._lr(sched, k) * g.get("lr_factor", 1.0)
        if stage == 1:
            (module.module if self.world > 1 else module).gamma = self.cfg.gamma_at(k)
        self.model.train()
        with self._autocast():
            loss, metrics, _ = module(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = torch.nn.utils.clip_grad_norm_(params, sched.grad_clip)
        optimizer.step()
        self.step += 1
        return _mean_over_ranks(metrics, self.world, self.device), float(gnorm)

    def _past_deadline(self, deadline: Optional[float], wall: float, stop_at: int) -> bool:
        """The run's time is up (and steps remain); with several processes, when any of them says so."""
        timed_out = deadline is not None and wall >= deadline and self.step < stop_at
        if deadline is not None and self.world > 1:
            # every process stops at the same step: the first to see the deadline decides
            flag = torch.tensor([1.0 if timed_out else 0.0], device=self.device if dist.get_backend() == "nccl" else "cpu")
            dist.all_reduce(flag, op=dist.ReduceOp.MAX)
            timed_out = bool(flag.item() > 0)
        return timed_out

    @torch.no_grad()
    def _depth_absrel(self, picks: list[int]) -> Optional[dict]:
        """Stage 1's depth AbsRel on held-out sets where the source has ground truth (simulator takes):
        on the pixels both sources see, on those only one sees, and on the person masks (as `rig model
        eval` reports them); monitoring only, no loss reads it."""
        from inference.train.depth_figures import stage1_absrel
        from inference.train.stages import stage1_forward

        src, sizes = self.eval_data, self.cfg.model.sizes
        figures: dict[str, list[float]] = {"depth_absrel": [], "depth_absrel_single": [], "depth_absrel_person": []}
        for index in picks:
            fs = src.frame_set(index, with_truth=True)
            if fs.depth.get(src.left) is None or fs.depth.get(src.right) is None:
                return None
            L = self.pre.views(fs, [src.left], sizes.fine).to(self.device)
            R = self.pre.views(fs, [src.right], sizes.fine).to(self.device)
            with self._autocast():
                *_, affine = stage1_forward(self.model, L, R)
            cams = (src.left, src.right)
            gt = {c: self.pre.depth(fs.depth[c], fs.cameras[c], sizes.coarse) for c in cams}
            figures["depth_absrel"] += stage1_absrel(affine, L, R, fs, src, gt, sizes.coarse)
            figures["depth_absrel_single"] += stage1_absrel(affine, L, R, fs, src, gt, sizes.coarse, single=True)
            if all(fs.masks.get(c) is not None for c in cams):
                masks = {c: self.pre.depth(fs.masks[c].astype(np.float32), fs.cameras[c], sizes.coarse) > 0.5 for c in cams}
                figures["depth_absrel_person"] += stage1_absrel(affine, L, R, fs, src, gt, sizes.coarse, masks)
        return {k: float(np.mean(v)) for k, v in figures.items() if v} or None

    @torch.no_grad()
    def evaluate(self, stage: int) -> dict:
        """Render held-out sets (evenly spread over the evaluation source) with the current stage."""
        if self.rank != 0:
            if self.world > 1:
                dist.barrier()
            return {}
        self.model.eval()
        n = len(self.eval_data)
        picks = sorted({int(round(i * (n - 1) / max(1, self.cfg.eval_sets - 1))) for i in range(min(n, self.cfg.eval_sets))})
        sup = self.eval_data.supervision
        module = Stage1Loss(self.model, self.cfg.loss, self.cfg.point_radius, (1,)) if stage == 1 else Stage2Loss(self.model, self.cfg.loss)
        renders, truths, psnrs, losses = [], [], [], []
        for j, index in enumerate(picks):
            cam = sup[j % len(sup)]
            with self._autocast():
                _, metrics, images = module(self._batch(self.eval_data, [(index, [cam])], stage))
            renders.append(images["render"][0])
            truths.append(images["truth"][0])
            psnrs.append(metrics["psnr"])
            losses.append(metrics["loss"])
        rec = {"step": self.step, "stage": stage, "eval": True, "psnr": float(np.mean(psnrs)), "loss": float(np.mean(losses))}
        rec.update(self._depth_absrel(picks) or {})
        self._log(rec)
        try:
            save_samples(self.out / "samples" / f"step-{self.step:06d}.png", renders, truths)
            save_loss_curve(self.out / METRICS, self.out / "loss.png")
        except OSError as exc:
            raise OutputError(f"{self.out}: cannot write the evaluation images ({exc.strerror})") from None
        self.model.train()
        if self.world > 1:
            dist.barrier()
        return rec


def _mean_over_ranks(metrics: dict, world: int, device: torch.device) -> dict:
    if world == 1:
        return metrics
    keys = sorted(metrics)
    # NCCL reduces GPU tensors only; gloo CPU ones
    on = device if dist.get_backend() == "nccl" else torch.device("cpu")
    t = torch.tensor([metrics[k] for k in keys], dtype=torch.float64, device=on)
    dist.all_reduce(t)
    return {k: float(v) / world for k, v in zip(keys, t.cpu())}


class _StopRequests:
    """SIGINT / SIGTERM as a request to stop after the step under way (`requested`); a second one
    raises KeyboardInterrupt at once. Only in one process's main thread: data-parallel ranks would
    see the request at different steps and wait for each other, so they keep the default handling."""

    def __init__(self, enabled: bool):
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.requested = False
        self._previous: dict = {}

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        print("\nrig train: stopping after this step, with a checkpoint (again to stop at once)", file=sys.stderr)

    def __enter__(self) -> "_StopRequests":
        if self.enabled:
            self._previous = {s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)


def _check_fresh(out: Path) -> None:
    if (out / CHECKPOINT).exists() or (out / METRICS).exists():
        raise InferenceError(f"{out}: already holds a training run; pass --resume to continue it, or choose a new folder")


def _config_value(cfg: ModelConfig, key: str):
    section, _, name = key.partition(".")
    return getattr(getattr(cfg, section), name)
