"""Room on a filesystem: `df` (so a host's own view, quotas of container mounts included), or
statvfs where df is missing."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rig.doctor.host import Host


@dataclass
class Space:
    mount: str
    size: int
    avail: int


def existing(path: Path) -> Path:
    """The path, or its nearest ancestor that exists (a take's folder is made when it starts)."""
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def space(host: Host, path: Path) -> Optional[Space]:
    path = existing(path)
    out = host.run(["df", "-B1", "--output=target,size,avail", str(path)])
    if out is not None and out.ok:
        lines = out.stdout.strip().splitlines()
        if len(lines) >= 2:
            try:
                target, size, avail = lines[-1].rsplit(None, 2)
                return Space(target, int(size), int(avail))
            except ValueError:
                pass
    try:
        st = os.statvfs(path)
    except OSError:
        return None
    return Space(str(path), st.f_blocks * st.f_frsize, st.f_bavail * st.f_frsize)
