"""Calibrated cameras and rigs: the projections P_i of the paper (section II-A).

Conventions (used everywhere in vmocap):
- World frame in metres. Extrinsics map world -> camera: X_cam = R @ X_world + t.
- Image pixels follow OpenCV: the centre of the top-left pixel is (0, 0), u right, v down.
- Distortion follows OpenCV's order k1 k2 p1 p2 k3 [k4 k5 k6]; absent terms are zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Iterator, Sequence

import numpy as np

from ..errors import RigFileError

N_DIST = 8  # k1 k2 p1 p2 k3 k4 k5 k6
MIN_DEPTH = 1e-6  # points closer than this in front of the optical centre count as behind
Z_UP = np.array([0.0, 0.0, 1.0])  # world up (default argument of look_at)


def binning_affine(factor: int) -> np.ndarray:
    """3x3 map from full-resolution pixels to pixels of the image binned `factor` times (REP 104;
    JPEG DCT scaling): binned pixel i centres on full pixel factor*i + (factor - 1)/2."""
    r = float(factor)
    return np.array([[1.0 / r, 0.0, -(r - 1) / (2 * r)], [0.0, 1.0 / r, -(r - 1) / (2 * r)], [0.0, 0.0, 1.0]])


@dataclass
class Camera:
    """One calibrated pinhole camera with OpenCV lens distortion."""

    name: str
    K: np.ndarray  # (3, 3) intrinsics
    dist: np.ndarray  # (8,) k1 k2 p1 p2 k3 k4 k5 k6
    R: np.ndarray  # (3, 3) world -> camera rotation
    t: np.ndarray  # (3,) world -> camera translation (metres)
    width: int
    height: int

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3).copy()
        # OpenCV's camera model (and ROS camera_info) has no skew: drop it so that every
        # projection in vmocap equals cv2.projectPoints.
        self.K[0, 1] = 0.0
        dist = np.zeros(N_DIST)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > N_DIST:
            raise ValueError(f"camera {self.name}: at most {N_DIST} distortion coefficients")
        dist[: given.size] = given
        self.dist = dist
        self.R = np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def center(self) -> np.ndarray:
        """Optical centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def projection_matrix(self) -> np.ndarray:
        """(3, 4) K [R | t] of the undistorted pinhole model."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def focal(self) -> float:
        """Mean focal length (px): a length's size in the image at a depth, the same along x and y."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (..., 3) -> pixels (..., 2) and in-front flags (...)."""
        uv, front = Rig([self]).project(points)
        return uv[0], front[0]

    def binned(self, factor: int) -> "Camera":
        """This camera as seen in its images reduced `factor` times (REP 104 binning; JPEG DCT
        scaling): binned pixel i averages full pixels factor*i ... factor*i + factor - 1, so its
        centre is at full pixel factor*i + (factor - 1)/2; the size rounds up as libjpeg's does.
        Distortion acts on normalized coordinates and is unchanged."""
        if int(factor) < 1:
            raise ValueError(f"camera {self.name}: binning must be >= 1, got {factor}")
        r = int(factor)
        return Camera(self.name, binning_affine(r) @ self.K, self.dist, self.R, self.t, -(-self.width // r), -(-self.height // r))

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> normalized undistorted image coordinates (..., 2)."""
        import cv2

        uv = np.asarray(uv, dtype=np.float64)
        flat = uv.reshape(-1, 1, 2)
        if flat.shape[0] == 0:
            return uv.copy()
        out = cv2.undistortPoints(
            flat,
            self.K,
            self.dist,
            R=None,
            P=None,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10),
        )
        return out.reshape(uv.shape)


@dataclass
class Rig:
    """Named cameras with one vectorized projection into all of them."""

    cameras: list[Camera] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.cameras = list(self.cameras)
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique: {names}")
        self._stack()

    def _stack(self) -> None:
        cams = self.cameras
        self._R = np.array([c.R for c in cams]).reshape(-1, 3, 3)
        self._t = np.array([c.t for c in cams]).reshape(-1, 3)
        self._K = np.array([c.K for c in cams]).reshape(-1, 3, 3)
        self._dist = np.array([c.dist for c in cams]).reshape(-1, N_DIST)
        self._distorted = np.array([c.has_distortion for c in cams], dtype=bool)
        self._rational = np.array([np.any(c.dist[5:] != 0) for c in cams], dtype=bool)

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            return self.cameras[self.names.index(key)]
        return self.cameras[key]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def subset(self, names: Iterable[str]) -> "Rig":
        return Rig([self[n] for n in names])

    def binned(self, factor: int) -> "Rig":
        """Every camera binned `factor` times (Camera.binned)."""
        return Rig([c.binned(factor) for c in self.cameras])

    def to_camera_frames(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera-frame points (C, ..., 3)."""
        p = np.asarray(points, dtype=np.float64)
        flat = p.reshape(-1, 3)
        cam = np.einsum("cij,nj->cni", self._R, flat) + self._t[:, None, :]
        return cam.reshape((len(self),) + p.shape)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (..., 3) into every camera.

        Returns pixels (C, ..., 2) and a boolean (C, ...) that is False for points behind the
        camera (their pixels are still computed but must not be used). Equals
        cv2.projectPoints to floating point precision for points in front of the camera.
        """
        p = np.asarray(points, dtype=np.float64)
        lead = p.shape[:-1]
        cam = self.to_camera_frames(p.reshape(-1, 3))  # (C, N, 3)
        uv, front = self.project_camera_points(cam)
        return uv.reshape((len(self),) + lead + (2,)), front.reshape((len(self),) + lead)

    def project_camera_points(self, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (C, N, 3) -> pixels (C, N, 2), in-front flags (C, N)."""
        z = cam[..., 2]
        front = z > MIN_DEPTH
        inv_z = 1.0 / np.where(front, z, 1.0)
        x = cam[..., 0] * inv_z
        y = cam[..., 1] * inv_z
        if self._distorted.any():
            x, y = self._distort(x, y)
        K = self._K
        u = K[:, 0, 0, None] * x + K[:, 0, 1, None] * y + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * y + K[:, 1, 2, None]
        return np.stack([u, v], axis=-1), front

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._dist[:, :, None]  # (C, 8, 1) broadcast over points
        k1, k2, p1, p2, k3 = d[:, 0], d[:, 1], d[:, 2], d[:, 3], d[:, 4]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if self._rational.any():
            k4, k5, k6 = d[:, 5], d[:, 6], d[:, 7]
            radial = radial / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xy2 = 2.0 * x * y
        xd = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2
        return xd, yd

    def check_sizes(self, sizes: Sequence[tuple[int, int]]) -> None:
        """Raise ValueError when image sizes (w, h) disagree with the calibration."""
        for cam, (w, h) in zip(self.cameras, sizes):
            if (int(w), int(h)) != (cam.width, cam.height):
                raise ValueError(
                    f"camera {cam.name}: image is {w}x{h} but the rig was calibrated "
                    f"at {cam.width}x{cam.height}"
                )


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = Z_UP) -> tuple[np.ndarray, np.ndarray]:
    """World->camera (R, t) of a camera at `eye` looking at `target` (OpenCV axes: z forward, y down)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def check_finite(path: object, fieldname: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """Parse a numeric field of a calibration file, raising RigFileError on bad shape/values."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise RigFileError(path, fieldname, f"not numeric ({exc})") from None
    if arr.size != int(np.prod(shape)):
        raise RigFileError(path, fieldname, f"expected {int(np.prod(shape))} numbers {shape}, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise RigFileError(path, fieldname, "contains NaN or infinite values")
    return arr.reshape(shape)
