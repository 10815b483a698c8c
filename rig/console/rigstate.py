"""The rig as the console runs it: one owner of the cameras at a time, previews from whatever runs.

    rig = ConsoleRig(cfg)          # rig.config.RigConfig
    rig.start()                    # previews: a RigSession of its own while nothing else runs
    rig.set_controls("left", exposure_us=3000)   # live, read back from the camera
    rig.start_take("take-007", notes="...")      # rig.capture.record.record, in a thread of its own
    rig.stop_take()
    rig.status()                   # what GET /api/status returns
    rig.close()

The console writes no capture, sync or recording logic of its own: previews come from a
`RigSession` while the rig is idle, and a take is `rig record`'s own `record()` (the same disk
check, the same writer), which the console hears through a tap (rig.capture.tap). In-process
cameras can be opened once, so the preview session closes before a take opens its own and opens
again after it; during the take the tap shows its sets. The tap only keeps references to the
newest frames: nothing on the take's thread encodes, copies or waits (previews are encoded at
the viewers' rate, on the server's threads, from the newest frame; a frame not yet sent is
replaced, never queued).
"""
from __future__ import annotations

import logging
import shutil
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

from rig.console import takes as take_names
from rig.errors import ConfigError, RigError

log = logging.getLogger(__name__)

FPS_WINDOW_S = 2.0  # a camera's fps is measured over the frames of the last this many seconds
FPS_WARN = 0.02  # a tile turns amber when its fps is more than 2 % off the target
STALE_S = 2.0  # no frame for this long: the camera is stopped (red)
RETRY_S = 2.0  # a preview session that failed to open is tried again after this long
EVENTS_KEPT = 50


@dataclass
class CameraView:
    """What one tile shows: the newest frame and the figures around it."""

    name: str
    role: str
    target_fps: float
    frame: Any = None  # the newest sync.frames.Frame
    image: Any = None  # its image
    frame_at: Optional[float] = None  # host monotonic seconds it arrived
    seq: int = 0  # counts frames seen (a preview is sent when it moved)
    arrivals: deque = field(default_factory=lambda: deque(maxlen=512))  # (monotonic s, device ns)
    dropped: int = 0
    delivered: int = 0
    controls: dict = field(default_factory=dict)
    control_error: Optional[str] = None
    board: Optional[dict] = None  # while calibrating: the board's corners found in `image` (drawn on the tile)

    def fps(self, now: float) -> Optional[float]:
        """Frames per second by the camera's own clock over the last FPS_WINDOW_S."""
        recent = [(t, d) for t, d in self.arrivals if now - t <= FPS_WINDOW_S]
        if len(recent) < 3:
            return None
        span_ns = recent[-1][1] - recent[0][1]
        return (len(recent) - 1) / (span_ns / 1e9) if span_ns > 0 else None

    def health(self, now: float) -> str:
        """ok, warn (fps more than 2 % off its target) or bad (no frames)."""
        if self.frame_at is None or now - self.frame_at > STALE_S:
            return "bad"
        fps = self.fps(now)
        if fps is not None and self.target_fps and abs(fps / self.target_fps - 1.0) > FPS_WARN:
            return "warn"
        return "ok"


