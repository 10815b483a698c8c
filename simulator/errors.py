"""Errors of the simulator."""
from common.errors import ReportedError


class SimulatorError(ReportedError):
    exit_code = 2
