"""`vmocap bench images --blackout FROM TO`: every camera sees no body for a while, then the body
again; how long the tracker takes to output it as tracked (issue: find the body again within
0.5 s of it being visible). `--cover CAMERA FROM TO`: one camera sees no body for a while (a
person covered in one view), the others go on seeing it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...bag import BagReader, BagWriter
from ...bag import messages as M
from ...cameras.projection import Rig
from ...topics import Topics


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


def covered(rec: Path, out: Path, stamps: np.ndarray, truth: np.ndarray, rig: Rig, camera: str,
            window_s: tuple[float, float]) -> Path:
    """A copy of the recording `rec` in which, from window_s[0] to window_s[1] (seconds after
    its first frame set), a grey panel stands between `camera` and the body: the panel covers
    the truth's keypoints projected in that camera (`truth` (T, 25, 3) at `stamps`) with a
    margin of half the body's image height; the rest of the image and the other cameras are as
    they were."""
    a, b = (int(stamps[0] + s * 1e9) for s in window_s)
    cam = rig.names.index(camera)
    topic = Topics().image(camera)
    row = {int(s): i for i, s in enumerate(stamps)}
    with BagReader(rec) as r, BagWriter(out, overwrite=True) as w:
        for m in r.messages():
            if m.topic == topic and a <= m.log_time_ns < b:
                img = m.decode()
                pixels = M.image_array(img).copy()
                i = row.get(M.stamp_ns(img), int(np.argmin(np.abs(stamps - M.stamp_ns(img)))))
                uv, front = rig.project(truth[i])
                pts = uv[cam][front[cam] & np.isfinite(uv[cam]).all(axis=1)]
                if len(pts):
                    lo, hi = pts.min(axis=0), pts.max(axis=0)
                    pad = 0.5 * (hi[1] - lo[1])
                    x0, y0 = np.maximum(np.floor(lo - pad), 0).astype(int)
                    x1, y1 = np.ceil(hi + pad).astype(int)
                    pixels[y0:y1, x0:x1] = 128
                w.write(m.topic, m.type, M.image_msg(pixels, M.stamp_ns(img), img["header"]["frame_id"], img["encoding"]),
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


def window_figures(est: np.ndarray, truth: np.ndarray, stamps: np.ndarray, window_s: tuple[float, float],
                   limit_mm: float) -> dict[str, float | int | None]:
    """Within window_s (seconds after the first frame set): the share of frame sets output as
    tracked, their MPJPE (mm) and how many of them were over `limit_mm` off."""
    t = (stamps - stamps[0]) * 1e-9
    inside = (t >= window_s[0] - 1e-6) & (t < window_s[1] - 1e-6)
    present = np.isfinite(truth).all(axis=(0, 2))
    e = np.linalg.norm(est[inside][:, present] - truth[inside][:, present], axis=-1).mean(axis=1) * 1000
    out = np.isfinite(e)
    return {"frames": int(inside.sum()), "tracked_pct": float(100 * out.mean()) if out.size else None,
            "mpjpe_mm": float(e[out].mean()) if out.any() else None, "over_limit": int((e[out] > limit_mm).sum())}
