"""A night of faults, in minutes: the simulated rig as daemons under `rig up`, `rig record` writing
takes back to back, `rig live` serving a viewer, and a daemon (a camera's, or the trigger board's)
killed with kill -9 at a fixed interval.

    .venv/bin/python benchmarks/soak.py [--minutes 10] [--kill-every 60] [--cameras 6] [--size 320x180]
        [--fps 15] [--take-seconds 30] [--out DIR] [--json]

Reported:
- per process (the supervisor, each daemon, `rig live`, each take's `rig record`): resident memory
  and open file descriptors sampled every few seconds, plotted (OUT/soak.png), and their growth after
  the warm-up (the first --warm-up seconds, and a restarted daemon's own first seconds): median of the
  last fifth of its samples against the median of its first fifth after warm-up; at most 10 %;
- takes: sets recorded, frames lost, each take validated; mismatched sets (a set whose frames show
  different instants of the simulated scene) must be 0;
- per kill: the victim, how long until the supervisor ran a new process for it and the rig's frames
  came again (the live view's frame sets move on), and the frames the takes lost meanwhile.

Everything runs on this machine, on loopback, under a shared-memory root of its own; every process
it started is stopped at the end, also on failure.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SAMPLE_S = 3.0
GROWTH_LIMIT = 0.10


def rig_config(root: Path, cameras: int, size: tuple[int, int], fps: float) -> Path:
    from rig.config import dump_config, parse_config
    from rig.sim.rig_config import sim_rig_config

    data = sim_rig_config(cameras, width=size[0], height=size[1], fps=fps)
    data["rig"]["name"] = "soak"
    data["rig"]["storage"] = str(root / "takes")
    data["sim"]["loop_frames"] = 30  # a pre-rendered loop: the scene costs nothing per frame
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def proc_figures(pid: int) -> tuple[int, int] | None:
    """(resident bytes, open file descriptors) of a live process, None when it is gone."""
    try:
        rss = next(int(line.split()[1]) * 1024 for line in open(f"/proc/{pid}/status") if line.startswith("VmRSS:"))
        return rss, len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, StopIteration, ValueError):
        return None


def supervisor_state(shm: Path, rig: str = "soak") -> dict:
    try:
        return json.loads((shm / rig / "supervisor.json").read_text())
    except (OSError, ValueError):
        return {}


class Viewer(threading.Thread):
    """A browser's part on `rig live`'s WebSocket: take every frame, acknowledge it (the server sends
    the next only then); counts frames and remembers the newest frame-set index."""

    def __init__(self, url: str, stop: threading.Event):
        super().__init__(name="soak-viewer", daemon=True)
        self.url, self.stop = url, stop
        self.frames = 0
        self.newest = -1
        self.reconnects = 0

    def run(self) -> None:
        import struct

        import websockets.sync.client as wsc

        while not self.stop.is_set():
            try:
                with wsc.connect(self.url, open_timeout=10, max_size=None, ping_interval=None) as ws:
                    while not self.stop.is_set():
                        try:
                            msg = ws.recv(timeout=0.5)
                        except TimeoutError:
                            continue
                        if isinstance(msg, bytes) and msg[:4] == b"RLVF":
                            index, viewpoint = struct.unpack_from("<qI", msg, 8)
                            self.frames += 1
                            self.newest = max(self.newest, index)
                            ws.send(json.dumps({"type": "ack", "set": index, "viewpoint": viewpoint}))
            except Exception:  # the server restarting or busy: connect again, as a page does
                self.reconnects += 1
                self.stop.wait(1.0)


class Soak:
    def __init__(self, args, root: Path):
        self.args, self.root = args, root
        self.shm = root / "shm"
        self.env = dict(os.environ, RIG_SHM_ROOT=str(self.shm))
        self.config = rig_config(root, args.cameras, args.size, args.fps)
        self.procs: list[subprocess.Popen] = []
        self.samples: list[dict] = []  # {t, role, pid, rss, fds}
        self.kills: list[dict] = []
        self.takes: list[dict] = []
        self.stop = threading.Event()
        self.t0 = time.monotonic()
        self.live_port = free_port()
        self.viewer: Viewer | None = None
        self.record: subprocess.Popen | None = None

    def now(self) -> float:
        return time.monotonic() - self.t0

    def start(self, argv: list, name: str) -> subprocess.Popen:
        """`rig ARGV` in its own process group; stdout to NAME.out, stderr to NAME.log."""
        p = subprocess.Popen([sys.executable, "-m", "rig", *map(str, argv)], cwd=REPO, env=self.env, stdout=open(self.root / f"{name}.out", "w"),
                             stderr=open(self.root / f"{name}.log", "w"), start_new_session=True)
        self.procs.append(p)
        return p

    # --- the rig ----------------------------------------------------------------------------------
    def bring_up(self) -> None:
        self.up = self.start(["up", "-c", self.config, "--no-advertise"], "up")
        deadline = time.monotonic() + 120
        while True:
            s = supervisor_state(self.shm)
            cams = s.get("cameras", {})
            if len(cams) == self.args.cameras + 1 and all(c["state"] == "running" for c in cams.values()):
                break
            if time.monotonic() > deadline or self.up.poll() is not None:
                raise SystemExit(f"error: rig up did not bring the daemons up: {s}")
            time.sleep(0.2)
        self.live = self.start(["live", "-c", self.config, "--port", self.live_port, "--threads", "1"], "live")
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.live_port}/status", timeout=5) as r:
                    if json.load(r).get("sets_in", 0) > 0:  # frame sets reach the model (it renders once a viewer is there)
                        break
            except OSError:
                pass
            if time.monotonic() > deadline or self.live.poll() is not None:
                raise SystemExit("error: rig live did not serve a frame")
            time.sleep(0.5)
        self.viewer = Viewer(f"ws://127.0.0.1:{self.live_port}/ws", self.stop)
        self.viewer.start()

    def processes(self) -> dict[str, int]:
        """role -> pid of every process of the rig now."""
        out = {"supervisor": self.up.pid, "live": self.live.pid}
        for name, c in supervisor_state(self.shm).get("cameras", {}).items():
            if c.get("pid"):
                out[f"daemon {name}"] = c["pid"]
        if self.record is not None and self.record.poll() is None:
            out["record"] = self.record.pid
        return out

    # --- the threads ------------------------------------------------------------------------------
    def sampler(self) -> None:
        while not self.stop.wait(SAMPLE_S):
            t = self.now()
            for role, pid in self.processes().items():
                f = proc_figures(pid)
                if f is not None:
                    self.samples.append({"t": round(t, 2), "role": role, "pid": pid, "rss": f[0], "fds": f[1]})

    def recorder(self) -> None:
        k = 0
        while not self.stop.is_set():
            take = self.root / "takes" / f"take-{k:03d}"
            started = self.now()
            self.record = self.start(["record", "-c", self.config, "-o", take, "--seconds", self.args.take_seconds, "--json",
                                      "--no-disk-check"], f"record-{k:03d}")
            self.record.wait()
            try:
                summary = json.loads((self.root / f"record-{k:03d}.out").read_text())
            except (ValueError, IndexError):
                summary = {}
            self.takes.append({"take": take.name, "started_s": round(started, 1), "ended_s": round(self.now(), 1),
                               "exit": self.record.returncode, "summary": summary})
            k += 1

    def killer(self) -> None:
        rng = random.Random(self.args.seed)
        while not self.stop.wait(self.args.kill_every):
            cams = supervisor_state(self.shm).get("cameras", {})
            victims = [n for n, c in cams.items() if c.get("pid")]
            if not victims:
                continue
            name = rng.choice(victims)
            pid = cams[name]["pid"]
            newest_before = self.viewer.newest if self.viewer else -1
            at = self.now()
            os.kill(pid, signal.SIGKILL)
            back, frames_again = None, None
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and (back is None or frames_again is None):
                c = supervisor_state(self.shm).get("cameras", {}).get(name, {})
                if back is None and c.get("state") == "running" and c.get("pid") not in (None, pid):
                    back = self.now() - at
                if back is not None and self.viewer is not None and self.viewer.newest > newest_before + 5:
                    frames_again = self.now() - at
                time.sleep(0.05)
            self.kills.append({"victim": name, "pid": pid, "at_s": round(at, 2), "daemon_back_s": None if back is None else round(back, 2),
                               "live_frames_again_s": None if frames_again is None else round(frames_again, 2)})
            print(f"[{at:6.1f} s] killed {name} (pid {pid}): daemon back in {back if back is None else round(back, 2)} s, "
                  f"live frames again in {frames_again if frames_again is None else round(frames_again, 2)} s", file=sys.stderr, flush=True)

    def run(self) -> dict:
        self.bring_up()
        self.t0 = time.monotonic()
        threads = [threading.Thread(target=f, daemon=True) for f in (self.sampler, self.recorder, self.killer)]
        for t in threads:
            t.start()
        self.stop.wait(self.args.minutes * 60)
        self.stop.set()
        for t in threads:
            t.join(self.args.take_seconds + 60)
        return self.report()

    def close(self) -> None:
        self.stop.set()
        for p in reversed(self.procs):
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except OSError:
                    pass
        for p in self.procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)

    # --- the figures ------------------------------------------------------------------------------
    def report(self) -> dict:
        from rig.storage.validate import validate

        takes = []
        for t in self.takes:
            v = validate(self.root / "takes" / t["take"]) if (self.root / "takes" / t["take"] / "sequence.json").exists() else None
            rows = _rows(self.root / "takes" / t["take"])
            mismatched = sum(1 for r in rows if len({round(f["sim_time_s"], 4) for f in r["frames"].values() if f}) > 1)
            kills = [k for k in self.kills if t["started_s"] <= k["at_s"] <= t["ended_s"]]
            s = t["summary"]
            takes.append({**{k: t[k] for k in ("take", "started_s", "ended_s", "exit")}, "sets": s.get("sets"),
                          "complete_sets": s.get("complete_sets"), "frames_lost": sum((s.get("frames_lost") or {}).values()),
                          "missing": sum(v.missing.values()) if v else None, "readable": v.readable if v else False,
                          "mismatched": mismatched, "kills": [k["victim"] for k in kills], "errors": s.get("errors")})
        for k in self.kills:  # the frames missing in the take around each kill
            take = next((t for t in takes if t["started_s"] <= k["at_s"] <= t["ended_s"]), None)
            k["take"] = take["take"] if take else None
            k["missing_in_take"] = take["missing"] if take and len(take["kills"]) == 1 else None
        return {"minutes": self.args.minutes, "cameras": self.args.cameras, "size": list(self.args.size), "fps": self.args.fps,
                "kill_every_s": self.args.kill_every, "take_seconds": self.args.take_seconds,
                "takes": takes, "kills": self.kills, "growth": growth(self.samples, self.args.warm_up),
                "viewer": {"frames": self.viewer.frames if self.viewer else 0, "reconnects": self.viewer.reconnects if self.viewer else 0},
                "mismatched_sets": sum(t["mismatched"] for t in takes), "sets": sum(t["sets"] or 0 for t in takes),
                "samples": self.samples}


def _rows(take: Path) -> list[dict]:
    try:
        return [json.loads(line) for line in (take / "index.jsonl").read_text().splitlines() if line.endswith("}")]
    except OSError:
        return []


def growth(samples: list[dict], warm_up_s: float) -> dict[str, dict]:
    """Per role, over each of its processes that lived long enough after the warm-up: the median of
    the last fifth of the samples against the median of the first fifth (resident memory, file
    descriptors). A role's figure is its worst process's."""
    out: dict[str, dict] = {}
    by_pid: dict[tuple[str, int], list[dict]] = {}
    for s in samples:
        by_pid.setdefault((s["role"], s["pid"]), []).append(s)
    for (role, pid), rows in by_pid.items():
        if role == "record":
            continue  # a take's process lives one take: compared across takes below
        restarted = rows[0]["t"] > 2 * SAMPLE_S  # a daemon the supervisor started again warms up too
        cutoff = rows[0]["t"] + warm_up_s if restarted else warm_up_s
        rows = [r for r in rows if r["t"] >= cutoff]
        if len(rows) < 10:
            continue
        n = max(2, len(rows) // 5)
        g = {k: statistics.median(r[k] for r in rows[-n:]) / max(1, statistics.median(r[k] for r in rows[:n])) - 1.0 for k in ("rss", "fds")}
        best = out.get(role)
        if best is None or max(g.values()) > max(best["rss"], best["fds"]):
            out[role] = {"rss": round(g["rss"], 4), "fds": round(g["fds"], 4), "pid": pid, "samples": len(rows),
                         "rss_mb": round(rows[-1]["rss"] / 1e6, 1), "fds_now": rows[-1]["fds"]}
    peaks = {}
    for s in samples:
        if s["role"] == "record":
            peaks.setdefault(s["pid"], []).append(s)
    if len(peaks) >= 4:  # each take's peak, the last takes against the first
        per_take = [max(r["rss"] for r in rows) for _, rows in sorted(peaks.items(), key=lambda kv: kv[1][0]["t"])]
        fds = [max(r["fds"] for r in rows) for _, rows in sorted(peaks.items(), key=lambda kv: kv[1][0]["t"])]
        n = max(1, len(per_take) // 3)
        out["record (per take)"] = {"rss": round(statistics.median(per_take[-n:]) / statistics.median(per_take[:n]) - 1.0, 4),
                                    "fds": round(statistics.median(fds[-n:]) / statistics.median(fds[:n]) - 1.0, 4), "takes": len(per_take)}
    return out


def plot(result: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.2))
    roles = sorted({s["role"] for s in result["samples"]})
    for role in roles:
        rows = [s for s in result["samples"] if s["role"] == role]
        style = "." if role == "record" else "-"
        a.plot([r["t"] / 60 for r in rows], [r["rss"] / 1e6 for r in rows], style, label=role, markersize=2)
        b.plot([r["t"] / 60 for r in rows], [r["fds"] for r in rows], style, label=role, markersize=2)
    for k in result["kills"]:
        for ax in (a, b):
            ax.axvline(k["at_s"] / 60, color="red", alpha=0.25)
    a.set_title("resident memory (MB)")
    b.set_title("open file descriptors")
    for ax in (a, b):
        ax.set_xlabel("minutes (red: a kill -9)")
        ax.grid(alpha=0.3)
    b.legend(fontsize=7, loc="upper left", ncol=2)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--kill-every", type=float, default=60.0, help="seconds between kills")
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--take-seconds", type=float, default=30.0)
    ap.add_argument("--warm-up", type=float, default=60.0, help="seconds before growth is counted")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="folder for soak.json, soak.png and the processes' logs (default: a temporary one)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.lower().split("x"))
    args.size = (w, h)
    root = args.out or Path(tempfile.mkdtemp(prefix="soak-"))
    root.mkdir(parents=True, exist_ok=True)
    soak = Soak(args, root)
    try:
        result = soak.run()
    finally:
        soak.close()
    plot(result, root / "soak.png")
    (root / "soak.json").write_text(json.dumps(result, indent=1))
    summary = {k: v for k, v in result.items() if k != "samples"}
    bad = [f"{role} {k} grew {100 * g[k]:.1f} %" for role, g in result["growth"].items() for k in ("rss", "fds") if g[k] > GROWTH_LIMIT]
    bad += [f"kill of {k['victim']} at {k['at_s']} s: not recovered" for k in result["kills"] if k["daemon_back_s"] is None or k["live_frames_again_s"] is None]
    bad += [f"{t['take']}: not readable" for t in result["takes"] if not t["readable"]]
    if result["mismatched_sets"]:
        bad.append(f"{result['mismatched_sets']} mismatched sets")
    summary["verdict"] = "pass" if not bad else "fail"
    summary["failures"] = bad
    if args.json:
        print(json.dumps(summary))
    else:
        print(json.dumps(summary, indent=1))
    print(f"soak: {summary['verdict']}; {len(result['kills'])} kills, {len(result['takes'])} takes, {result['sets']} sets; "
          f"plot {root / 'soak.png'}", file=sys.stderr)
    return 0 if not bad else 1


if __name__ == "__main__":
    raise SystemExit(main())
