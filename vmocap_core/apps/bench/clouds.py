"""Keypoint clouds of a recorded output, row-aligned with the truth's stamps: what the image
benchmark scores (images.py) and the landmark models learn from (landmark_fit.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...bag import BagReader
from ...bag import messages as M
from ...keypoints import KEYPOINTS


def read_clouds(path: Path, stamps: np.ndarray, topic: str, kind: str | None = None) -> np.ndarray:
    """(T, 25, 3) keypoint clouds of `topic` at the truth stamps (NaN where none); with `kind`,
    only clouds of that kind (e.g. "lattice" markers), their zero-weight points NaN."""
    out = np.full((len(stamps), len(KEYPOINTS), 3), np.nan)
    row = {int(s): i for i, s in enumerate(stamps)}
    with BagReader(path) as r:
        for m in r.messages([topic]):
            d = m.decode()
            P, S, k = M.cloud_keypoints(d)
            i = row.get(M.stamp_ns(d))
            if P is not None and i is not None and kind in (None, k):
                out[i] = P if kind is None else np.where((S > 0)[:, None], P, np.nan)
    return out
