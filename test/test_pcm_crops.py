"""Crop and heatmap-cell geometry: the exact image <-> crop <-> map affines (no model needed)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vmocap_core.cameras.projection import Camera, Rig, look_at
from vmocap_core.errors import ModelError
from vmocap_core.keypoints import INDEX, KEYPOINTS, LOWER_BODY
from vmocap_core.method.rotation import trunk_tilt
from vmocap_core.pcm.blazepose import rotated_crops
from vmocap_core.pcm.blazepose_net import CROP_TO_MAP
from vmocap_core.pcm.crops import (
    BODY_FRACTION,
    COMPACT_HEIGHT,
    TURNED_BODY_FRACTION,
    Crops,
    body_length,
    compose_affine,
    crop_affine,
    crops_from_skeleton,
    stance_height,
    tilt_from_points,
)
from vmocap_core.pcm.model import letterbox_affine
from vmocap_core.pcm.views import PcmViews, apply_affine, invert_affine, stride_affine

N = 256


def test_crop_affine_centre_edges_and_rotation() -> None:
    c, side = np.array([400.0, 300.0]), 512.0
    A = crop_affine(c, side, 0.0, N)[0]
    # the crop centre (N-1)/2 is the crop's image centre; crop edges (-0.5, N-0.5) are the side's edges
    np.testing.assert_allclose(apply_affine(A, c), [(N - 1) / 2] * 2, atol=1e-12)
    np.testing.assert_allclose(apply_affine(A, c - side / 2), [-0.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(apply_affine(A, c + side / 2), [N - 0.5, N - 0.5], atol=1e-12)
    # rotation pi/2: a person leaning to image +u (head at c + (d, 0)) is upright in the crop
    A = crop_affine(c, side, np.pi / 2, N)[0]
    np.testing.assert_allclose(apply_affine(A, c + [100.0, 0.0]), [(N - 1) / 2, (N - 1) / 2 - 50.0], atol=1e-9)
    assert tilt_from_points(c, c + [100.0, 0.0]) == pytest.approx(np.pi / 2)
    assert tilt_from_points(c, c - [0.0, 100.0]) == pytest.approx(0.0)


def _blob(w: int, h: int, uv: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    g = np.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * sigma**2))
    return np.round(g * 255).astype(np.uint8)


@pytest.mark.parametrize("rotation", [0.0, 0.7, np.pi])
@pytest.mark.parametrize("side", [256.0, 400.0])
def test_warp_affine_agrees_with_the_affine(rotation: float, side: float) -> None:
    """cv2.warpAffine with image_to_crop puts an image point exactly where the affine says."""
    uv = np.array([331.3, 207.8])
    img = _blob(640, 480, uv)
    A = crop_affine([300.0, 250.0], side, rotation, N)[0]
    crop = cv2.warpAffine(img, A, (N, N), flags=cv2.INTER_LINEAR).astype(np.float64)
    xs, ys = np.meshgrid(np.arange(N), np.arange(N))
    w = np.where(crop > 20, crop, 0)
    centroid = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
    np.testing.assert_allclose(centroid, apply_affine(A, uv), atol=0.1)


def test_blazepose_half_cell_convention() -> None:
    """Map cell (x, y) is centred on crop pixel (4x - 0.5, 4y - 0.5) (measured, see blazepose_net.py)."""
    c, side, rot = np.array([500.0, 400.0]), 600.0, 0.3
    image_to_crop = crop_affine(c, side, rot, N)[0]
    image_to_map = compose_affine(CROP_TO_MAP, image_to_crop)
    cells = np.array([[0, 0], [10, 20], [63, 63]], dtype=np.float64)
    crop_px = cells * 4 - 0.5
    np.testing.assert_allclose(apply_affine(invert_affine(image_to_crop), crop_px),
                               apply_affine(invert_affine(image_to_map), cells), atol=1e-9)
    np.testing.assert_allclose(apply_affine(CROP_TO_MAP, np.array([N / 2 - 0.5, N / 2 - 0.5])), [32, 32])
    # PcmViews.peaks uses the same mapping: a one-hot map at cell (10, 20)
    maps = np.zeros((1, 1, 64, 64), np.float32)
    maps[0, 0, 20, 10] = 1.0
    pv = PcmViews(maps, image_to_map[None], [0], [INDEX["nose"]], [[True]], [1.0])
    uv, _ = pv.peaks()
    s = side / N
    R = np.array([[np.cos(rot), -np.sin(rot)], [np.sin(rot), np.cos(rot)]])
    expect = c + s * R @ (np.array([39.5, 79.5]) - (N - 1) / 2)
    np.testing.assert_allclose(uv[0, 0], expect, atol=1e-9)


def test_letterbox_affine_maps_edges_to_edges() -> None:
    A = letterbox_affine(1024, 768, 224, 224)
    s = 224 / 1024
    np.testing.assert_allclose(apply_affine(A, np.array([-0.5, -0.5])), [-0.5, -0.5 + (224 - 768 * s) / 2])
    np.testing.assert_allclose(apply_affine(A, np.array([1023.5, 767.5])), [223.5, 223.5 - (224 - 768 * s) / 2])


def _rig() -> Rig:
    cams = []
    for k, eye in enumerate([[4.0, 0.0, 1.2], [0.0, 4.0, 1.2], [0.0, 0.0, 6.0]]):
        R, t = look_at(np.array(eye), np.array([0.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]) if k < 2 else np.array([0.0, 1.0, 0.0]))
        cams.append(Camera(f"c{k}", [[800, 0, 511.5], [0, 800, 383.5], [0, 0, 1]], np.zeros(5), R, t, 1024, 768))
    return Rig(cams)


def _standing(z0: float = 0.0, flip: bool = False) -> np.ndarray:
    kp = np.zeros((len(KEYPOINTS), 3))
    h = {"pelvis": 0.95, "neck": 1.45, "nose": 1.62, "left_ankle": 0.08, "right_ankle": 0.08, "left_wrist": 0.9, "right_wrist": 0.9}
    for i, k in enumerate(KEYPOINTS):
        kp[i, 2] = h.get(k, 1.1)
        kp[i, 1] = 0.15 if k.startswith("left") else (-0.15 if k.startswith("right") else 0.0)
    if flip:  # upside down (handstand), around z = 0.9
        kp[:, 2] = 1.8 - kp[:, 2]
    kp[:, 2] += z0
    return kp


def test_crops_from_skeleton_upright_inverted_and_behind() -> None:
    rig = _rig()
    kp = _standing()
    centre, side, rot, ok = crops_from_skeleton(rig, kp)
    assert ok.all()
    uv, _ = rig.project(kp)
    # side-view cameras: upright, square covers the projected height * 1.25
    for c in (0, 1):
        assert abs(rot[c]) < 1e-6
        extent = uv[c, :, 1].max() - uv[c, :, 1].min()
        assert side[c] == pytest.approx(1.25 * extent, rel=1e-6)
        lo, hi = uv[c].min(axis=0), uv[c].max(axis=0)
        np.testing.assert_allclose(centre[c], (lo + hi) / 2, atol=1e-6)
    np.testing.assert_allclose(rot, trunk_tilt(rig, kp), atol=1e-9)  # same convention as the lead's
    _, _, rot_inv, _ = crops_from_skeleton(rig, _standing(flip=True))
    assert np.abs(np.abs(rot_inv[:2]) - np.pi).max() < 1e-6
    # explicit rotation overrides; a body behind a camera gives usable=False
    _, _, rot0, _ = crops_from_skeleton(rig, kp, rotation=np.zeros(3))
    assert not rot0.any()
    _, _, rot_nan, _ = crops_from_skeleton(rig, kp, rotation=np.array([np.nan, 0.5, 0.0]))
    np.testing.assert_allclose(rot_nan, [0.0, 0.5, 0.0])  # unknown tilt -> upright crop
    _, _, _, ok_behind = crops_from_skeleton(rig, _standing(z0=7.0))
    assert not ok_behind[2]  # above the top camera: behind it
    with pytest.raises(ModelError):
        crops_from_skeleton(rig, kp[:10])


def test_crop_side_does_not_shrink_with_foreshortening() -> None:
    """A body seen end-on (here a standing one from the ceiling camera; a person lying along a
    camera's line of sight) gets a crop scaled by its pose-independent length, not by its tiny
    2D extent (BlazePose lost the hips on getup_faceup with extent-fitted crops)."""
    rig = _rig()
    kp = _standing()
    _, side, _, ok = crops_from_skeleton(rig, kp)
    uv, _ = rig.project(kp)
    extent = np.ptp(uv[2], axis=0).max()
    assert body_length(kp) == pytest.approx(1.02 + 0.5 + 0.17)
    least = BODY_FRACTION * 1.25 * body_length(kp) * 800 / (6.0 - 0.95)  # focal 800, pelvis 5.05 m below
    assert ok[2] and side[2] == pytest.approx(least) and side[2] > 2 * 1.25 * extent
    # the side views see the standing body at full length: the extent rules there (see above)
    assert (side[:2] > least * 4.05 / 5.05).all()


def test_a_body_lying_keeps_the_scale_of_a_standing_one() -> None:
    """A trunk leaning from the world's up gets the larger least side (TURNED_BODY_FRACTION at
    90 degrees and more: lying, upside down), and so does a body whose height is short of a
    standing one's (sitting); a body bending over up to 45 degrees keeps the upright one."""
    rig = _rig()
    standing = _standing()
    lying = standing.copy()  # the same body turned about the x axis onto its back, at 0.3 m
    lying[:, 1], lying[:, 2] = standing[:, 2] - 0.95, 0.3 - standing[:, 1]
    bent = standing.copy()  # the trunk 30 degrees forward about the pelvis
    top = bent[:, 2] > 0.95
    a = np.radians(30.0)
    bent[top, 0] = (bent[top, 2] - 0.95) * np.sin(a)
    bent[top, 2] = 0.95 + (bent[top, 2] - 0.95) * np.cos(a)

    def least(kp: np.ndarray, fraction: float) -> np.ndarray:
        depth = rig.to_camera_frames(kp[INDEX["pelvis"]][None])[:, 0, 2]
        return fraction * 1.25 * body_length(kp) * 800 / depth

    _, side, _, _ = crops_from_skeleton(rig, lying)
    assert (side >= least(lying, TURNED_BODY_FRACTION) - 1e-9).all()
    assert np.isclose(side, least(lying, TURNED_BODY_FRACTION)).any()  # the floor rules somewhere
    _, side_bent, _, _ = crops_from_skeleton(rig, bent)
    _, side_old, _, _ = crops_from_skeleton(rig, bent, turned_fraction=BODY_FRACTION)
    np.testing.assert_allclose(side_bent, side_old)
    _, side_people, _, _ = crops_from_skeleton(rig, lying, turned_fraction=BODY_FRACTION)
    assert (side_people <= side + 1e-9).all() and (side_people < side).any()
    # sitting on the floor, trunk upright, legs out in front: not standing either
    sitting = standing - [0.0, 0.0, 0.85]
    legs = np.array([k.split("_")[-1] in ("knee", "ankle", "heel", "toe") for k in KEYPOINTS])
    sitting[legs, 2] = 0.1
    sitting[legs, 0] = np.where([k.endswith("knee") for k in np.array(KEYPOINTS)[legs]], 0.45, 0.95)
    assert stance_height(sitting) < COMPACT_HEIGHT[0] < COMPACT_HEIGHT[1] < stance_height(standing)
    _, side_sitting, _, _ = crops_from_skeleton(rig, sitting)
    assert (side_sitting >= least(sitting, TURNED_BODY_FRACTION) - 1e-9).all()
    assert np.isclose(side_sitting, least(sitting, TURNED_BODY_FRACTION)).any()


