"""Camera frame sources behind one interface (bags, video files, Aravis, V4L2)."""

from .base import Frame, FrameSource

__all__ = ["Frame", "FrameSource"]
