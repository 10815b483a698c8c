"""Frame sets to training tensors.

The trainer reads any `FrameSource`: a numbered collection of synchronised frame sets, each the raw
frames of the rig's cameras (any size, with their lens distortion) and their calibrated
`CameraModel`s. `rig train` serves recorded and simulated sequences this way (the reader lives in
`rig.storage.dataset`, a layer above this package). Frames are mapped onto each camera's undistorted
pinhole image at the size a stage needs, with the runtime's precomputed tables.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Optional, Protocol

import numpy as np
import torch

from calibration.camera import CameraModel
from inference.runtime.preprocess import Resampler, pinhole


@dataclass
class FrameSet:
    images: dict[str, np.ndarray]  # HxWx3 uint8 RGB (or HxW grey) as recorded
    cameras: dict[str, CameraModel]
    depth: dict[str, Optional[np.ndarray]] = field(default_factory=dict)  # ground truth, evaluation only
    masks: dict[str, Optional[np.ndarray]] = field(default_factory=dict)  # person masks, evaluation only
    key: str = ""  # where it came from (sequence and set), for logs


class FrameSource(Protocol):
    left: str
    right: str
    supervision: list[str]

    def __len__(self) -> int: ...

    def frame_set(self, index: int, with_truth: bool = False) -> FrameSet: ...


@dataclass
class Views:
    """N cameras of one frame set at one size: images (N, 3, H, W) in [0, 1], K (N, 3, 3), poses (N, 4, 4)."""

    images: torch.Tensor
    K: torch.Tensor
    poses: torch.Tensor

    def to(self, device, non_blocking: bool = False) -> "Views":
        return Views(*(t.to(device, non_blocking=non_blocking) for t in (self.images, self.K, self.poses)))

    def pin_memory(self) -> "Views":
        """Page-locked copies (DataLoader(pin_memory=True) calls this): a CUDA copy from them can
        overlap the step under way (`to(device, non_blocking=True)`)."""
        return Views(self.images.pin_memory(), self.K.pin_memory(), self.poses.pin_memory())

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.images, self.K, self.poses))


class Preprocessor:
    """Resamples frames onto pinhole images; tables are cached per camera and size."""

    def __init__(self, max_tables: int = 256):
        self._tables: dict[tuple, Resampler] = {}
        self._max = max_tables

    def _resampler(self, camera: CameraModel, size: tuple[int, int]) -> Resampler:
        key = (camera.name, camera.width, camera.height, camera.K.tobytes(), np.asarray(camera.dist).tobytes(), camera.model, tuple(size))
        r = self._tables.get(key)
        if r is None:
            if len(self._tables) >= self._max:
                self._tables.pop(next(iter(self._tables)))
            r = self._tables[key] = Resampler(camera, size)
        return r

    def image(self, frame: np.ndarray, camera: CameraModel, size: tuple[int, int]) -> np.ndarray:
        if frame.ndim == 2:
            frame = np.repeat(frame[:, :, None], 3, axis=2)
        if frame.dtype == np.uint16:
            frame = (frame >> 8).astype(np.uint8)
        return self._resampler(camera, size).image(frame)

    def depth(self, depth: np.ndarray, camera: CameraModel, size: tuple[int, int]) -> np.ndarray:
        return self._resampler(camera, size).depth(depth)

    def views(self, fs: FrameSet, names: list[str], size: tuple[int, int]) -> Views:
        imgs, ks, poses = [], [], []
        for n in names:
            cam = fs.cameras[n]
            img = self.image(fs.images[n], cam, size)
            imgs.append(torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1))
            ks.append(torch.from_numpy(pinhole(cam, size).K.astype(np.float32)))
            poses.append(torch.from_numpy(cam.extrinsic.astype(np.float32)))
        return Views(torch.stack(imgs), torch.stack(ks), torch.stack(poses))


def stack_views(items: list[Views], device=None) -> Views:
    """Frame sets (each N cameras) to one batch: (B*N, ...) grouped by frame set."""
    return Views(*(torch.cat([getattr(v, k) for v in items]).to(device) for k in ("images", "K", "poses")))


class CachedViews:
    """A FrameSource's views, each (frame set, camera, size) decoded and resampled once per run.

    Reading a frame set decodes every camera's image file (PNG/JPEG) and resampling maps it onto the
    pinhole image; a run draws each set many times, so both are kept here, least recently used first
    out once `max_bytes` is reached. A frame set is read only when a view it holds is missing. With
    DataLoader workers each worker process keeps its own cache."""

    def __init__(self, source: FrameSource, pre: Preprocessor, max_bytes: int):
        self.source = source
        self.pre = pre
        self.max_bytes = max(0, int(max_bytes))
        self._views: "OrderedDict[tuple, Views]" = OrderedDict()
        self._bytes = 0
        self.reads = 0  # frame sets read (decoded) so far: what the cache saves is visible in benchmarks

    def views(self, index: int, names: list[str], size: tuple[int, int]) -> Views:
        keys = [(index, n, tuple(size)) for n in names]
        missing = [n for n, k in zip(names, keys) if k not in self._views]
        fresh: dict[str, Views] = {}
        if missing:
            fs = self.source.frame_set(index)
            self.reads += 1
            fresh = {n: self.pre.views(fs, [n], size) for n in missing}
            for n, v in fresh.items():
                self._store((index, n, tuple(size)), v)
        parts = []
        for n, k in zip(names, keys):
            v = fresh.get(n)
            if v is None:
                v = self._views[k]
                self._views.move_to_end(k)
            parts.append(v)
        return stack_views(parts)

    def _store(self, key: tuple, v: Views) -> None:
        if v.nbytes > self.max_bytes:
            return
        self._views[key] = v
        self._bytes += v.nbytes
        while self._bytes > self.max_bytes:
            _, old = self._views.popitem(last=False)
            self._bytes -= old.nbytes
