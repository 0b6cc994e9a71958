"""Virtual markers refined by triangulating each view's PCM peak (peak_refinement.py)."""

from __future__ import annotations

import numpy as np
from test_core_lattice import gaussian_pcm, rig4

from vmocap_core.method import _lattice_kernels as _kernels
from vmocap_core.method.lattice import lattice_search
from vmocap_core.method.refinement import local_peaks, refine_markers, refine_markers_numpy
from vmocap_core.method.triangulation import triangulate
from vmocap_core.pcm.views import PcmViews


def rotated_crop_affine(centre_px: np.ndarray, side_px: float, angle: float, cells: int = 64) -> np.ndarray:
    """image -> map affine of a square crop (side_px, rotated by angle) mapped onto cells x cells."""
    s = cells / side_px
    c, n = np.cos(angle), np.sin(angle)
    M = s * np.array([[c, n], [-n, c]])
    return np.hstack([M, (np.array([cells / 2 - 0.5] * 2) - M @ centre_px)[:, None]])


def render(rig, points, affines, peaks_px, amps, sigma=2.0) -> PcmViews:
    """One view per camera with the given image->map affines; the peak of view v, channel j at
    image pixel peaks_px[v, j] with amplitude amps[v, j]."""
    V, J = peaks_px.shape[:2]
    H = W = 64 if affines is not None else None
    maps = np.zeros((V, J, H, W), np.float32)
    ys, xs = np.mgrid[0:H, 0:W]
    for v in range(V):
        m = peaks_px[v] @ affines[v, :, :2].T + affines[v, :, 2]
        for j in range(J):
            maps[v, j] = amps[v, j] * np.exp(-((xs - m[j, 0]) ** 2 + (ys - m[j, 1]) ** 2) / (2 * sigma**2))
    return PcmViews(maps, affines, np.arange(V), np.arange(J), np.ones((V, J), bool), np.ones(V))


def crop_views(rig, truth: np.ndarray, shifts_px: np.ndarray | None = None, amps: np.ndarray | None = None) -> PcmViews:
    """64 x 64 maps of 400 px crops around the points, rotated differently per camera."""
    uv, _ = rig.project(truth)  # (C, J, 2)
    C, J = uv.shape[:2]
    centre = uv.mean(axis=1)
    A = np.stack([rotated_crop_affine(centre[c], 400.0, 0.3 * c - 0.4) for c in range(C)])
    peaks = uv + (0.0 if shifts_px is None else shifts_px)
    return render(rig, truth, A, peaks, np.ones((C, J)) if amps is None else amps)


def test_exact_peaks_give_the_point_in_rotated_crops():
    """Noise-free Gaussians in rotated, scaled crops (BlazePose-like maps, 6.25 px per cell):
    a lattice marker 3 cm off comes back to the truth (parabola sub-cell peaks are exact for a
    Gaussian; the crop affine and the lens distortion are inverted exactly)."""
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0], [-0.2, 0.1, 0.3]])
    pcm = crop_views(rig, truth)
    start = truth + np.array([[0.03, -0.02, 0.01], [-0.02, 0.0, 0.03], [0.01, 0.03, -0.02]])
    for fn in (refine_markers, refine_markers_numpy):
        out, ok = fn(rig, pcm, start)
        assert ok.all(), fn.__name__
        assert np.linalg.norm(out - truth, axis=1).max() < 1e-3, fn.__name__
    uv, val = local_peaks(rig, pcm, start)
    proj, _ = rig.project(truth)
    assert np.abs(uv - proj).max() < 1e-3 and (val > 0.93).all()  # value: the best cell, <= half a cell off


