"""Calibration views (`rig calibrate capture`): stills, not the session's synchronised sets.

Calibration views do not need the trigger board: every camera is opened directly, cameras that take
triggers are switched to software trigger and fired one after the other for each view (a loop of
commands, microseconds to milliseconds apart: not a hardware-synchronous exposure, so the board is
held still), and a free-running camera gives the newest frame it has (what queued up while the last
view was detected is dropped). A view is kept only when it adds coverage (calibration.selection).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

# `rig calibrate capture`'s defaults: frame sets looked at before giving up, seconds to wait for a
# camera's frame (a simulated camera renders its view on the busy host).
MAX_FRAMES = 2000
TIMEOUT_S = 5.0


def stereo_roles(cameras) -> dict:
    """The stereo pair among the cameras' configs: {"left": name, "right": name} (what a config names)."""
    return {c.role: c.name for c in cameras if c.role in ("left", "right")}


def still_settings(cameras) -> list:
    """The cameras' settings for stills: cameras that take triggers are fired by software so that
    every camera exposes the same instant without the trigger board; free-running ones are paired
    by time."""
    settings = []
    for c in cameras:
        s = dataclasses.replace(c, trigger="software" if c.trigger in ("hardware", "software") else "free")
        if hasattr(c, "rig"):
            s.rig = c.rig  # the whole rig, which simulated cameras need to show the shared scene
        settings.append(s)
    return settings


class ViewCapture:
    """The stills of a calibration capture, one set at a time: `rig calibrate capture` loops over
    them, the console's calibration panel shows each set and keeps views by hand or when the board
    is still. Use as a context manager (the cameras of `settings` (`still_settings`) are opened and
    started, and closed on leaving).

        with ViewCapture(settings, board, out, roles) as cap:
            images, found = cap.grab(timeout)     # a set of stills and the board's corners in each
            verdict = cap.consider(images, found)  # kept (OUT/CAMERA/NNNN.png) when it adds coverage
    """

    def __init__(self, settings, board, out: Path, roles: dict):
        from calibration.detect import make_detector
        from calibration.selection import ViewSelector

        self.settings, self.board, self.out, self.roles = settings, board, Path(out), roles
        self.detectors = {s.name: make_detector(board) for s in settings}  # one each: detection runs in parallel
        self.selector = ViewSelector({s.name: (s.width, s.height) for s in settings})
        self.kept: list[dict] = []
        self.sightings = {s.name: 0 for s in settings}
        self.looked = 0
        self.cameras: list = []
        self._pool = None

    def __enter__(self) -> "ViewCapture":
        from concurrent.futures import ThreadPoolExecutor

        from rig.cameras import open_camera

        try:
            for s in self.settings:
                self.cameras.append(open_camera(s))
            for cam in self.cameras:
                cam.start()
        except BaseException:
            self.close()
            raise
        self._pool = ThreadPoolExecutor(max_workers=len(self.cameras))
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        for cam in self.cameras:
            try:
                cam.stop()
                cam.close()
            except Exception:  # closing must not hide the error that stopped the capture
                pass
        self.cameras = []

    def grab(self, timeout: float) -> tuple[dict, dict]:
        """One set of stills ({camera: image}) and the board's corners found in each ({camera:
        calibration.detect.Corners or None})."""
        images = _grab_set(self.cameras, timeout)
        self.looked += 1
        found = dict(zip(images, self._pool.map(lambda kv: self.detectors[kv[0]](kv[1]), images.items())))
        for name, corners in found.items():
            self.sightings[name] += corners is not None
        return images, found

    def consider(self, images: dict, found: dict, force: bool = False):
        """Keep the set when it adds coverage (or, with `force`, whenever the board is seen): its
        images are written as OUT/CAMERA/NNNN.png. The selector's verdict."""
        import json

        import cv2

        from calibration.detect import to_gray
        from rig.errors import StorageError

        verdict = self.selector.consider(found, force=force)
        if verdict.keep:
            index = len(self.kept)
            if index == 0 and self.roles:  # tells `rig calibrate run` which cameras are the stereo pair
                self.out.mkdir(parents=True, exist_ok=True)
                (self.out / "roles.json").write_text(json.dumps(self.roles) + "\n")
            for name, img in images.items():
                path = self.out / name / f"{index:04d}.png"
                path.parent.mkdir(parents=True, exist_ok=True)
                if not cv2.imwrite(str(path), _to_bgr(img, to_gray)):
                    raise StorageError(f"{path}: could not write the image (disk full or no permission?)")
            self.kept.append({"view": f"{index:04d}", "cameras": verdict.cameras, "reason": verdict.reason})
        return verdict

    def summary(self) -> dict:
        """Views kept and looked at, coverage, views per camera, how often each camera saw the board,
        and each kept view."""
        per_camera = {s.name: sum(1 for k in self.kept if s.name in k["cameras"]) for s in self.settings}
        return {"output": str(self.out), "views_kept": len(self.kept), "views_looked_at": self.looked,
                "coverage": self.selector.coverage(), "views_per_camera": per_camera, "board_seen": dict(self.sightings),
                "kept": list(self.kept)}


