"""Trigger boards, chosen by URI scheme as the cameras are (rig.cameras).

A module of this package named after a scheme opens that scheme's boards (`sim.py`: the emulated
board of `sim://trigger`); any other scheme is a pyserial URL, opened as it is (`serial.py`:
`serial:///dev/ttyACM0`, `socket://HOST:PORT`, `rfc2217://...`). Adding a kind of board is adding a
module. A backend defines

    open(trigger, inputs, rig=None) -> (url, device)

`trigger`: the rig's TriggerConfig; `inputs`: camera name -> that camera's hardware-trigger input
(`fire(pulse_index, host_ns)`), which an emulated board drives; `rig`: the RigConfig whose cameras
are opened in this process, when they are. It returns the URL the board is driven through
(sync.board.TriggerBoard) and the device behind it that the caller closes after the board (an
emulator), or None. A board that a board daemon owns (`rig up`) is reached through that daemon
instead: rig.daemon.board_client.open_board chooses.
"""
from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType
from typing import Any, Callable, Optional

from sync.board import TriggerBoard

DEFAULT = "serial"  # what opens the schemes no module is named after


def backend(scheme: str) -> ModuleType:
    names = {info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_")}
    return importlib.import_module(f"{__name__}.{scheme if scheme in names else DEFAULT}")


def open_board(trigger, inputs: dict[str, Callable[[int, int], None]], rig=None) -> tuple[TriggerBoard, Optional[Any]]:
    """The rig's trigger board (not yet connected) and the device behind it to close after it, or None."""
    url, device = backend(trigger.uri.split("://", 1)[0]).open(trigger, inputs, rig)
    return TriggerBoard(url), device
