"""Ctrl-C (or `kill`, which `rig record` turns into the same KeyboardInterrupt) reaching the recorder
while it waits for room in a camera's queue: the set being queued is written whole, and every set
written after it (`rig record` writes the sets still in flight) is indexed. Another exception there
leaves the frames that did not reach their queue as gaps, and the rows after it are still written.
Before, the interrupted set waited forever for its unqueued frame and no row after it was written:
their images were on the disk but not in the take."""
from __future__ import annotations

import json
import os
import signal
import threading

import numpy as np
import pytest

from rig.config import CameraConfig
from rig.storage.layout import INDEX
from rig.storage.recorder import QUEUE_FRAMES, SequenceWriter
from rig.storage.validate import validate
from sync.frames import Frame, FrameSet

W, H = 640, 360
CAMS = [CameraConfig(name=n, uri=f"sim://{n}", role=n, width=W, height=H, pixel_format="RGB8", trigger="software")
        for n in ("left", "right")]


def frame_set(i: int, image: np.ndarray) -> FrameSet:
    ts = 1_000_000 + i * 33_000_000
    return FrameSet(index=i, frames={c.name: Frame(image, c.name, i + 1, ts, ts, "RGB8") for c in CAMS}, host_ts_ns=ts)


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals reach the main thread only")
@pytest.mark.parametrize("stop", [KeyboardInterrupt, SystemExit])
def test_interrupt_while_queueing_a_set_loses_no_written_frame(tmp_path, stop):
    image = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)  # noise: slow to compress
    seq = tmp_path / "seq"
    writer = SequenceWriter(seq, CAMS, rate_hz=30.0, codec="png", encoders=1)

    def interrupt(signum, frame):
        raise stop

    previous = signal.signal(signal.SIGALRM, interrupt)
    sent = 0
    try:
        # the queues fill in milliseconds (a noise frame takes tens of ms to compress): the alarm
        # finds write() waiting for room, as Ctrl-C does when compression or the disk lags
        signal.setitimer(signal.ITIMER_REAL, 0.3)
        with pytest.raises(stop):
            for i in range(10 * QUEUE_FRAMES):
                writer.write(frame_set(i, image))
                sent += 1
        assert sent < 10 * QUEUE_FRAMES
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    # what `rig record` does next: write the sets still in flight, then close the take
    for i in range(sent + 1, sent + 3):
        assert writer.write(frame_set(i, image))
    writer.close()

    rows = [json.loads(line) for line in (seq / INDEX).read_text().splitlines()]
    assert len(rows) == sent + 3  # every set, the interrupted one too (with what it queued)
    assert [r["trigger"] for r in rows[-2:]] == [sent + 1, sent + 2]
    for cam in CAMS:
        on_disk = sorted(f"frames/{cam.name}/{p.name}" for p in (seq / "frames" / cam.name).iterdir())
        indexed = sorted(r["frames"][cam.name]["file"] for r in rows if r["frames"][cam.name] is not None)
        assert on_disk == indexed  # every image written is in the take
        assert writer.frames_written[cam.name] == len(indexed)
    interrupted = rows[sent]["frames"]
    if stop is KeyboardInterrupt:  # the take stops by writing what is in flight: this set too
        assert all(f is not None for f in interrupted.values())
    else:  # the frame that never reached its queue is a marked gap
        assert sum(f is None for f in interrupted.values()) >= 1
    v = validate(seq)
    assert v.readable and v.sets == sent + 3, v.errors
    assert not any(n.startswith(".") for n in os.listdir(seq))
