"""Simulated time zero: scene time t = (monotonic_ns - SIM_EPOCH_NS) / 1e9 while running live.

Camera daemons of one rig are separate processes that must show the same scene instant at the same
host time: `rig up` gives them all its own zero in $RIG_SIM_EPOCH_NS (the monotonic clock is
system-wide)."""
from __future__ import annotations

import os

from sync.frames import monotonic_ns

SIM_EPOCH_NS = int(os.environ.get("RIG_SIM_EPOCH_NS") or 0) or monotonic_ns()
