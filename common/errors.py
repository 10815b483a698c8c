"""The root of every package's errors: an error the user is told about in one line.

Each package derives its own (`RigError`, `CalibrationError`, `SyncError`, `SimulatorError`,
`InferenceError`); the CLI catches this one class, prints the message on one line and exits with
`exit_code`: 2 for bad input (arguments, a config, a file given), 1 for a failure during the work.
"""


class ReportedError(Exception):
    exit_code = 1
