"""Lattice search for virtual markers (paper II-D, eq. 1-2 and the weight of eq. 5).

For every keypoint j, the (2k+1)^3 lattice of spacing s around a centre c_j is projected into
every view, the views' PCMs are sampled bilinearly at the projections, and the lattice point
with the largest sum over views is the virtual marker; that sum is its weight W_j. A
projection outside a map, or a point behind the camera, contributes 0.

All keypoints, lattice points and views are evaluated in one vectorized pass.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..cameras.projection import Rig
from ..pcm.views import PcmViews
from . import _lattice_kernels as _kernels


@functools.lru_cache(maxsize=32)
def lattice_offsets(k: int, spacing: float) -> np.ndarray:
    """(L, 3) offsets of the (2k+1)^3 lattice of spacing `spacing`, centre first (cached:
    the same few lattices serve every frame; do not modify the returned array)."""
    r = np.arange(-k, k + 1, dtype=np.float64) * spacing
    g = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    # Centre first so that ties (e.g. all zeros) keep the marker where it was.
    centre = len(g) // 2
    order = np.r_[centre, np.arange(centre), np.arange(centre + 1, len(g))]
    out = g[order]
    out.flags.writeable = False
    return out


@dataclass
class LatticeResult:
    markers: np.ndarray  # (J, 3) in the channel order of the PCMs
    weights: np.ndarray  # (J,) summed PCM score at the marker (eq. 5)
    n_views: np.ndarray  # (J,) number of views that saw a nonzero PCM value at the marker


class PcmSampler:
    """Samples the PCMs of one frame set at 3D points: the sum over views of eq. 1."""

    def __init__(self, rig: Rig, pcm: PcmViews) -> None:
        self.rig = rig
        self.pcm = pcm
        V, J, H, W = pcm.maps.shape
        self._flat = pcm.maps.reshape(-1)
        self._shape = (V, J, H, W)
        self._R = rig._R[pcm.camera]  # (V, 3, 3)
        self._t = rig._t[pcm.camera]
        self._valid = pcm.valid.astype(np.float32)  # (V, J)
        self._valid_b = np.ascontiguousarray(pcm.valid)
        self._maps = np.ascontiguousarray(pcm.maps, dtype=np.float32)
        # Fold the view's image->map affine into one per-view map: pixel = K x'' -> map.
        A = pcm.image_to_map  # (V, 2, 3)
        K = rig._K[pcm.camera]  # (V, 3, 3)
        self._M = np.einsum("vij,vjk->vik", A[:, :, :2], K[:, :2, :]) + np.concatenate(
            [np.zeros((V, 2, 2)), A[:, :, 2:]], axis=2
        )  # (V, 2, 3): map = M @ (x'', y'', 1)
        self._dist = rig._dist[pcm.camera]  # (V, 8)
        self._distorted = bool(rig._distorted[pcm.camera].any())
        self._R32 = self._R.astype(np.float32)
        self._t32 = self._t.astype(np.float32)
        self._d32 = self._dist.astype(np.float32)[:, :, None, None]
        self._M32 = self._M.astype(np.float32)[:, :, :, None, None]
        self._rational = bool(rig._rational[pcm.camera].any())

    def sample_lattice(self, centres: np.ndarray, offsets: np.ndarray, cubic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Scores (J, L) and view counts (J, L) of the points centres (J, 3) + offsets (L, 3):
        the compiled kernel when numba is there, else the numpy reference (bilinear only)."""
        if not _kernels.AVAILABLE:
            return self.sample_lattice_numpy(centres, offsets)
        J, L = centres.shape[0], offsets.shape[0]
        scores = np.zeros((J, L), dtype=np.float32)
        nviews = np.zeros((J, L), dtype=np.int32)
        _kernels.score_lattice(
            np.ascontiguousarray(centres, dtype=np.float64), np.ascontiguousarray(np.matmul(offsets, self._R.transpose(0, 2, 1))),
            self._R, self._t, self._dist, self._M, self._maps, self._valid_b, scores, nviews, cubic,
        )
        return scores, nviews

    def sample_lattice_numpy(self, centres: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """numpy reference of sample_lattice: the rotation is applied to centres and offsets
        separately (R (c + o) + t = (R c + t) + R o), then broadcast."""
        c = np.matmul(self._R, centres.T) + self._t[:, :, None]  # (V, 3, J)
        o = np.matmul(self._R, offsets.T)  # (V, 3, L)
        return self.sample_camera_frame(c.astype(np.float32)[:, :, :, None] + o.astype(np.float32)[:, :, None, :])

    def sample_camera_frame(self, pc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points of every view (V, 3, J, L) -> (score (J, L), views (J, L))."""
        vals = self.view_values(pc)
        seen = vals > 0
        return vals.sum(axis=0), seen.sum(axis=0)

    def view_values(self, pc: np.ndarray) -> np.ndarray:
        """Camera-frame points of every view (V, 3, J, L) -> each view's PCM value (V, J, L):
        bilinear, 0 behind the camera, off the map or where the view has no channel."""
        z = pc[:, 2]
        front = z > 1e-6
        inv_z = np.float32(1.0) / np.where(front, z, np.float32(1.0))
        x = pc[:, 0] * inv_z
        y = pc[:, 1] * inv_z
        if self._distorted:
            d = self._d32
            r2 = x * x + y * y
            radial = 1 + r2 * (d[:, 0] + r2 * (d[:, 1] + r2 * d[:, 4]))
            if self._rational:
                radial = radial / (1 + r2 * (d[:, 5] + r2 * (d[:, 6] + r2 * d[:, 7])))
            xy2 = 2 * x * y
            x, y = (
                x * radial + d[:, 2] * xy2 + d[:, 3] * (r2 + 2 * x * x),
                y * radial + d[:, 2] * (r2 + 2 * y * y) + d[:, 3] * xy2,
            )
        M = self._M32
        mx = M[:, 0, 0] * x + M[:, 0, 1] * y + M[:, 0, 2]
        my = M[:, 1, 0] * x + M[:, 1, 1] * y + M[:, 1, 2]
        vals = self._bilinear(mx, my)
        vals *= front
        vals *= self._valid[:, :, None]
        return vals

    def point_values(self, points: np.ndarray) -> np.ndarray:
        """Each view's PCM value at one point per channel (J, 3) -> (V, J), or at L points per
        channel (J, L, 3) -> (V, J, L)."""
        pts = np.asarray(points, dtype=np.float64)
        J = pts.shape[0]
        c = np.matmul(self._R, pts.reshape(-1, 3).T) + self._t[:, :, None]  # (V, 3, J * L)
        vals = self.view_values(c.astype(np.float32).reshape(len(c), 3, J, -1))
        return vals[:, :, 0] if pts.ndim == 2 else vals

    def _bilinear(self, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
        """Bilinear PCM values at map coordinates (V, J, L); 0 outside the map."""
        V, J, H, W = self._shape
        x0f = np.floor(mx)
        y0f = np.floor(my)
        fx = mx - x0f
        fy = my - y0f
        # Clip into a safe range first so the int conversion cannot overflow.
        x0 = np.clip(x0f, -1, W).astype(np.int32)
        y0 = np.clip(y0f, -1, H).astype(np.int32)
        base = ((np.arange(V, dtype=np.int32)[:, None] * J + np.arange(J, dtype=np.int32)[None, :]) * (H * W))[:, :, None]
        out = np.zeros(mx.shape, dtype=np.float32)
        for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            xi = x0 + dx
            yi = y0 + dy
            inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            idx = base + np.clip(yi, 0, H - 1) * W + np.clip(xi, 0, W - 1)
            cell = np.where(inside, self._flat[idx], 0.0)
            # A NaN or out-of-range PCM value must not steer the search: sanitize what is read.
            cell = np.clip(np.nan_to_num(cell, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
            out += cell * wgt
        return out


def lattice_search(
    rig: Rig,
    pcm: PcmViews,
    centres: np.ndarray,
    k: int = 5,
    spacing: float = 0.01,
    coarse_to_fine: bool = False,
    subcell: bool = True,
    sampler: PcmSampler | None = None,
) -> LatticeResult:
    """Virtual markers of all PCM channels around `centres` (J, 3) (channel order of `pcm`).

    coarse_to_fine: search the same volume (+-k*s) first on a lattice of spacing ~2.5 s,
    then the full resolution s around the coarse winner (125 + 27 instead of 1331 samples for k=5).
    subcell: refine the argmax along each axis by a parabola through it and its two lattice
    neighbours (at most s/2), which removes most of the lattice quantization error.
    sampler: a PcmSampler of these rig and PCMs already built for this frame (else built here).
    """
    sampler = sampler or PcmSampler(rig, pcm)
    centres = np.asarray(centres, dtype=np.float64)
    if coarse_to_fine and k > 2:
        kc = 2
        sc = k * spacing / kc
        best, _, _ = _search(sampler, centres, lattice_offsets(kc, sc))
        centres = best
        # The coarse winner lies within +-sc/2 of the optimum; the fine lattice (+-k s) and the
        # sub-lattice refinement (one more step) cover that with k = ceil(sc / 2s - 1).
        k = min(k, max(1, int(np.ceil(sc / spacing / 2.0 - 1.0 - 1e-9))))
    offsets = lattice_offsets(k, spacing)
    best, score, nviews = _search(sampler, centres, offsets)
    if subcell:
        best = _refine(sampler, best, score, spacing)
    return LatticeResult(best, score, nviews)


def _search(sampler: PcmSampler, centres: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    score, nviews = sampler.sample_lattice(centres, offsets)
    arg = score.argmax(axis=1)
    j = np.arange(len(centres))
    return centres + offsets[arg], score[j, arg].astype(np.float64), nviews[j, arg]


def _refine(sampler: PcmSampler, best: np.ndarray, score: np.ndarray, spacing: float) -> np.ndarray:
    """Sub-lattice refinement: a parabola along x, y and z through the marker and its two
    lattice neighbours, on bicubic samples of the PCMs (bilinear samples peak on cell centres)."""
    steps = np.array([[0, 0, 0], [-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], float) * spacing
    s, _ = sampler.sample_lattice(best, steps, cubic=_kernels.AVAILABLE)  # (J, 7)
    s = s.astype(np.float64)
    c, minus, plus = s[:, :1], s[:, 1::2], s[:, 2::2]
    denom = minus - 2 * c + plus
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(denom < -1e-9, 0.5 * (minus - plus) / denom, 0.0)
    delta = np.clip(delta, -1.0, 1.0) * spacing  # the bilinear argmax can be a step off
    return best + np.where(score[:, None] > 0, delta, 0.0)


_warm = False


def warm_up(rig: Rig) -> None:
    """Compile (or load from numba's cache) the lattice kernel now, with the argument types of
    real calls, instead of on the first tracked frame (a fresh compile takes seconds)."""
    global _warm
    if _warm or not _kernels.AVAILABLE or len(rig) == 0:
        return
    A = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    pcm = PcmViews(np.zeros((1, 1, 4, 4), np.float32), A, [0], [0], [[True]], [1.0])
    lattice_search(rig, pcm, np.zeros((1, 3)), k=3, spacing=0.02, coarse_to_fine=True, subcell=True)
    _warm = True