def test_rotated_crops_variants() -> None:
    cam = np.arange(3)
    centre, side = np.zeros((3, 2)) + 100, np.full(3, 300.0)
    tilt = np.array([0.05, np.pi, -1.0])
    lower = np.isin(np.array(KEYPOINTS), LOWER_BODY)
    c = rotated_crops(cam, centre, side, tilt, "lower_body")
    # camera 0 is nearly upright: one view; cameras 1 and 2 get an upright + a rotated view
    assert c.camera.tolist() == [0, 1, 2, 1, 2]
    np.testing.assert_allclose(c.rotation, [0, 0, 0, np.pi, -1.0])
    assert c.valid[0].all()
    assert (c.valid[1] == ~lower).all() and (c.valid[3] == lower).all()
    assert not (c.valid[1] & c.valid[3]).any() and (c.valid[1] | c.valid[3]).all()
    a = rotated_crops(cam, centre, side, tilt, "all")
    np.testing.assert_allclose(a.rotation, tilt)
    assert len(rotated_crops(cam, centre, side, tilt, "none")) == 3
    with pytest.raises(ModelError):
        rotated_crops(cam, centre, side, tilt, "sideways")
    with pytest.raises(ModelError):
        Crops([0], [[np.nan, 0.0]], [100.0], [0.0])


