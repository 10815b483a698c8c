"""Where a rig's daemons keep their files: one folder per rig under the shared-memory root.

    <root>/<rig>/<camera>          the camera's frame ring (rig.daemon.ring)
    <root>/<rig>/<camera>.json     how to reach its daemon: pid, API URL, trigger port (written once it serves)
    <root>/<rig>/@board.json       how to reach the trigger board's daemon, with its heartbeat
    <root>/<rig>/supervisor.json   `rig up`'s state: its pid, each daemon's pid, restarts, health

The root is /dev/shm/rig (memory, gone at reboot, as frames should be), or $RIG_SHM_ROOT: two
"hosts" on one machine, and tests, use roots of their own.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, Optional

DEFAULT_ROOT = "/dev/shm/rig"


def root() -> Path:
    return Path(os.environ.get("RIG_SHM_ROOT") or DEFAULT_ROOT)


def _safe(name: str) -> str:
    """A rig or camera name as one path component (names come from a config file)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", name) or "_"


def rig_dir(rig: str) -> Path:
    return root() / _safe(rig)


def ring_path(rig: str, camera: str) -> Path:
    return rig_dir(rig) / _safe(camera)


def info_path(rig: str, camera: str) -> Path:
    return rig_dir(rig) / f"{_safe(camera)}.json"


def board_info_path(rig: str) -> Path:
    """The trigger board daemon's info file ('@' is never in a camera's file name: _safe replaces it)."""
    return rig_dir(rig) / "@board.json"


def supervisor_path(rig: str) -> Path:
    return rig_dir(rig) / "supervisor.json"


def read_json(path: Path) -> Optional[dict[str, Any]]:
    """A state file's content, or None when it is missing, being replaced or not JSON."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def pid_alive(pid: Any) -> bool:
    try:
        pid = int(pid)
        if pid <= 0:
            return False
        os.kill(pid, 0)
    except (TypeError, ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True  # another user's process: alive
    return True
