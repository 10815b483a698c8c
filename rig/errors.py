"""The rig's exception hierarchy. Every message says what went wrong and what to do about it.

`exit_code` is what the CLI exits with: 2 for bad input (a config, a URI, a file), 1 for a device or
I/O failure during work.
"""
from common.errors import ReportedError


class RigError(ReportedError):
    exit_code = 1


class ConfigError(RigError):
    """A rig configuration or command-line value is invalid."""

    exit_code = 2


class BackendError(ConfigError):
    """No backend handles a URI scheme."""


class DeviceError(RigError):
    """A device failed: could not be opened, stopped answering, or rejected a setting."""


class DeviceNotFound(DeviceError):
    exit_code = 2


class CameraTimeout(DeviceError):
    """No frame arrived within the timeout; the camera still answers."""


class CameraDisconnected(DeviceError):
    """The camera stopped answering (unplugged, powered off, network lost)."""


class StorageError(RigError):
    """Writing to disk failed (full disk, permissions)."""
