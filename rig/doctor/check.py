"""One line of the doctor's report: what was checked, what was found, what the rig needs, the fix."""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Optional

OK, WARN, FAIL = "ok", "warn", "fail"
STATUSES = (OK, WARN, FAIL)


@dataclass
class Check:
    area: str                  # usb, network, devices, memory, disk, compute
    name: str                  # what was checked, e.g. "net.core.rmem_max" or "MTU eth1 (left)"
    status: str                # ok | warn | fail
    measured: str              # what this host has
    needed: str                # what this rig needs
    fix: Optional[str] = None  # the exact shell command that fixes it (never run by the doctor)
    note: str = ""             # why, or what to do when no single command fixes it

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"status {self.status!r} is not one of {STATUSES}")

    def to_json(self) -> dict:
        return asdict(self)


def worst(checks: list[Check]) -> str:
    """The report's verdict: fail if any check fails, else warn if any warns, else ok."""
    statuses = {c.status for c in checks}
    return FAIL if FAIL in statuses else WARN if WARN in statuses else OK


def mib(n: float) -> str:
    """Bytes as MiB for a report line (1 decimal below 10 MiB)."""
    v = n / (1 << 20)
    return f"{v:.1f} MiB" if v < 10 else f"{v:.0f} MiB"


def rate(bps: float) -> str:
    """Bytes per second as MB/s (decimal, as disk makers and dd state them)."""
    return f"{bps / 1e6:.1f} MB/s"
