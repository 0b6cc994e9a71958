"""`vmocap bench images --blackout FROM TO`: every camera sees no body for a while, then the body
again; how long the tracker takes to output it as tracked (issue: find the body again within
0.5 s of it being visible)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...bag import BagReader, BagWriter
from ...bag import messages as M


def blacked_out(rec: Path, out: Path, stamps: np.ndarray, window_s: tuple[float, float]) -> Path:
    """A copy of the recording `rec` whose images show noise, no body, from window_s[0] to
    window_s[1] (seconds after its first frame set), then the body again. (Black images would
    be dropped as covered cameras, and the tracker would wait for them rather than lose the body.)"""
    a, b = (int(stamps[0] + s * 1e9) for s in window_s)
    rng = np.random.default_rng(0)
    with BagReader(rec) as r, BagWriter(out, overwrite=True) as w:
        for m in r.messages():
            if m.type == "sensor_msgs/msg/Image" and a <= m.log_time_ns < b:
                img = m.decode()
                shape = M.image_array(img).shape
                noise = rng.integers(40, 200, size=shape, dtype=np.uint8)
                w.write(m.topic, m.type, M.image_msg(noise, M.stamp_ns(img), img["header"]["frame_id"], img["encoding"]),
                        m.log_time_ns)
            else:
                w.write(m.topic, m.type, m.data, m.log_time_ns)
    return out


def reacquisition_s(est: np.ndarray, stamps: np.ndarray, visible_again_s: float) -> float | None:
    """Seconds from the body being visible again (`visible_again_s` after the first frame set)
    to the first frame set output as tracked; None when it never was."""
    t = (stamps - stamps[0]) * 1e-9
    after = np.flatnonzero((t >= visible_again_s - 1e-6) & np.isfinite(est).all(axis=(1, 2)))
    return float(t[after[0]] - visible_again_s) if after.size else None
