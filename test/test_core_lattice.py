"""Lattice search on analytic heatmaps, and triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from vmocap_core.cameras.projection import Camera, Rig, look_at
from vmocap_core.keypoints import indices
from vmocap_core.method import _lattice_kernels as _kernels
from vmocap_core.method.lattice import PcmSampler, lattice_offsets, lattice_search
from vmocap_core.method.triangulation import triangulate
from vmocap_core.pcm.views import PcmViews, stride_affine


def rig4() -> Rig:
    cams = []
    for i in range(4):
        ang = np.pi / 4 + i * np.pi / 2
        R, t = look_at(np.array([4 * np.cos(ang), 4 * np.sin(ang), 2.2]), np.array([0, 0, 1.0]))
        K = np.array([[800.0, 0, 511.5], [0, 800.0, 383.5], [0, 0, 1]])
        cams.append(Camera(f"c{i}", K, [-0.05, 0.01, 0, 0, 0], R, t, 1024, 768))
    return Rig(cams)


def gaussian_pcm(rig: Rig, points: np.ndarray, stride: int = 4, sigma: float = 2.0) -> PcmViews:
    """Exact Gaussians (sigma in cells) centred on the projections, built analytically."""
    W, H = 1024 // stride, 768 // stride
    A = stride_affine(stride)
    uv, _ = rig.project(points)  # (C, J, 2)
    m = uv @ A[:, :2].T + A[:, 2]
    xs, ys = np.arange(W), np.arange(H)
    gx = np.exp(-0.5 * ((xs[None, None, :] - m[..., 0, None]) / sigma) ** 2)  # (C, J, W)
    gy = np.exp(-0.5 * ((ys[None, None, :] - m[..., 1, None]) / sigma) ** 2)
    maps = gy[..., :, None] * gx[..., None, :]
    J = points.shape[0]
    return PcmViews(maps, np.repeat(A[None], len(rig), 0), np.arange(len(rig)), indices(["neck", "left_wrist", "right_ankle"])[:J],
                    np.ones((len(rig), J), bool), np.ones(len(rig)))


def test_lattice_argmax_on_analytic_heatmaps():
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0], [-0.1, 0.1, 0.1]])
    pcm = gaussian_pcm(rig, truth)
    start = truth + np.array([[0.03, -0.02, 0.04], [-0.04, 0.0, 0.02], [0.01, 0.03, -0.04]])
    coarse = lattice_search(rig, pcm, start, k=5, spacing=0.01, subcell=False)
    # The argmax lattice point is within a lattice step of the truth (bilinear sampling of a
    # peaked map favours points that project onto cell centres).
    assert np.abs(coarse.markers - truth).max() <= 0.01 + 1e-9
    fine = lattice_search(rig, pcm, start, k=5, spacing=0.01, subcell=True)
    assert np.linalg.norm(fine.markers - truth, axis=1).max() < 0.002
    assert ((fine.weights > 3.6) & (fine.weights <= 4.0)).all()  # eq. 5: four views near their peak
    assert (fine.n_views == 4).all()


def test_coarse_to_fine_matches_full_search():
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0]])
    pcm = gaussian_pcm(rig, truth)
    start = truth + 0.04
    full = lattice_search(rig, pcm, start, k=5, spacing=0.01)
    c2f = lattice_search(rig, pcm, start, k=5, spacing=0.01, coarse_to_fine=True)
    assert np.linalg.norm(full.markers - c2f.markers, axis=1).max() < 0.002


def test_compiled_kernel_equals_numpy_reference():
    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0], [3.0, 3.0, 1.0]])  # the last is off-image for some views
    pcm = gaussian_pcm(rig, truth)
    pcm.maps[1, 0, 50:60, 50:60] = np.nan
    pcm.maps[2, 1, 10:20, 10:20] = -3.0
    sampler = PcmSampler(rig, pcm)
    off = lattice_offsets(3, 0.02)
    a, na = sampler.sample_lattice(truth, off)
    b, nb = sampler.sample_lattice_numpy(truth, off)
    assert np.abs(a - b).max() < 1e-4 and (na == nb).all()
    assert _kernels.AVAILABLE, "numba is pinned in requirements.lock"


def test_bicubic_samples_equal_opencv_inter_cubic():
    import cv2

    rig = rig4()
    truth = np.array([[0.02, -0.03, 1.5], [0.3, 0.2, 1.0]])
    pcm = gaussian_pcm(rig, truth)
    only0 = PcmViews(pcm.maps[:1], pcm.image_to_map[:1], pcm.camera[:1], pcm.keypoints, pcm.valid[:1], pcm.presence[:1])
    pts = truth + np.array([0.013, -0.007, 0.004])
    got, _ = PcmSampler(rig, only0).sample_lattice(pts, np.zeros((1, 3)), cubic=True)
    uv, _ = rig.project(pts)
    m = uv[0] @ pcm.image_to_map[0, :, :2].T + pcm.image_to_map[0, :, 2]
    for j in range(2):
        ref = cv2.remap(pcm.maps[0, j], np.float32([[m[j, 0]]]), np.float32([[m[j, 1]]]), cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)[0, 0]
        assert got[j, 0] == pytest.approx(ref, abs=2e-3)


def test_nan_and_negative_heatmaps_do_not_steer():
    rig = rig4()
    truth = np.array([[0.0, 0.0, 1.2]])
    pcm = gaussian_pcm(rig, truth)
    pcm.maps[0] = np.nan  # a broken CNN output in one view
    pcm.maps[1] *= -1.0
    res = lattice_search(rig, pcm, truth + 0.02, k=4, spacing=0.01)
    assert np.isfinite(res.markers).all()
    assert np.linalg.norm(res.markers - truth) < 0.01  # two views left
    assert res.n_views[0] == 2 and 1.9 < res.weights[0] <= 2.0
    clean = pcm.sanitized()
    assert np.isfinite(clean.maps).all() and clean.maps.min() >= 0 and not clean.valid[0].any()


def test_points_off_map_and_behind_cameras_score_zero():
    rig = rig4()
    pcm = gaussian_pcm(rig, np.array([[0.0, 0.0, 1.0]]))
    far = np.array([[40.0, 40.0, 1.0]])
    res = lattice_search(rig, pcm, far, k=1, spacing=0.01)
    assert res.weights[0] == 0.0 and res.n_views[0] == 0


def test_weighted_triangulation_recovers_points():
    rig = rig4()
    pts = np.array([[0.1, 0.2, 1.0], [-0.3, 0.0, 1.7]])
    uv, _ = rig.project(pts)
    w = np.ones((4, 2))
    got, resid = triangulate(rig, uv, w)
    assert np.abs(got - pts).max() < 1e-6 and resid.max() < 1e-4
    w[1:, 1] = 0.0  # seen by one camera only
    got, resid = triangulate(rig, uv, w)
    assert np.isnan(got[1]).all() and np.isfinite(got[0]).all()
