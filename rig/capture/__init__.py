"""Running a rig: the session (cameras, trigger board, FrameSets out), grab, sync check, record."""
