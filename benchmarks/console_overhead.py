"""What the console's previews cost a take: recording throughput with the console's viewers open
against the same take recorded without the console, in the same run.

A simulated rig (six cameras by default) records takes of fixed length with rig record's own
`record()`, in rounds that alternate:
- `plain`: `record()` alone, as `rig record` runs it;
- `console`: the same take started from the console (rig.console.rigstate.ConsoleRig.start_take,
  which calls the same `record()` with its tap), with VIEWERS WebSocket viewers on the console's
  server, each taking every camera's preview at --preview-fps and acknowledging each one as a
  browser does (the server sends a camera's next preview only after the last was acknowledged).
Throughput: complete sets written per second of take, and MB/s written; lost: sets skipped and
frames lost. The ratio console / plain is the figure (acceptance: at least 0.9).

    .venv/bin/python benchmarks/console_overhead.py [--cameras 6] [--size 640x360] [--fps 15] [--seconds 10]
        [--codec png] [--viewers 1] [--preview-fps 5] [--rounds 2] [--json]

PNG compression makes the recorder itself CPU-bound, so that previews competing for the CPU show;
with `--codec raw` the disk decides.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def rig_config(root: Path, cameras: int, size: tuple[int, int], fps: float):
    from rig.config import dump_config, load_config, parse_config
    from rig.sim.rig_config import sim_rig_config

    data = sim_rig_config(cameras, width=size[0], height=size[1], fps=fps)
    data["rig"]["storage"] = str(root / "takes")
    path = root / "rig.toml"
    path.write_text(dump_config(parse_config(data, path)))
    return load_config(path)


def _viewer_process(url: str, rate: float, count, stop) -> None:
    """A browser's part, in a process of its own as a browser is: connect, take every camera's
    preview, acknowledge each one (the server sends the next only then), reconnect if dropped."""
    import websockets.exceptions
    import websockets.sync.client as wsc

    while not stop.is_set():
        try:
            # as a browser: answers the server's pings, sends none of its own
            with wsc.connect(url, open_timeout=10, max_size=None, ping_interval=None) as ws:
                ws.send(json.dumps({"type": "prefs", "rate": rate, "width": 320}))
                while not stop.is_set():
                    try:
                        msg = ws.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    if isinstance(msg, bytes):
                        n = struct.unpack(">I", msg[:4])[0]
                        header = json.loads(msg[4:4 + n])
                        with count.get_lock():
                            count.value += 1
                        ws.send(json.dumps({"type": "ack", "camera": header["camera"]}))
        except (OSError, websockets.exceptions.WebSocketException):
            time.sleep(0.5)


class PreviewViewer:
    """A WebSocket viewer of the console in its own process (not competing for this one's GIL)."""

    def __init__(self, url: str, rate: float):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self._count = ctx.Value("q", 0)
        self._stop = ctx.Event()
        self._proc = ctx.Process(target=_viewer_process, args=(url, rate, self._count, self._stop), daemon=True)

    @property
    def previews(self) -> int:
        return int(self._count.value)

    def start(self) -> None:
        self._proc.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float) -> None:
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()


def plain_take(cfg, out: Path, seconds: float, codec: str) -> dict:
    from rig.capture.record import record

    return record(cfg, out, seconds=seconds, codec=codec).to_dict()


def console_take(rig, server, name: str, seconds: float, codec: str, viewers: int, rate: float) -> dict:
    threads = [PreviewViewer(server.url.replace("http", "ws") + "ws", rate) for _ in range(viewers)]
    for t in threads:
        t.start()
    deadline = time.monotonic() + 120
    while any(t.previews < 3 * len(rig.views) for t in threads):  # previews flowing before the take
        if time.monotonic() > deadline:
            raise SystemExit("error: the console's previews did not start")
        time.sleep(0.1)
    before = [t.previews for t in threads]
    rig.start_take(name, seconds=seconds, codec=codec)
    while rig.take["state"] not in ("done", "failed"):
        time.sleep(0.1)
    for t in threads:
        t.stop()
    if rig.take["state"] == "failed":
        raise SystemExit(f"error: the console's take failed: {rig.take['error']}")
    summary = dict(rig.take["summary"])
    took = rig.take["ended_monotonic"] - rig.take["started_monotonic"]
    summary["previews_per_s"] = round(sum(t.previews - b for t, b in zip(threads, before)) / took, 2)
    for t in threads:
        t.join(5)
    return summary


def figures(s: dict) -> dict:
    secs = s["seconds"] or 1e-9
    return {"complete_sets_per_s": round(s["complete_sets"] / secs, 3), "mb_per_s": s["mb_per_s"], "sets": s["sets"],
            "complete_sets": s["complete_sets"], "sets_skipped": s["sets_skipped"], "frames_lost": sum(s["frames_lost"].values()),
            "cpu_percent": s["cpu_percent"], "seconds": s["seconds"], **({"previews_per_s": s["previews_per_s"]} if "previews_per_s" in s else {})}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=6)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--codec", choices=("raw", "png"), default="png")
    ap.add_argument("--viewers", type=int, default=1)
    ap.add_argument("--preview-fps", type=float, default=5.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    from rig.console.rigstate import ConsoleRig
    from rig.console.server import ConsoleServer

    root = Path(tempfile.mkdtemp(prefix="console-overhead-"))
    try:
        cfg = rig_config(root, args.cameras, size, args.fps)
        rows = {"plain": [], "console": []}
        rig = ConsoleRig(cfg)
        server = ConsoleServer(rig, "127.0.0.1", 0).start()
        try:
            for k in range(args.rounds):
                # plain first in each round: the console's previews are closed while it records
                rows["plain"].append(figures(plain_take(cfg, root / "takes" / f"plain-{k}", args.seconds, args.codec)))
                if k == 0:
                    rig.start()
                else:
                    rig.resume_previews()
                rows["console"].append(figures(console_take(rig, server, f"console-{k}", args.seconds, args.codec, args.viewers,
                                                           args.preview_fps)))
                rig.pause_previews()  # the console lets go of the cameras for the next plain take
                print(f"round {k + 1}: plain {rows['plain'][-1]}\n         console {rows['console'][-1]}", file=sys.stderr, flush=True)
        finally:
            server.stop()
            rig.close()
        med = {m: statistics.median(r["complete_sets_per_s"] for r in rows[m]) for m in rows}
        mb = {m: statistics.median(r["mb_per_s"] for r in rows[m]) for m in rows}
        report = {"rig": {"cameras": args.cameras, "size": list(size), "fps": args.fps, "codec": args.codec, "seconds": args.seconds},
                  "viewers": args.viewers, "preview_fps": args.preview_fps, "rounds": rows,
                  "complete_sets_per_s": med, "mb_per_s": mb, "ratio": round(med["console"] / med["plain"], 4) if med["plain"] else None,
                  "ratio_mb": round(mb["console"] / mb["plain"], 4) if mb["plain"] else None}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    if args.json:
        print(json.dumps(report))
    else:
        print(f"{args.cameras} cameras {size[0]}x{size[1]} at {args.fps:g} fps, {args.codec}, takes of {args.seconds:g} s, "
              f"{args.viewers} viewer(s) at {args.preview_fps:g} previews/s per camera, {args.rounds} rounds")
        print(f"complete sets per second: plain {med['plain']:.2f}, with the console {med['console']:.2f}: ratio {report['ratio']}")
        print(f"MB/s written: plain {mb['plain']:.1f}, with the console {mb['console']:.1f}: ratio {report['ratio_mb']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