def test_camera_keypoints_merges_views_per_camera() -> None:
    """Two views of camera 1 (upper body upright, lower body rotated) give one row per camera."""
    from vmocap_core.pcm.peaks import camera_keypoints

    J = len(KEYPOINTS)
    lower = np.isin(np.array(KEYPOINTS), LOWER_BODY)
    maps = np.zeros((3, J, 64, 64), np.float32)
    maps[0, :, 10, 10] = 0.9  # camera 0: everything at cell (10, 10)
    maps[1, :, 20, 20] = 0.8  # camera 1 upright view
    maps[2, :, 30, 30] = 0.7  # camera 1 rotated view
    A = np.repeat(stride_affine(4.0)[None], 3, axis=0)  # cell x at pixel 4x + 1.5
    valid = np.stack([np.ones(J, bool), ~lower, lower])
    pv = PcmViews(maps, A, [0, 1, 1], np.arange(J), valid, [0.99, 0.99, 0.99])
    uv, w = camera_keypoints(pv, 3)
    assert uv.shape == (3, J, 2) and w.shape == (3, J)
    np.testing.assert_allclose(uv[0], 41.5)
    np.testing.assert_allclose(uv[1, ~lower], 81.5)
    np.testing.assert_allclose(uv[1, lower], 121.5)
    np.testing.assert_allclose(w[1], np.where(lower, 0.7, 0.8), rtol=1e-6)
    assert not w[2].any() and np.isnan(uv[2]).all()  # camera 2 has no view
    pv.presence[:] = [0.99, 0.01, 0.99]  # a view without a person says nothing
    _, w = camera_keypoints(pv, 3)
    assert not w[1, ~lower].any() and w[1, lower].all()
