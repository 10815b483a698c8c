"""The status line and the progress bar draw on a terminal (a real pty here) and stay silent on
anything else, so piped and --json output is never mixed with them."""
from __future__ import annotations

import io
import os
import re

import pytest

from rig.progress import ProgressBar, StatusLine

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


@pytest.fixture
def terminal():
    """A file on the slave side of a pty, and a function that reads what reached the master side."""
    master, slave = os.openpty()
    stream = os.fdopen(slave, "w")

    def seen() -> str:
        stream.flush()
        chunks = []
        os.set_blocking(master, False)
        while True:
            try:
                chunk = os.read(master, 65536)
            except BlockingIOError:
                break
            if not chunk:
                break
            chunks.append(chunk)
        return ANSI.sub("", b"".join(chunks).decode(errors="replace"))

    yield stream, seen
    stream.close()
    os.close(master)


def test_the_status_line_redraws_in_place_and_ends_with_its_last_text(terminal):
    stream, seen = terminal
    status = StatusLine(stream, min_interval=0.0)
    status.update("  1.0 s  30 sets")
    status.update("  2.0 s  60 sets")
    status.done("  3.0 s  90 sets")
    out = seen()
    assert "30 sets" in out and "60 sets" in out and "90 sets" in out
    assert "\n" not in out.replace("\r\n", "\n").rstrip("\n"), "one line, redrawn in place"
    assert out.rstrip("\r\n").endswith("90 sets")


def test_the_status_line_keeps_to_its_pace_unless_forced(terminal):
    stream, seen = terminal
    status = StatusLine(stream, min_interval=60.0)
    status.update("first")
    status.update("too soon")
    status.update("forced", force=True)
    status.done()
    out = seen()
    assert "first" in out and "too soon" not in out and "forced" in out


def test_the_progress_bar_counts_and_is_not_drawn_without_work(terminal):
    stream, seen = terminal
    with ProgressBar("left: pre-rendering", stream) as bar:
        for i in range(1, 5):
            bar.update(i, 4)
    out = seen()
    assert "left: pre-rendering" in out and "4/4" in out
    with ProgressBar("right: pre-rendering", stream):
        pass  # e.g. the loop came from the cache: nothing to show
    assert seen() == ""


def test_both_are_silent_when_the_stream_is_not_a_terminal():
    buf = io.StringIO()
    status = StatusLine(buf)
    status.update("text", force=True)
    status.done("end")
    with ProgressBar("work", buf) as bar:
        bar.update(1, 2)
    assert buf.getvalue() == ""
    assert not StatusLine(buf).enabled and not ProgressBar("x", buf).enabled