class ConsoleRig:
    def __init__(self, cfg, session_factory: Optional[Callable] = None, record_fn: Optional[Callable] = None,
                 board_file: Optional[Path] = None):
        from rig.capture.record import record
        from rig.capture.session import RigSession
        from rig.console.calibration import ConsoleCalibration

        self.cfg = cfg
        self._session_factory = session_factory or RigSession
        self._record = record_fn or record
        self.views = {c.name: CameraView(c.name, c.role, float(c.fps)) for c in cfg.cameras}
        if cfg.trigger is not None:
            for v in self.views.values():
                cam = cfg.camera(v.name)
                if cam.trigger in ("hardware", "software"):
                    v.target_fps = float(cfg.trigger.rate_hz)
        self.storage = cfg.resolve(cfg.storage)
        self.lock = threading.RLock()
        self.session = None  # the session running now (the console's own, or a take's)
        self.activity = "starting"  # starting, previewing, recording, stopping, idle
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self._closed = threading.Event()
        self._yield = threading.Event()  # the preview session must let go of the cameras
        self._released = threading.Event()
        self._released.set()
        self._thread: Optional[threading.Thread] = None
        self.take: Optional[dict] = None  # the take running or last run
        self._take_stop: Optional[threading.Event] = None
        self._take_thread: Optional[threading.Thread] = None
        self.summaries: dict[str, dict] = {}
        self.check: Optional[dict] = None  # the sync check running or last run
        self._cache: dict[str, tuple[float, Any]] = {}
        self.doctor: Optional[dict] = None  # the host checks running or last run
        self.notes = take_names.Notes(self.storage)
        self.live = None  # rig.console.live.ConsoleLive, fed every frame set seen (previews or a take)
        self.calibration = ConsoleCalibration(self, board_file)

    # --- life ------------------------------------------------------------------------------------
    def start(self) -> "ConsoleRig":
        self._thread = threading.Thread(target=self._preview_loop, name="console-previews", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._closed.set()
        if self.live is not None:
            self.live.stop()
        self.calibration.stop()
        self.stop_take()
        if self._take_thread is not None:
            self._take_thread.join(30)
        self._yield.set()
        if self._thread is not None:
            self._thread.join(15)

    def event(self, kind: str, detail: str, level: str = "info") -> None:
        with self.lock:
            # "time" is for the page to show; how recent an event is goes by the monotonic clock,
            # which a wall-clock step (NTP) does not move
            self.events.append({"time": time.time(), "mono": time.monotonic(), "kind": kind, "detail": detail, "level": level})

    # --- the session tap (rig.capture.tap) ------------------------------------------------------------
    def opened(self, session) -> None:
        with self.lock:
            self.session = session
        self._refresh_controls()

    def frame_set(self, fs, figures: dict) -> None:
        now = time.monotonic()
        for name, frame in fs.frames.items():
            v = self.views.get(name)
            if v is None or frame is None:
                continue
            v.frame, v.frame_at = frame, now
            v.image = frame.image  # a reference (the work may let go of frame.image after the tap)
            v.seq += 1
            v.arrivals.append((now, frame.device_ts_ns))
        if figures and self.take is not None:
            self.take["figures"] = figures
        live = self.live
        if live is not None:
            live.offer(fs)

    def show_stills(self, images: dict, boards: dict) -> None:
        """Calibration stills on the tiles, with the board found in each (`boards`: camera -> corners to draw or None)."""
        now = time.monotonic()
        for name, image in images.items():
            v = self.views.get(name)
            if v is None:
                continue
            v.image, v.frame, v.frame_at, v.board = image, None, now, boards.get(name)
            v.seq += 1

    def closed(self) -> None:
        with self.lock:
            session, self.session = self.session, None
        if session is not None:
            try:
                stats = session.camera_stats()
                for name, s in stats.items():
                    if name in self.views:
                        self.views[name].dropped += s.get("dropped", 0)
            except Exception:
                pass

    # --- previews while nothing else runs --------------------------------------------------------------
    def _preview_loop(self) -> None:
        while not self._closed.is_set():
            if self._yield.is_set():
                self._released.set()
                time.sleep(0.05)
                continue
            self._released.clear()
            try:
                self.activity = "starting" if self.activity != "recording" else self.activity
                session = self._session_factory(self.cfg, on_event=self._on_session_event)
                with session:
                    self.opened(session)
                    try:
                        self.activity = "previewing"
                        base = dict(self._dropped_base())
                        for fs in session.framesets(until=lambda: self._yield.is_set() or self._closed.is_set()):
                            self.frame_set(fs, {})
                            self._live_drops(session, base)
                    finally:
                        self.closed()
            except RigError as exc:
                self.event("preview", f"the rig did not start: {exc}", "error")
                self.activity = "idle"
                self._closed.wait(RETRY_S)
            except Exception as exc:  # a bug must not end the previews for good
                log.exception("console previews")
                self.event("preview", f"previews stopped: {exc}", "error")
                self.activity = "idle"
                self._closed.wait(RETRY_S)
            finally:
                self._released.set()

    def _dropped_base(self) -> dict[str, int]:
        return {n: v.dropped for n, v in self.views.items()}

    def _live_drops(self, session, base: dict) -> None:
        """Sets emitted without a camera's frame, counted as they happen (not only when the session ends)."""
        stats = session.camera_stats()
        for name, s in stats.items():
            if name in self.views:
                self.views[name].delivered = s.get("delivered", 0)
                self.views[name].dropped_live = base.get(name, 0) + s.get("dropped", 0)

    def _on_session_event(self, ev) -> None:
        level = "error" if ev.kind in ("board_disconnected", "camera_lost", "board_error", "boot") else "info"
        self.event(ev.kind, ev.detail, level)

    def pause_previews(self, timeout: float = 20.0) -> None:
        """Let go of the cameras (another program needs them: `rig record` beside the console, say)."""
        self._take_the_rig(timeout)

    def resume_previews(self) -> None:
        self._yield.clear()

    def _take_the_rig(self, timeout: float = 20.0) -> None:
        """Make the preview session let go of the cameras (a take opens its own)."""
        self._yield.set()
        if not self._released.wait(timeout):
            self._yield.clear()
            raise RigError("the previews did not let go of the cameras in time; try again")

    # --- exposure and gain --------------------------------------------------------------------------
    def _refresh_controls(self) -> None:
        session = self.session
        if session is None:
            return
        for name, cam in getattr(session, "cameras", {}).items():
            if name in self.views:
                try:
                    self.views[name].controls = cam.controls()
                except Exception as exc:
                    self.views[name].controls = {"error": str(exc)}

    def set_controls(self, camera: str, exposure_us=None, gain=None) -> dict[str, dict]:
        """Set exposure and/or gain on one camera or on all ("*"): every value is checked against
        every camera's range before any camera changes; then each camera's read-back (or why it did
        not take it). ConfigError: a bad value (nothing changed)."""
        if exposure_us is None and gain is None:
            raise ConfigError("give exposure_us and/or gain")
        with self.lock:
            session = self.session
            if session is None:
                raise RigError("the rig is not running (no camera to set); wait for the previews")
            cams = dict(getattr(session, "cameras", {}))
            names = list(cams) if camera == "*" else [camera]
            for n in names:
                if n not in cams:
                    raise ConfigError(f"no camera {n!r} running (cameras: {', '.join(cams) or 'none'})")
            from rig.cameras.base import check_control

            for n in names:  # all checked first
                ranges = cams[n].controls().get("ranges", {})
                for key, value in (("exposure_us", exposure_us), ("gain", gain)):
                    if value is not None:
                        check_control(n, key, value, tuple(ranges.get(key, (0.0, float("inf")))))
            out = {}
            for n in names:
                v = self.views[n]
                asked = {k: x for k, x in (("exposure_us", exposure_us), ("gain", gain)) if x is not None}
                try:
                    got = cams[n].set_controls(**asked)
                except RigError as exc:
                    v.control_error = str(exc)
                    out[n] = {"ok": False, "error": str(exc), "controls": v.controls}
                    continue
                v.controls = got
                missed = [k for k, x in asked.items() if got.get(k) is None or abs(float(got[k]) - float(x)) > max(1e-6, 0.01 * abs(float(x)))]
                v.control_error = (f"the camera reports {', '.join(f'{k} {got.get(k)}' for k in missed)} "
                                   f"(asked {', '.join(f'{k} {asked[k]:g}' for k in missed)})") if missed else None
                out[n] = {"ok": not missed, "error": v.control_error, "controls": got}
            self.event("controls", f"{camera}: " + ", ".join(f"{k} {x:g}" for k, x in (("exposure_us", exposure_us), ("gain", gain)) if x is not None))
            return out

    # --- takes --------------------------------------------------------------------------------------
    def _check_free(self, what: str) -> None:
        """One piece of work owns the cameras at a time: ConfigError naming the one running."""
        if self.take is not None and self.take["state"] in ("starting", "recording", "stopping"):
            raise ConfigError(f"{what}: take {self.take['take']} is running; stop it first")
        if self.check is not None and self.check["state"] in ("starting", "running"):
            raise ConfigError(f"{what}: a sync check is running; wait for its verdict")
        if self.calibration.running:
            raise ConfigError(f"{what}: the calibration is {self.calibration.state}; stop it first")

    CODECS = ("raw", "png")

    def start_take(self, name: Optional[str] = None, notes: Optional[str] = None, seconds: Optional[float] = None,
                   codec: str = "raw") -> dict:
        if codec not in self.CODECS:
            raise ConfigError(f"codec must be one of {', '.join(self.CODECS)}, got {str(codec)[:20]!r}")
        with self.lock:
            self._check_free("record")
            name = take_names.check_new(self.storage, name) if name else take_names.next_name(self.storage)
            if notes is not None:
                self.notes.save(name, notes)
            stop = threading.Event()
            self._take_stop = stop
            self.take = {"take": name, "state": "starting", "started": None, "figures": {}, "error": None,
                         "seconds": seconds, "out": str(self.storage / name)}
            self.activity = "recording"
        self._take_thread = threading.Thread(target=self._run_take, args=(name, stop, seconds, codec), name=f"console-take-{name}", daemon=True)
        self._take_thread.start()
        return dict(self.take)

    def _run_take(self, name: str, stop: threading.Event, seconds: Optional[float], codec: str = "raw") -> None:
        take = self.take
        out = self.storage / name
        try:
            self._take_the_rig()  # the previews let go of the cameras; the take opens them itself
            take["started"] = time.time()
            take["started_monotonic"] = time.monotonic()
            take["state"] = "recording"
            self.event("record", f"take {name} started")
            # rig record's own take: its disk check, its writer; until stopped (or `seconds`)
            result = self._record(self.cfg, out, seconds=seconds if seconds else 24 * 3600.0, stop=stop, tap=self, codec=codec,
                                  notes=lambda text: self.event("record", text))
            summary = result.to_dict()
            take["summary"] = summary
            self.summaries[name] = summary
            take["state"] = "done"
            self.event("record", f"take {name}: {summary.get('sets')} sets, stopped by {summary.get('stopped_by')}")
        except RigError as exc:
            take["state"], take["error"] = "failed", str(exc)
            self.event("record", f"take {name} failed: {exc}", "error")
        except Exception as exc:
            log.exception("console take")
            take["state"], take["error"] = "failed", f"{type(exc).__name__}: {exc}"
            self.event("record", f"take {name} failed: {exc}", "error")
        finally:
            take["ended_monotonic"] = time.monotonic()
            self.notes.settle(name)
            with self.lock:
                self.activity = "previewing"
            self._yield.clear()

    def stop_take(self) -> Optional[dict]:
        with self.lock:
            if self.take is None or self.take["state"] not in ("starting", "recording"):
                return None
            self.take["state"] = "stopping"
            if self._take_stop is not None:
                self._take_stop.set()
            return dict(self.take)

    # --- sync ---------------------------------------------------------------------------------------
    MAX_CHECK_S = 600.0

    def start_sync_check(self, seconds: float = 10.0) -> dict:
        """`rig sync check`'s own run (rig.capture.sync_check) for `seconds`, in a thread; its verdict in status()."""
        import math

        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not math.isfinite(seconds) or not 0 < seconds <= self.MAX_CHECK_S:
            raise ConfigError(f"sync check: seconds must be a number above 0 and at most {self.MAX_CHECK_S:g}, got {seconds!r}")
        with self.lock:
            self._check_free("sync check")
            self.check = {"state": "starting", "seconds": float(seconds), "verdict": None, "failures": [], "report": None, "error": None,
                          "figures": {}}
            self.activity = "sync check"
        threading.Thread(target=self._run_check, args=(float(seconds),), name="console-sync-check", daemon=True).start()
        return dict(self.check)

    def _run_check(self, seconds: float) -> None:
        from rig.capture.sync_check import sync_check

        check = self.check
        try:
            self._take_the_rig()
            check["state"] = "running"
            self.event("sync", f"sync check for {seconds:g} s")
            report = sync_check(self.cfg, seconds, tap=_CheckTap(self, check))
            check.update(state="done", verdict=report["verdict"], failures=report["failures"], report=_slim_report(report))
            self.event("sync", f"sync check: {report['verdict']}" + (f" ({'; '.join(report['failures'])})" if report["failures"] else ""),
                       "info" if report["verdict"] == "pass" else "error")
        except RigError as exc:
            check.update(state="failed", error=str(exc))
            self.event("sync", f"sync check failed: {exc}", "error")
        except Exception as exc:
            log.exception("console sync check")
            check.update(state="failed", error=f"{type(exc).__name__}: {exc}")
        finally:
            with self.lock:
                self.activity = "previewing"
            self._yield.clear()

    def _sync(self) -> dict:
        """The running session's board and grouping figures: rate, pulses, lost pulses, the clock
        model's residual, the exposure skew across cameras (device clocks against the fitted pulse
        times, as rig sync check measures it) and each camera's drops."""
        session = self.session
        out: dict = {"rate_hz": self.cfg.trigger.rate_hz if self.cfg.trigger else None, "board": None}
        if session is not None:
            try:
                g = session.grouper.stats() if session.grouper is not None else {}
                out["skew_us"] = g.get("skew_us")
                out["sets"] = g.get("sets")
                out["cameras"] = {n: {k: c.get(k) for k in ("drops", "lost_frames", "missed_triggers")} for n, c in g.get("cameras", {}).items()}
                if session.board is not None:
                    r = session.board.report()
                    clock = r.get("clock") or {}
                    out["board"] = {"connected": r.get("connected"), "pulses": r.get("pulses"), "lost_pulses": r.get("missing_pulse_reports"),
                                    "clock_residual_p99_us": clock.get("fit_residual_p99_us"), "drift_ppm": clock.get("drift_ppm"),
                                    "last_error": r.get("last_error")}
            except Exception as exc:  # a figure the session could not give is not a fault of the page
                out["error"] = str(exc)
        c = self.check
        out["check"] = None if c is None else {k: c.get(k) for k in ("state", "seconds", "verdict", "failures", "error", "report", "figures")}
        return out

    # --- health -------------------------------------------------------------------------------------
    DOCTOR_TEST_BYTES = 64 << 20  # the disk write test of `rig doctor` here: enough to pass the page cache on a small rig

    def start_doctor(self) -> dict:
        """`rig doctor`'s checks (rig.doctor.run_checks) in a thread; their lines in status()["health"]."""
        with self.lock:
            self._check_free("doctor")
            if self.doctor is not None and self.doctor["state"] == "running":
                raise ConfigError("doctor: the checks are running")
            self.doctor = {"state": "running", "checks": None, "verdict": None, "error": None}
        threading.Thread(target=self._run_doctor, name="console-doctor", daemon=True).start()
        return dict(self.doctor)

    def _run_doctor(self) -> None:
        from rig.doctor import run_checks
        from rig.doctor.check import worst
        from rig.doctor.host import Host

        d = self.doctor
        try:
            Path(self.storage).mkdir(parents=True, exist_ok=True)
            checks = run_checks(self.cfg, Host("/"), output=Path(self.storage), minutes=60.0, test_bytes=self.DOCTOR_TEST_BYTES)
            d.update(state="done", checks=[c.to_json() for c in checks], verdict=worst(checks))
            self.event("doctor", f"host checks: {d['verdict']}", "info" if d["verdict"] == "ok" else "error")
        except (RigError, OSError) as exc:
            d.update(state="failed", error=str(exc))
        except Exception as exc:
            log.exception("console doctor")
            d.update(state="failed", error=f"{type(exc).__name__}: {exc}")

    FAULT_EVENTS = ("camera_lost", "camera_back", "board_disconnected", "board_connected", "board_error", "boot")
    RECENT_S = 120.0
    DISK_LOW_MINUTES = 10.0

    def faults(self, cams: list[dict], now: float) -> list[dict]:
        """The banners: cameras with no frames, a lost board, a disk with under DISK_LOW_MINUTES of the
        rig's data left, and what happened lately (a camera or daemon that went and came back)."""
        out = [{"kind": "camera", "level": "error", "detail": f"{c['name']}: no frames" + (f" for {c['age_s']:.0f} s" if c["age_s"] else "")}
               for c in cams if c["health"] == "bad" and self.activity not in ("starting", "idle")]
        session = self.session
        board = getattr(session, "board", None) if session is not None else None
        if board is not None and not getattr(board, "connected", True):
            out.append({"kind": "board", "level": "error", "detail": f"trigger board unplugged ({getattr(board, 'last_error', '') or 'no reply'})"})
        disk = self._disk()
        if disk.get("free_bytes") is not None:
            rate = self._cached("data_rate", lambda: _data_rate(self.cfg))
            if rate > 0 and disk["free_bytes"] / rate / 60.0 < self.DISK_LOW_MINUTES:
                out.append({"kind": "disk", "level": "error",
                            "detail": f"disk nearly full: {disk['free_bytes'] / 1e9:.1f} GB free, {disk['free_bytes'] / rate / 60.0:.1f} minutes of the rig's data"})
        for e in list(self.events):
            if e["kind"] in self.FAULT_EVENTS and now - e["mono"] < self.RECENT_S:
                out.append({"kind": e["kind"], "level": "warn" if e["kind"] in ("camera_back", "board_connected") else "error",
                            "detail": e["detail"], "time": e["time"]})
        from rig.config import calibration_problems

        for problem in self._cached("calibration_problems", lambda: calibration_problems(self.cfg)):
            out.append({"kind": "calibration", "level": "warn", "detail": f"{problem}; the Calibration panel makes one"})
        if self.activity == "idle":
            out.append({"kind": "rig", "level": "error", "detail": "the rig is not running (see the events)"})
        return out

    # --- what the page shows ------------------------------------------------------------------------
    def status(self) -> dict:
        now = time.monotonic()
        cams = []
        for v in self.views.values():
            fps = v.fps(now)
            controls = v.controls or {}
            # the camera's own read-back (set_controls), else what its newest frame carries
            reported = controls.get("exposure_us") if controls.get("live") else None
            if reported is None and v.frame is not None:
                reported = getattr(v.frame, "exposure_us", None)
            cams.append({"name": v.name, "role": v.role, "target_fps": v.target_fps, "fps": round(fps, 2) if fps else None,
                         "dropped": int(getattr(v, "dropped_live", v.dropped)),
                         "age_s": round(now - v.frame_at, 3) if v.frame_at is not None else None,
                         "health": v.health(now), "exposure_us": reported if reported is not None else controls.get("exposure_us"),
                         "frame_exposure_us": getattr(v.frame, "exposure_us", None) if v.frame is not None else None,
                         "gain": controls.get("gain"), "ranges": controls.get("ranges", {}), "live_controls": bool(controls.get("live")),
                         "control_error": v.control_error, "seq": v.seq, "board": v.board,
                         "size": list(v.image.shape[1::-1]) if v.image is not None else None})
        return {"rig": self.cfg.name, "activity": self.activity, "cameras": cams, "recording": self._recording(now),
                "takes": self._cached("takes", lambda: take_names.listing(self.storage, self.summaries, running=self._running_take())), "events": list(self.events)[-20:],
                "disk": self._disk(), "sync": self._sync(), "faults": self.faults(cams, now), "health": self.doctor,
                "live": self.live.status() if self.live is not None else {"state": "off", "error": None},
                "calibration": self.calibration.status()}

    def _running_take(self) -> Optional[str]:
        t = self.take
        return t["take"] if t is not None and t["state"] in ("starting", "recording", "stopping") else None

    def _recording(self, now: float) -> dict:
        t = self.take
        if t is None:
            return {"state": "idle", "take": None, "sets": 0, "lost": 0}
        f = t.get("figures") or {}
        start = t.get("started_monotonic")
        end = t.get("ended_monotonic") or now
        elapsed = (end - start) if start else 0.0
        sets = int(f.get("sets", 0))
        lost = sets - int(f.get("complete", sets)) + int(f.get("skipped", 0))
        rate = (f.get("bytes") or 0) / elapsed if elapsed > 0 else None
        summary = t.get("summary") or {}
        out = {"state": t["state"], "take": t["take"], "sets": sets if "sets" not in summary else summary["sets"],
               "lost": lost, "elapsed_s": round(elapsed, 2), "write_mb_per_s": round(rate / 1e6, 2) if rate else None,
               "disk_mb_per_s": summary.get("disk_mb_per_s"), "error": t.get("error"), "summary": summary or None}
        disk = self._disk()
        if rate and disk.get("free_bytes") is not None:
            out["minutes_left"] = round(disk["free_bytes"] / rate / 60.0, 1)
        return out

    SLOW_FIGURES_S = 1.0  # the disk's free space and the takes' list are read at most this often

    def _cached(self, key: str, fn):
        now = time.monotonic()
        hit = self._cache.get(key)
        if hit is None or now - hit[0] > self.SLOW_FIGURES_S:
            hit = (now, fn())
            self._cache[key] = hit
        return hit[1]

    def _disk(self) -> dict:
        return self._cached("disk", self._read_disk)

    def _read_disk(self) -> dict:
        from rig.storage.disk import nearest_existing_folder

        try:
            usage = shutil.disk_usage(nearest_existing_folder(Path(self.storage)))
        except OSError:
            return {"free_bytes": None}
        return {"free_bytes": usage.free, "total_bytes": usage.total, "folder": str(self.storage)}


def _data_rate(cfg) -> float:
    from rig.storage.disk import rig_data_rate

    try:
        return float(rig_data_rate(cfg))
    except Exception:  # a rig whose rate cannot be told has no disk banner
        return 0.0


class _CheckTap:
    """The console's tap on a sync check: the previews, and the check's own running figures."""

    def __init__(self, rig: ConsoleRig, check: dict):
        self.rig, self.check = rig, check

    def opened(self, session) -> None:
        self.rig.opened(session)

    def frame_set(self, fs, figures: dict) -> None:
        self.rig.frame_set(fs, {})
        self.check["figures"] = figures

    def closed(self) -> None:
        self.rig.closed()


def _slim_report(report: dict) -> dict:
    """The figures of a sync check's report the page shows (JSON-able, small)."""
    keys = ("sets", "complete_sets", "pulses", "skew_us", "clock_residual_us", "clock_residual_source", "drift_ppm", "drops_detected",
            "mismatched_sets", "seconds", "errors")
    return {k: report.get(k) for k in keys}
