"""The CNN budget rewrites (pcm/budget.py) on the real BlazePose model and the bundled crops.

Figures behind the bounds (docs/cnn_budget.md): the slimmed heatmap convolution computes the
same maps (float rounding only); at 224 x 224 the peaks of the two bundled crops, scaled to the
256 grid, move 0.35 cells median / 0.73 p95 from the 256 ones, at 160 x 160 1.5 / 14 (keypoints
lost), so the 224 bounds below catch a broken rewrite (wrong upsampling matrices: tens of cells)
without pinning the network's own scale response.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vmocap_core.errors import ModelError
from vmocap_core.pcm import budget, fetch, selfcheck
from vmocap_core.pcm.blazepose import BlazePoseLandmark
from vmocap_core.pcm.selfcheck import peak_centroids


@pytest.fixture(scope="module")
def crops() -> np.ndarray:
    try:
        fetch.fetch(quiet=True)
    except ModelError as exc:
        pytest.skip(f"PCM models unavailable (no network?): {exc}")
    return selfcheck.reference_crops()


def _run(crops: np.ndarray, precision: str, **kw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    check = selfcheck.verdict("full")
    name = "pose_landmark_full" + (check.int8_build if precision == "int8" else "")
    if precision == "int8":  # the build and kernels the self-check found correct on this CPU
        kw.setdefault("session_config", check.session_config)
    m = BlazePoseLandmark(fetch.model_path(name), threads=1, precision=precision, **kw)
    side = m.input_size[0]
    x = crops if side == crops.shape[1] else np.stack([cv2.resize(c, (side, side), interpolation=cv2.INTER_AREA) for c in crops])
    maps, presence = m.decode(m.run(x))
    centres, _ = peak_centroids(maps)
    return maps, presence, centres * (budget.NATIVE_SIZE / side)  # in cells of the 256 grid


def test_slim_heatmap_convolution_gives_the_same_maps(crops) -> None:
    full, p_full, _ = _run(crops, "float", slim=False)
    slim, p_slim, _ = _run(crops, "float", slim=True)
    assert np.abs(slim - full).max() < 1e-5
    assert np.abs(p_slim - p_full).max() < 1e-6


@pytest.mark.parametrize("precision", ["float", "int8"])
def test_smaller_input_keeps_peaks_and_presence(crops, precision: str) -> None:
    """224 x 224 input: maps of 56 x 56 cells, peaks near the 256 ones, presence kept; the int8
    graph's interpolation matrices (int8_prepare.prepare) are resized as the float Resize sizes."""
    if precision == "int8" and not selfcheck.verdict("full").int8_correct:
        pytest.skip("int8 fails the self-check on this CPU")
    _, p256, c256 = _run(crops, precision, input_size=256)
    maps, p224, c224 = _run(crops, precision, input_size=224)
    assert maps.shape == (len(crops), 25, 56, 56)
    d = np.linalg.norm(c224 - c256, axis=-1)[:, BlazePoseLandmark.channel_valid]
    assert np.median(d) < 0.7 and np.percentile(d, 95) < 2.0, (np.median(d), np.percentile(d, 95))
    assert (p224 > 0.5).all() and (p256 > 0.5).all()


def test_input_size_choice_and_bad_values(monkeypatch) -> None:
    monkeypatch.delenv(budget.INPUT_ENV, raising=False)
    assert budget.input_size() == budget.DEFAULT_INPUT_SIZE
    monkeypatch.setenv(budget.INPUT_ENV, "224")
    assert budget.input_size() == 224 and budget.input_size(192) == 192
    for bad in ("300", "abc", "200"):
        monkeypatch.setenv(budget.INPUT_ENV, bad)
        with pytest.raises(ModelError, match="input size"):
            budget.input_size()


def test_bench_cnn_command_prints_variants_and_ratios(crops, capsys) -> None:
    import json

    from vmocap_core import cli

    assert cli.main(["bench", "cnn", "--repeat", "1", "--sizes", "224", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    for rows in r["precisions"].values():
        assert set(rows) == {"published", "slim_224"}
        assert rows["published"]["frame_set"]["ratio_to_published"] == 1.0
        assert rows["slim_224"]["per_crop"]["median_ms"] > 0 and rows["slim_224"]["frame_set"]["cpu_ms"] > 0
