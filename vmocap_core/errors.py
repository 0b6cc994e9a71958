"""Explicit error classes of vmocap (one base class, one subclass per kind of bad input)."""

from __future__ import annotations


class VmocapError(Exception):
    """Base class of every error vmocap raises on purpose."""


class RigFileError(VmocapError):
    """A rig/calibration file is malformed: names the file and the field."""

    def __init__(self, path: object, field: str, problem: str) -> None:
        self.path = str(path)
        self.field = field
        self.problem = problem
        super().__init__(f"{self.path}: field '{field}': {problem}")


class HeatmapError(VmocapError):
    """Heatmaps (PCMs) that cannot be used: wrong shape, wrong mapping."""


class MotionFileError(VmocapError):
    """A motion clip (.npz) that does not follow the documented format."""


class ModelError(VmocapError):
    """A PCM model that is missing, corrupt or does not fit the interface."""


class BagError(VmocapError):
    """An MCAP bag that cannot be read or written."""


class CalibrationError(VmocapError):
    """A calibration that cannot be computed (names the camera and the reason)."""


class SourceError(VmocapError):
    """A camera source that cannot be opened or read."""


class DetectionFileError(VmocapError):
    """A 2D detection file (e.g. Shelf) that is malformed: names the file and line."""
