"""Capture daemons: one process per camera, frames in shared memory, a control API."""
