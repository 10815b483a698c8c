"""The rig's exception hierarchy. Every message says what went wrong and what to do about it.

`exit_code` is what the CLI exits with: 2 for bad input (a config, a URI, a file), 1 for a device or
I/O failure during work.
"""
from common.errors import ReportedError


class RigError(ReportedError):
    exit_code = 1


class ConfigError(RigError):
    """A rig configuration or command-line value is invalid.

    `problems` lists every mistake found, one line each (a config file can have several); the message
    is the first, with a count of the others, so that other commands still print one line.
    """

    exit_code = 2

    def __init__(self, message: str, problems: list[str] | None = None):
        super().__init__(message)
        self.problems = list(problems) if problems else [message]

    @classmethod
    def of(cls, problems: list[str]) -> "ConfigError":
        more = len(problems) - 1
        message = problems[0] if not more else (
            f"{problems[0]} (and {more} more problem{'s' if more > 1 else ''}: `rig config check` lists every one)")
        return cls(message, problems)


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
