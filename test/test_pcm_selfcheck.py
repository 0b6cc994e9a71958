"""The int8 self-check (pcm/selfcheck.py): it passes where int8 is right, catches an int8 model
that is wrong, falls back to float loudly, and really runs the x86 kernels without VNNI.

The last point needs another CPU than CI's: `qemu-x86_64 -cpu Haswell-noTSX` (Debian's
qemu-user, installed by scripts/setup.sh) runs the check under an emulated AVX2 CPU without
AVX-512/VNNI, whose cpuid onnxruntime's kernel dispatch reads; there the native uint8 x int8
kernels saturate (the bug this check exists for) and the uint8 x uint8 ones must agree.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from vmocap_core.errors import ModelError
from vmocap_core.pcm import fetch, selfcheck
from vmocap_core.pcm.blazepose import BlazePoseLandmark

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache() -> Path:
    try:
        fetch.fetch(quiet=True)
    except ModelError as exc:
        pytest.skip(f"PCM models unavailable (no network?): {exc}")
    return fetch.model_dir()


def all_kernels_env(**extra: str) -> dict[str, str]:
    """The environment without a restriction of the kernels the check tries
    (scripts/slow_class.sh names the 7-bit ones only): these tests watch the check choose."""
    env = {k: v for k, v in os.environ.items() if k != selfcheck.KERNELS_ENV}
    return {**env, **extra}


@pytest.fixture
def fresh_verdicts(monkeypatch):
    monkeypatch.setattr(selfcheck, "_verdicts", {})
    monkeypatch.delenv("VMOCAP_PCM_PRECISION", raising=False)


def test_check_passes_here_and_the_default_model_follows_it(cache, fresh_verdicts) -> None:
    result = selfcheck.run_check(repeats=2)
    print(json.dumps(result.to_dict()))
    assert result.int8_correct, result.reason
    a = result.tried[result.int8_kernels]
    assert a.ok and a.peaks >= 30 and a.median_cells <= selfcheck.MEDIAN_CELLS
    assert set(result.ms_per_crop) == {"float", "int8"} and all(v > 0 for v in result.ms_per_crop.values())
    model = BlazePoseLandmark(threads=1)
    verdict = selfcheck.verdict()
    assert model.precision == verdict.precision and model.precision_reason == verdict.reason
    assert model.path.name == (f"pose_landmark_full{verdict.int8_build}.onnx" if verdict.precision == "int8"
                               else "pose_landmark_full.onnx")


def test_peak_centroids_find_a_known_blob() -> None:
    maps = np.zeros((1, 2, 64, 64))
    yy, xx = np.mgrid[:64, :64]
    maps[0, 0] = np.exp(-((xx - 20.3) ** 2 + (yy - 41.6) ** 2) / 2.0)
    maps[0, 1, 5, 7] = 1.0
    c, v = selfcheck.peak_centroids(maps)
    assert np.allclose(c[0, 0], [20.3, 41.6], atol=0.05) and np.allclose(c[0, 1], [7, 5])
    assert np.allclose(v[0], [maps[0, 0].max(), 1.0])


def _cache_copy(src: Path, dst: Path, int8: Callable[[str], onnx.ModelProto | bytes]) -> Path:
    """A model cache with the float model and every int8 build replaced by `int8(file name)`,
    their checksums in the manifest."""
    dst.mkdir()
    shutil.copy(src / "pose_landmark_full.onnx", dst)
    manifest = json.loads((src / fetch.MANIFEST).read_text())
    for name in fetch.INT8:
        data = int8(f"{name}.onnx")
        (dst / f"{name}.onnx").write_bytes(data if isinstance(data, bytes) else data.SerializeToString())
        manifest["files"][f"{name}.onnx"] = fetch.sha256(dst / f"{name}.onnx")
    (dst / fetch.MANIFEST).write_text(json.dumps(manifest))
    return dst


def _wrong_int8(src: Path, file: str) -> onnx.ModelProto:
    """An int8 build with its weights' signs flipped in half the quantized layers: a model that
    loads and runs but computes something else, as the saturating kernels did."""
    m = onnx.load(str(src / file))
    flipped = 0
    for t in m.graph.initializer:
        if t.name.endswith("_quantized") and t.data_type == onnx.TensorProto.INT8 and flipped % 2 == 0:
            w = numpy_helper.to_array(t)
            t.CopyFrom(numpy_helper.from_array((-w.astype(np.int16)).clip(-127, 127).astype(np.int8), t.name))
        flipped += 1
    return m


def test_a_wrong_int8_model_falls_back_to_float_with_one_warning(cache, fresh_verdicts, tmp_path, monkeypatch, caplog) -> None:
    monkeypatch.setenv("VMOCAP_MODELS", str(_cache_copy(cache, tmp_path / "models", lambda f: _wrong_int8(cache, f))))
    with caplog.at_level(logging.WARNING, logger="vmocap.pcm"):
        a, b = BlazePoseLandmark(threads=1), BlazePoseLandmark(threads=1)
    assert a.precision == b.precision == "float"
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, "one warning per process"
    text = warnings[0].getMessage()
    assert "not usable on this CPU" in text and platform.machine() in text
    assert "cells median" in text and "float model" in text
    with pytest.raises(ModelError, match="int8 was asked for"):
        BlazePoseLandmark(threads=1, precision="int8")


def test_a_corrupt_int8_file_falls_back_to_float(cache, fresh_verdicts, tmp_path, monkeypatch, caplog) -> None:
    d = _cache_copy(cache, tmp_path / "models", lambda f: b"not an onnx model")
    for name in fetch.INT8:
        (d / f"{name}.onnx").write_bytes(b"corrupted after the manifest was written")
    monkeypatch.setenv("VMOCAP_MODELS", str(d))
    with caplog.at_level(logging.WARNING, logger="vmocap.pcm"):
        m = BlazePoseLandmark(threads=1)
    assert m.precision == "float"
    assert any("corrupt" in r.getMessage() and "vmocap models fetch" in r.getMessage() for r in caplog.records)


def test_models_check_command_prints_cpu_precision_and_times(cache) -> None:
    out = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "models", "check", "--repeats", "1"],
                         capture_output=True, text=True, timeout=120, env=all_kernels_env())
    assert out.returncode == 0, out.stderr
    for word in ("CPU:", "int8 u8s8:", "time per crop", "precision:"):
        assert word in out.stdout, out.stdout


def _linked_cache(src: Path, dst: Path) -> Path:
    """A model cache of links to src's model files and manifest, without its kept verdicts: a
    check run on it keeps its verdict there."""
    dst.mkdir()
    for f in src.iterdir():
        if f.is_file() and not f.name.startswith("selfcheck_"):
            (dst / f.name).symlink_to(f)
    return dst


def test_non_vnni_x86_kernels_saturate_and_the_check_catches_it(cache, tmp_path) -> None:
    """Runs where qemu-x86_64 can emulate an AVX2-only x86 CPU (x86 hosts, qemu-user installed).
    On an AVX2-only host the emulated CPU has the host's flags and model name, so the
    emulation's verdict (crops 150x slower) would replace the host's own: it is kept in a cache of
    its own, and the host's verdicts stay as they were."""
    qemu = shutil.which("qemu-x86_64")
    if platform.machine() != "x86_64":
        pytest.skip("the emulated-Haswell check runs on x86_64 hosts")
    if qemu is None:
        if os.environ.get("CI"):
            pytest.fail("qemu-x86_64 missing: scripts/setup.sh installs qemu-user (needed for the non-VNNI check)")
        pytest.skip("qemu-x86_64 not installed (apt-get install qemu-user)")
    # the ROS wheels' start-up hook re-executes Python, which would leave the emulator: skip it
    models = _linked_cache(cache, tmp_path / "models")
    env = all_kernels_env(_ROS_WHEELS_BOOTSTRAP_COMPLETE="1", PYTHONPATH=str(REPO), VMOCAP_MODELS=str(models))
    kept = {f.name: f.read_bytes() for f in cache.glob("selfcheck_*.json")}
    cmd = [qemu, "-cpu", "Haswell-noTSX", sys.executable, "-m", "vmocap_core.cli", "models", "check", "--repeats", "1", "--json"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    assert {f.name: f.read_bytes() for f in cache.glob("selfcheck_*.json")} == kept, "the host's verdicts changed"
    assert list(models.glob("selfcheck_*.json")), "the emulated check kept no verdict in its own cache"
    result = json.loads(out.stdout)
    print(json.dumps({k: result[k] for k in ("cpu", "tried", "precision", "reason")}))
    assert "avx2" in result["cpu"]["flags"] and "avx512f" not in result["cpu"]["flags"], "emulated AVX2-only CPU"
    native = result["tried"]["u8s8"]
    assert not native["ok"] and native["median_cells"] > 1.0, "the native kernels saturate on this CPU class"
    # the 7-bit build runs on the same fast kernels without saturating (quantize.WEIGHT_GRIDS)
    assert result["tried"]["u8s8-w7"]["ok"] and result["int8_kernels"] == "u8s8-w7"
