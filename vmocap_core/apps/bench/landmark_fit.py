"""Landmark models learnt from rendered recordings (method/landmarks.py): what
`scripts/learn_landmarks.py` writes and `vmocap bench images --leave-one-out` scores with.

For each clip, our skeleton is identified on the true joint centres and fitted to every frame;
each lattice marker's offset from its true joint centre, in its segment's frame, is a sample.
A model is the median over clips of each clip's median (every clip one vote, however long).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...graph_config import Topics
from ...method.init import fit_skeleton, frame_poses
from ...method.landmarks import SEGMENT, learn_offsets
from .clouds import read_clouds

Samples = dict[str, np.ndarray]  # left keypoint -> (n, 3) offsets in metres


def read_markers(path: Path, stamps: np.ndarray) -> np.ndarray:
    """(T, 25, 3) lattice markers of a `vmocap process` output at the truth stamps (NaN: none
    or weight 0)."""
    return read_clouds(path, stamps, Topics().markers, kind="lattice")


def clip_samples(truth: np.ndarray, markers: np.ndarray) -> Samples:
    """Landmark samples of one clip: truth (T, 25, 3) joint centres, markers (T, 25, 3)."""
    fitted = fit_skeleton(truth, 1.0)
    if fitted is None:  # a 1 m bound accepts any body
        raise ValueError("the truth does not fit the skeleton")
    sk, fit = fitted
    return learn_offsets(sk, np.array(frame_poses(sk, truth, fit.q)), markers, truth)


def model_yaml(name: str, samples: dict[str, Samples], note: str) -> dict[str, object]:
    """A landmark model file's content (load_landmarks) from the samples of several clips
    (clip name -> samples)."""
    offsets = {k: [round(float(x) * 1e3, 1) for x in np.median([np.median(s[k], axis=0) for s in samples.values()], axis=0)]
               for k in SEGMENT if k.startswith("left_")}
    return {"name": name, "note": note, "learnt_on": list(samples), "offsets_mm": offsets}
