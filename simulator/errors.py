"""Errors of the simulator."""


class SimulatorError(Exception):
    exit_code = 2
