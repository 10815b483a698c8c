"""A trigger board on a serial port or any other pyserial URL (`serial:///dev/ttyACM0`,
`socket://127.0.0.1:7000`, `rfc2217://...`): sync.link opens the URL as it is."""
from __future__ import annotations


def open(trigger, inputs, rig=None):  # noqa: A001 - the backend contract's name
    return trigger.uri, None
