"""Errors of the model pipeline (export, runtime)."""
from common.errors import ReportedError


class InferenceError(ReportedError):
    exit_code = 2
