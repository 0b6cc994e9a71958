"""The benchmark commands run and print the documented JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def vmocap(*args: str) -> str:
    out = subprocess.run([sys.executable, "-m", "vmocap_core.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_bench_accuracy_json(tmp_path):
    clip = ROOT / "vmocap_core" / "data" / "motions" / "kick.npz"
    d = json.loads(vmocap("bench", "accuracy", "--motion", str(clip), "--json", "--plots", str(tmp_path)))
    r = d["motions"]["kick"]
    assert r["inverted"] is False
    for who in ("method", "baseline"):
        for key in ("mpjpe_mm", "pck50", "pck100", "pck150", "groups"):
            assert key in r[who]
    assert set(d["summary"]) == {"regular"}
    assert r["method"]["mpjpe_mm"] < r["baseline"]["mpjpe_mm"]
    assert (tmp_path / "kick.png").stat().st_size > 1000


def test_bench_speed_json():
    d = json.loads(vmocap("bench", "speed", "--frames", "15", "--json"))
    assert d["cameras"] == 4 and d["keypoints"] == 25 and d["lattice_points"] == 1331
    assert set(d["stages_ms"]) == {"lattice", "ik", "filter", "ik2"}
    assert 0 < d["backend_ms"]["median"] <= d["backend_ms"]["p95"]


def test_unknown_motion_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not a zip")
    out = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "bench", "accuracy", "--motion", str(bad)],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "not a motion clip" in (out.stderr + out.stdout)
