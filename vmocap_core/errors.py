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


class OutputPathError(VmocapError):
    """An output path that would write onto an input or replace a file not meant to be replaced."""


class ChunkCrcError(BagError):
    """A chunk of an MCAP file whose contents do not match its CRC (or cannot be decompressed):
    names the file, the chunk (index, byte offset, time range) and the way to read the rest."""

    def __init__(self, path: object, index: int, count: int, offset: int, start_ns: int, end_ns: int,
                 problem: str, rel_s: tuple[float, float]) -> None:
        self.path, self.index, self.offset = str(path), index, offset
        self.start_ns, self.end_ns = start_ns, end_ns
        self.what = (f"{self.path}: chunk {index} of {count} (byte offset {offset}; messages {start_ns}..{end_ns} ns, "
                     f"{rel_s[0]:.3f}-{rel_s[1]:.3f} s into the recording) is damaged: {problem}")
        super().__init__(f"{self.what}; read the intact chunks with --recover")
