"""The exported model in two parts, for serving many viewpoints of one frame set (onnxruntime + numpy
only; this module never imports torch or onnx).

`rig model export -o M.onnx` writes, beside the whole pipeline M.onnx, the same graph cut in two:

    M.stage1.onnx  source inputs -> stage-1 tensors      point_init + affine_transform: once per frame set
    M.view.onnx    stage-1 tensors + source inputs       depth_init onwards: once per viewpoint
                   + target_K, target_pose -> image, depth

The stage-1 tensors (inference.model.pipeline.STAGE1_OUTPUT_NAMES) are the affine-transformed point
maps of both sources and their splatting opacities: everything the target-dependent stages read
from stage 1. Both parts come from the same trace as M.onnx, so stage1 then view computes what
M.onnx computes.

    from inference.runtime import SplitPipeline
    pipe = SplitPipeline("M.onnx")                                  # opens M.stage1.onnx and M.view.onnx
    feeds = pipe.source_feeds(left_rgb, right_rgb, left_cam, right_cam)
    s1 = pipe.stage1(feeds)                                         # once per frame set
    for cam in viewers:
        view = pipe.render(s1, feeds, cam)                          # NovelView, per viewpoint
    image, depth = pipe.view(s1, feeds, target_K, target_pose)      # the same from arrays
"""
from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from calibration.camera import CameraModel
from inference.errors import InferenceError
from inference.runtime.pipeline import ModelInfo, NovelView, open_session, read_model_info
from inference.runtime.preprocess import InputPreparer, intrinsics, pose

PARTS = ("stage1", "view")
# Stage 1 without its scale search, written beside a model that has the search (inference.export).
UNSCALED_PART = "stage1_unscaled"
TARGET_INPUTS = ("target_K", "target_pose")
DEPTH_INPUTS = ("left_depth", "right_depth")  # the oracle backbone's, last in the whole model's inputs


def part_path(path: str | os.PathLike, part: str) -> Path:
    """Where the export writes `part` ("stage1" or "view") of the model at `path`:
    M.onnx -> M.stage1.onnx, M.fp16.onnx -> M.fp16.stage1.onnx."""
    if part not in PARTS + (UNSCALED_PART,):
        raise InferenceError(f"unknown model part {part!r} (the parts are {', '.join(PARTS + (UNSCALED_PART,))})")
    path = Path(path)
    return path.with_name(f"{path.stem}.{part}.onnx")


