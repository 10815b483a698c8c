"""An onlooker of a running session: what the console (rig/console/) hears from the library's own
take, sync check and calibration capture while they run, instead of running them a second time.

    class Previews:                          # any object with these three methods
        def opened(self, session): ...       # the session is open: its cameras (controls) are reachable
        def frame_set(self, fs, figures): ...  # each set as the work handles it; figures: its own counts
        def closed(self): ...                # the session is closing

A tap must return at once (keep a reference, never encode or copy there): it runs on the work's
own thread, and a slow onlooker would slow the take. An exception in a tap is logged and the tap
dropped, never the work's.
"""
from __future__ import annotations

import contextlib
import logging
from typing import Any, Iterator, Optional, Protocol

log = logging.getLogger(__name__)


class SessionTap(Protocol):
    def opened(self, session: Any) -> None: ...

    def frame_set(self, fs: Any, figures: dict) -> None: ...

    def closed(self) -> None: ...


class _Guarded:
    """A tap whose failures are logged once and then silence it."""

    def __init__(self, tap: SessionTap):
        self.tap: Optional[SessionTap] = tap

    def _call(self, name: str, *args) -> None:
        if self.tap is None:
            return
        try:
            getattr(self.tap, name)(*args)
        except Exception:
            log.exception("session tap %s failed; it hears nothing more of this run", name)
            self.tap = None

    def opened(self, session) -> None:
        self._call("opened", session)

    def frame_set(self, fs, figures: dict) -> None:
        self._call("frame_set", fs, figures)

    def closed(self) -> None:
        self._call("closed")


@contextlib.contextmanager
def tapped(tap: Optional[SessionTap], session) -> Iterator[Optional[_Guarded]]:
    """Tell `tap` (if any) the session is open, and that it closes when the block ends."""
    if tap is None:
        yield None
        return
    guarded = tap if isinstance(tap, _Guarded) else _Guarded(tap)
    guarded.opened(session)
    try:
        yield guarded
    finally:
        guarded.closed()


def guard(tap: Optional[SessionTap]) -> Optional[_Guarded]:
    return None if tap is None or isinstance(tap, _Guarded) else _Guarded(tap)
