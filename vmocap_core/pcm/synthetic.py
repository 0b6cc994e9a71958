"""Synthetic multi-camera PCMs from 3D ground truth: the benchmark's documented noise model.

Default noise model (seeded, per keypoint channel c, camera i, frame t):
- maps at stride 4 of a 1024x768 image (256x192 cells);
- a Gaussian of sigma 2 cells at the true projection displaced by N(0, 6 px) per axis,
  temporally correlated as AR(1) with rho 0.5; amplitude U(0.6, 1.0);
- 5 % missing (empty channel), 3 % an extra false peak of amplitude U(0.5, 1.0) uniformly in
  the person's bounding box, 2 % left/right swap (the peak sits on the mirror keypoint);
- when the body is inverted in that camera's input (the trunk tilted more than 90 degrees
  from upright after the rotation the filter asked for that camera), lower-body channels get
  30 % missing, 15 % swap and amplitude U(0.2, 0.6) instead: what the paper reports of a CNN
  on inverted people.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cameras.projection import Camera, Rig, look_at
from ..keypoints import KEYPOINTS, LOWER_BODY, MIRROR, indices
from ..method.rotation import trunk_tilt
from .views import PcmViews, stride_affine

ORIGIN = np.zeros(3)  # default rig centre


@dataclass
class NoiseModel:
    stride: int = 4
    sigma_cells: float = 2.0
    offset_px: float = 6.0
    ar_rho: float = 0.5
    amplitude: tuple[float, float] = (0.6, 1.0)
    p_missing: float = 0.05
    p_false: float = 0.03
    false_amplitude: tuple[float, float] = (0.5, 1.0)
    p_swap: float = 0.02
    inverted_p_missing: float = 0.30
    inverted_p_swap: float = 0.15
    inverted_amplitude: tuple[float, float] = (0.2, 0.6)


def benchmark_rig(centre: np.ndarray = ORIGIN, width: int = 1024, height: int = 768,
                  volume_radius: float = 1.9, volume_height: float = 2.2, camera_radius: float = 5.0,
                  camera_height: float = 2.5) -> Rig:
    """4 cameras on the diagonals of a lab around a cylindrical capture volume (radius 1.9 m,
    2.2 m high, centred on `centre`), 2.5 m high, aimed at the volume's centre at 1 m height,
    with the longest focal length that keeps the whole volume inside every image (2 % margin)
    and mild barrel distortion: a lab rig like the paper's 4-camera, 1024x768 setup."""
    target = np.array([centre[0], centre[1], 1.0])
    ang = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1) * volume_radius
    hull = np.concatenate([ring + [centre[0], centre[1], 0.0], ring + [centre[0], centre[1], volume_height]])
    poses = []
    f = np.inf
    for a in np.radians([45.0, 135.0, 225.0, 315.0]):
        eye = np.array([centre[0] + camera_radius * np.cos(a), centre[1] + camera_radius * np.sin(a), camera_height])
        R, t = look_at(eye, target)
        pc = hull @ R.T + t
        xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        f = min(f, 0.98 * (width / 2) / np.abs(xn).max(), 0.98 * (height / 2) / np.abs(yn).max())
        poses.append((R, t))
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    return Rig([Camera(f"cam{i}", K, [-0.05, 0.01, 0, 0, 0], R, t, width, height) for i, (R, t) in enumerate(poses)])


