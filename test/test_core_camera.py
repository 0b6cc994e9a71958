"""Cameras, rigs and rig files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vmocap_core.cameras.projection import Camera, Rig, look_at
from vmocap_core.cameras.rig_file import load_panoptic_cameras, load_rig, load_shelf_calibration, save_rig
from vmocap_core.errors import RigFileError


def make_rig(dist_list):
    cams = []
    for i, dist in enumerate(dist_list):
        ang = i * np.pi / 2
        R, t = look_at(np.array([4 * np.cos(ang), 4 * np.sin(ang), 2.0]), np.array([0, 0, 1.0]))
        K = np.array([[900.0 + 10 * i, 0.0, 511.5], [0, 905.0, 383.5], [0, 0, 1]])
        cams.append(Camera(f"c{i}", K, dist, R, t, 1024, 768))
    return Rig(cams)


@pytest.mark.parametrize(
    "dist",
    [[0, 0, 0, 0, 0], [-0.2, 0.05, 0.001, -0.002, 0.01], [0.1, -0.05, 0.001, 0.002, 0.01, 0.02, -0.01, 0.005]],
)
def test_projection_equals_opencv(dist):
    rig = make_rig([dist] * 3)
    pts = np.random.default_rng(0).uniform([-1, -1, 0], [1, 1, 2], (200, 3))
    uv, front = rig.project(pts)
    assert uv.shape == (3, 200, 2) and front.all()
    for c, cam in enumerate(rig):
        rvec, _ = cv2.Rodrigues(cam.R)
        ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
        assert np.abs(uv[c] - ref[:, 0]).max() < 1e-6


def test_points_behind_camera_are_flagged():
    rig = make_rig([[0] * 5])
    cam = rig[0]
    behind = cam.center + 2.0 * (cam.center - np.array([0, 0, 1.0]))
    _, front = rig.project(np.stack([behind, np.array([0, 0, 1.0])]))
    assert front.tolist() == [[False, True]]


def test_rig_file_roundtrip(tmp_path):
    rig = make_rig([[-0.1, 0.01, 0, 0, 0], [0.1, -0.05, 0.001, 0.002, 0.01, 0.02, -0.01, 0.005]])
    path = tmp_path / "rig.yaml"
    save_rig(rig, path)
    back = load_rig(path)
    assert back.names == rig.names
    pts = np.random.default_rng(1).uniform(-1, 1, (10, 3)) + [0, 0, 1]
    assert np.allclose(back.project(pts)[0], rig.project(pts)[0], atol=1e-9)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["cameras"][0].pop("camera_matrix"), "camera_matrix"),
        (lambda d: d["cameras"][0]["camera_matrix"].update(data=[1.0] * 8), "camera_matrix"),
        (lambda d: d["cameras"][1]["extrinsics"].update(translation=[0, float("nan"), 1]), "cameras[1].extrinsics.translation"),
        (lambda d: d["cameras"][0]["extrinsics"]["rotation"].update(data=[2.0] * 9), "rotation"),
        (lambda d: d["cameras"][0].update(image_width=-5), "image_width"),
        (lambda d: d["cameras"][0]["distortion_coefficients"].update(data=[0.1, 0.2, 0.3]), "distortion_coefficients"),
    ],
)
def test_malformed_rig_files_name_file_and_field(tmp_path, edit, field):
    import yaml

    path = tmp_path / "rig.yaml"
    save_rig(make_rig([[0] * 5, [0] * 5]), path)
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(RigFileError) as err:
        load_rig(path)
    assert str(path) in str(err.value) and field in str(err.value)


def test_unreadable_rig_file(tmp_path):
    with pytest.raises(RigFileError, match="cannot read"):
        load_rig(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cameras: [unclosed")
    with pytest.raises(RigFileError, match="YAML"):
        load_rig(bad)


def test_shelf_and_panoptic_import(shared_data):
    shelf = load_shelf_calibration(shared_data / "shelf" / "calibration.json")
    assert len(shelf) == 5 and shelf[0].width == 1032
    # Cameras of the Shelf rig look at the same shelf area: the world origin is in front.
    _, front = shelf.project(np.zeros((1, 3)))
    assert front.all()
    pan = load_panoptic_cameras(shared_data / "panoptic_demo" / "camera_parameters.json", ["00_03", "00_06"])
    assert pan[0].width == 1920 and pan[0].has_distortion
    # centimetres -> metres: Panoptic cameras sit a few metres from the dome centre.
    assert 1.0 < np.linalg.norm(pan[0].center) < 6.0


@pytest.mark.parametrize("r", [2, 4])
def test_binned_camera_sees_where_a_reduced_jpeg_puts_a_point(r):
    """A white 8x8-aligned square in a JPEG decoded reduced r times lands where the binned camera
    projects the point that the full camera projects onto the square's centre."""
    from vmocap_core.cameras.bag import decode_compressed

    cam = make_rig([[-0.2, 0.05, 0.001, -0.002, 0.01]])[0]
    pts = np.random.default_rng(1).uniform([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5], (50, 3))
    uv, _ = cam.project(pts)
    uv_b, _ = cam.binned(r).project(pts)
    assert np.abs(uv_b - (uv - (r - 1) / 2) / r).max() < 1e-9  # binned pixel i centres on full r*i + (r-1)/2
    assert (cam.binned(r).width, cam.binned(r).height) == (-(-1024 // r), -(-768 // r))
    img = np.zeros((768, 1024, 3), np.uint8)
    img[320:336, 480:496] = 255  # centre at full pixel (487.5, 327.5)
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    small = decode_compressed({"data": jpg.tobytes(), "format": "jpeg"}, binning=r)[..., 0].astype(float)
    assert small.shape == (768 // r, 1024 // r)
    ys, xs = np.mgrid[: small.shape[0], : small.shape[1]]
    centre = np.array([(xs * small).sum(), (ys * small).sum()]) / small.sum()
    assert np.abs(centre - (np.array([487.5, 327.5]) - (r - 1) / 2) / r).max() < 0.05


@pytest.mark.parametrize("r", [2, 4])
def test_bin_image_is_the_block_mean_the_binned_camera_describes(r):
    """A raw image reduced r times (what a camera node publishes with binning r) averages r x r
    blocks: a bright square's centre lands where Camera.binned says, as PNG's reduced decoding
    does; sizes round up as libjpeg's."""
    from vmocap_core.cameras.bag import bin_image, decode_compressed

    img = np.zeros((768, 1024, 3), np.uint8)
    img[321:335, 481:497] = 255  # centre at full pixel (488.5, 327.5)
    small = bin_image(img, r)
    assert small.shape == (768 // r, 1024 // r, 3)
    ok, png = cv2.imencode(".png", img)
    assert np.array_equal(small, decode_compressed({"data": png.tobytes(), "format": "png"}, binning=r))
    g = small[..., 0].astype(float)
    ys, xs = np.mgrid[: g.shape[0], : g.shape[1]]
    centre = np.array([(xs * g).sum(), (ys * g).sum()]) / g.sum()
    assert np.abs(centre - (np.array([488.5, 327.5]) - (r - 1) / 2) / r).max() < 0.1
    assert bin_image(img[:767, :1023], r).shape[:2] == (-(-767 // r), -(-1023 // r))
    assert bin_image(img, 1) is img


def test_binning_must_be_a_reduction_libjpeg_offers():
    from vmocap_core.cameras.bag import bin_image, decode_compressed
    from vmocap_core.errors import SourceError

    with pytest.raises(SourceError, match="binning must be one of"):
        decode_compressed({"data": b"\xff\xd8", "format": "jpeg"}, binning=3)
    with pytest.raises(SourceError, match="binning must be one of"):
        bin_image(np.zeros((4, 4, 3), np.uint8), 3)
    with pytest.raises(ValueError, match="binning must be >= 1"):
        make_rig([[0] * 5])[0].binned(0)
