"""Rig files: read and write vmocap's YAML rig format, import other calibration formats.

vmocap rig file (YAML, metres)::

    cameras:
      - camera_name: cam0          # ROS camera_info fields (camera_calibration_parsers layout)
        image_width: 1024
        image_height: 768
        camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
        distortion_model: plumb_bob   # or rational_polynomial (8 coefficients)
        distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, p1, p2, k3]}
        rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
        projection_matrix: {rows: 3, cols: 4, data: [...]}
        extrinsics:                   # world -> camera: X_cam = R X_world + t
          rotation: {rows: 3, cols: 3, data: [...]}
          translation: [tx, ty, tz]

Every malformed field raises RigFileError naming the file and the field.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import yaml

from ..errors import RigFileError
from .projection import Camera, Rig, check_finite


def _matrix_block(data: np.ndarray) -> dict[str, Any]:
    rows, cols = data.shape if data.ndim == 2 else (1, data.size)
    return {"rows": int(rows), "cols": int(cols), "data": [float(x) for x in data.ravel()]}


def camera_info_dict(camera: Camera) -> dict[str, Any]:
    """The ROS camera_info YAML fields of a camera (camera_calibration_parsers layout)."""
    rational = bool(np.any(camera.dist[5:] != 0))
    dist = camera.dist if rational else camera.dist[:5]
    P = np.hstack([camera.K, np.zeros((3, 1))])
    return {
        "camera_name": camera.name,
        "image_width": camera.width,
        "image_height": camera.height,
        "camera_matrix": _matrix_block(camera.K),
        "distortion_model": "rational_polynomial" if rational else "plumb_bob",
        "distortion_coefficients": _matrix_block(np.asarray(dist)),
        "rectification_matrix": _matrix_block(np.eye(3)),
        "projection_matrix": _matrix_block(P),
    }


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    cams = []
    for cam in rig:
        d = camera_info_dict(cam)
        d["extrinsics"] = {"rotation": _matrix_block(cam.R), "translation": [float(x) for x in cam.t]}
        cams.append(d)
    return {"cameras": cams}


def save_rig(rig: Rig, path: str | Path, overwrite: bool = True, inputs: Iterable[str | Path] = ()) -> None:
    """Write a rig file atomically (vmocap_core.files: a reader never sees a half-written file);
    `vmocap calibrate` passes overwrite=False unless told otherwise."""
    from ..files import write_text

    write_text(path, yaml.safe_dump(rig_to_dict(rig), sort_keys=False), inputs, overwrite)


def _field(path: Path, d: Any, key: str, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise RigFileError(path, f"{where}{key}", "missing")
    return d[key]


def _matrix(path: Path, d: Any, key: str, where: str, shape: tuple[int, ...]) -> np.ndarray:
    block = _field(path, d, key, where)
    data = block.get("data") if isinstance(block, dict) else block
    return check_finite(path, f"{where}{key}", data, shape)


def camera_from_dict(d: Any, path: Path, where: str = "") -> Camera:
    name = str(_field(path, d, "camera_name", where))
    w = _field(path, d, "image_width", where)
    h = _field(path, d, "image_height", where)
    if not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
        raise RigFileError(path, f"{where}image_width/image_height", f"must be positive integers, got {w!r} x {h!r}")
    K = _matrix(path, d, "camera_matrix", where, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RigFileError(path, f"{where}camera_matrix", "focal lengths must be positive")
    block = _field(path, d, "distortion_coefficients", where)
    raw = block.get("data") if isinstance(block, dict) else block
    n = len(raw) if isinstance(raw, list) else -1
    if n not in (0, 4, 5, 8):
        raise RigFileError(path, f"{where}distortion_coefficients", f"expected 0, 4, 5 or 8 numbers, got {n}")
    dist = check_finite(path, f"{where}distortion_coefficients", raw, (n,))
    ext = _field(path, d, "extrinsics", where)
    R = _matrix(path, ext, "rotation", f"{where}extrinsics.", (3, 3))
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise RigFileError(path, f"{where}extrinsics.rotation", "not a rotation matrix")
    t = check_finite(path, f"{where}extrinsics.translation", _field(path, ext, "translation", f"{where}extrinsics."), (3,))
    return Camera(name=name, K=K, dist=dist, R=R, t=t, width=w, height=h)


def load_rig(path: str | Path) -> Rig:
    """Read a vmocap rig file (RigFileError on any malformed field)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise RigFileError(path, "<file>", f"cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise RigFileError(path, "<file>", f"not valid YAML ({exc})") from None
    cams = _field(path, doc, "cameras", "")
    if not isinstance(cams, list) or not cams:
        raise RigFileError(path, "cameras", "must be a non-empty list")
    cameras = [camera_from_dict(c, path, f"cameras[{i}].") for i, c in enumerate(cams)]
    try:
        return Rig(cameras)
    except ValueError as exc:
        raise RigFileError(path, "cameras", str(exc)) from None


def load_shelf_calibration(path: str | Path) -> Rig:
    """Shelf/Campus calibration.json: {"0": {"K": 9, "RT": 12 (world->camera), "imgSize": [w, h]}}."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise RigFileError(path, "<file>", f"cannot read JSON ({exc})") from None
    cams = []
    for key in sorted(doc, key=lambda k: (len(k), k)):
        entry = doc[key]
        K = check_finite(path, f"{key}.K", _field(path, entry, "K", f"{key}."), (3, 3))
        RT = check_finite(path, f"{key}.RT", _field(path, entry, "RT", f"{key}."), (3, 4))
        w, h = check_finite(path, f"{key}.imgSize", _field(path, entry, "imgSize", f"{key}."), (2,))
        cams.append(Camera(name=str(key), K=K, dist=np.zeros(5), R=RT[:, :3], t=RT[:, 3], width=int(w), height=int(h)))
    return Rig(cams)


def load_panoptic_cameras(path: str | Path, names: Iterable[str]) -> Rig:
    """CMU Panoptic camera_parameters.json (centimetres) -> Rig in metres for the named cameras."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise RigFileError(path, "<file>", f"cannot read JSON ({exc})") from None
    entries = doc.get("cameras", doc) if isinstance(doc, dict) else doc
    by_name: dict[str, Any] = {}
    if isinstance(entries, list):
        by_name = {str(c.get("name")): c for c in entries if isinstance(c, dict)}
    elif isinstance(entries, dict):
        by_name = {str(k): v for k, v in entries.items()}
    cams = []
    for name in names:
        if name not in by_name:
            raise RigFileError(path, name, "no such camera in the file")
        c = by_name[name]
        K = check_finite(path, f"{name}.K", _field(path, c, "K", f"{name}."), (3, 3))
        dist = check_finite(path, f"{name}.distCoef", _field(path, c, "distCoef", f"{name}."), (5,))
        R = check_finite(path, f"{name}.R", _field(path, c, "R", f"{name}."), (3, 3))
        t = check_finite(path, f"{name}.t", _field(path, c, "t", f"{name}."), (3,)) / 100.0
        w, h = check_finite(path, f"{name}.resolution", _field(path, c, "resolution", f"{name}."), (2,))
        cams.append(Camera(name=name, K=K, dist=dist, R=R, t=t, width=int(w), height=int(h)))
    return Rig(cams)
