"""Faults a test injects into an emulated GoPro: HTTP errors (a count of requests or a stretch of
time), a dead link (HTTP stalls, the UDP stream goes silent) and a download cut short."""
from __future__ import annotations

import threading
from typing import Callable, Optional


class Faults:
    def __init__(self, clock: Callable[[], float]):
        self._clock = clock
        self._lock = threading.Lock()
        self._error_count = 0
        self._error_until = 0.0
        self._error_status = 500
        self._drop_until = 0.0
        self._cut_after: Optional[int] = None

    def inject_http_errors(self, count: Optional[int] = None, seconds: Optional[float] = None, status: int = 500) -> None:
        if (count is None) == (seconds is None):
            raise ValueError("inject_http_errors takes a count of requests or a number of seconds (one of them)")
        if not 400 <= int(status) <= 599:
            raise ValueError(f"an injected HTTP error needs a 4xx or 5xx status, not {status}")
        with self._lock:
            self._error_status = int(status)
            if count is not None:
                self._error_count += max(0, int(count))
            else:
                self._error_until = max(self._error_until, self._clock() + float(seconds))

    def take_error(self) -> Optional[int]:
        """The status to answer this request with, or None to serve it."""
        with self._lock:
            if self._error_count > 0:
                self._error_count -= 1
                return self._error_status
            if self._clock() < self._error_until:
                return self._error_status
            return None

    def drop_link(self, seconds: float) -> None:
        with self._lock:
            self._drop_until = max(self._drop_until, self._clock() + max(0.0, float(seconds)))

    def link_down_for(self) -> float:
        """Seconds until the link is back (0: it is up)."""
        with self._lock:
            return max(0.0, self._drop_until - self._clock())

    def cut_next_download(self, after_bytes: int) -> None:
        with self._lock:
            self._cut_after = max(0, int(after_bytes))

    def take_cut(self) -> Optional[int]:
        with self._lock:
            cut, self._cut_after = self._cut_after, None
            return cut