class SplitPipeline:
    """The model as stage 1 (once per frame set) and view (once per viewpoint).

    `path` names the whole model M.onnx (or M.fp16.onnx); the parts beside it are opened, the whole
    file itself is not needed. Sessions are ONNX Runtime's, which may be run from several threads
    at once; `stage1_ms` and `view_ms` are the wall times of the latest calls (`render` returns
    its own with the view)."""

    def __init__(self, path: str | os.PathLike, providers: list[str] | None = None, threads: int | None = None, scale_every: int = 1):
        """`scale_every` > 1: for a model with the scale search, run the whole stage 1 (the search
        included) on one frame set in `scale_every` and reuse its factor on the sets between, with
        stage 1 without the search (M.stage1_unscaled.onnx; see `stage1`). 1: every set searched."""
        self.path = Path(path)
        if self.path.suffix == ".pt":
            raise InferenceError(f"{self.path}: a checkpoint, not an ONNX model; export it first "
                                 f"(rig model export --checkpoint {self.path} -o MODEL.onnx)")
        paths = {part: part_path(self.path, part) for part in PARTS}
        for part, p in paths.items():
            if not p.is_file():
                raise InferenceError(f"{p}: no such file (the {part} part of {self.path.name}; re-export the model with `rig model export`, which writes both parts)")
        self.stage1_path, self.view_path = paths["stage1"], paths["view"]
        # Two sessions take turns, beside capture, encoding and the server: threads that spin
        # after a run keep the other session's threads and the rest of the loop from the cores.
        # Measured on the 2-core host (benchmarks/live_latency.py): the loop's own share of the
        # latency (p50 minus its stage 1 + view) 16-43 ms (median 26) in six runs without spinning,
        # 28-62 ms (median 46) in nine with it; throughput the same within the host's drift.
        self.stage1_session = open_session(self.stage1_path, providers, threads, spinning=False)
        self.view_session = open_session(self.view_path, providers, threads, spinning=False)
        self.stage1_info = _part_info(self.stage1_session, self.stage1_path, "stage1")
        self.view_info = _part_info(self.view_session, self.view_path, "view")
        a, b = self.stage1_info, self.view_info
        for key in ("splat_sap.config", "splat_sap.weights", "splat_sap.precision"):
            if a.metadata.get(key) != b.metadata.get(key):
                raise InferenceError(f"{self.stage1_path.name} and {self.view_path.name} come from different exports ({key} differs); re-export the model with `rig model export`")
        self.stage1_outputs = a.outputs
        missing = [n for n in a.outputs if n not in b.inputs]
        if missing or b.inputs[: len(a.outputs)] != a.outputs:
            raise InferenceError(f"{self.view_path}: its inputs {b.inputs} do not start with the stage-1 outputs {a.outputs}; re-export the model with `rig model export`")
        # What the caller feeds: the sources (stage 1's inputs and the view's other ones), then the target.
        self.source_inputs = a.inputs + tuple(n for n in b.inputs[len(a.outputs):] if n not in a.inputs and n not in TARGET_INPUTS)
        # The whole model's inputs, in its order (ModelInfo as NovelViewPipeline has it).
        whole_inputs = tuple(n for n in self.source_inputs if n not in DEPTH_INPUTS) + TARGET_INPUTS + tuple(n for n in self.source_inputs if n in DEPTH_INPUTS)
        self.info = ModelInfo(a.config, whole_inputs, b.outputs, a.precision, a.weights, dict(a.metadata))
        self.sizes = self.info.config.sizes
        self.prepare = InputPreparer(self.sizes, self.info.needs_depth)
        self.stage1_ms = 0.0
        self.view_ms = 0.0
        self.scale_every = max(1, int(scale_every))
        self.unscaled_session = None
        self._factor: float | None = None  # the scale search's factor on the last searched set
        self._since_search = 0
        self._scale_lock = threading.Lock()
        self.sets_searched = 0  # stage 1 runs with the search
        self.sets_scaled = 0  # stage 1 runs that reused the factor
        if self.scale_every > 1 and self.info.config.stage1.scale_search and self.info.config.stage1.affine == "learned":
            unscaled = part_path(self.path, UNSCALED_PART)
            if unscaled.is_file():  # exports before it lack the part: every set is searched
                self.unscaled_session = open_session(unscaled, providers, threads, spinning=False)
                info = _part_info(self.unscaled_session, unscaled, UNSCALED_PART)
                for key in ("splat_sap.config", "splat_sap.weights", "splat_sap.precision"):
                    if info.metadata.get(key) != a.metadata.get(key):
                        raise InferenceError(f"{unscaled.name} and {self.stage1_path.name} come from different exports ({key} differs); re-export the model with `rig model export`")
                if info.inputs != a.inputs or info.outputs != a.outputs:
                    raise InferenceError(f"{unscaled}: its inputs and outputs are not stage 1's; re-export the model with `rig model export`")

    @property
    def providers(self) -> list[str]:
        return self.view_session.get_providers()

    def source_feeds(self, left, right, left_cam: CameraModel, right_cam: CameraModel, left_depth=None, right_depth=None) -> dict[str, np.ndarray]:
        """The frame set's inputs (both parts' source inputs, no target) from frames and cameras."""
        try:
            # The preparer also makes a target's arrays; the left camera stands in and is dropped.
            feeds = self.prepare(left, right, left_cam, right_cam, left_cam, left_depth, right_depth)
        except InferenceError as exc:
            raise InferenceError(f"{self.path}: {exc}") from None
        for name in TARGET_INPUTS:
            feeds.pop(name, None)
        return feeds

    def target(self, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """(target_K, target_pose) of a viewpoint camera (any size: rendered as its pinhole at the output size)."""
        return intrinsics(camera, self.sizes.output), pose(camera)

    def stage1(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Run stage 1 on a frame set's inputs; returns the stage-1 tensors by name (the view's first inputs)."""
        missing = [n for n in self.stage1_info.inputs if n not in feeds]
        if missing:
            raise InferenceError(f"missing model inputs: {', '.join(missing)}")
        start = time.perf_counter()
        inputs = {n: feeds[n] for n in self.stage1_info.inputs}
        if self.unscaled_session is None:
            out = dict(zip(self.stage1_outputs, self.stage1_session.run(list(self.stage1_outputs), inputs)))
        else:
            out = self._stage1_reusing_factor(inputs)
        self.stage1_ms = (time.perf_counter() - start) * 1000.0
        return out

    def _stage1_reusing_factor(self, inputs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Stage 1 with the scale search on one set in `scale_every`, its factor reused between.

        The search is stage 1's last step: both point maps scaled by the factor k about their own
        camera centres (inference.model.scale_search.rescale). On a searched set the whole stage 1
        runs (its output is returned as it is), and so does the part without the search, whose
        left points times k are the searched ones: k is their least-squares ratio (exact but for
        float rounding, 5e-7 m). On the sets between, only the part without the search runs and
        its points are scaled by that k here, as the model scales them."""
        names = list(self.stage1_outputs)
        with self._scale_lock:
            search = self._factor is None or self._since_search >= self.scale_every
            self._since_search = 1 if search else self._since_search + 1
        unscaled = dict(zip(names, self.unscaled_session.run(names, inputs)))
        left = unscaled["stage1_points_left"].astype(np.float64)
        if search:
            out = dict(zip(names, self.stage1_session.run(names, inputs)))
            scaled = out["stage1_points_left"].astype(np.float64)
            k = float((scaled * left).sum() / max(float((left * left).sum()), 1e-30))
            with self._scale_lock:
                self._factor = k
                self.sets_searched += 1
            return out
        k = self._factor
        # The right camera's centre in the left camera's frame (poses are world-to-camera).
        right_to_left = inputs["left_pose"][0].astype(np.float64) @ np.linalg.inv(inputs["right_pose"][0].astype(np.float64))
        centre = right_to_left[:3, 3].reshape(1, 3, 1, 1)
        right = unscaled["stage1_points_right"].astype(np.float64)
        unscaled["stage1_points_left"] = (left * k).astype(np.float32)
        unscaled["stage1_points_right"] = (centre + (right - centre) * k).astype(np.float32)
        with self._scale_lock:
            self.sets_scaled += 1
        return unscaled

    def scale_status(self) -> dict | None:
        """How stage 1 finds the scale factor (None: the model has no scale search)."""
        cfg = self.info.config.stage1
        if not (cfg.scale_search and cfg.affine == "learned"):
            return None
        every = self.scale_every if self.unscaled_session is not None else 1
        return {"search_every": every, "factor": None if self._factor is None else round(self._factor, 5),
                "sets_searched": self.sets_searched if self.unscaled_session is not None else None,
                "sets_reusing": self.sets_scaled}

    def view(self, stage1_out: dict[str, np.ndarray], feeds: dict[str, np.ndarray], target_K: np.ndarray, target_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The view at (target_K (1, 3, 3) at the output size, target_pose (1, 4, 4) world-to-camera)
        from stage 1's tensors and the same frame set's inputs; returns (image (1,3,H,W), depth (1,1,H,W))."""
        return self._view(stage1_out, feeds, target_K, target_pose)[:2]

    def render(self, stage1_out: dict[str, np.ndarray], feeds: dict[str, np.ndarray], target_cam: CameraModel) -> NovelView:
        """The view of a target camera as a NovelView ((H, W, 3) image, (H, W) depth, its ms)."""
        image, depth, ms = self._view(stage1_out, feeds, *self.target(target_cam))
        return NovelView(np.ascontiguousarray(image[0].transpose(1, 2, 0)), depth[0, 0], ms)

    def _view(self, stage1_out, feeds, target_K, target_pose) -> tuple[np.ndarray, np.ndarray, float]:
        target = {"target_K": target_matrix(target_K, 3, "target_K"), "target_pose": target_matrix(target_pose, 4, "target_pose")}
        missing = [n for n in self.stage1_outputs if n not in stage1_out] + [n for n in self.view_info.inputs if n not in stage1_out and n not in target and n not in feeds]
        if missing:
            raise InferenceError(f"missing model inputs: {', '.join(missing)}")
        merged = {**feeds, **target, **stage1_out}
        start = time.perf_counter()
        image, depth = self.view_session.run(list(self.view_info.outputs), {n: merged[n] for n in self.view_info.inputs})
        ms = (time.perf_counter() - start) * 1000.0
        self.view_ms = ms
        return image, depth, ms

    def describe(self) -> dict:
        return {
            "model": str(self.path),
            "parts": {"stage1": str(self.stage1_path), "view": str(self.view_path)},
            "providers": self.providers,
            "precision": self.info.precision,
            "weights": self.info.weights,
            "backbone": self.info.config.backbone.kind,
            "sizes": self.sizes.describe(),
        }


def _part_info(session, path: Path, part: str) -> ModelInfo:
    info = read_model_info(session, path)
    found = info.metadata.get("splat_sap.part")
    if found != part:
        raise InferenceError(f"{path}: not the {part} part of a Splat-SAP model (its splat_sap.part is {found!r}); re-export the model with `rig model export`")
    names = tuple(i.name for i in session.get_inputs())
    if names != info.inputs:
        raise InferenceError(f"{path}: inputs {names} do not match its metadata {info.inputs}")
    return info


def target_matrix(value, n: int, name: str) -> np.ndarray:
    """A target camera's K (n = 3) or pose (n = 4) as the model's (1, n, n) float32 input."""
    a = np.asarray(value, dtype=np.float32)
    if a.shape == (n, n):
        a = a[None]
    if a.shape != (1, n, n):
        raise InferenceError(f"{name} must be a {n}x{n} matrix (or 1x{n}x{n}), got shape {a.shape}")
    return np.ascontiguousarray(a)
