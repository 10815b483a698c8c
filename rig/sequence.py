"""The recorded sequence folder: layout, image files, index rows, validation and repair.

Layout (documented for users in docs/sequence-format.md):

    SEQ/sequence.json        what was recorded: cameras, sizes, pixel formats, rate, start time
    SEQ/rig.toml             copy of the rig configuration
    SEQ/calibration.json     copy of the rig calibration (when the rig has one)
    SEQ/index.jsonl          one row per FrameSet, appended and flushed as sets land
    SEQ/frames/CAM/NNNNNNNN.ppm|pgm   one binary netpbm image per frame (P6 RGB, P5 mono 8/16-bit)

An index row is written only after every image it names is completely written, so the index never
points at a file that is not there (up to the last sync on a power cut; `validate` checks, `repair`
truncates).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np

from rig.errors import RigError

FORMAT_VERSION = 1
INDEX = "index.jsonl"
META = "sequence.json"
FRAMES = "frames"


class SequenceError(RigError):
    exit_code = 2


# ---- images --------------------------------------------------------------------------------------

def image_suffix(image_ndim: int) -> str:
    return ".ppm" if image_ndim == 3 else ".pgm"


def netpbm_header(image: np.ndarray) -> bytes:
    h, w = image.shape[:2]
    magic = b"P6" if image.ndim == 3 else b"P5"
    maxval = 65535 if image.dtype == np.uint16 else 255
    return b"%s\n%d %d\n%d\n" % (magic, w, h, maxval)


def encode_netpbm(image: np.ndarray) -> tuple[bytes, memoryview]:
    """Header and pixel bytes of a binary PPM/PGM (16-bit samples are big-endian, as netpbm says)."""
    if image.dtype == np.uint16:
        data = image.astype(">u2", copy=False)
    elif image.dtype == np.uint8:
        data = image
    else:
        raise ValueError(f"cannot store {image.dtype} images")
    return netpbm_header(image), memoryview(np.ascontiguousarray(data)).cast("B")


def expected_size(width: int, height: int, channels: int, bytes_per_sample: int) -> int:
    header = len(b"%s\n%d %d\n%d\n" % (b"P6", width, height, 65535 if bytes_per_sample == 2 else 255))
    return header + width * height * channels * bytes_per_sample


def read_netpbm(path: Path) -> np.ndarray:
    """Read a binary PPM/PGM written by the recorder (RGB order, uint8 or uint16)."""
    with open(path, "rb") as f:
        data = f.read()
    parts = data.split(b"\n", 3)
    if len(parts) < 4 or parts[0] not in (b"P5", b"P6"):
        raise SequenceError(f"{path}: not a binary PPM/PGM image")
    w, h = (int(x) for x in parts[1].split())
    maxval = int(parts[2])
    channels = 3 if parts[0] == b"P6" else 1
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    need = w * h * channels * dtype.itemsize
    if len(parts[3]) < need:
        raise SequenceError(f"{path}: torn image ({len(parts[3])} of {need} bytes)")
    arr = np.frombuffer(parts[3], dtype=dtype, count=w * h * channels)
    arr = arr.reshape((h, w, 3) if channels == 3 else (h, w))
    return arr.astype(np.uint16) if maxval > 255 else arr


# ---- metadata -----------------------------------------------------------------------------------

@dataclass
class CameraEntry:
    name: str
    role: str
    width: int
    height: int
    pixel_format: str  # what the sensor delivered
    channels: int  # as stored: 3 (RGB) or 1
    bytes_per_sample: int

    @property
    def frame_bytes(self) -> int:
        return expected_size(self.width, self.height, self.channels, self.bytes_per_sample)

    @property
    def suffix(self) -> str:
        return ".ppm" if self.channels == 3 else ".pgm"

    @property
    def bayer(self) -> bool:
        return self.pixel_format.startswith("Bayer")

    def stored(self, image: np.ndarray) -> np.ndarray:
        """What is written for a Frame image of this camera."""
        if self.bayer:
            from rig.cameras.pixels import mosaic

            return mosaic(image, self.pixel_format)
        return image

    def decoded(self, stored: np.ndarray) -> np.ndarray:
        """The Frame image back from what was stored."""
        if self.bayer:
            from rig.cameras.pixels import demosaic

            return demosaic(stored, self.pixel_format)
        return stored


def stored_layout(pixel_format: str) -> tuple[int, int]:
    """(channels, bytes per sample) of the stored image for a sensor pixel format.

    Bayer sensors are stored as their mosaic (one sample per pixel, a third of RGB's bytes): the
    backend's demosaic keeps every sample, so re-mosaicking the Frame recovers the sensor data
    exactly and the reader's demosaic gives back the very same RGB image.
    """
    if pixel_format in ("Mono8", "BayerRG8", "BayerGR8", "BayerGB8", "BayerBG8"):
        return 1, 1
    if pixel_format == "Mono16":
        return 1, 2
    return 3, 1  # RGB8


@dataclass
class SequenceMeta:
    cameras: list[CameraEntry]
    rig: str = ""
    rate_hz: Optional[float] = None
    created: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = {"version": FORMAT_VERSION, "rig": self.rig, "rate_hz": self.rate_hz, "created": self.created,
             "cameras": [c.__dict__ for c in self.cameras]}
        d.update(self.extra)
        return d

    @classmethod
    def load(cls, root: Path) -> "SequenceMeta":
        path = root / META
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise SequenceError(f"{root}: not a sequence ({META} missing)") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise SequenceError(f"{path}: corrupt ({exc})") from None
        if d.get("version") != FORMAT_VERSION:
            raise SequenceError(f"{path}: unsupported sequence version {d.get('version')!r}")
        try:
            cams = [CameraEntry(**c) for c in d["cameras"]]
        except (KeyError, TypeError) as exc:
            raise SequenceError(f"{path}: malformed camera list ({exc})") from None
        extra = {k: v for k, v in d.items() if k not in ("version", "rig", "rate_hz", "created", "cameras")}
        return cls(cams, d.get("rig", ""), d.get("rate_hz"), d.get("created", ""), extra)

    def camera(self, name: str) -> CameraEntry:
        for c in self.cameras:
            if c.name == name:
                return c
        raise SequenceError(f"no camera '{name}' in this sequence (have: {', '.join(c.name for c in self.cameras)})")


def write_json_atomic(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# ---- index --------------------------------------------------------------------------------------

@dataclass
class IndexScan:
    rows: list[dict]
    good_bytes: int  # offset after the last complete, parseable row
    torn_tail: bool  # trailing bytes that are not a complete row
    corrupt_lines: list[int]  # 1-based numbers of unparseable lines before the tail


def scan_index(root: Path) -> IndexScan:
    path = root / INDEX
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SequenceError(f"{root}: not a sequence ({INDEX} missing)") from None
    rows: list[dict] = []
    corrupt: list[int] = []
    pos = 0
    good = 0
    line_no = 0
    torn = False
    while pos < len(data):
        nl = data.find(b"\n", pos)
        line_no += 1
        if nl < 0:  # no newline: the recorder died mid-row
            torn = True
            break
        line = data[pos:nl]
        pos = nl + 1
        try:
            row = json.loads(line)
            if not isinstance(row, dict) or "set" not in row or "frames" not in row:
                raise ValueError("not an index row")
        except ValueError:
            corrupt.append(line_no)
            continue
        if corrupt:  # rows after a corrupt one are kept but the damage is reported
            rows.append(row)
        else:
            rows.append(row)
            good = pos
    if corrupt and corrupt[-1] == line_no and not torn:
        # the last line is damaged: treat it as a torn tail (power cut mid-write)
        corrupt.pop()
        torn = True
    return IndexScan(rows, good if not corrupt else good, torn, corrupt)


def iter_frame_files(root: Path, row: dict) -> Iterator[tuple[str, Optional[dict]]]:
    for cam, rec in row["frames"].items():
        yield cam, rec


# ---- validation and repair ------------------------------------------------------------------------

@dataclass
class Validation:
    root: Path
    sets: int = 0
    complete_sets: int = 0
    frames: dict[str, int] = field(default_factory=dict)
    missing: dict[str, int] = field(default_factory=dict)
    gaps: int = 0  # trigger indices skipped between consecutive sets
    skew_us: dict[str, float] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    torn_tail: bool = False
    readable_sets: int = 0
    calibrated: bool = False
    duration_s: float = 0.0

    @property
    def readable(self) -> bool:
        return not self.errors

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.root),
            "readable": self.readable,
            "sets": self.sets,
            "complete_sets": self.complete_sets,
            "incomplete_sets": self.sets - self.complete_sets,
            "readable_sets": self.readable_sets,
            "frames": self.frames,
            "missing": self.missing,
            "gaps": self.gaps,
            "skew_us": self.skew_us,
            "duration_s": round(self.duration_s, 3),
            "torn_tail": self.torn_tail,
            "calibrated": self.calibrated,
            "errors": self.errors,
            "warnings": self.warnings,
        }


def validate(root: str | Path, check_pixels: bool = False) -> Validation:
    """Check every indexed frame is present and whole; count sets, frames, gaps, skew."""
    root = Path(root)
    v = Validation(root)
    meta = SequenceMeta.load(root)
    scan = scan_index(root)
    v.torn_tail = scan.torn_tail
    if scan.torn_tail:
        v.warnings.append(f"{INDEX}: torn last row (recording was interrupted); `rig record repair` removes it")
    for ln in scan.corrupt_lines:
        v.errors.append(f"{INDEX}: line {ln} is corrupt")
    v.frames = {c.name: 0 for c in meta.cameras}
    v.missing = {c.name: 0 for c in meta.cameras}
    entries = {c.name: c for c in meta.cameras}
    skews = []
    last_trigger = None
    first_ts = last_ts = None
    first_bad_set = None
    for row in scan.rows:
        v.sets += 1
        complete = True
        ts = []
        row_ok = True
        for cam, rec in row["frames"].items():
            if cam not in entries:
                v.errors.append(f"set {row['set']}: unknown camera '{cam}'")
                row_ok = False
                continue
            if rec is None:
                complete = False
                v.missing[cam] += 1
                continue
            path = root / rec["file"]
            try:
                size = path.stat().st_size
            except FileNotFoundError:
                v.errors.append(f"set {row['set']}: {rec['file']} is missing")
                row_ok = False
                continue
            if size != entries[cam].frame_bytes:
                v.errors.append(f"set {row['set']}: {rec['file']} is torn ({size} of {entries[cam].frame_bytes} bytes)")
                row_ok = False
                continue
            if check_pixels:
                try:
                    read_netpbm(path)
                except SequenceError as exc:
                    v.errors.append(str(exc))
                    row_ok = False
                    continue
            v.frames[cam] += 1
            ts.append(rec["host_ts_ns"])
        if not row_ok and first_bad_set is None:
            first_bad_set = v.sets - 1
        if complete:
            v.complete_sets += 1
        if len(ts) > 1:
            skews.append((max(ts) - min(ts)) / 1e3)
        if ts:
            first_ts = min(ts) if first_ts is None else first_ts
            last_ts = max(ts)
        trig = row.get("trigger")
        if trig is not None and last_trigger is not None and trig > last_trigger + 1:
            v.gaps += trig - last_trigger - 1
        if trig is not None:
            last_trigger = trig
    v.readable_sets = v.sets if first_bad_set is None else first_bad_set
    if skews:
        s = np.array(skews)
        v.skew_us = {"p50": float(np.percentile(s, 50)), "p99": float(np.percentile(s, 99)), "max": float(s.max())}
    if first_ts is not None and last_ts is not None:
        v.duration_s = (last_ts - first_ts) / 1e9
    cal = root / "calibration.json"
    if cal.exists():
        from calibration.camera import CalibrationError, RigCalibration

        try:
            RigCalibration.load(cal)
            v.calibrated = True
        except CalibrationError as exc:
            v.errors.append(str(exc))
    if v.sets == 0:
        v.warnings.append("no frame sets recorded")
    return v


def repair(root: str | Path) -> dict[str, Any]:
    """Truncate the index after the last set whose row and images are whole. Images are kept."""
    root = Path(root)
    meta = SequenceMeta.load(root)
    entries = {c.name: c for c in meta.cameras}
    data = (root / INDEX).read_bytes()
    keep = 0
    kept_rows = 0
    pos = 0
    while pos < len(data):
        nl = data.find(b"\n", pos)
        if nl < 0:
            break
        try:
            row = json.loads(data[pos:nl])
            ok = isinstance(row, dict) and all(
                rec is None
                or (cam in entries and (root / rec["file"]).is_file() and (root / rec["file"]).stat().st_size == entries[cam].frame_bytes)
                for cam, rec in row["frames"].items()
            )
        except (ValueError, KeyError, TypeError):
            ok = False
        if not ok:
            break
        pos = nl + 1
        keep = pos
        kept_rows += 1
    removed = len(data) - keep
    if removed:
        with open(root / INDEX, "r+b") as f:
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    return {"path": str(root), "kept_sets": kept_rows, "removed_bytes": removed}
