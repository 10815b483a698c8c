"""Disk: free space and a measured sequential write rate where the takes go, against the rig's data
rate (every camera's frame bytes x frames per second)."""
from __future__ import annotations

import os
from pathlib import Path

from rig.doctor.check import FAIL, OK, WARN, Check, mib, rate
from rig.doctor.host import Host
from rig.doctor.needs import RigNeeds
from rig.doctor.space import existing, space
from rig.errors import StorageError
from rig.storage.disk import measure_write_rate

AREA = "disk"
TEST_BYTES = 256 << 20   # the write test stops after this much...
TEST_SECONDS = 3.0       # ...or this long, whichever comes first, and never takes over a tenth of the free room
# A take writes more than its frames (the index, per-set syncs for crash safety): a disk within this
# share of its sequential rate has no room for that or for another program's writes.
HEADROOM = 0.8


def write_rate(folder: Path, max_bytes: int = TEST_BYTES, max_seconds: float = TEST_SECONDS) -> tuple[int, float]:
    """(bytes, seconds) of a sequential write of random data to a file in `folder`, on the disk
    (O_DIRECT, else fsync'd) and removed after: the same measurement `rig record` makes before a take."""
    measured = measure_write_rate(folder, seconds=max_seconds, max_bytes=max_bytes)
    if measured is None:  # under a megabyte free: nothing to measure, and nothing to record either
        return 0, 0.0
    return measured.bytes, measured.seconds


def rate_status(measured_bps: float, need_bps: float) -> str:
    if measured_bps < need_bps:
        return FAIL
    if need_bps > HEADROOM * measured_bps:
        return WARN
    return OK


def free_status(free: int, need: float) -> str:
    if free < need:
        return FAIL
    if free < 2 * need:  # room for this take but not the next one
        return WARN
    return OK


def checks(host: Host, needs: RigNeeds, output: Path, minutes: float, test_bytes: int = TEST_BYTES) -> list[Check]:
    need_rate = needs.data_rate
    folder = existing(Path(output))
    where = str(output) if folder == Path(output) else f"{output} (not made yet: measured on {folder})"
    out = []
    sp = space(host, folder)
    take = need_rate * minutes * 60
    if sp is None:
        out.append(Check(AREA, f"free space {output}", WARN, "unreadable", f">= {take / 1e9:.1f} GB"))
    else:
        st = free_status(sp.avail, take)
        fit = f", {sp.avail / need_rate / 60:.0f} min of recording" if need_rate else ""
        out.append(Check(AREA, f"free space {output}", st, f"{sp.avail / 1e9:.1f} GB{fit}",
                         f">= {take / 1e9:.1f} GB ({minutes:g} min at {rate(need_rate)})" + (", twice for a second take" if st == WARN else ""),
                         None, "" if st == OK else f"free room on {sp.mount} or record elsewhere (rig record -o DIR; rig doctor --output DIR)"))
    if not os.access(folder, os.W_OK | os.X_OK):
        out.append(Check(AREA, f"write rate {output}", FAIL, f"{folder} is not writable", f">= {rate(need_rate)}",
                         None, "rig record cannot write its take there"))
        return out
    size = test_bytes if sp is None else min(test_bytes, sp.avail // 10)  # never a tenth of the free room
    try:
        written, seconds = write_rate(folder, size)
    except StorageError as exc:  # the disk the doctor is to judge failed the test (EIO, a quota): a finding
        out.append(Check(AREA, f"write rate {where}", FAIL, str(exc), f">= {rate(need_rate)}", None,
                         "rig record cannot write its take there"))
        return out
    if written == 0:  # too little room to measure anything: say so, not that the disk is slow
        out.append(Check(AREA, f"write rate {where}", WARN, "not measured: too little free room for the write test",
                         f">= {rate(need_rate)}", None,
                         "the test takes at most a tenth of the free room and needs a megabyte at least: "
                         "free room or record elsewhere, then run rig doctor again"))
        return out
    measured = written / seconds if seconds > 0 else 0.0
    st = rate_status(measured, need_rate)
    note = {FAIL: "the disk cannot keep up: fewer cameras, smaller frames, a lower rate, or a faster disk",
            WARN: f"the rig needs more than {HEADROOM:.0%} of the disk's sequential rate: little room for the index, syncs and other writes",
            OK: ""}[st]
    out.append(Check(AREA, f"write rate {where}", st, f"{rate(measured)} ({mib(written)} in {seconds:.2f} s, to the disk)",
                     f">= {rate(need_rate)} ({len(needs.cameras)} camera{'s' if len(needs.cameras) != 1 else ''})", None, note))
    return out
