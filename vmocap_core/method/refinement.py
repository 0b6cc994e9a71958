"""Virtual markers refined by triangulating each view's own PCM peak (our addition to II-D).

The lattice argmax of eq. 1 maximizes a sum of peaks: where the views' peaks do not meet in one
point (each CNN map is displaced by its own error), the sum's maximum snaps towards the views
that happen to agree, a mode rather than a mean of the views, so it scatters more than the
least-squares point of the views' peaks. The lattice marker is still the best place to look:
it is robust to a view's missing, swapped or false peak. So, per keypoint:

1. project the lattice marker into every view and take the PCM maximum within `radius` cells
   of it (sub-cell by a parabola through the log values, exact for a Gaussian peak). A maximum
   on the window's rim is kept: rejecting it was worse (walk 23.6 -> 24.5 mm), a lattice
   marker a few cells off cuts its own view's peak; the triangulation below drops outliers;
2. per camera the strongest view;
3. robust weighted triangulation: least squares of the reprojection errors in image pixels
   weighted by the peak values, dropping the camera with the largest error while the weighted
   mean error exceeds `max_error_px`. The compiled kernel (_kernels.refine_markers) runs
   Gauss-Newton from the lattice marker; the numpy reference (`refine_markers_numpy`, used
   without numba) a weighted DLT (triangulation.triangulate_robust): algebraic instead of geometric error, so
   they differ by a few mm (median 2.6 mm on the synthetic benchmark), equally accurate.

Where fewer than two cameras remain, or the residual stays too large, the lattice marker is
kept. The marker's weight W (eq. 5) stays the lattice sum. Measured on the synthetic benchmark
(bench accuracy, seed 0): virtual markers 42 -> 37.5 mm, first IK 27.5 -> 25.6 mm, output
regular 28.1 -> 26.1 mm, inverted 25.3 -> 24.4 mm.
"""

from __future__ import annotations

import numpy as np

from ..cameras.projection import Rig
from ..pcm.views import PcmViews, invert_affine
from . import _lattice_kernels as _kernels
from .lattice import PcmSampler
from .triangulation import triangulate_robust

LOG_FLOOR = 1e-6  # PCM values below this count as this in the parabola fit (log of 0)


