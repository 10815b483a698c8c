"""The rig: configuration, camera backends, capture, recording, live output and the `rig` CLI."""
from sync.frames import Frame, FrameSet

__all__ = ["Frame", "FrameSet"]
