"""Fixtures for the rig package: a fresh Aravis fake GigE Vision camera per test (a real GVCP/GVSP peer)."""
from __future__ import annotations

import shutil
import socket
import subprocess
import time

import pytest

FAKE_CAMERA = "arv-fake-gv-camera-0.8"


def _aravis_available() -> str | None:
    if shutil.which(FAKE_CAMERA) is None:
        return f"{FAKE_CAMERA} not installed (Debian package aravis-tools)"
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the machine
        return f"Aravis GObject bindings not importable: {exc}"
    return None


def _gvcp_port_free() -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", 3956))
        return True
    except OSError:
        return False
    finally:
        s.close()


class FakeCamera:
    """arv-fake-gv-camera-0.8 on 127.0.0.1; `kill()` makes it vanish mid-stream."""

    address = "127.0.0.1"
    uri = "aravis://127.0.0.1"

    def __init__(self):
        deadline = time.monotonic() + 5
        while not _gvcp_port_free():  # the previous test's camera may still be exiting
            if time.monotonic() > deadline:
                raise RuntimeError("GVCP port 3956 on 127.0.0.1 is taken by another process")
            time.sleep(0.05)
        self.proc = subprocess.Popen([FAKE_CAMERA, "-i", self.address], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5
        while _gvcp_port_free():
            if self.proc.poll() is not None:
                raise RuntimeError(f"{FAKE_CAMERA} exited with {self.proc.returncode}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{FAKE_CAMERA} did not open its GVCP port")
            time.sleep(0.02)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


@pytest.fixture
def fake_camera():
    reason = _aravis_available()
    if reason:
        pytest.skip(reason)
    cam = FakeCamera()
    try:
        yield cam
    finally:
        cam.kill()
