"""The interface every camera source implements."""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """One image of one camera."""

    camera: str  # camera name, as in the rig
    stamp_ns: int  # capture time in nanoseconds (ROS time base)
    image: np.ndarray  # (H, W, 3) uint8 BGR or (H, W) uint8 mono
    seq: int = 0  # per-camera frame counter as the source saw it

    @property
    def encoding(self) -> str:
        return "bgr8" if self.image.ndim == 3 else "mono8"


class FrameSource(abc.ABC):
    """A camera (or a recording of one) delivering Frames; use as a context manager."""

    name: str

    @abc.abstractmethod
    def open(self) -> None:
        """Acquire the device or file. Raises SourceError with a clear message on failure."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device or file; safe to call twice."""

    @abc.abstractmethod
    def read(self, timeout: float = 1.0) -> Frame | None:
        """Next frame, or None when none arrived within `timeout` seconds (or at the end of a
        recording, see `exhausted`). Raises SourceError on an unrecoverable failure."""

    @property
    def exhausted(self) -> bool:
        """True for a recording that has no more frames; live sources never are."""
        return False

    # Optional capabilities (additive; defaults describe a plain free-running source).
    live: bool = False  # frames arrive on their own clock (camera), not on demand (recording)
    software_trigger: bool = False  # True when `trigger()` fires one exposure

    def trigger(self) -> None:
        """Fire one exposure (software trigger mode). Sources without it raise SourceError."""
        from ..errors import SourceError

        raise SourceError(f"camera {getattr(self, 'name', '?')}: no software trigger")

    @property
    def size(self) -> tuple[int, int] | None:
        """(width, height) of the images once open, when known."""
        return None

    def stats(self) -> dict[str, int | float]:
        """Counters of the source (frames, dropped, incomplete...), for diagnostics."""
        return {}

    def __enter__(self) -> "FrameSource":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
