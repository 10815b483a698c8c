"""What `rig demo` and `rig demo --gopro` say and check of the disk: sizes, free space, bytes written."""
from __future__ import annotations

import shutil
from pathlib import Path


def mb(n: int) -> str:
    return f"{n / 1e6:.0f} MB" if n >= 10e6 else f"{n / 1e6:.1f} MB"


def check_space(out: Path, need: int) -> None:
    """One line (exit 2) when the folder's disk has less than `need` bytes free, with a tenth to spare."""
    from rig.errors import ConfigError

    base = out.absolute()
    while not base.exists():
        base = base.parent
    free = shutil.disk_usage(base).free
    if free < need * 1.1:
        raise ConfigError(f"{out}: the demo writes about {mb(need)} but {base} has {mb(free)} free; "
                          "free some space, or choose a shorter take (--seconds) or fewer cameras")


def written(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
