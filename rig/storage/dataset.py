"""Read recorded sequences for training and evaluation.

    seq = Sequence("recordings/take-001")
    for sample in seq.samples(cameras=["left", "right", "sup2"], size=(512, 288)):
        sample.images["left"]      # HxWx3 uint8 RGB at the chosen size
        sample.cameras["left"]     # CameraModel with intrinsics scaled to that size
        sample.depth["sup2"]       # float32 metres, rendered from the scene (simulator takes only; None otherwise)

Only sets in which every chosen camera has a frame are yielded. Images are resized with area
interpolation when shrinking; the intrinsics follow the pixel-centre convention of
`CameraModel.scaled`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional
from typing import Sequence as Seq

import cv2
import numpy as np

from calibration.camera import CameraModel, RigCalibration
from rig.storage.index import scan_index
from rig.storage.layout import CALIBRATION_COPY, SequenceError, SequenceMeta
from rig.storage.netpbm import NetpbmError, read_netpbm


@dataclass
class Sample:
    set: int
    trigger: Optional[int]
    images: dict[str, np.ndarray]
    cameras: dict[str, CameraModel]
    depth: dict[str, Optional[np.ndarray]] = field(default_factory=dict)
    host_ts_ns: dict[str, int] = field(default_factory=dict)


class Sequence:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.meta = SequenceMeta.load(self.root)
        self.rows = scan_index(self.root).rows
        cal = self.root / CALIBRATION_COPY
        self.calibration: Optional[RigCalibration] = RigCalibration.load(cal) if cal.exists() else None
        sim = self.meta.extra.get("simulator")
        # simulator takes: the exact cameras and the scene, to render ground-truth depth on demand
        self.ground_truth: Optional[RigCalibration] = RigCalibration.from_dict({"version": 1, "cameras": sim["cameras"]}) if sim else None
        self._truth = None

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.meta.cameras]

    def __len__(self) -> int:
        return len(self.rows)

    def camera_model(self, name: str) -> CameraModel:
        if self.calibration is None and self.ground_truth is not None:
            return self.ground_truth[name]  # an uncalibrated simulator take: its exact cameras
        if self.calibration is None:
            raise SequenceError(f"{self.root}: no calibration.json; calibrate the rig (`rig calibrate run`) before training")
        if name not in self.calibration:
            raise SequenceError(f"{self.root}: calibration has no camera '{name}'")
        return self.calibration[name]

    def has_ground_truth(self) -> bool:
        return self.ground_truth is not None

    def samples(self, cameras: Optional[Seq[str]] = None, size: Optional[tuple[int, int]] = None,
                with_depth: bool = True) -> Iterator[Sample]:
        names = list(cameras) if cameras else self.camera_names
        for n in names:
            self.meta.camera(n)  # clear error for a camera the sequence does not have
        models = {n: self.camera_model(n) for n in names}
        if size is not None:
            models = {n: m.scaled(*size) for n, m in models.items()}
        for row in self.rows:
            recs = row["frames"]
            if any(recs.get(n) is None for n in names):
                continue
            images, depth, ts = {}, {}, {}
            for n in names:
                rec = recs[n]
                path = self.root / rec["file"]
                try:
                    stored = read_netpbm(path)
                except FileNotFoundError:
                    raise SequenceError(f"{path}: missing; `rig record validate {self.root}` lists every damaged frame") from None
                except NetpbmError as exc:
                    raise SequenceError(f"{exc}; `rig record validate {self.root}` lists every damaged frame") from None
                img = self.meta.camera(n).decoded(stored)
                if img.ndim == 2:
                    img = np.repeat(img[:, :, None], 3, axis=2)
                if img.dtype == np.uint16:
                    img = (img >> 8).astype(np.uint8)
                if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
                    img = _resize(img, size)
                images[n] = img
                ts[n] = rec["host_ts_ns"]
                depth[n] = self.depth(n, rec.get("sim_time_s"), size) if with_depth else None
            yield Sample(row["set"], row.get("trigger"), images, models, depth, ts)

    def depth(self, cam: str, sim_time_s: Optional[float], size: Optional[tuple[int, int]] = None) -> Optional[np.ndarray]:
        """Ground-truth depth (metres, 0 = nothing) of a simulator frame, rendered at the chosen size."""
        if self.ground_truth is None or sim_time_s is None:
            return None
        from rig.cameras.sim import GroundTruth

        if self._truth is None:
            self._truth = GroundTruth(self.meta.extra["simulator"]["scene"])
        model = self.ground_truth[cam]
        if size is not None:
            model = model.scaled(*size)
        return self._truth.depth(model, sim_time_s)


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    shrink = size[0] < img.shape[1]
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