def _parabola_vertex(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through (-1, left), (0, centre),
    (1, right); 0 where the three values are not concave."""
    den = left - 2.0 * centre + right
    concave = den < -1e-12
    return np.where(concave, np.clip(0.5 * (left - right) / np.where(concave, den, -1.0), -0.5, 0.5), 0.0)


def local_peaks(rig: Rig, pcm: PcmViews, points: np.ndarray, radius: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Per view and channel, the image pixel (V, J, 2) of the PCM maximum within `radius`
    cells of the projection of `points` (J, 3) (channel order), and its value (V, J); the value
    is 0 where the view is not valid for the channel or the point is behind the camera."""
    maps = pcm.maps
    V, J, H, W = maps.shape
    uv, front = rig.project(points)  # (C, J, 2)
    A = pcm.image_to_map
    xy = np.einsum("vij,vkj->vki", A[:, :, :2], uv[pcm.camera]) + A[:, None, :, 2]  # (V, J, 2)
    finite = np.isfinite(xy).all(axis=-1)
    cell = np.rint(np.nan_to_num(xy)).astype(np.int64)
    off = np.arange(-radius, radius + 1)
    K = off.size
    # Window cells (clipped one cell inside the map so the parabola has both neighbours).
    xs = np.clip(cell[..., 0, None] + off, 1, W - 2)  # (V, J, K)
    ys = np.clip(cell[..., 1, None] + off, 1, H - 2)
    vi = np.arange(V)[:, None, None, None]
    ji = np.arange(J)[None, :, None, None]
    win = maps[vi, ji, ys[..., :, None], xs[..., None, :]].reshape(V, J, K * K)  # (V, J, K*K)
    arg = win.argmax(axis=2)
    val = np.take_along_axis(win, arg[..., None], axis=2)[..., 0].astype(np.float64)
    iy, ix = np.divmod(arg, K)
    px = np.take_along_axis(xs, ix[..., None], axis=2)[..., 0]
    py = np.take_along_axis(ys, iy[..., None], axis=2)[..., 0]
    vj = (np.arange(V)[:, None], np.arange(J)[None, :])

    def log_at(dx: int, dy: int) -> np.ndarray:
        return np.log(np.maximum(maps[vj[0], vj[1], py + dy, px + dx].astype(np.float64), LOG_FLOOR))

    centre = log_at(0, 0)
    sub = np.stack([px + _parabola_vertex(log_at(-1, 0), centre, log_at(1, 0)),
                    py + _parabola_vertex(log_at(0, -1), centre, log_at(0, 1))], axis=-1)
    inv = invert_affine(A)
    out = np.einsum("vij,vkj->vki", inv[:, :, :2], sub) + inv[:, None, :, 2]
    ok = pcm.valid & front[pcm.camera] & finite & np.isfinite(val)
    return out, np.where(ok, np.clip(val, 0.0, 1.0), 0.0)


def refine_markers(rig: Rig, pcm: PcmViews, markers: np.ndarray, radius: int = 5, min_value: float = 0.1,
                   max_error_px: float = 12.0, min_views: int = 2,
                   sampler: PcmSampler | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lattice markers (J, 3) (channel order) -> refined markers (J, 3) and a mask (J,) of
    those that were refined (the others, and non-finite ones, are returned unchanged). See the
    module doc. sampler: the lattice search's PcmSampler of the same rig and PCMs, if at hand."""
    markers = np.asarray(markers, dtype=np.float64)
    if not _kernels.AVAILABLE:
        return refine_markers_numpy(rig, pcm, markers, radius, min_value, max_error_px, min_views)
    sampler = sampler or PcmSampler(rig, pcm)
    A = pcm.image_to_map[:, :, :2]
    cell_px = 1.0 / np.sqrt(np.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]))
    out = np.empty_like(markers)
    ok = np.zeros(markers.shape[0], dtype=bool)
    _kernels.refine_markers(np.ascontiguousarray(markers), sampler._R, sampler._t, sampler._dist, sampler._M,
                            sampler._maps, sampler._valid_b, pcm.camera.astype(np.int64), cell_px, int(radius),
                            float(min_value), float(max_error_px), int(min_views), out, ok)
    return out, ok


def refine_markers_numpy(rig: Rig, pcm: PcmViews, markers: np.ndarray, radius: int = 5, min_value: float = 0.1,
                         max_error_px: float = 12.0, min_views: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """numpy reference of `refine_markers` (weighted DLT instead of Gauss-Newton)."""
    markers = np.asarray(markers, dtype=np.float64)
    uv, val = local_peaks(rig, pcm, markers, radius)
    C, J = len(rig), markers.shape[0]
    cam_uv = np.zeros((C, J, 2))
    cam_w = np.zeros((C, J))
    # One observation per camera: a camera with several views (input rotation) keeps the
    # strongest; a few views, so a loop over views.
    for v in range(pcm.n_views):
        c = pcm.camera[v]
        better = val[v] > cam_w[c]
        cam_uv[c, better] = uv[v, better]
        cam_w[c, better] = val[v, better]
    cam_w = np.where(cam_w >= min_value, np.sqrt(cam_w), 0.0)
    pts, resid = triangulate_robust(rig, cam_uv, cam_w, max_error_px, min_views)
    ok = np.isfinite(resid) & (resid <= max_error_px) & np.isfinite(pts).all(axis=1) & np.isfinite(markers).all(axis=1)
    out = markers.copy()
    out[ok] = pts[ok]
    return out, ok


_warm = False


def warm_up(rig: Rig) -> None:
    """Compile (or load from numba's cache) the refinement kernel now, with the argument types
    of real calls, instead of on the first tracked frame."""
    global _warm
    if _warm or not _kernels.AVAILABLE or len(rig) == 0:
        return
    A = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    pcm = PcmViews(np.zeros((1, 1, 4, 4), np.float32), A, [0], [0], [[True]], [1.0])
    refine_markers(rig, pcm, np.zeros((1, 3)))
    _warm = True
