"""Compiled inner loop of the lattice search (numba).

The numpy implementation in lattice.PcmSampler is the reference; this kernel computes the same
sum of eq. 1 without materializing the (views x keypoints x lattice) intermediate arrays, which
is what makes a 25-keypoint, 4-camera, 11^3 lattice fit a per-frame budget of a few ms.
"""

from __future__ import annotations

import math

import numpy as np

try:
    from numba import njit

    AVAILABLE = True
except ImportError:  # numba is pinned in requirements.lock; the numpy path still works without it
    AVAILABLE = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def wrap(f):
            return f

        return wrap


@njit(cache=True, inline="always")
def _cell(maps: np.ndarray, v: int, j: int, y: int, x: int) -> float:
    """A PCM cell clipped to [0, 1], NaN read as 0: a broken CNN output must not steer."""
    c = maps[v, j, y, x]
    if not (c > 0.0):
        return 0.0
    return c if c < 1.0 else 1.0


@njit(cache=True, inline="always")
def _cubic_weight(d: float) -> float:
    """Keys' cubic convolution kernel with a = -0.75, as OpenCV's INTER_CUBIC."""
    a = -0.75
    d = abs(d)
    if d <= 1.0:
        return ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0
    if d < 2.0:
        return ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a
    return 0.0


@njit(cache=True, inline="always")
def _bicubic(maps: np.ndarray, v: int, j: int, x0: int, y0: int, fx: float, fy: float, W: int, H: int) -> float:
    """Bicubic value from the 4x4 cells around (x0 + fx, y0 + fy); cells off the map are 0.
    Bilinear interpolation of a peaked map has its maxima on cell centres, which biases the
    argmax by up to half a cell; the cubic kernel does not (used for sub-lattice refinement)."""
    val = 0.0
    for dy in range(-1, 3):
        yi = y0 + dy
        if yi < 0 or yi >= H:
            continue
        wy = _cubic_weight(dy - fy)
        for dx in range(-1, 3):
            xi = x0 + dx
            if xi < 0 or xi >= W:
                continue
            val += _cell(maps, v, j, yi, xi) * _cubic_weight(dx - fx) * wy
    return val


# Serial on purpose: a parallel loop over keypoints was faster only on an idle machine; next to
# the CNN (which keeps both cores busy) its thread pool waited for cores and a search took
# 24 ms instead of 1.6 ms (measured with load ~4.5).
@njit(cache=True, fastmath=False, nogil=True)
def score_lattice(
    centres: np.ndarray,  # (J, 3) float64 world
    rotated_offsets: np.ndarray,  # (V, L, 3) float64: R_v @ offset_l, shared by all keypoints
    R: np.ndarray,  # (V, 3, 3) float64 world->camera of each view's camera
    t: np.ndarray,  # (V, 3)
    dist: np.ndarray,  # (V, 8) k1 k2 p1 p2 k3 k4 k5 k6
    M: np.ndarray,  # (V, 2, 3) distorted normalized coords -> map coords
    maps: np.ndarray,  # (V, J, H, W) float32
    valid: np.ndarray,  # (V, J) bool
    scores: np.ndarray,  # out (J, L) float32
    nviews: np.ndarray,  # out (J, L) int32
    cubic: bool,  # bicubic (OpenCV's INTER_CUBIC kernel) instead of bilinear sampling
    log_eps: float,  # > 0: sum log(1 + PCM / log_eps) / log(1 + 1 / log_eps) instead of PCM (lattice.py)
) -> None:
    V, J, H, W = maps.shape
    L = rotated_offsets.shape[1]
    log_norm = 1.0 / math.log1p(1.0 / log_eps) if log_eps > 0.0 else 1.0
    for j in range(J):
        for v in range(V):
            if not valid[v, j]:
                continue
            # Camera-frame centre once per (view, keypoint); R o per lattice point below.
            cx = R[v, 0, 0] * centres[j, 0] + R[v, 0, 1] * centres[j, 1] + R[v, 0, 2] * centres[j, 2] + t[v, 0]
            cy = R[v, 1, 0] * centres[j, 0] + R[v, 1, 1] * centres[j, 1] + R[v, 1, 2] * centres[j, 2] + t[v, 1]
            cz = R[v, 2, 0] * centres[j, 0] + R[v, 2, 1] * centres[j, 1] + R[v, 2, 2] * centres[j, 2] + t[v, 2]
            k1, k2, p1, p2, k3, k4, k5, k6 = dist[v, 0], dist[v, 1], dist[v, 2], dist[v, 3], dist[v, 4], dist[v, 5], dist[v, 6], dist[v, 7]
            rational = k4 != 0.0 or k5 != 0.0 or k6 != 0.0
            for l in range(L):
                X = cx + rotated_offsets[v, l, 0]
                Y = cy + rotated_offsets[v, l, 1]
                Z = cz + rotated_offsets[v, l, 2]
                if Z <= 1e-6:
                    continue  # behind the camera: contributes 0
                iz = 1.0 / Z
                x = X * iz
                y = Y * iz
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                if rational:
                    radial /= 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
                xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
                yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
                mx = M[v, 0, 0] * xd + M[v, 0, 1] * yd + M[v, 0, 2]
                my = M[v, 1, 0] * xd + M[v, 1, 1] * yd + M[v, 1, 2]
                if not (mx > -1.0 and mx < W and my > -1.0 and my < H):
                    continue  # outside the map: contributes 0
                x0 = int(math.floor(mx))
                y0 = int(math.floor(my))
                fx = mx - x0
                fy = my - y0
                if cubic:
                    val = _bicubic(maps, v, j, x0, y0, fx, fy, W, H)
                else:
                    val = 0.0
                    if y0 >= 0:
                        if x0 >= 0:
                            val += _cell(maps, v, j, y0, x0) * (1.0 - fx) * (1.0 - fy)
                        if x0 + 1 < W:
                            val += _cell(maps, v, j, y0, x0 + 1) * fx * (1.0 - fy)
                    if y0 + 1 < H:
                        if x0 >= 0:
                            val += _cell(maps, v, j, y0 + 1, x0) * (1.0 - fx) * fy
                        if x0 + 1 < W:
                            val += _cell(maps, v, j, y0 + 1, x0 + 1) * fx * fy
                if not (val > 0.0):
                    continue
                if log_eps > 0.0:
                    val = math.log1p((val if val < 1.0 else 1.0) / log_eps) * log_norm
                scores[j, l] += val
                nviews[j, l] += 1
