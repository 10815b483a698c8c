"""Trigger board protocol and driver, clock model, frame grouping and offline alignment."""
from sync.frames import PIXEL_FORMATS, Frame, FrameSet, monotonic_ns

__all__ = ["PIXEL_FORMATS", "Frame", "FrameSet", "monotonic_ns"]
