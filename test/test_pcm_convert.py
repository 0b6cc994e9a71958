"""Our TFLite -> ONNX translator against the TFLite reference interpreter, and the model cache."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import pytest

from vmocap_core.errors import ModelError
from vmocap_core.pcm import fetch, tflite2onnx
from vmocap_core.pcm.blazepose import BlazePoseLandmark
from vmocap_core.pcm.crops import Crops
from vmocap_core.pcm.detector import PoseDetector

REPO = Path(__file__).resolve().parents[1]
MESSI = Path("/usr/share/doc/opencv-doc/examples/data/messi5.jpg")
PANOPTIC = REPO.parent / "shared" / "data" / "panoptic_demo" / "00_03" / "00_03_00004500.jpg"


def require_models() -> None:
    """Use the cache; build it if possible (needs the network); otherwise skip."""
    try:
        for name in fetch.SOURCES:
            fetch.model_path(name)
            fetch.model_path(name, "tflite")
    except ModelError:
        try:
            fetch.fetch(quiet=True)
        except ModelError as exc:
            pytest.skip(f"PCM models unavailable (no network?): {exc}")


def real_image() -> np.ndarray:
    for p in (MESSI, PANOPTIC):
        if p.exists():
            return cv2.imread(str(p))
    pytest.skip("no real image (apt-get install opencv-doc, or ../shared/data/panoptic_demo)")


def _reference(tflite_path: Path, x: np.ndarray) -> dict[str, np.ndarray]:
    interp = pytest.importorskip("ai_edge_litert.interpreter").Interpreter(model_path=str(tflite_path))
    interp.allocate_tensors()
    interp.set_tensor(interp.get_input_details()[0]["index"], x)
    interp.invoke()
    return {d["name"]: interp.get_tensor(d["index"]) for d in interp.get_output_details()}


def _onnx_all_outputs(path: Path, x: np.ndarray) -> dict[str, np.ndarray]:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(names, {sess.get_inputs()[0].name: x})))


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_landmark_onnx_matches_tflite_on_a_real_image(variant: str) -> None:
    require_models()
    if variant == "lite":
        try:
            fetch.model_path("pose_landmark_lite")
        except ModelError as exc:
            pytest.skip(f"optional lite model not fetched: {exc}")
    img = real_image()
    model = BlazePoseLandmark(variant=variant)
    det = PoseDetector().detect([img])[0]
    assert det, "the detector must find the person in the real image"
    centre, side, rot = det[0].crop()
    x = model.preprocess([img], model.views_from_crops(Crops([0], centre, side, rot)))
    ref = _reference(fetch.model_path(f"pose_landmark_{variant}", "tflite"), x)
    got = _onnx_all_outputs(fetch.model_path(f"pose_landmark_{variant}"), x)
    heat_ref = 1 / (1 + np.exp(-ref["Identity_3"]))
    heat_got = 1 / (1 + np.exp(-got["Identity_3"]))
    diff = np.abs(heat_got - heat_ref).max()
    print(f"{variant}: landmark heatmap max abs diff {diff:.2e}, logits {np.abs(got['Identity_3'] - ref['Identity_3']).max():.2e}")
    assert diff < 1e-3
    assert np.abs(got["Identity_1"] - ref["Identity_1"]).max() < 1e-3  # presence
    assert ref["Identity_1"].item() > 0.9  # a person really is in the crop
    np.testing.assert_allclose(got["Identity_4"], ref["Identity_4"], atol=1e-3)  # world landmarks


def test_detector_onnx_matches_tflite_on_a_real_image() -> None:
    require_models()
    img = real_image()
    det = PoseDetector()
    x, _ = det.preprocess([img])
    ref = _reference(fetch.model_path("pose_detection", "tflite"), x)
    got = _onnx_all_outputs(fetch.model_path("pose_detection"), x)
    for name in ("Identity", "Identity_1"):  # raw box offsets (input px) and score logits
        rel = (np.abs(got[name] - ref[name]) / (1.0 + np.abs(ref[name]))).max()
        print(f"detector {name} max relative diff {rel:.1e}")
        assert rel < 1e-3, name  # fp32 summation order (XNNPACK vs onnxruntime) differs
    scores = 1 / (1 + np.exp(-np.clip(ref["Identity_1"], -80, 80)))
    assert scores.max() > 0.8


def test_batched_conversion_equals_single(tmp_path: Path) -> None:
    """The dynamic batch axis computes each item exactly as batch 1 would."""
    require_models()
    model = BlazePoseLandmark()
    rng = np.random.default_rng(1)
    x = rng.integers(0, 256, (3, 256, 256, 3), dtype=np.uint8)
    batch = model.run(x)
    for k in range(3):
        one = model.run(x[k : k + 1])
        for a, b in zip(batch, one):
            np.testing.assert_allclose(a[k : k + 1], b, atol=2e-4)


def test_corrupt_cache_is_detected_and_rebuilt_offline(tmp_path: Path) -> None:
    require_models()
    d = tmp_path / "models"
    shutil.copytree(fetch.model_dir(), d, ignore=shutil.ignore_patterns("pose2sim"))
    assert fetch.verify(d) == {}
    onnx_path = d / "pose_landmark_full.onnx"
    data = bytearray(onnx_path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    onnx_path.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="vmocap models fetch"):
        fetch.model_path("pose_landmark_full", directory=d)
    assert "pose_landmark_full.onnx" in fetch.verify(d)
    (d / "pose_detection.onnx").unlink()
    with pytest.raises(ModelError, match="missing.*vmocap models fetch"):
        fetch.model_path("pose_detection", directory=d)
    # the checked .tflite files are still there: the rebuild needs no network
    fetch.fetch(d, quiet=True)
    assert fetch.verify(d) == {}
    assert fetch.model_path("pose_landmark_full", directory=d).exists()


def test_bad_tflite_input_is_a_model_error() -> None:
    with pytest.raises(ModelError):
        tflite2onnx.convert(b"\x00" * 64, "garbage")
    require_models()
    data = fetch.model_path("pose_detection", "tflite").read_bytes()
    with pytest.raises(ModelError):
        tflite2onnx.convert(data[: len(data) // 3], "truncated")


def test_fetch_reports_a_bad_wheel_clearly(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "mediapipe-0.10.14-cp311-none-any.whl"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ModelError, match="not a readable wheel"):
        fetch.fetch(tmp_path / "cache", wheel=bad, quiet=True)
    from vmocap_core.cli import main

    assert main(["models", "fetch", "--dir", str(tmp_path / "cache"), "--wheel", str(bad)]) == 1
    assert "not a readable wheel" in capsys.readouterr().err
    with pytest.raises(ModelError, match="vmocap models fetch"):
        fetch.model_path("pose_landmark_full", directory=tmp_path / "cache")


def test_tf_graph_reader_rejects_garbage() -> None:
    from vmocap_core.pcm.tfgraph import read_graph

    for junk in (b"", b"\xff\xff\xff", b"\x0a\x05ab"):
        with pytest.raises(ModelError):
            read_graph(junk)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_detector_turned_pass_finds_a_turned_person_where_they_are(k: int) -> None:
    """detect_turned looks at the image turned by quarter turns (a body lying or upside down):
    its detections are in the given image's pixels, the hip where the upright pass on the
    unturned image puts it, turned with the image."""
    require_models()
    img = real_image()
    det = PoseDetector()
    up = det.detect([img])[0]
    assert up
    H, W = img.shape[:2]
    x, y = up[0].keypoints[0]
    for _ in range(k):  # np.rot90: (x, y) -> (y, W - 1 - x) per quarter turn
        x, y, H, W = y, W - 1 - x, W, H
    turned_img = np.ascontiguousarray(np.rot90(img, k))
    found = det.detect_turned([turned_img])[0]
    assert found and found[0].score > 0.5
    assert np.linalg.norm(found[0].keypoints[0] - [x, y]) < 0.03 * max(H, W), (found[0].keypoints[0], (x, y))
    box = found[0].box  # the detector's box (the face), corners ordered again after the turn
    assert box[0] < box[2] and box[1] < box[3]
