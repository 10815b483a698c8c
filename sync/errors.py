"""Errors of the sync layer (trigger boards, grouping)."""
from common.errors import ReportedError


class SyncError(ReportedError):
    exit_code = 1


class TriggerBoardError(SyncError):
    """The trigger board is absent, unplugged or speaks something else."""
