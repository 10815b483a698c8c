"""A disk that fills during a take: what the recorder reports is what the take holds. The frames a
camera wrote for sets that were never indexed (another camera's frame of the set hit the full disk)
are not in the take, so they are not counted as recorded (before, `rig record` said `left: 8
frames` of a take whose index held 6, and its `frames_lost` hid those two)."""
from __future__ import annotations

import json

import numpy as np

from rig.config import CameraConfig
from rig.storage.layout import INDEX
from rig.storage.recorder import SequenceWriter
from rig.storage.validate import validate
from sync.frames import Frame, FrameSet

# a small camera that is always sets ahead of a big one: the big one fills the disk
CAMS = [CameraConfig(name="small", uri="sim://small", role="left", width=64, height=48, pixel_format="Mono8", trigger="software"),
        CameraConfig(name="big", uri="sim://big", role="right", width=640, height=360, pixel_format="RGB8", trigger="software")]


def test_frames_of_sets_the_full_disk_cut_off_are_not_counted_as_recorded(small_filesystem):
    seq = small_filesystem(3) / "seq"
    rng = np.random.default_rng(0)
    images = {"small": rng.integers(0, 256, (48, 64), dtype=np.uint8), "big": rng.integers(0, 256, (360, 640, 3), dtype=np.uint8)}
    writer = SequenceWriter(seq, CAMS, rate_hz=30.0)
    for i in range(40):
        frames = {c.name: Frame(images[c.name], c.name, i + 1, i, i, c.pixel_format) for c in CAMS}
        if not writer.write(FrameSet(index=i, frames=frames, host_ts_ns=i)):
            break
    writer.close()
    assert writer.error is not None and "disk full" in str(writer.error)

    rows = [json.loads(line) for line in (seq / INDEX).read_text().splitlines()]
    assert len(rows) == writer.sets_written  # (none, when the big camera filled the disk before the small one wrote)
    indexed = {c.name: [r["frames"][c.name]["file"] for r in rows if r["frames"][c.name]] for c in CAMS}
    assert writer.frames_written == {n: len(files) for n, files in indexed.items()}
    assert writer.bytes_written == sum((seq / f).stat().st_size for files in indexed.values() for f in files)
    assert writer.raw_bytes == sum(writer.entries[n].raw_bytes * k for n, k in writer.frames_written.items())
    v = validate(seq, check_pixels=True)
    assert v.readable and v.frames == writer.frames_written, v.errors