def test_displaced_views_give_their_weighted_least_squares_point():
    """Each view's peak displaced by 6 px in a different direction (what a CNN does): the
    refined marker is the least-squares point of the peaks, the plain lattice argmax of eq. 1
    (a mode of the summed maps) is farther from it."""
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5]])
    uv, _ = rig.project(truth)
    shifts = np.array([[6.0, 2.0], [-6.0, 1.0], [1.0, 6.0], [0.0, -6.0]])[:, None, :]
    pcm = gaussian_pcm(rig, truth)
    H, W = pcm.maps.shape[2:]
    ys, xs = np.mgrid[0:H, 0:W]
    amps = [1.0, 0.6, 0.6, 0.6]
    for v in range(4):
        c = (uv[v, 0] + shifts[v, 0]) @ pcm.image_to_map[v, :, :2].T + pcm.image_to_map[v, :, 2]
        pcm.maps[v, 0] = amps[v] * np.exp(-((xs - c[0]) ** 2 + (ys - c[1]) ** 2) / (2 * 2.0**2))
    lattice = lattice_search(rig, pcm, truth, k=5, spacing=0.01)
    refined, ok = refine_markers(rig, pcm, lattice.markers)
    consensus, _ = triangulate(rig, uv + shifts, np.sqrt(np.array(amps))[:, None])
    assert ok[0]
    e_ref, e_lat = np.linalg.norm(refined - consensus), np.linalg.norm(lattice.markers - consensus)
    assert e_ref < 0.003 and e_ref < 0.5 * e_lat, (e_ref, e_lat)


def test_a_wrong_peak_in_one_view_is_dropped():
    """A swapped/false peak 16 px off in one view (still inside the window): the residual is too
    large, that camera is dropped and the other three give the point."""
    rig = rig4()
    truth = np.array([[0.1, 0.0, 1.2]])
    shifts = np.zeros((4, 1, 2))
    shifts[2, 0] = [16.0, -4.0]
    pcm = crop_views(rig, truth, shifts)
    for fn in (refine_markers, refine_markers_numpy):
        out, ok = fn(rig, pcm, truth + 0.01, max_error_px=5.0)
        assert ok[0] and np.linalg.norm(out[0] - truth[0]) < 2e-3, fn.__name__
        # without the drop the wrong view pulls the point by centimetres
        pulled, _ = fn(rig, pcm, truth + 0.01, max_error_px=1e6)
        assert np.linalg.norm(pulled[0] - truth[0]) > 5e-3, fn.__name__


def test_too_few_views_or_bad_input_keep_the_lattice_marker():
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0], [-0.2, 0.1, 0.3]])
    pcm = crop_views(rig, truth)
    pcm.valid[1:, 0] = False  # channel 0 seen by one view only
    pcm.maps[:, 1] = 0.0  # channel 1: empty maps everywhere
    pcm.maps[0, 2, 30:34, 30:34] = np.nan  # channel 2: a broken view, the other three suffice
    start = truth + 0.02
    start[1] = np.nan  # and no marker for channel 1 at all
    for fn in (refine_markers, refine_markers_numpy):
        out, ok = fn(rig, pcm, start)
        assert ok.tolist() == [False, False, True], fn.__name__
        np.testing.assert_array_equal(out[:2], start[:2])
        assert np.linalg.norm(out[2] - truth[2]) < 2e-3


def test_compiled_kernel_agrees_with_numpy_reference_under_noise():
    rng = np.random.default_rng(3)
    rig = rig4()
    truth = rng.uniform([-0.5, -0.5, 0.1], [0.5, 0.5, 1.8], (20, 3))
    uv, _ = rig.project(truth)
    pcm = crop_views(rig, truth, rng.normal(0.0, 6.0, uv.shape), rng.uniform(0.6, 1.0, uv.shape[:2]))
    start = truth + rng.normal(0.0, 0.02, truth.shape)
    a, oka = refine_markers(rig, pcm, start)
    b, okb = refine_markers_numpy(rig, pcm, start)
    both = oka & okb
    assert both.sum() >= 18
    # Gauss-Newton on pixel errors vs DLT on algebraic errors: close, not equal
    assert np.median(np.linalg.norm(a[both] - b[both], axis=1)) < 0.005
    assert _kernels.AVAILABLE, "numba is pinned in requirements.lock"
