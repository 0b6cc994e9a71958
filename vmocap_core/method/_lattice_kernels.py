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
) -> None:
    V, J, H, W = maps.shape
    L = rotated_offsets.shape[1]
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
                scores[j, l] += val
                nviews[j, l] += 1


@njit(cache=True, inline="always")
def _to_map(R: np.ndarray, t: np.ndarray, dist: np.ndarray, M: np.ndarray, v: int,
            X: float, Y: float, Z: float) -> tuple[float, float, bool]:
    """World point -> map coordinates of view v (pinhole + OpenCV distortion + the view's
    affine), and whether it is in front of the camera."""
    x = R[v, 0, 0] * X + R[v, 0, 1] * Y + R[v, 0, 2] * Z + t[v, 0]
    y = R[v, 1, 0] * X + R[v, 1, 1] * Y + R[v, 1, 2] * Z + t[v, 1]
    z = R[v, 2, 0] * X + R[v, 2, 1] * Y + R[v, 2, 2] * Z + t[v, 2]
    if z <= 1e-6:
        return 0.0, 0.0, False
    x /= z
    y /= z
    k1, k2, p1, p2, k3, k4, k5, k6 = dist[v, 0], dist[v, 1], dist[v, 2], dist[v, 3], dist[v, 4], dist[v, 5], dist[v, 6], dist[v, 7]
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return M[v, 0, 0] * xd + M[v, 0, 1] * yd + M[v, 0, 2], M[v, 1, 0] * xd + M[v, 1, 1] * yd + M[v, 1, 2], True


@njit(cache=True, inline="always")
def _log_cell(maps: np.ndarray, v: int, j: int, y: int, x: int) -> float:
    return math.log(max(_cell(maps, v, j, y, x), 1e-6))


@njit(cache=True, inline="always")
def _vertex(left: float, centre: float, right: float) -> float:
    """Vertex offset of the parabola through (-1, left), (0, centre), (1, right), in [-0.5, 0.5]."""
    den = left - 2.0 * centre + right
    if not (den < -1e-12):
        return 0.0
    return min(0.5, max(-0.5, 0.5 * (left - right) / den))


