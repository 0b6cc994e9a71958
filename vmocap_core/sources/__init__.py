"""Camera frame sources behind one interface (bags, video files, Aravis, V4L2).

Aravis (PyGObject) is imported only when an AravisFrameSource is opened.
"""

from .aravis import AravisFrameSource
from .base import Frame, FrameSource
from .clock import ClockMapper
from .factory import make_source
from .rig import FrameSet, SourceRig
from .v4l2 import V4L2FrameSource
from .video import VideoFrameSource, open_videos

__all__ = ["Frame", "FrameSource", "AravisFrameSource", "ClockMapper", "FrameSet", "SourceRig", "V4L2FrameSource",
           "VideoFrameSource", "open_videos", "make_source"]
