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

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional
from typing import Sequence as Seq

import cv2
import numpy as np

from calibration.camera import CameraModel, RigCalibration
from rig.cameras.pixels import rgb8
from rig.storage.index import scan_index
from rig.storage.layout import CALIBRATION_COPY, ImageError, SequenceError, SequenceMeta
from rig.truth import renderer, truth_cameras


@dataclass
class Sample:
    set: int
    trigger: Optional[int]
    images: dict[str, np.ndarray]
    cameras: dict[str, CameraModel]
    depth: dict[str, Optional[np.ndarray]] = field(default_factory=dict)
    host_ts_ns: dict[str, int] = field(default_factory=dict)
    masks: dict[str, Optional[np.ndarray]] = field(default_factory=dict)
    key: str = ""


class Sequence:
    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.meta = SequenceMeta.load(self.root)
        self.rows = scan_index(self.root).rows
        cal = self.root / CALIBRATION_COPY
        self.calibration: Optional[RigCalibration] = RigCalibration.load(cal) if cal.exists() else None
        exact = truth_cameras(self.meta.extra)
        # simulator takes: the exact cameras and the scene, to render ground-truth depth on demand
        self.ground_truth: Optional[RigCalibration] = RigCalibration.from_dict({"version": 1, "cameras": exact}) if exact else None
        self._truth = None

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.meta.cameras]

    def sources(self) -> tuple[str, str]:
        """The cameras with roles left and right (the model's sources)."""
        roles = {c.role: c.name for c in self.meta.cameras if c.role in ("left", "right")}
        if "left" not in roles or "right" not in roles:
            raise SequenceError(f"{self.root}: the sequence has no camera with role left and one with role right (the model's sources)")
        return roles["left"], roles["right"]

    @property
    def supervision(self) -> list[str]:
        """The cameras with role supervision, in the take's order."""
        return [c.name for c in self.meta.cameras if c.role == "supervision"]

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
            yield self._read(row, names, models, size, with_depth)

    def complete_sets(self, cameras: Seq[str]) -> list[int]:
        """Row positions of the sets in which every one of `cameras` has a frame."""
        return [i for i, row in enumerate(self.rows) if all(row["frames"].get(n) is not None for n in cameras)]

    def sample(self, position: int, cameras: Seq[str], size: Optional[tuple[int, int]] = None, with_depth: bool = False) -> Sample:
        """The set at row `position` (see `complete_sets`), random access."""
        names = list(cameras)
        models = {n: self.camera_model(n) for n in names}
        if size is not None:
            models = {n: m.scaled(*size) for n, m in models.items()}
        return self._read(self.rows[position], names, models, size, with_depth)

    def _read(self, row: dict, names: list[str], models: dict, size, with_depth: bool) -> Sample:
        recs = row["frames"]
        images, depth, masks, ts = {}, {}, {}, {}
        for n in names:
            rec = recs[n]
            path = self.root / rec["file"]
            entry = self.meta.camera(n)
            try:
                stored = entry.read(path)  # raw netpbm or PNG, as the take recorded this camera
            except FileNotFoundError:
                raise SequenceError(f"{path}: missing; `rig record validate {self.root}` lists every damaged frame") from None
            except ImageError as exc:
                raise SequenceError(f"{exc}; `rig record validate {self.root}` lists every damaged frame") from None
            img = rgb8(entry.decoded(stored))
            if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
                img = _resize(img, size)
            images[n] = img
            ts[n] = rec["host_ts_ns"]
            depth[n], masks[n] = self.truth(n, rec.get("sim_time_s"), size) if with_depth else (None, None)
        return Sample(row["set"], row.get("trigger"), images, models, depth, ts, masks)

    def depth(self, cam: str, sim_time_s: Optional[float], size: Optional[tuple[int, int]] = None) -> Optional[np.ndarray]:
        """Ground-truth depth (metres, 0 = nothing) of a simulator frame, rendered at the chosen size."""
        return self.truth(cam, sim_time_s, size)[0]

    def release_truth(self) -> None:
        """Let go of the scene the truth is rendered from (made again on the next `truth`)."""
        self._truth = None

    def truth(self, cam: str, sim_time_s: Optional[float], size: Optional[tuple[int, int]] = None):
        """Ground-truth depth and person mask of a simulator frame at the chosen size ((None, None) for a recorded take)."""
        if self.ground_truth is None or sim_time_s is None:
            return None, None
        if self._truth is None:
            self._truth = renderer(self.meta.extra)
        model = self.ground_truth[cam]
        if size is not None:
            model = model.scaled(*size)
        return self._truth.depth_and_mask(model, sim_time_s)


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    shrink = size[0] < img.shape[1]
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


