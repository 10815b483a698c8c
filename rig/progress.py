"""What a long command shows while it works: a status line, and a progress bar for a step with a
known length, on a terminal; notes, one plain line per start-up phase, on stderr.

The status line and the bar are silent when the stream is not a terminal (piped, redirected to a
file, captured by a test), so machine-read output stays clean. Notes are plain lines on a terminal
or not (they read as well in a log), and silent in --json mode, where stderr carries only errors.

Drawing is left to `rich` (terminal width, cursor handling, redraw in place); rich is imported only
when there is a terminal to draw on.
"""
from __future__ import annotations

import sys
import time
from typing import Any, Optional, TextIO


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def _console(stream: TextIO) -> Any:
    from rich.console import Console

    # the terminal test is ours (isatty, as always); rich must not second-guess it from the environment
    return Console(file=stream, force_terminal=True, highlight=False, markup=False)


MIN_RATE_S = 1.0  # a rate over a shorter span is noise: the first sets can land microseconds apart
MIN_RATE_COUNT = 5


def rate(count: float, elapsed: float, *, min_elapsed: float = MIN_RATE_S, min_count: float = MIN_RATE_COUNT) -> Optional[float]:
    """`count` per second over `elapsed` seconds, or None while too little has passed for the rate
    to mean anything (a status line showed "124008 sets/s" for its first set)."""
    if elapsed < min_elapsed or count < min_count:
        return None
    return count / elapsed


def rate_text(value: Optional[float], width: int = 5, decimals: int = 1) -> str:
    """A rate for a status line: the number, or dashes of the same width until there is one."""
    return f"{value:{width}.{decimals}f}" if value is not None else "--".rjust(width)


class Notes:
    """One plain line on stderr per start-up phase, e.g. `rig: warming up the trigger board clock
    (3.0 s)`, so that a start that takes seconds is never silent. Call it with the text. Quiet (the
    --json mode) prints nothing. A library takes it as an optional callback and stays silent
    without one."""

    def __init__(self, stream: TextIO | None = None, quiet: bool = False):
        self.stream = stream
        self.quiet = quiet

    def __call__(self, text: str) -> None:
        if self.quiet:
            return
        stream = self.stream or sys.stderr  # looked up late: tests and `rig demo` swap sys.stderr
        try:
            stream.write(f"rig: {text}\n")
            stream.flush()
        except (OSError, ValueError):  # a closed or broken stderr must not stop the work
            pass


class StatusLine:
    """One line, redrawn in place: `update(text)` as often as wanted (redraws at most every
    `min_interval` s unless `force`), `done(text)` to leave the last text on its own line."""

    def __init__(self, stream: TextIO | None = None, min_interval: float = 0.2):
        self.stream = stream or sys.stderr
        self.enabled = _is_terminal(self.stream)
        self.min_interval = min_interval
        self._last = 0.0
        self._live: Any = None

    def update(self, text: str, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < self.min_interval:
            return
        self._last = now
        from rich.text import Text

        line = Text(text, no_wrap=True, overflow="ellipsis")  # one line, whatever the terminal's width
        if self._live is None:
            from rich.live import Live

            # no redirection of sys.stdout/stderr: commands print their results after done()
            self._live = Live(line, console=_console(self.stream), auto_refresh=False, transient=False,
                              redirect_stdout=False, redirect_stderr=False)
            self._live.start(refresh=True)
        else:
            self._live.update(line, refresh=True)

    def done(self, text: str | None = None) -> None:
        if not self.enabled:
            return
        if text is not None:
            self.update(text, force=True)
        if self._live is not None:
            self._live.stop()  # leaves the last text and moves to the next line
            self._live = None


class ProgressBar:
    """A bar for a step of known length, e.g. rendering N frames: `update(done, total)`.

    It appears at the first update (a step that turns out to have nothing to do, such as a loop
    found in the cache, shows nothing) and vanishes when closed. A context manager:

        with ProgressBar("left: pre-rendering") as bar:
            work(progress=bar.update)
    """

    def __init__(self, description: str, stream: TextIO | None = None):
        self.description = description
        self.stream = stream or sys.stderr
        self.enabled = _is_terminal(self.stream)
        self._progress: Any = None
        self._task: Optional[int] = None

    def update(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self._progress is None:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self._progress = Progress(TextColumn(self.description, markup=False), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                      TextColumn("eta"), TimeRemainingColumn(), console=_console(self.stream),
                                      auto_refresh=False, transient=True, redirect_stdout=False, redirect_stderr=False)
            self._progress.start()
            self._task = self._progress.add_task(self.description, total=total)
        self._progress.update(self._task, completed=done, total=total, refresh=True)

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
