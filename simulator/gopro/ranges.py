"""Media downloads with HTTP Range (RFC 9110 section 14), so that an interrupted download resumes.

One range per request, as a client resuming a download asks (`bytes=N-`, `bytes=N-M`, `bytes=-N`);
a request for several ranges gets the whole file (a server may ignore Range). Our own sender
rather than Starlette's FileResponse: the emulator must be able to cut a body or stall it part way
(`Body.cut_after`, the link check), which is what a client's resume is tested against.
"""
from __future__ import annotations

import asyncio
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Awaitable, Callable, Optional

CHUNK = 64 * 1024
_RANGE = re.compile(r"^\s*bytes\s*=\s*(\d*)\s*-\s*(\d*)\s*$", re.IGNORECASE)


class Unsatisfiable(ValueError):
    pass


def parse_range(header: Optional[str], size: int) -> Optional[tuple[int, int]]:
    """(first, last) byte, inclusive, of a single-range header; None for the whole file.

    Raises Unsatisfiable when the range starts past the end of the file (416).
    """
    if not header:
        return None
    m = _RANGE.match(header)
    if not m or (not m.group(1) and not m.group(2)):
        return None  # not a single byte range we understand: the whole file
    first, last = m.group(1), m.group(2)
    if not first:  # suffix: the last N bytes
        n = int(last)
        if n == 0:
            raise Unsatisfiable(header)
        return max(0, size - n), size - 1
    start = int(first)
    end = min(int(last), size - 1) if last else size - 1
    if start >= size or (last and int(last) < start):
        raise Unsatisfiable(header)
    return start, end


@dataclass
class Body:
    """How a file is sent: `cut_after` bytes then the connection closes (None: all of it);
    `pace` (bytes per second) slows it; `hold` is awaited before each chunk and returns False
    when the link is gone (the rest is then never sent)."""

    path: Path
    first: int
    last: int
    cut_after: Optional[int] = None
    pace: Optional[float] = None
    hold: Optional[Callable[[], Awaitable[bool]]] = None

    async def send(self, send) -> str:
        """Send the bytes as ASGI body messages: "complete", "cut" (`cut_after` reached) or "gone"
        (the link or the client went away)."""
        remaining = self.last - self.first + 1
        budget = self.cut_after if self.cut_after is not None else remaining
        with open(self.path, "rb") as f:
            f.seek(self.first)
            while remaining > 0:
                if self.hold is not None and not await self.hold():
                    return "gone"
                if budget <= 0:
                    return "cut"
                chunk = f.read(min(CHUNK, remaining, budget))
                if not chunk:
                    return "cut"  # the file shrank under us
                remaining -= len(chunk)
                budget -= len(chunk)
                await send({"type": "http.response.body", "body": chunk, "more_body": remaining > 0})
                if self.pace:
                    await asyncio.sleep(len(chunk) / self.pace)
        return "complete"