class TrainingSet:
    """Frame sets of one or more sequences for `rig train` and `rig model eval` (the FrameSource of
    inference.train.data): the cameras with roles left and right are the sources, every camera with
    role supervision a target. Frames are served as recorded (full size, with lens distortion) with
    their calibrated cameras; only sets in which every camera has a frame are used."""

    def __init__(self, roots: Seq[str | Path]):
        if not roots:
            raise SequenceError("no sequence given")
        self.sequences = [Sequence(r) for r in roots]
        first = self.sequences[0]
        self.left, self.right = first.sources()
        self.supervision = first.supervision
        if not self.supervision:
            raise SequenceError(f"{first.root}: the sequence has no supervision camera (training renders the sources into them)")
        names = [self.left, self.right] + self.supervision
        self.positions: list[tuple[int, int]] = []
        for k, seq in enumerate(self.sequences):
            have = {c.name: c.role for c in seq.meta.cameras}
            if any(have.get(n) != r for n, r in zip(names, ["left", "right"] + ["supervision"] * len(self.supervision))):
                raise SequenceError(f"{seq.root}: its cameras differ from {first.root}'s ({', '.join(names)} with the same roles)")
            for n in names:
                seq.camera_model(n)  # a clear error now for a sequence without calibration
            self.positions += [(k, p) for p in seq.complete_sets(names)]
        self.names = names
        self._truth_order: list[int] = []  # the takes whose scenes are kept, the one read last at the end

    @property
    def roots(self) -> list[str]:
        """Each take's folder."""
        return [str(s.root) for s in self.sequences]

    def without_ground_truth(self) -> list[str]:
        """The folders of the takes that hold no ground truth (the supervised recipe needs it)."""
        return [str(s.root) for s in self.sequences if not s.has_ground_truth()]

    def __len__(self) -> int:
        return len(self.positions)

    # A simulated take renders its truth from its scene, which holds about 90 MB (a 640x360 take): kept
    # for every take of a large data set it filled the host (17 GB for 192 takes in one training run).
    # The scenes of the takes read last are kept; the others are let go, and made again if needed.
    TRUTH_SCENES_KEPT = 4

    def frame_set(self, index: int, with_truth: bool = False) -> Sample:
        k, p = self.positions[index]
        s = self.sequences[k].sample(p, self.names, with_depth=with_truth)
        s.key = f"{self.sequences[k].root.name}#{s.set}"
        if with_truth:
            self._keep_truth(k)
        return s

    def _keep_truth(self, k: int) -> None:
        order = self._truth_order
        if k in order:
            order.remove(k)
        order.append(k)
        while len(order) > self.TRUTH_SCENES_KEPT:
            self.sequences[order.pop(0)].release_truth()


def expand_sequences(paths: list[Path]) -> list[Path]:
    """A folder with dataset.json (rig sim dataset) stands for its takes. A file given for a take is
    SequenceError (one line), not the NotADirectoryError of reading into it later."""
    out = []
    for p in paths:
        if p.exists() and not p.is_dir():
            raise SequenceError(f"{p}: is a file, not a sequence folder (give the folder rig record or rig sim dataset wrote)")
        listing = p / "dataset.json"
        if listing.is_file():
            try:
                takes = json.loads(listing.read_text())["takes"]
            except (OSError, ValueError, KeyError, TypeError):
                raise SequenceError(f"{listing}: not a readable data-set listing") from None
            out += [p / t for t in takes]
        else:
            out.append(p)
    return out
