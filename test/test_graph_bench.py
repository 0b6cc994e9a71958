"""`vmocap bench graph --json` runs every launch mode end to end (small images to stay fast) and
reports the documented fields with plausible values."""

import json
import subprocess
import sys

import pytest
from graph_helpers import REPO, domain_env


@pytest.mark.graph_replay
def test_bench_graph_json(tmp_path):
    env = {**domain_env(21), "TMPDIR": str(tmp_path)}  # no --workdir: its own temp dir must go at the end
    r = subprocess.run(
        [sys.executable, "-m", "vmocap_core.cli", "bench", "graph", "--json", "--seconds", "3", "--warmup", "1",
         "--size", "320x240", "--frames", "10"],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert set(out["modes"]) == {"default", "processes", "single_process"}
    assert "avx2" in out["cpu"] or "x86_64" not in out["cpu"]
    for mode, m in out["modes"].items():
        assert m["pcm"] == "bag"
        assert {"rate_hz", "dropped_pct", "latency_ms", "pcm"} <= set(m)
        # frame sets really flow through the whole graph (rates are low on a loaded 2-core box)
        assert m["rate_hz"] > 1.0 and m["input_rate_hz"] > 10.0, (mode, m)
        assert 0.0 <= m["dropped_pct"] < 100.0
        # at least one period (30 Hz default), less than the run: the output never stopped
        assert 1000.0 / 30.0 - 1.0 < m["longest_gap_ms"] < 3000.0, (mode, m)
        markers = m["stages_ms"]["markers"]
        assert 0.0 < markers["p50"] <= markers["p95"] < 5000.0, (mode, m)
        assert set(m["cpu_pct"]) == {"vmocap_pcm", "vmocap_markers", "vmocap_skeleton"}
        assert 0.0 <= m["tracking_pct"] <= 100.0  # a 10-frame loop jumps back: tracking is not the point here
        assert m["precision"] == "n/a"  # heatmaps from the bag: no CNN
    assert out["offline_ms_per_frame"] > 0
    assert not list(tmp_path.glob("vmocap_bench_graph_*")), "the benchmark left its ~180 MB work folder behind"


def test_bench_graph_people_json(tmp_path):
    """`--people 1`: a rendered person through the graph with max_people 2 and the real CNN;
    every stage node's figures are reported, and how often the looped scene jumps back (everyone
    found anew) within the measured window."""
    import ctypes.util
    import importlib.util

    if ctypes.util.find_library("OSMesa") is None or importlib.util.find_spec("pyrender") is None:
        pytest.skip("needs libosmesa6 and pyrender-maintained (scripts/setup.sh)")
    env = {**domain_env(22), "TMPDIR": str(tmp_path)}
    r = subprocess.run(
        [sys.executable, "-m", "vmocap_core.cli", "bench", "graph", "--json", "--seconds", "3", "--warmup", "1",
         "--pcm", "model", "--people", "1", "--frames", "60", "--modes", "default", "--cache", str(tmp_path / "cache")],
        env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-4000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    m = out["modes"]["default"]
    assert out["people"] == 1 and m["rate_hz"] > 1.0, m
    assert out["scene_restarts_in_window"] == 2  # a 2 s scene at 30 Hz, measured from 1 s to 4 s
    assert set(m["cpu_pct"]) == {"vmocap_pcm", "vmocap_markers", "vmocap_skeleton"}, m
    assert all(m["stages_ms"][s]["p50"] > 0.0 for s in ("pcm", "markers", "skeleton")), m
    assert not list(tmp_path.glob("vmocap_bench_graph_*"))
