"""Simulator takes for training: whole sequences rendered offline, as fast as the renderer goes.

    summary = write_dataset("data/sim", takes=8, seconds=2.0, seed=0)   # data/sim/take-000 ... take-007
    summary = write_take("data/one", seed=1234, seconds=1.0, fps=30.0, size=(640, 360))

Each take is a folder in the sequence format of docs/sequence-format.md, the very layout that
`rig record` writes (rig/storage/recorder.py), so `rig.storage.dataset.Sequence` reads a rendered
take exactly like a recorded one:

    TAKE/sequence.json        cameras (left, sup1 .. sup4, right; roles left | supervision | right),
                              rate, and the `simulator` entry: the scene options and the exact
                              cameras (ground-truth depth renders from them on demand), plus `take`,
                              everything drawn from the take's seed (simulator.variety)
    TAKE/index.jsonl          one row per set; every frame record has `sim_time_s`
    TAKE/frames/CAM/NNNNNNNN.ppm

A take goes only into a new or empty folder (as `rig record`). Uncompressed, as recordings are: a
640x360 take at 30 fps is about 124 MB per second (six cameras); rendering it takes about 7 s of one
CPU core per second of take, plus about 2 s to build the scene.

The simulator sits below `rig` (tests/test_layering.py), so this module writes the format itself;
the tests read every take back through the rig's reader.

Seeds. Take i of a data set with seed K has the seed K * 1000 + i (i < 1000), which is also its
scene seed. Data sets with different K therefore never share a take: held-out takes for evaluation
come from another K (e.g. training with --seed 0, evaluation with --seed 1).

Frames. Set n shows scene time start_s + n / fps (start_s drawn from the seed), rendered for every
camera at that instant (a hardware-triggered rig: no skew between cameras). Timestamps are those
of an ideal rig: host and device time n / fps from the take's start, frame ids from 1, no drops.
With `noise=True` every image goes through the sensor model (simulator.sensor: shot and read
noise at gain 0 dB, nominal exposure, no motion blur), seeded per camera and frame.
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from common.files import atomic_write_json
from simulator.errors import SimulatorError
from simulator.render import render
from simulator.scene import Scene
from simulator.sensor import NOMINAL_EXPOSURE_S, SensorModel
from simulator.variety import TakeVariety, draw_variety

FORMAT_VERSION = 1  # docs/sequence-format.md
META = "sequence.json"
INDEX = "index.jsonl"
FRAMES = "frames"
DATASET = "dataset.json"
TAKES_PER_SEED = 1000  # take i of data set seed K has seed K * TAKES_PER_SEED + i
MAX_SEED = (2**31 - 1) // TAKES_PER_SEED - 1  # every take seed stays a valid scene seed

Progress = Callable[[int, int], None]  # (frames done, frames in all)


def take_seed(dataset_seed: int, index: int) -> int:
    """The seed of take `index` of the data set with seed `dataset_seed`."""
    if not 0 <= index < TAKES_PER_SEED:
        raise SimulatorError(f"a data set has at most {TAKES_PER_SEED} takes, got take index {index}")
    return dataset_seed * TAKES_PER_SEED + index


def _check(seconds: float, fps: float, size, n_cameras: int) -> tuple[int, int, int]:
    """Validate the take's shape; returns (width, height, number of sets)."""
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise SimulatorError(f"size must be (width, height), got {size!r}") from None
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise SimulatorError(f"size must be between 16x16 and 8192x8192, got {w}x{h}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= 1000):
        raise SimulatorError(f"fps must be a number between 0 and 1000, got {fps!r}")
    if not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
        raise SimulatorError(f"seconds must be a positive number, got {seconds!r}")
    if not isinstance(n_cameras, int) or not 2 <= n_cameras <= 64:
        raise SimulatorError(f"cameras must be an integer from 2 to 64, got {n_cameras!r}")
    return w, h, max(1, int(round(seconds * fps)))


def _check_new_folder(root: Path) -> None:
    """As `rig record`: write only into a new or empty folder, never over or into another take."""
    try:
        taken = root.exists() and (not root.is_dir() or any(root.iterdir()))
    except OSError as exc:
        raise SimulatorError(f"{root}: cannot read the output folder ({exc.strerror})") from None
    if taken:
        what = "already holds a sequence" if (root / META).exists() or (root / INDEX).exists() else "is not an empty folder"
        raise SimulatorError(f"{root}: {what}; choose a new folder")


def _ppm(image: np.ndarray) -> bytes:
    """A binary PPM (P6) as rig/storage/netpbm.py writes it: one header field per line."""
    h, w = image.shape[:2]
    return b"P6\n%d %d\n255\n" % (w, h) + np.ascontiguousarray(image, dtype=np.uint8).tobytes()


def _role(name: str) -> str:
    return name if name in ("left", "right") else "supervision"


class TakeRenderer:
    """The scene, lighting and exact cameras of one take, and its images (what `write_take` stores)."""

    def __init__(self, variety: TakeVariety, size: tuple[int, int], n_cameras: int = 6, noise: bool = False,
                 distortion: bool = True):
        self.variety = variety
        self.scene = Scene.from_options(variety.scene)
        variety.lighting.apply(self.scene)
        self.rig = variety.placement.cameras(size[0], size[1], n_cameras, variety.seed, distortion=distortion)
        self.noise = noise
        # The sensor model only adds noise here (rendering is done once per frame, below); sensor
        # seeds differ per camera through the camera name.
        self._sensors = {c.name: SensorModel(lambda: self.scene, c, {"seed": variety.seed, "motion_blur": False}) for c in self.rig.cameras}

    def scene_time(self, set_index: int, fps: float) -> float:
        return self.variety.start_s + set_index / fps

    def image(self, camera: str, t: float, frame_index: int) -> np.ndarray:
        """RGB uint8 of `camera` at scene time t; with noise, through the sensor model."""
        r = render(self.scene, self.rig[camera], t)
        if not self.noise:
            return r.rgb
        sensor = self._sensors[camera]
        return sensor.digitise(r.radiance, NOMINAL_EXPOSURE_S, sensor.frame_rng(frame_index))


def write_take(out_dir, seed: int, seconds: float, fps: float = 30.0, size: tuple[int, int] = (640, 360), *,
               cameras: int = 6, noise: bool = False, distortion: bool = True,
               progress: Optional[Progress] = None) -> dict:
    """Render one take of `seconds` at `fps` (sets = round(seconds * fps)), `cameras` cameras of
    `size` (width, height) into the new folder `out_dir`. `seed` draws everything that varies
    (simulator.variety). Returns a summary (JSON-serialisable)."""
    w, h, n_sets = _check(seconds, fps, size, cameras)
    variety = draw_variety(seed)
    root = Path(out_dir)
    _check_new_folder(root)
    started = time.monotonic()
    take = TakeRenderer(variety, (w, h), cameras, noise=noise, distortion=distortion)
    names = take.rig.names
    try:
        for n in names:
            (root / FRAMES / n).mkdir(parents=True, exist_ok=True)
        meta = {
            "version": FORMAT_VERSION, "rig": f"sim-take-{variety.seed}", "rate_hz": float(fps),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "cameras": [{"name": n, "role": _role(n), "width": w, "height": h, "pixel_format": "RGB8",
                         "channels": 3, "bytes_per_sample": 1} for n in names],
            "simulator": {"scene": dict(variety.scene), "cameras": take.rig.to_dict()["cameras"],
                          "take": {**variety.to_dict(), "noise": bool(noise), "distortion": bool(distortion)}},
        }
        atomic_write_json(root / META, meta)
        # As the recorder does: a row is appended only once every image it names is written.
        with open(root / INDEX, "ab", buffering=0) as index:
            for s in range(n_sets):
                t = take.scene_time(s, fps)
                ts_ns = int(round(s * 1e9 / fps))
                frames = {}
                for n in names:
                    rel = f"{FRAMES}/{n}/{s + 1:08d}.ppm"
                    (root / rel).write_bytes(_ppm(take.image(n, t, s)))
                    frames[n] = {"frame_id": s + 1, "device_ts_ns": ts_ns, "host_ts_ns": ts_ns, "file": rel, "sim_time_s": t}
                row = {"set": s, "trigger": s, "host_ts_ns": ts_ns, "frames": frames}
                index.write((json.dumps(row, separators=(",", ":")) + "\n").encode())
                if progress is not None:
                    progress(s + 1, n_sets)
            os.fsync(index.fileno())
    except OSError as exc:
        raise SimulatorError(f"{root}: cannot write the take ({exc.strerror or exc})") from None
    return {"out": str(root), "seed": variety.seed, "sets": n_sets, "fps": float(fps), "size": [w, h],
            "cameras": names, "noise": bool(noise), "distortion": bool(distortion),
            "variety": variety.to_dict(), "wall_s": round(time.monotonic() - started, 3)}


def write_dataset(out_dir, takes: int, seconds: float, seed: int = 0, *, fps: float = 30.0,
                  size: tuple[int, int] = (640, 360), cameras: int = 6, noise: bool = False, distortion: bool = True,
                  progress: Optional[Progress] = None) -> dict:
    """Render `takes` takes into OUT/take-000, OUT/take-001, ... (take i has seed
    `take_seed(seed, i)` = seed * 1000 + i) and write OUT/dataset.json listing them. `progress`
    gets (frames done, frames in all) over the whole data set. Returns a summary."""
    if not isinstance(takes, int) or isinstance(takes, bool) or not 1 <= takes <= TAKES_PER_SEED:
        raise SimulatorError(f"takes must be an integer from 1 to {TAKES_PER_SEED}, got {takes!r}")
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
        raise SimulatorError(f"seed must be an integer from 0 to {MAX_SEED}, got {seed!r}")
    _, _, n_sets = _check(seconds, fps, size, cameras)
    root = Path(out_dir)
    _check_new_folder(root)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimulatorError(f"{root}: cannot create the output folder ({exc.strerror})") from None
    started = time.monotonic()
    total = takes * n_sets
    summaries = []
    for i in range(takes):
        done = i * n_sets
        step = None if progress is None else (lambda k, _n, done=done: progress(done + k, total))
        summaries.append(write_take(root / f"take-{i:03d}", take_seed(seed, i), seconds, fps, size, cameras=cameras,
                                    noise=noise, distortion=distortion, progress=step))
    summary = {"out": str(root), "seed": seed, "take_seeds": [s["seed"] for s in summaries],
               "takes": [Path(s["out"]).name for s in summaries], "sets_per_take": n_sets, "fps": float(fps),
               "size": list(summaries[0]["size"]), "cameras": summaries[0]["cameras"], "noise": bool(noise),
               "distortion": bool(distortion), "wall_s": round(time.monotonic() - started, 3)}
    try:
        atomic_write_json(root / DATASET, {**summary, "variety": [s["variety"] for s in summaries]})
    except OSError as exc:
        raise SimulatorError(f"{root / DATASET}: cannot write ({exc.strerror})") from None
    return summary
