"""Marker and table exports of a session: TRC (OpenSim), C3D, CSV.

| format | units | axes | gaps |
|---|---|---|---|
| TRC | mm | Y up (OpenSim): (x, y, z)_vmocap -> (x, z, -y) | `NaN` fields |
| C3D | mm (POINT:UNITS), float | Z up as recorded (POINT:X_SCREEN +X, Y_SCREEN +Z) | residual -1 (invalid point) |
| CSV | m, rad | Z up as recorded | empty fields |
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..keypoints import KEYPOINTS
from .session import Session

# Z up (vmocap world) -> Y up (OpenSim, BVH/Blender): a proper rotation of -90 deg about X.
Z_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _fields(values: np.ndarray, fmt: str, gap: str = "") -> list[str]:
    """Formatted numbers of one row, `gap` for NaN. TRC gaps are written `NaN`: OpenSim's reader
    drops empty trailing fields and then rejects the row's column count (Pose2Sim reads both)."""
    return [gap if not np.isfinite(v) else fmt % v for v in values]


def _rows(n: int, desc: str, progress: bool) -> range | tqdm:
    return tqdm(range(n), desc=desc, unit="frame", disable=not progress or n < 1000, leave=False)


def write_trc(session: Session, path: str | Path, progress: bool = False) -> None:
    """OpenSim marker file (tab separated, header of PathFileType 4): keypoints as markers."""
    write_marker_trc(path, list(KEYPOINTS), session.keypoints, session.rate_hz, session.times, progress)


def write_marker_trc(path: str | Path, names: list[str], points: np.ndarray, rate_hz: float, times: np.ndarray,
                     progress: bool = False) -> None:
    """A TRC of `points` (N, M, 3), metres in the vmocap world (Z up), named `names`: mm, Y up."""
    path = Path(path)
    P = points @ Z_TO_Y_UP.T * 1000.0  # mm, Y up
    N, K = P.shape[:2]
    rate = f"{rate_hz:.6f}"
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{N}\t{K}\tmm\t{rate}\t1\t{N}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in names).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, K + 1)),
        "",
    ]
    flat = P.reshape(N, -1)
    for i in _rows(N, "TRC", progress):
        lines.append("\t".join([str(i + 1), f"{times[i]:.6f}"] + _fields(flat[i], "%.4f", "NaN")))
    path.write_text("\n".join(lines) + "\n")


def write_csv(session: Session, path: str | Path, progress: bool = False) -> None:
    """One row per frame: frame, time, the JointState values, then every keypoint's x, y, z."""
    header = [
        f"# vmocap session: rate {session.rate_hz:.6f} Hz; time s; positions m, world frame Z up "
        "(x forward at rest, y left); joint values as published on joint_states (root_x/y/z in m, "
        "rotation vectors and hinge angles in rad); empty fields: not tracked (gap)",
        ",".join(["frame", "time_s"] + session.joint_names + [f"{n}_{a}" for n in KEYPOINTS for a in "xyz"]),
    ]
    rows = np.concatenate([session.angles, session.keypoints.reshape(session.n_frames, -1)], axis=1)
    lines = [",".join([str(i), f"{session.times[i]:.6f}"] + _fields(rows[i], "%.9g")) for i in _rows(session.n_frames, "CSV", progress)]
    Path(path).write_text("\n".join(header + lines) + "\n")


def write_c3d(session: Session, path: str | Path, progress: bool = False) -> None:
    """C3D (Intel, float points in mm, Z up) with the keypoint names as POINT:LABELS."""
    import c3d

    w = c3d.Writer(point_rate=float(session.rate_hz), analog_rate=0.0, point_scale=-1.0, point_units="mm  ")
    P = session.keypoints * 1000.0
    ok = np.asarray(np.isfinite(P).all(axis=2))
    pts = np.zeros(P.shape[:2] + (5,), dtype=np.float32)
    pts[..., :3] = np.where(ok[..., None], P, 0.0)
    pts[..., 3] = np.where(ok, 0.0, -1.0)  # residual -1: the point is invalid in this frame
    empty = np.zeros((0, 0), dtype=np.float32)
    w.add_frames([(p, empty) for p in pts])
    w.set_point_labels(list(KEYPOINTS))
    w.set_screen_axis(X="+X", Y="+Z")
    with open(path, "wb") as f, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data")  # there is none, by design
        w.write(f)
