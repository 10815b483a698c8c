"""The console's calibration panel: `rig calibrate capture`'s stills shown live, views kept by hand
or when the board is still and adds coverage, then `rig calibrate run`'s solve.

    cal = ConsoleCalibration(rig, board_file)   # rig: rig.console.rigstate.ConsoleRig
    cal.start(auto=True)       # the previews let go of the cameras; stills are taken and shown
    cal.capture()              # keep the next set in which the board is seen
    cal.solve()                # stop capturing, solve, write the calibration the config names
    cal.status()               # coverage per camera and per pair, what is still missing, the report

Nothing of the capture or the solve is written here: the stills, the detection and the choice of
views are rig.capture.calibration_views.ViewCapture (`rig calibrate capture`'s own), and the solve
is rig.calibrate.run (`rig calibrate run`'s own). What this adds is what a person at the rig
needs: the board drawn on every tile, a view kept once the board is held still (two sets in a row
whose corners moved less than STILL_FRACTION of the image diagonal), coverage maps, and whether the
views are enough for a calibration the report will call good (its own limits).
"""
from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

from common.errors import ReportedError
from rig.errors import ConfigError

log = logging.getLogger(__name__)

STILL_FRACTION = 0.004  # corners moved less than this share of the image diagonal since the last set: the board is still
MAX_POINTS = 400  # corners sent to the page per camera (drawn on its tile)
GRAB_TIMEOUT_S = 30.0  # a simulated camera renders each still on the busy host
VIEWS_PER_STATION = 2  # a simulated board is held still for this many sets at each station


