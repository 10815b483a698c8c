"""Errors of the model pipeline (export, runtime)."""


class InferenceError(Exception):
    exit_code = 2
