"""Reference calibrations of other tools, and the comparison of a calibration against one."""

from __future__ import annotations

import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..cameras.projection import Camera, Rig, check_finite
from ..errors import RigFileError
from .geometry import rotation_angle_deg

QUALISYS_SUBPIXELS = 64  # Qualisys stores image coordinates in 1/64 pixel units
# Qualisys camera axes: x right, y up, z backwards; OpenCV's: x right, y down, z forward.
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


def load_caliscope(path: str | Path, prefix: str = "") -> Rig:
    """caliscope's camera_array.toml: per camera matrix, distortions, rotation, translation.
    Its rotation/translation map world -> camera (checked by reprojecting its own
    stereotriangulated points), like vmocap's. Cameras are named `prefix + cam_id`."""
    path = Path(path)
    d = tomllib.loads(path.read_text())
    cams = d.get("cameras", {k[4:]: v for k, v in d.items() if k.startswith("cam_")})
    out = []
    for key, c in sorted(cams.items(), key=lambda kv: int(kv[0])):
        where = f"cameras.{key}."
        if c.get("ignore"):
            continue
        size = check_finite(path, where + "size", c.get("size"), (2,))
        out.append(Camera(
            f"{prefix}{key}", check_finite(path, where + "matrix", c.get("matrix"), (3, 3)),
            check_finite(path, where + "distortions", c.get("distortions"), (5,)),
            check_finite(path, where + "rotation", c.get("rotation"), (3, 3)),
            check_finite(path, where + "translation", c.get("translation"), (3,)), size[0], size[1]))
    if not out:
        raise RigFileError(path, "cameras", "no camera")
    return Rig(out)


def load_qualisys(path: str | Path, sizes: dict[str, tuple[int, int]] | None = None,
                  intrinsics_only: bool = False) -> Rig:
    """The rig of a Qualisys .qca.txt calibration (cameras named by their serial).

    `transform` holds the camera position (mm) and a rotation whose rows are the Qualisys camera
    axes in world coordinates (y up, z backwards): world->camera for OpenCV is
    R = diag(1, -1, -1) @ rows, t = -R @ position. Intrinsics are in 1/64 pixel relative to the
    sensor; the video field of view gives the crop. `sizes` (name -> (w, h)) overrides the image
    size where a video was stored cropped at the right/bottom (e.g. 1080 of 1088 columns).
    intrinsics_only: K and the image size only (no distortion, extrinsics at identity; the
    file's transform and distortion are not read)."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise RigFileError(path, "xml", str(exc)) from None
    cams: list[Camera] = []
    for cam in root.iter("camera"):
        name = cam.get("serial") or f"cam{len(cams) + 1:02d}"
        tr, it, fov = cam.find("transform"), cam.find("intrinsic"), cam.find("fov_video")
        if it is None or fov is None or (tr is None and not intrinsics_only):
            raise RigFileError(path, f"camera {name}", "missing " + ("intrinsic or fov_video" if intrinsics_only
                                                                      else "transform, intrinsic or fov_video"))
        try:
            fx = float(it.get("focalLengthU")) / QUALISYS_SUBPIXELS
            fy = float(it.get("focalLengthV")) / QUALISYS_SUBPIXELS
            cx = float(it.get("centerPointU")) / QUALISYS_SUBPIXELS - float(fov.get("left"))
            cy = float(it.get("centerPointV")) / QUALISYS_SUBPIXELS - float(fov.get("top"))
            w = int(fov.get("right")) - int(fov.get("left")) + 1
            h = int(fov.get("bottom")) - int(fov.get("top")) + 1
            R, t, dist = np.eye(3), np.zeros(3), [0.0] * 5
            if not intrinsics_only:
                assert tr is not None
                rows = np.array([[float(tr.get(f"r{i}{j}")) for j in (1, 2, 3)] for i in (1, 2, 3)])
                R = QUALISYS_TO_OPENCV @ rows
                t = -R @ (np.array([float(tr.get(a)) for a in "xyz"]) / 1000.0)
                dist = [float(it.get(k)) for k in ("radialDistortion1", "radialDistortion2", "tangentalDistortion1",
                                                   "tangentalDistortion2", "radialDistortion3")]
        except (TypeError, ValueError) as exc:
            raise RigFileError(path, f"camera {name}", f"bad number ({exc})") from None
        if sizes and name in sizes:
            w, h = sizes[name]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cams.append(Camera(name, K, dist, R, t, w, h))
    if not cams:
        raise RigFileError(path, "cameras", "no camera")
    return Rig(cams)


def load_qualisys_intrinsics(path: str | Path) -> Rig:
    """The intrinsics of a Qualisys calibration (`load_qualisys(intrinsics_only=True)`)."""
    return load_qualisys(path, intrinsics_only=True)


def load_reference(path: str | Path) -> Rig:
    """A reference rig by file type: caliscope .toml, Qualisys .qca(.txt), vmocap rig .yaml."""
    p = str(path)
    if p.endswith(".toml"):
        return load_caliscope(path)
    if ".qca" in p:
        return load_qualisys_intrinsics(path)
    from ..cameras.rig_file import load_rig

    return load_rig(path)


def compare_intrinsics(est: Camera, ref: Camera) -> dict:
    fx, fy = est.K[0, 0], est.K[1, 1]
    rfx, rfy = ref.K[0, 0], ref.K[1, 1]
    return {
        "fx": float(fx), "fy": float(fy), "ref_fx": float(rfx), "ref_fy": float(rfy),
        "focal_err_pct": float(100 * max(abs(fx - rfx) / rfx, abs(fy - rfy) / rfy)),
        "principal_err_px": float(np.hypot(est.K[0, 2] - ref.K[0, 2], est.K[1, 2] - ref.K[1, 2])),
    }


def compare_extrinsics(est: Rig, ref: Rig) -> dict:
    """Relative poses of every camera pair (gauge-free: independent of the world frame).

    For each ordered pair (i, j): position of camera j in camera i's frame and the rotation
    from camera i to camera j, estimated vs reference. Per camera, the worst pair it is in."""
    n = len(est)
    pos = np.zeros((n, n))
    rot = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            e_i, e_j, r_i, r_j = est[i], est[j], ref[i], ref[j]
            pe = e_i.R @ e_j.center + e_i.t  # camera j's centre in camera i's frame
            pr = r_i.R @ r_j.center + r_i.t
            pos[i, j] = np.linalg.norm(pe - pr)
            rot[i, j] = rotation_angle_deg(e_j.R @ e_i.R.T, r_j.R @ r_i.R.T)
    return {
        "names": est.names,
        "pair_position_err_m": pos.tolist(),
        "pair_rotation_err_deg": rot.tolist(),
        "max_position_err_m": float(pos.max()),
        "max_rotation_err_deg": float(rot.max()),
        "per_camera_position_err_m": {est.names[i]: float(pos[i].max() if n > 1 else 0) for i in range(n)},
        "per_camera_rotation_err_deg": {est.names[i]: float(rot[i].max() if n > 1 else 0) for i in range(n)},
    }