def capture_views(settings, board, out: Path, roles: dict, views: int, limit: int, interval: float, timeout: float) -> dict:
    """Look at up to `limit` sets of stills from the cameras of `settings` (`still_settings`) and keep
    those that add coverage of the board, until `views` are kept: OUT/CAMERA/NNNN.png, and
    OUT/roles.json naming the stereo pair (`roles`) with the first. The summary: ViewCapture.summary."""
    import time

    from rig.progress import StatusLine

    status = StatusLine()
    capture = ViewCapture(settings, board, out, roles)
    try:
        with capture:
            while capture.looked < limit and len(capture.kept) < views:
                images, found = capture.grab(timeout)
                capture.consider(images, found)
                status.update(f"looked at {capture.looked}/{limit} frame sets, kept {len(capture.kept)} views (stops at {views})")
                if interval > 0:
                    time.sleep(interval)
    finally:
        status.done()
    return capture.summary()


def check_capture(summary: dict, board_file, names: list[str]) -> None:
    """A capture that `rig calibrate run` cannot use fails (exit 1) and says why; the views it kept
    stay in its folder."""
    from calibration.solve import MIN_VIEWS_PER_CAMERA
    from rig.errors import RigError

    looked = summary["views_looked_at"]
    if summary["views_kept"] == 0:
        if not any(summary["board_seen"].values()):
            raise RigError(f"the board was never seen in {looked} frame sets: check that {board_file} describes the board shown "
                           "(type, squares, sizes, marker dictionary) and that the cameras see it; no view was kept")
        raise RigError(f"the board was seen but never with enough corners ({looked} frame sets); no view was kept")
    few = {n: summary["views_per_camera"][n] for n in names if summary["views_per_camera"][n] < MIN_VIEWS_PER_CAMERA}
    if few:
        which = ", ".join(f"'{n}' in {v}" for n, v in few.items())
        raise RigError(f"too few views for `rig calibrate run`: the board was seen by {which} of the {summary['views_kept']} kept views "
                       f"({MIN_VIEWS_PER_CAMERA} per camera are needed); show it to those cameras and capture again into a new folder "
                       f"(the views kept are in {summary['output']})")


def _to_bgr(image, to_gray):
    """PNG-ready pixels: mono stays mono, RGB becomes OpenCV's BGR order."""
    import cv2
    import numpy as np

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if img.dtype != np.uint8 and img.dtype != np.uint16:
        return to_gray(img)
    return img


def _grab_set(cameras, timeout: float) -> dict:
    """One synchronised set of images: software-triggered cameras fire together; free-running cameras
    give their newest frame."""
    from rig.errors import CameraTimeout

    triggered = [c for c in cameras if c.settings.trigger == "software"]
    for cam in triggered:
        cam.software_trigger()
    images = {}
    for cam in cameras:
        try:
            frame = cam.get_frame(timeout)
        except CameraTimeout as exc:
            raise CameraTimeout(f"{exc} (a slow camera, or a simulated one on a busy machine: give it longer with --timeout SECONDS)") from None
        if cam.settings.trigger == "software":
            images[cam.name] = frame.image
        else:
            while True:  # drop what queued up while we were detecting: the newest frame is the present
                try:
                    frame = cam.get_frame(0.0)
                except CameraTimeout:
                    break
            images[cam.name] = frame.image
    return images