@njit(cache=True, nogil=True)
def refine_markers(
    markers: np.ndarray,  # (J, 3) float64 lattice markers, channel order
    R: np.ndarray,  # (V, 3, 3)
    t: np.ndarray,  # (V, 3)
    dist: np.ndarray,  # (V, 8)
    M: np.ndarray,  # (V, 2, 3) distorted normalized coords -> map coords
    maps: np.ndarray,  # (V, J, H, W) float32
    valid: np.ndarray,  # (V, J) bool
    camera: np.ndarray,  # (V,) int64 camera of each view
    cell_px: np.ndarray,  # (V,) image pixels per map cell
    radius: int,
    min_value: float,
    max_error_px: float,
    min_views: int,
    out: np.ndarray,  # out (J, 3)
    ok: np.ndarray,  # out (J,) bool
) -> None:
    """peak_refinement.py: per keypoint, each view's PCM maximum near the projected marker,
    the strongest view per camera, then Gauss-Newton on the weighted squared reprojection error
    in image pixels (weight = peak value), dropping the worst camera while the weighted mean
    error exceeds max_error_px."""
    V, J, H, W = maps.shape
    n_cam = 0
    for v in range(V):
        n_cam = max(n_cam, camera[v] + 1)
    obs = np.zeros((V, 2))
    wv = np.zeros(V)
    best = np.empty(n_cam, dtype=np.int64)
    use = np.empty(V, dtype=np.int64)
    h = 1e-4  # metres, numerical derivative step
    for j in range(J):
        out[j, 0], out[j, 1], out[j, 2] = markers[j, 0], markers[j, 1], markers[j, 2]
        ok[j] = False
        if not (math.isfinite(markers[j, 0]) and math.isfinite(markers[j, 1]) and math.isfinite(markers[j, 2])):
            continue
        for c in range(n_cam):
            best[c] = -1
        for v in range(V):
            wv[v] = 0.0
            if not valid[v, j]:
                continue
            mx, my, front = _to_map(R, t, dist, M, v, markers[j, 0], markers[j, 1], markers[j, 2])
            if not front or not (mx > -radius - 1.0 and mx < W + radius and my > -radius - 1.0 and my < H + radius):
                continue
            cx, cy = int(math.floor(mx + 0.5)), int(math.floor(my + 0.5))
            x0, x1 = max(1, cx - radius), min(W - 2, cx + radius)
            y0, y1 = max(1, cy - radius), min(H - 2, cy + radius)
            top, px, py = -1.0, -1, -1
            for yy in range(y0, y1 + 1):
                for xx in range(x0, x1 + 1):
                    val = _cell(maps, v, j, yy, xx)
                    if val > top:
                        top, px, py = val, xx, yy
            if px < 0 or top < min_value:
                continue
            c0 = _log_cell(maps, v, j, py, px)
            obs[v, 0] = px + _vertex(_log_cell(maps, v, j, py, px - 1), c0, _log_cell(maps, v, j, py, px + 1))
            obs[v, 1] = py + _vertex(_log_cell(maps, v, j, py - 1, px), c0, _log_cell(maps, v, j, py + 1, px))
            wv[v] = top
            c = camera[v]
            if best[c] < 0 or top > wv[best[c]]:
                best[c] = v
        n = 0
        for c in range(n_cam):
            if best[c] >= 0:
                use[n] = best[c]
                n += 1
        while n >= min_views:
            X, Y, Z = markers[j, 0], markers[j, 1], markers[j, 2]
            for _ in range(4):  # Gauss-Newton from the lattice marker (a few cm away at most)
                a00 = a01 = a02 = a11 = a12 = a22 = 0.0
                b0 = b1 = b2 = 0.0
                for i in range(n):
                    v = use[i]
                    mx, my, front = _to_map(R, t, dist, M, v, X, Y, Z)
                    if not front:
                        continue
                    s = cell_px[v]
                    rx, ry = (obs[v, 0] - mx) * s, (obs[v, 1] - my) * s
                    gx0, gy0, _f = _to_map(R, t, dist, M, v, X + h, Y, Z)
                    gx1, gy1, _f = _to_map(R, t, dist, M, v, X, Y + h, Z)
                    gx2, gy2, _f = _to_map(R, t, dist, M, v, X, Y, Z + h)
                    jx0, jx1, jx2 = (gx0 - mx) * s / h, (gx1 - mx) * s / h, (gx2 - mx) * s / h
                    jy0, jy1, jy2 = (gy0 - my) * s / h, (gy1 - my) * s / h, (gy2 - my) * s / h
                    w = wv[v]
                    a00 += w * (jx0 * jx0 + jy0 * jy0)
                    a01 += w * (jx0 * jx1 + jy0 * jy1)
                    a02 += w * (jx0 * jx2 + jy0 * jy2)
                    a11 += w * (jx1 * jx1 + jy1 * jy1)
                    a12 += w * (jx1 * jx2 + jy1 * jy2)
                    a22 += w * (jx2 * jx2 + jy2 * jy2)
                    b0 += w * (jx0 * rx + jy0 * ry)
                    b1 += w * (jx1 * rx + jy1 * ry)
                    b2 += w * (jx2 * rx + jy2 * ry)
                # 3x3 symmetric solve by cofactors (two rays make it well conditioned)
                c00 = a11 * a22 - a12 * a12
                c01 = a02 * a12 - a01 * a22
                c02 = a01 * a12 - a02 * a11
                det = a00 * c00 + a01 * c01 + a02 * c02
                if not (abs(det) > 1e-12):
                    break
                c11 = a00 * a22 - a02 * a02
                c12 = a01 * a02 - a00 * a12
                c22 = a00 * a11 - a01 * a01
                X += (c00 * b0 + c01 * b1 + c02 * b2) / det
                Y += (c01 * b0 + c11 * b1 + c12 * b2) / det
                Z += (c02 * b0 + c12 * b1 + c22 * b2) / det
            # weighted mean reprojection error (px); drop the worst camera while too large
            sw = se = 0.0
            worst, worst_e = -1, -1.0
            for i in range(n):
                v = use[i]
                mx, my, front = _to_map(R, t, dist, M, v, X, Y, Z)
                e = math.hypot(obs[v, 0] - mx, obs[v, 1] - my) * cell_px[v] if front else 1e9
                sw += wv[v]
                se += wv[v] * e
                if e > worst_e:
                    worst, worst_e = i, e
            resid = se / sw if sw > 0 else 1e9
            if resid <= max_error_px and math.isfinite(X + Y + Z):
                out[j, 0], out[j, 1], out[j, 2] = X, Y, Z
                ok[j] = True
                break
            if n <= min_views:
                break
            use[worst] = use[n - 1]
            n -= 1