def _moved(now, before) -> Optional[float]:
    """Mean displacement (pixels) of the corners two detections share, or None when they share too few."""
    if now is None or before is None:
        return None
    common, ia, ib = np.intersect1d(now.ids, before.ids, return_indices=True)
    if len(common) < max(4, len(now.ids) // 2):
        return None
    return float(np.mean(np.linalg.norm(now.points[ia] - before.points[ib], axis=1)))


class ConsoleCalibration:
    def __init__(self, rig, board_file: Optional[Path]):
        self.rig = rig
        self.board_file = Path(board_file) if board_file else None
        self.lock = threading.Lock()
        self.state = "off"  # off, starting, capturing, solving, done, failed
        self.auto = True
        self.error: Optional[str] = None
        self.folder: Optional[Path] = None
        self.capture_obj = None  # the ViewCapture running or last run
        self.last: Optional[str] = None  # what became of the last set
        self.decision: Optional[str] = None  # what became of the last view considered (kept or not); stays until the next
        self.still = False
        self.result: Optional[dict] = None  # the last solve's report, verdicts and warnings
        self._stop = threading.Event()
        self._want_view = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._previous: dict = {}

    # --- the work -----------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.state in ("starting", "capturing", "solving")

    def _board(self):
        from calibration.boards import load_board

        if self.board_file is None:
            raise ConfigError("calibration: no board file; start the console with --board BOARD.toml "
                              "(`rig config init --sim` writes board.toml beside the config)")
        try:
            return load_board(self.board_file)
        except (ReportedError, OSError, ValueError) as exc:
            raise ConfigError(f"calibration: {exc}") from None

    def start(self, auto: bool = True) -> dict:
        """Take the cameras from the previews and show stills with the board found in them."""
        if not isinstance(auto, bool):
            raise ConfigError(f"auto must be true or false, got {auto!r}")
        board = self._board()
        with self.rig.lock:
            self.rig._check_free("calibration")
            if self.running:
                raise ConfigError("calibration: already running")
            stamp = time.strftime("%Y%m%d-%H%M%S")
            folder = Path(self.rig.storage) / f"calibration-{stamp}"
            k = 1
            while folder.exists():
                k += 1
                folder = Path(self.rig.storage) / f"calibration-{stamp}-{k}"
            self.folder, self.auto, self.error, self.result, self.last, self.decision, self.still = folder, auto, None, None, None, None, False
            self.state = "starting"
            self.rig.activity = "calibrating"
            self._stop.clear()
            self._want_view.clear()
        self._thread = threading.Thread(target=self._run, args=(board,), name="console-calibration", daemon=True)
        self._thread.start()
        return self.status()

    def set_auto(self, auto: bool) -> dict:
        if not isinstance(auto, bool):
            raise ConfigError(f"auto must be true or false, got {auto!r}")
        self.auto = auto
        return self.status()

    def capture(self) -> dict:
        """Keep the next set in which the board is seen, whether or not it adds coverage."""
        if self.state not in ("starting", "capturing"):
            raise ConfigError("capture view: start the calibration first")
        self._want_view.set()
        return self.status()

    def stop(self, wait: float = 30.0) -> dict:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread() and self.state in ("starting", "capturing"):
            t.join(wait)
        return self.status()

    def _run(self, board) -> None:
        from rig.capture.calibration_views import ViewCapture, stereo_roles, still_settings
        from rig.sim.calibration import calibration_session

        rig = self.rig
        try:
            rig._take_the_rig()
            settings = still_settings(rig.cfg.cameras)  # views are stills: no trigger board
            # Simulated cameras have nobody to carry the board: the scene becomes a calibration
            # session (the board at stations through the volume), as in `rig calibrate capture`.
            session = calibration_session(settings, board, views_per_station=VIEWS_PER_STATION) \
                if any(s.scheme == "sim" for s in settings) else None
            cap = ViewCapture(settings, board, self.folder, stereo_roles(rig.cfg.cameras))
            self.capture_obj = cap
            self._previous = {}
            with cap:
                self.state = "capturing"
                rig.event("calibration", f"calibration views into {self.folder}" + (f" ({session.describe()})" if session else ""))
                while not self._stop.is_set() and not rig._closed.is_set():
                    images, found = cap.grab(GRAB_TIMEOUT_S)
                    self._one_set(cap, images, found)
            self.state = "off"
        except Exception as exc:
            self._failed("calibration capture", exc)
        finally:
            for v in rig.views.values():
                v.board = None
            with rig.lock:
                rig.activity = "previewing"
            rig._yield.clear()

    def _one_set(self, cap, images: dict, found: dict) -> None:
        moves = {n: _moved(c, self._previous.get(n)) for n, c in found.items() if c is not None}
        diag = {s.name: float(np.hypot(s.width, s.height)) for s in cap.settings}
        still = bool(moves) and all(m is not None and m < STILL_FRACTION * diag[n] for n, m in moves.items())
        self._previous, self.still = dict(found), still
        self.rig.show_stills(images, {n: self._drawn(c, still) for n, c in found.items()})
        if self._want_view.is_set():
            verdict = cap.consider(images, found, force=True)
            if verdict.keep:
                self._want_view.clear()
            self._kept(verdict, "by hand")
        elif self.auto and still:
            self._kept(cap.consider(images, found), "board still")
        elif not moves:
            self.last = "board not seen"
        elif not still:
            self.last = "waiting for the board to be still"

    def _kept(self, verdict, how: str) -> None:
        if verdict.keep:
            self.decision = f"view {len(self.capture_obj.kept) - 1:04d} kept ({how}): {verdict.reason}"
            self.rig.event("calibration", self.decision)
        else:
            self.decision = f"not kept ({how}): {verdict.reason}"
        self.last = self.decision

    @staticmethod
    def _drawn(corners, still: bool) -> Optional[dict]:
        if corners is None:
            return None
        pts = corners.points
        if len(pts) > MAX_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_POINTS).astype(int)]
        return {"points": np.round(pts, 1).tolist(), "still": still}

    # --- coverage -----------------------------------------------------------------------------------
    def needs(self) -> list[str]:
        """What the kept views still lack for a calibration the report calls good (its own limits:
        views and image coverage per camera, views the stereo pair shares, every camera tied to the
        left one by shared views); empty: enough."""
        from calibration.quality import MIN_JOINT_VIEWS
        from calibration.report import MIN_COVERAGE, MIN_GOOD_VIEWS, MIN_STEREO_VIEWS

        cap = self.capture_obj
        if cap is None:
            return ["no views yet"]
        sel = cap.selector
        per, cov, pairs = sel.views_per_camera(), sel.coverage(), sel.pairs()
        out = []
        for name in per:
            if per[name] < MIN_GOOD_VIEWS:
                out.append(f"{name}: {per[name]} of {MIN_GOOD_VIEWS} views")
            if cov[name] < MIN_COVERAGE:
                out.append(f"{name}: the board covered {cov[name] * 100:.0f} % of the image ({MIN_COVERAGE * 100:.0f} % needed)")
        left, right = cap.roles.get("left"), cap.roles.get("right")
        shared = lambda a, b: pairs.get((a, b), pairs.get((b, a), 0))  # noqa: E731
        if left and right and shared(left, right) < MIN_STEREO_VIEWS:
            out.append(f"stereo pair {left}-{right}: {shared(left, right)} of {MIN_STEREO_VIEWS} views together")
        start = left or next(iter(per), None)
        tied, grew = {start}, True
        while grew:
            grew = False
            for name in per:
                if name not in tied and any(shared(name, t) >= MIN_JOINT_VIEWS for t in tied):
                    tied.add(name)
                    grew = True
        out += [f"{name}: fewer than {MIN_JOINT_VIEWS} views shared with the cameras tied to {start}" for name in per if name not in tied]
        return out

    def status(self) -> dict:
        cap = self.capture_obj
        s = {"state": self.state, "auto": self.auto, "error": self.error, "board": str(self.board_file) if self.board_file else None,
             "folder": str(self.folder) if self.folder else None, "last": self.last, "decision": self.decision, "still": self.still, "result": self.result,
             "output": str(self._output()) if self.rig.cfg.calibration else None}
        if cap is not None:
            sel = cap.selector
            needs = self.needs()
            s.update(views=len(cap.kept), looked=cap.looked, coverage=sel.coverage(), cells=sel.cells(),
                     views_per_camera=sel.views_per_camera(),
                     pairs=[{"a": a, "b": b, "views": n} for (a, b), n in sel.pairs().items()], needs=needs, ready=not needs)
        return s

    # --- the solve ----------------------------------------------------------------------------------
    def _output(self) -> Path:
        return self.rig.cfg.resolve(self.rig.cfg.calibration)

    def solve(self) -> dict:
        """Stop capturing and run `rig calibrate run`'s solve on the views kept, in a thread; the
        calibration is written where the rig's config names it (an earlier one is kept beside it)."""
        if not self.rig.cfg.calibration:
            raise ConfigError("solve: the rig's config names no calibration file ([rig] calibration = \"calib.json\")")
        if self.state == "solving":
            raise ConfigError("solve: already solving")
        cap = self.capture_obj
        if cap is None or not cap.kept:
            raise ConfigError("solve: no calibration views kept yet (start the calibration and show the board)")
        self.stop()
        self.state, self.error, self.result = "solving", None, None
        threading.Thread(target=self._solve, name="console-solve", daemon=True).start()
        return self.status()

    def _solve(self) -> None:
        from calibration.report import format_report
        from rig.calibrate.run import UnusableCalibration, calibrate_images, run_inputs

        rig, folder = self.rig, self.folder
        try:
            rig.event("calibration", f"solving from {len(self.capture_obj.kept)} views in {folder}")
            inputs = run_inputs(str(folder), str(self.board_file), config=str(rig.cfg.path) if rig.cfg.path else None)
            solved = folder / "calib.json"  # solved beside its views, then put where the config names it
            try:
                result = calibrate_images(inputs, solved)
            except UnusableCalibration as exc:
                self.result = {"report": format_report(exc.rig), "verdicts": None, "warnings": [], "written": None}
                raise
            failed = result.write_error()
            if failed is not None:
                raise failed
            summary = result.summary()
            target = self._output()
            kept = self._keep_previous(target)
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(f".{target.name}.tmp")
            shutil.copyfile(solved, tmp)
            tmp.replace(target)
            verdicts = {n: c.get("verdict") for n, c in summary["per_camera"].items()}
            self.result = {"report": format_report(result.rig), "verdicts": verdicts,
                           "warnings": summary.get("warnings", []), "rms_px": summary.get("rms_px"),
                           "written": str(target), "previous": str(kept) if kept else None}
            self.state = "done"
            rig.event("calibration", f"calibration written to {target}" + (f" (the previous one kept as {kept.name})" if kept else ""))
        except Exception as exc:
            self._failed("solve", exc)

    def _failed(self, what: str, exc: Exception) -> None:
        """The work stopped: its one line on the panel and in the events (a bug is logged whole, and
        does not take the console with it)."""
        if isinstance(exc, ReportedError):
            self.error = str(exc)
        else:
            log.exception("console %s", what)
            self.error = f"{type(exc).__name__}: {exc}"
        self.state = "failed"
        self.rig.event("calibration", f"{what} failed: {self.error}", "error")

    @staticmethod
    def _keep_previous(target: Path) -> Optional[Path]:
        """An existing calibration is never lost: renamed to NAME.YYYYmmdd-HHMMSS.json first."""
        if not target.exists():
            return None
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(target.stat().st_mtime))
        kept = target.with_name(f"{target.stem}.{stamp}{target.suffix}")
        k = 1
        while kept.exists():
            k += 1
            kept = target.with_name(f"{target.stem}.{stamp}-{k}{target.suffix}")
        target.replace(kept)
        return kept