class SyntheticPcmSource:
    """Renders PcmViews for each frame of a ground-truth trajectory seen by a rig."""

    def __init__(self, rig: Rig, positions: np.ndarray, present: np.ndarray, seed: int = 0,
                 noise: NoiseModel | None = None, fps: float = 60.0) -> None:
        self.rig = rig
        self.gt = positions  # (T, 25, 3)
        self.channels = np.flatnonzero(present)  # keypoint index of each PCM channel
        self.noise = noise or NoiseModel()
        self.fps = fps
        self.rng = np.random.default_rng(seed)
        C, J = len(rig), self.channels.size
        self._ar = self.rng.normal(0.0, self.noise.offset_px, (C, J, 2))
        mirror = MIRROR[self.channels]
        # Channel of each channel's mirror keypoint (itself when the mirror is not rendered).
        pos = {k: i for i, k in enumerate(self.channels)}
        self._mirror_channel = np.array([pos.get(int(m), i) for i, m in enumerate(mirror)])
        self._lower = np.isin(self.channels, indices(LOWER_BODY))
        W, H = rig[0].width // self.noise.stride, rig[0].height // self.noise.stride
        self.map_size = (W, H)
        r = int(np.ceil(4 * self.noise.sigma_cells))
        self._win = np.arange(-r, r + 1)
        self._drawn_t = -1
        self._drawn: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return self.gt.shape[0]

    def looped(self, k: int) -> int:
        """The trajectory's frame at frame k of a longer session: forward, then backward, and
        so on, so the body never jumps (a body that jumps back to where the clip started is
        another body to the tracker: method/path_gate.py)."""
        n = len(self)
        if n < 2:
            return 0
        i = k % (2 * n - 2)
        return i if i < n else 2 * n - 2 - i

    def render(self, t: int, rotation: np.ndarray | None = None) -> PcmViews:
        """PCMs of frame t; `rotation` (C,) is the input rotation each camera was asked for
        (radians, as from tracker.trunk_tilt), None for none."""
        nm, rig = self.noise, self.rig
        C, J = len(rig), self.channels.size
        d = self._draws(t)
        gt = self.gt[t]
        tilt = trunk_tilt(rig, gt) if np.isfinite(gt[[0, 1]]).all() else np.zeros(C)
        rot = np.zeros(C) if rotation is None else np.asarray(rotation)
        rel = np.angle(np.exp(1j * (tilt - rot)))
        inverted = (np.abs(rel) > np.pi / 2)[:, None] & self._lower[None, :]  # (C, J)
        p_miss = np.where(inverted, nm.inverted_p_missing, nm.p_missing)
        p_swap = np.where(inverted, nm.inverted_p_swap, nm.p_swap)
        lo = np.where(inverted, nm.inverted_amplitude[0], nm.amplitude[0])
        hi = np.where(inverted, nm.inverted_amplitude[1], nm.amplitude[1])
        amp = lo + (hi - lo) * d["amp"]
        u = d["event"]
        missing = u < p_miss
        swap = (u >= p_miss) & (u < p_miss + p_swap)
        src = np.where(swap, self._mirror_channel[None, :], np.arange(J)[None, :])
        ci = np.arange(C)[:, None]
        uv, front = d["uv"], d["front"]
        peak_uv = uv[ci, src] + d["offset"][ci, src]
        ok = ~missing & front[ci, src]
        # False peaks inside the person's bounding box in that image.
        lo_uv = np.nanmin(np.where(front[..., None], uv, np.nan), axis=1)  # (C, 2)
        hi_uv = np.nanmax(np.where(front[..., None], uv, np.nan), axis=1)
        false = d["false"] < nm.p_false
        false_uv = lo_uv[:, None, :] + (hi_uv - lo_uv)[:, None, :] * d["false_pos"]
        false_amp = nm.false_amplitude[0] + (nm.false_amplitude[1] - nm.false_amplitude[0]) * d["false_amp"]
        A = stride_affine(nm.stride)
        c_idx = np.concatenate([np.nonzero(ok)[0], np.nonzero(false)[0]])
        j_idx = np.concatenate([np.nonzero(ok)[1], np.nonzero(false)[1]])
        centers = np.concatenate([peak_uv[ok], false_uv[false]]) @ A[:, :2].T + A[:, 2]
        amps = np.concatenate([amp[ok], false_amp[false]])
        maps = self._splat(C, J, c_idx, j_idx, centers, amps)
        return PcmViews(
            maps=maps,
            image_to_map=np.repeat(A[None], C, axis=0),
            camera=np.arange(C),
            keypoints=self.channels,
            valid=np.ones((C, J), dtype=bool),
            presence=np.ones(C),
            stamp_ns=int(round(t * 1e9 / self.fps)),
        )

    def _draws(self, t: int) -> dict[str, np.ndarray]:
        """The random numbers of frame t, drawn once: rendering the same frame for another input
        rotation (e.g. the baseline's upright input) reuses them."""
        if self._drawn_t == t:
            return self._drawn
        nm, rng = self.noise, self.rng
        C, J = len(self.rig), self.channels.size
        # AR(1) displacement, stationary with std offset_px.
        self._ar = nm.ar_rho * self._ar + np.sqrt(1 - nm.ar_rho**2) * rng.normal(0.0, nm.offset_px, (C, J, 2))
        uv, front = self.rig.project(self.gt[t][self.channels])  # (C, J, 2)
        self._drawn = {
            "uv": uv,
            "front": front,
            "offset": self._ar.copy(),
            "amp": rng.random((C, J)),
            "event": rng.random((C, J)),
            "false": rng.random((C, J)),
            "false_pos": rng.random((C, J, 2)),
            "false_amp": rng.random((C, J)),
        }
        self._drawn_t = t
        return self._drawn

    def _splat(self, C: int, J: int, c_idx: np.ndarray, j_idx: np.ndarray, centers: np.ndarray, amps: np.ndarray) -> np.ndarray:
        """Gaussians (max-combined, as a CNN's map saturates) into a (C, J, H, W) stack."""
        W, H = self.map_size
        maps = np.zeros((C, J, H, W), dtype=np.float32)
        finite = np.isfinite(centers).all(axis=1)
        c_idx, j_idx, centers, amps = c_idx[finite], j_idx[finite], centers[finite], amps[finite]
        if not len(amps):
            return maps
        base = np.round(centers).astype(np.int64)
        xs = base[:, 0, None] + self._win[None, :]  # (P, K)
        ys = base[:, 1, None] + self._win[None, :]
        gx = np.exp(-0.5 * ((xs - centers[:, 0, None]) / self.noise.sigma_cells) ** 2)
        gy = np.exp(-0.5 * ((ys - centers[:, 1, None]) / self.noise.sigma_cells) ** 2)
        vals = amps[:, None, None] * gy[:, :, None] * gx[:, None, :]  # (P, K, K)
        inside = ((ys >= 0) & (ys < H))[:, :, None] & ((xs >= 0) & (xs < W))[:, None, :]
        P, K = xs.shape
        flat = (((c_idx * J + j_idx)[:, None, None] * H + np.clip(ys, 0, H - 1)[:, :, None]) * W
                + np.clip(xs, 0, W - 1)[:, None, :])
        np.maximum.at(maps.reshape(-1), flat[inside], vals[inside].astype(np.float32))
        return maps


__all__ = ["NoiseModel", "SyntheticPcmSource", "benchmark_rig", "KEYPOINTS"]
