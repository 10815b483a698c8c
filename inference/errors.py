"""Errors of the model pipeline (export, runtime)."""
from common.errors import ReportedError


class InferenceError(ReportedError):
    exit_code = 2


class OutputError(InferenceError):
    """Writing a result failed during the work (disk full, folder gone): exit 1, as in every command."""

    exit_code = 1
