"""Session plots for `vmocap process --plots DIR`: joint angles and keypoint speeds over time
(gaps stay gaps: the curves break where the subject was not tracked)."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from ..files import output_folder, write_figure
from ..keypoints import INDEX
from ..method.skeleton import REVOLUTE
from .session import Session

SPHERICAL = ("waist", "neck", "left_shoulder", "right_shoulder", "left_hip", "right_hip")
SPEED_KEYPOINTS = ("pelvis", "nose", "left_wrist", "right_wrist", "left_ankle", "right_ankle")
PLOT_FILES = ("joint_angles.png", "keypoint_speeds.png")


def plot_session(session: Session, folder: str | Path, inputs: Iterable[str | Path] = ()) -> list[Path]:
    """Write PLOT_FILES (joint angles, keypoint speeds) into `folder`, replacing earlier ones
    but never one of `inputs` (vmocap_core.files); returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    inputs = list(inputs)
    folder = output_folder(folder, PLOT_FILES, inputs)
    t = session.times
    col = {n: i for i, n in enumerate(session.joint_names)}
    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for n in REVOLUTE:
        if n in col:
            a.plot(t, np.degrees(session.angles[:, col[n]]), label=n)
    a.set_ylabel("hinge angle (deg)")
    a.legend(ncol=4, fontsize=8)
    for n in SPHERICAL:
        found = [col.get(f"{n}_{x}") for x in ("rx", "ry", "rz")]
        if None not in found:
            axes = [int(i) for i in found if i is not None]
            b.plot(t, np.degrees(np.linalg.norm(session.angles[:, axes], axis=1)), label=n)
    b.set_ylabel("rotation from rest (deg)")
    b.set_xlabel("time (s)")
    b.legend(ncol=3, fontsize=8)
    fig.tight_layout()
    out = [folder / name for name in PLOT_FILES]
    write_figure(fig, out[0], inputs, dpi=90)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(10, 4))
    # Central differences over consecutive tracked frames only (NaN next to a gap).
    v = np.gradient(session.keypoints, 1.0 / session.rate_hz, axis=0) if session.n_frames > 1 else session.keypoints * np.nan
    for n in SPEED_KEYPOINTS:
        ax.plot(t, np.linalg.norm(v[:, INDEX[n]], axis=1), label=n)
    ax.set_ylabel("speed (m/s)")
    ax.set_xlabel("time (s)")
    ax.legend(ncol=3, fontsize=8)
    fig.tight_layout()
    write_figure(fig, out[1], inputs, dpi=90)
    plt.close(fig)
    return out
