"""The int8 landmark model (pcm/quantize.py) against the float one on real images, and its build.

Tolerances: the int8 build (everything after the 128 x 128 stem to the 8 x 8 encoder, with
equalization and GPTQ rounding) moves the heatmap peaks (5 x 5-weighted centroids) 0.049 cells
median and 0.35 cells at the 95th percentile from the float ones on 88 real crops (Pose2Sim,
Panoptic), 0.051 / 0.49 on this test's 8 crops, the presence output by at most 0.2; the demo's
reprojection error did not grow. The bounds (selfcheck.py, shared with the self-check that picks
the precision where the code runs) are ~1.5-2.5x those figures: loose enough for another CPU's
kernels, tight enough to catch a broken build (the whole network with rounding to
nearest and no equalization gives 0.33 / 1.7 cells; the per-tensor-weight rewrite that
runner.DISABLED_OPTIMIZERS switches off gives ~11 cells).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx import numpy_helper

from vmocap_core.errors import ModelError
from vmocap_core.pcm import fetch, int8_equalize, int8_prepare, quantize, selfcheck
from vmocap_core.pcm.blazepose import BlazePoseLandmark, resolve_precision
from vmocap_core.pcm.crops import Crops
from vmocap_core.pcm.detector import PoseDetector
from vmocap_core.pcm.selfcheck import MEDIAN_CELLS, P95_CELLS, PRESENCE, peak_centroids

PANOPTIC = Path(__file__).resolve().parents[2] / "shared" / "data" / "panoptic_demo"
MESSI = Path("/usr/share/doc/opencv-doc/examples/data/messi5.jpg")


@pytest.fixture(scope="module")
def models() -> tuple[PoseDetector, BlazePoseLandmark, BlazePoseLandmark]:
    try:
        fetch.fetch(quiet=True)
        return PoseDetector(threads=1), BlazePoseLandmark(precision="float"), BlazePoseLandmark(precision="int8")
    except ModelError as exc:
        pytest.skip(f"PCM models unavailable (no network?): {exc}")


@pytest.fixture(scope="module")
def images() -> list[np.ndarray]:
    files = sorted(PANOPTIC.glob("*/*_00004500.jpg"))
    imgs = [cv2.imread(str(f)) for f in files] + ([cv2.imread(str(MESSI))] if MESSI.exists() else [])
    if not imgs:
        pytest.skip("no real images (../shared/data/panoptic_demo, opencv-doc's messi5.jpg)")
    return imgs


def test_default_precision_and_override(monkeypatch) -> None:
    monkeypatch.delenv("VMOCAP_PCM_PRECISION", raising=False)
    assert resolve_precision("full") == "auto" and resolve_precision("lite") == "float"
    monkeypatch.setenv("VMOCAP_PCM_PRECISION", "float")
    assert resolve_precision("full") == "float"
    monkeypatch.setenv("VMOCAP_PCM_PRECISION", "int8")
    assert resolve_precision("lite") == "float"  # no int8 lite: the environment does not break it
    with pytest.raises(ModelError):
        resolve_precision("lite", "int8")
    with pytest.raises(ModelError):
        resolve_precision("full", "int4")


@pytest.mark.parametrize("build", ["_int8", "_int8w7"])
def test_int8_heatmaps_match_float_on_real_images(models, images, build: str) -> None:
    """Both int8 builds on kernels that compute them exactly on every x86 CPU: the 8-bit one on
    the native kernels where the self-check passed them, else on uint8 x uint8; the 7-bit one on
    the native kernels (no saturation with 7-bit weights)."""
    det, flt, _ = models
    check = selfcheck.verdict("full")
    config = {} if build == "_int8w7" or check.int8_kernels == "u8s8" else selfcheck.INT8_KERNELS["u8u8"][1]
    q = BlazePoseLandmark(fetch.model_path(f"pose_landmark_full{build}"), precision="int8", session_config=config)
    assert flt.path.name == "pose_landmark_full.onnx"
    found = det.detect(images)
    cams, rects = [], []
    for c, dets in enumerate(found):
        for d in dets[:3]:  # up to 3 people per Panoptic view
            cams.append(c)
            rects.append(d.crop())
    # Panoptic's 5 views hold 3 people each; without the lab's data only messi5.jpg's one player
    assert len(cams) >= min(5, len(images)), "people found in the real images"
    crops = Crops(cams, [r[0] for r in rects], [r[1] for r in rects], [r[2] for r in rects])
    a, b = flt.infer(images, crops), q.infer(images, crops)
    ca, va = peak_centroids(a.maps)
    cb, _ = peak_centroids(b.maps)
    confident = (va > 0.5) & flt.channel_valid[None]
    shift = np.linalg.norm(cb - ca, axis=-1)[confident]
    side = np.asarray(crops.side)[:, None].repeat(a.maps.shape[1], 1)[confident]
    px = shift * side / a.maps.shape[-1]  # image pixels
    dp = np.abs(a.presence - b.presence)
    print(f"int8 vs float on {len(cams)} real crops, {shift.size} confident peaks: centroid shift median "
          f"{np.median(shift):.3f} cells (p95 {np.percentile(shift, 95):.3f}, max {shift.max():.2f}); image px median "
          f"{np.median(px):.2f}, p95 {np.percentile(px, 95):.2f}; max |heatmap diff| {np.abs(a.maps - b.maps).max():.3f}; "
          f"presence diff max {dp.max():.3f}")
    assert np.median(shift) <= MEDIAN_CELLS
    assert np.percentile(shift, 95) <= P95_CELLS
    assert dp.max() <= PRESENCE
    assert np.array_equal(a.valid, b.valid), "the same views and keypoints are usable"


@pytest.mark.parametrize("name", sorted(fetch.INT8))
def test_int8_build_is_deterministic(models, tmp_path: Path, name: str) -> None:
    _, flt, _ = models
    source, bits = fetch.INT8[name]
    quantize.build(flt.path.with_name(f"{source}.onnx"), tmp_path / "again.onnx", weight_bits=bits)
    digest = lambda p: hashlib.sha256(Path(p).read_bytes()).hexdigest()  # noqa: E731
    assert digest(tmp_path / "again.onnx") == digest(fetch.model_path(name))


def test_seven_bit_weights_stay_on_their_grid(models) -> None:
    """The 7-bit build's quantized weights lie within +-64, so a uint8 x int8 pair sum stays in 16 bits."""
    import onnx

    m = onnx.load(str(fetch.model_path("pose_landmark_full_int8w7")))
    w = [numpy_helper.to_array(t) for t in m.graph.initializer if t.data_type == onnx.TensorProto.INT8]
    assert len(w) > 40 and max(int(np.abs(a.astype(np.int16)).max()) for a in w) <= 64
    assert 2 * 255 * 64 < 2**15 - 1


