"""USB (UVC) cameras through OpenCV's V4L2 backend.

Format negotiation: the requested pixel format (FOURCC), resolution and rate are set and then
read back; what the driver accepted is in `negotiated`, and `strict=True` turns a mismatch
into a SourceError. Stamps: the driver's buffer timestamp (CAP_PROP_POS_MSEC, normally
CLOCK_MONOTONIC at capture) mapped to ROS time by a ClockMapper; host arrival time only
when the driver gives none. A camera unplugged mid-capture raises SourceError from `read`
(a SourceRig then reconnects it when the device node returns).

The lowest layer (opening the device, checking the node exists) is the `backend` object,
which tests replace: no /dev/video* is needed to test the logic above it.
"""

from __future__ import annotations

import glob
import os
import time
from typing import Any

import cv2
import numpy as np

from ..errors import SourceError
from .base import Frame, FrameSource
from .clock import ClockMapper


class OpenCVV4L2Backend:
    """The real devices: cv2.VideoCapture with the V4L2 API."""

    def open(self, device: str) -> Any:
        return cv2.VideoCapture(device, cv2.CAP_V4L2)

    def exists(self, device: str) -> bool:
        return os.path.exists(device)

    def list_devices(self) -> list[str]:
        return sorted(glob.glob("/dev/video*"))


def fourcc_str(value: float) -> str:
    v = int(value)
    return "".join(chr((v >> (8 * i)) & 0xFF) for i in range(4)).strip("\x00")


class V4L2FrameSource(FrameSource):
    live = True

    def __init__(self, device: str | int = "/dev/video0", camera: str | None = None, width: int | None = None,
                 height: int | None = None, fps: float | None = None, fourcc: str | None = "MJPG",
                 mono: bool = False, buffers: int | None = None, strict: bool = False,
                 read_timeout_ms: int = 2000, backend: Any = None) -> None:
        self.device = f"/dev/video{device}" if isinstance(device, int) else str(device)
        self.name = camera or os.path.basename(self.device)
        self.req: dict[str, Any] = {"width": width, "height": height, "fps": fps, "fourcc": fourcc}
        if fourcc is not None and len(fourcc) != 4:
            raise SourceError(f"camera {self.name}: pixel format must be a FOURCC like MJPG or YUYV, not '{fourcc}'")
        self.mono = mono
        self.buffers = buffers
        self.strict = strict
        self.read_timeout_ms = int(read_timeout_ms)
        self.backend = backend or OpenCVV4L2Backend()
        self.clock = ClockMapper()
        self.negotiated: dict[str, Any] = {}
        self._cap: Any = None
        self._seq = 0
        self._counts = {"frames": 0, "read_failures": 0, "host_stamps": 0, "stamp_regressions": 0}
        self._last_dev_ns = -1

    def open(self) -> None:
        if not self.backend.exists(self.device):
            raise SourceError(f"camera {self.name}: device {self.device} does not exist")
        cap = self.backend.open(self.device)
        if cap is None or not cap.isOpened():
            raise SourceError(f"camera {self.name}: cannot open {self.device} (busy, or not a capture device)")
        self._cap = cap
        r = self.req
        # Order matters for V4L2: the pixel format first, then size, then rate.
        if r["fourcc"]:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*r["fourcc"]))
        if r["width"]:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, r["width"])
        if r["height"]:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, r["height"])
        if r["fps"]:
            cap.set(cv2.CAP_PROP_FPS, r["fps"])
        if self.buffers:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, self.buffers)
        # bound the driver wait (V4L2 select) so an unplugged camera is noticed promptly
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.read_timeout_ms)
        self.negotiated = {
            "fourcc": fourcc_str(cap.get(cv2.CAP_PROP_FOURCC)),
            "width": int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
            "height": int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            "fps": float(cap.get(cv2.CAP_PROP_FPS)),
        }
        diffs = [f"{k} {r[k]} -> {self.negotiated[k]}" for k in ("fourcc", "width", "height")
                 if r[k] and str(r[k]) != str(self.negotiated[k])]
        if r["fps"] and abs(self.negotiated["fps"] - r["fps"]) > 0.01 * r["fps"]:
            diffs.append(f"fps {r['fps']} -> {self.negotiated['fps']}")
        self.negotiated["mismatch"] = diffs
        if diffs and self.strict:
            self.close()
            raise SourceError(f"camera {self.name}: {self.device} did not accept the requested format: {', '.join(diffs)}")
        self.clock.reset()
        self._last_dev_ns = -1

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    @property
    def size(self) -> tuple[int, int] | None:
        return (self.negotiated["width"], self.negotiated["height"]) if self.negotiated else None

    def read(self, timeout: float = 1.0) -> Frame | None:
        if self._cap is None:
            raise SourceError(f"camera {self.name}: read before open")
        ok, img = self._cap.read()  # blocks until the driver has a buffer (V4L2 select timeout)
        host_ns = time.time_ns()
        if not ok or img is None:
            self._counts["read_failures"] += 1
            if not self.backend.exists(self.device):
                self.close()
                raise SourceError(f"camera {self.name}: {self.device} disconnected")
            return None
        dev_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
        if dev_ms > 0:
            dev_ns = int(round(dev_ms * 1e6))
            if dev_ns <= self._last_dev_ns:
                self._counts["stamp_regressions"] += 1
            self._last_dev_ns = dev_ns
            stamp = self.clock.update(dev_ns, host_ns)
        else:
            self._counts["host_stamps"] += 1
            stamp = host_ns
        img = np.asarray(img)
        if img.ndim == 2 and not self.mono:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.ndim == 3 and self.mono:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        self._seq += 1
        self._counts["frames"] += 1
        return Frame(self.name, stamp, img, seq=self._seq)

    def stats(self) -> dict[str, int | float]:
        return {**self._counts, "clock_offset_ms": self.clock.offset_ns * 1e-6, "clock_drift_ppm": self.clock.drift_ppm}
