"""Camera ingest: calibrated projections, rig files, frame sources (bags, video files, Aravis, V4L2), synchronization.

The concrete sources are imported on first use (importing `vmocap_core.cameras.bag` does not
load OpenCV or Aravis; Aravis/PyGObject is imported only when an AravisFrameSource opens).
"""

from __future__ import annotations

import importlib
from typing import Any

from .base import Frame, FrameSource

_LAZY = {
    "AravisFrameSource": ".aravis", "ClockMapper": ".clock", "make_source": ".factory", "FrameSet": ".rig_source",
    "SourceRig": ".rig_source", "V4L2FrameSource": ".v4l2", "VideoFrameSource": ".video", "open_videos": ".video",
}

__all__ = ["Frame", "FrameSource", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