def test_build_refuses_a_calibration_for_another_model(models, tmp_path: Path) -> None:
    _, flt, _ = models
    other = tmp_path / "pose_landmark_full.onnx"
    other.write_bytes(flt.path.read_bytes() + b"\0")
    with pytest.raises(ModelError, match="recalibrate"):
        quantize.build(other, tmp_path / "x.onnx", quantize.calibration_path("pose_landmark_full"))


def test_prepared_and_equalized_graph_computes_the_float_function(models, images) -> None:
    """prepare() (Resize as MatMuls, Pads folded) and equalize() (the committed scales) change
    how the float network is computed, not what: heatmaps and presence agree to float rounding."""
    import json

    import onnx
    import onnxruntime as ort

    det, flt, _ = models
    d = det.detect(images[:1])[0][0]
    crop = flt.sample(images[:1], flt.views_from_crops(Crops([0], [d.crop()[0]], [d.crop()[1]], [d.crop()[2]])))
    x = flt.normalize(crop)
    original = onnx.load(str(flt.path))
    model = int8_prepare.prepare(original)
    assert not [n for n in model.graph.node if n.op_type == "Resize"]
    int8_equalize.equalize(model, json.loads(quantize.calibration_path("pose_landmark_full").read_text())["equalization"])
    outs = ["Identity_1", "Identity_3"]
    run = lambda m: ort.InferenceSession(m.SerializeToString(), providers=["CPUExecutionProvider"]).run(outs, {"input_1": x})  # noqa: E731
    (p0, h0), (p1, h1) = run(original), run(model)
    assert np.abs(h1 - h0).max() <= 1e-4 * np.abs(h0).max()
    assert np.abs(p1 - p0).max() <= 1e-5
