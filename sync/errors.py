"""Errors of the sync layer (trigger boards, grouping)."""


class SyncError(Exception):
    exit_code = 1


class TriggerBoardError(SyncError):
    """The trigger board is absent, unplugged or speaks something else."""
