"""Camera frame sources behind one interface (bags, video files, Aravis, V4L2).

The concrete sources are imported on first use (importing `vmocap_core.sources.bag` does not
load OpenCV or Aravis; Aravis/PyGObject is imported only when an AravisFrameSource opens).
"""

from __future__ import annotations

import importlib
from typing import Any

from .base import Frame, FrameSource

_LAZY = {
    "AravisFrameSource": ".aravis", "ClockMapper": ".clock", "make_source": ".factory", "FrameSet": ".rig",
    "SourceRig": ".rig", "V4L2FrameSource": ".v4l2", "VideoFrameSource": ".video", "open_videos": ".video",
}

__all__ = ["Frame", "FrameSource", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
