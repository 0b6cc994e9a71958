"""RTS smoothers (smoothing.py), the live fixed-lag mode and the offline mode on the synthetic
benchmark (short clip)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vmocap_core.apps.bench.accuracy import BUNDLED, RATE_HZ, prepare, run_motion, score_run
from vmocap_core.method.config import PipelineConfig
from vmocap_core.method.smoothing import FixedLagSmoother, MotionModel, gaussian_smooth, rts_smooth, runs

MODEL = MotionModel("ca", 2000.0, 0.02, 60.0)


def test_rts_follows_a_parabola_without_lag_and_removes_noise() -> None:
    t = np.arange(240) / 60.0
    truth = np.stack([0.5 * 3.0 * t**2, np.sin(2 * np.pi * 0.5 * t), 0.3 * t], axis=1)  # (T, 3)
    noisy = truth + np.random.default_rng(0).normal(0, 0.02, truth.shape)
    sm = rts_smooth(noisy, MODEL)
    err_noisy = np.linalg.norm(noisy - truth, axis=1).mean()
    err_sm = np.linalg.norm(sm - truth, axis=1).mean()
    assert err_sm < 0.6 * err_noisy
    # a noise-free parabola is the model's own motion: reproduced (no lag at either end)
    clean = rts_smooth(truth[:, :1], MODEL)
    assert np.abs(clean - truth[:, :1]).max() < 1e-6


def test_fixed_lag_is_the_rts_estimate_given_the_data_so_far() -> None:
    x = np.random.default_rng(1).normal(0, 1, (50, 4, 3)).cumsum(axis=0) * 0.01
    lag = 3
    f = FixedLagSmoother(MODEL, lag)
    outs = [f(s) for s in x]
    assert all(o is None for o in outs[:lag])
    for t in (lag, 20, 49):
        ref = rts_smooth(x[: t + 1], MODEL)[t - lag]
        assert np.allclose(outs[t], ref, atol=1e-12)


def test_nan_frames_are_not_measurements_and_runs_split_gaps() -> None:
    x = np.linspace(0, 1, 30)[:, None] * np.ones((1, 3))
    x[10] = np.nan
    sm = rts_smooth(x, MODEL)
    assert np.isfinite(sm).all() and np.allclose(sm, np.linspace(0, 1, 30)[:, None], atol=1e-6)
    assert runs(np.array([0, 1, 1, 0, 1, 0, 0, 1, 1, 1], bool)) == [slice(1, 3), slice(4, 5), slice(7, 10)]
    assert np.allclose(gaussian_smooth(np.ones((5, 2)), 1.5), 1.0)
    with pytest.raises(ValueError):
        MotionModel("jerk", 1.0, 0.1, 60.0)
    with pytest.raises(ValueError):
        PipelineConfig.from_dict({"smoothing_lag_frames": -1})


@pytest.fixture(scope="module")
def walk():
    m = prepare(BUNDLED / "walk.npz")
    n = int(2.5 * RATE_HZ)
    return dataclasses.replace(m, positions=m.positions[:n])


def test_lag_and_offline_modes_on_a_clip(walk) -> None:
    """Fixed lag: outputs the frame `lag` back (same stamps as the live frames); offline: more
    accurate than live on the same PCMs, constant bone lengths."""
    live = score_run(run_motion(walk, 0, PipelineConfig.of(fps=RATE_HZ)))["method"]
    lag_run = run_motion(walk, 0, PipelineConfig.of(fps=RATE_HZ, smoothing_lag_frames=3))
    lag = score_run(lag_run)["method"]
    off = score_run(run_motion(walk, 0, PipelineConfig.of(fps=RATE_HZ, offline=True)))["method"]
    assert "tracking" not in lag_run.status[-3:]  # the last 3 frames still wait for their lag
    assert lag_run.status[-4] == "tracking"
    assert off["mpjpe_mm"] < lag["mpjpe_mm"] < live["mpjpe_mm"], (off, lag, live)
    assert off["bone_length_std_m"] < 1e-6


def test_offline_on_a_recording_never_tracked_is_a_clear_error() -> None:
    from vmocap_core.errors import VmocapError
    from vmocap_core.method.offline import reconstruct
    from vmocap_core.method.results import TrackResult
    nan = np.full((25, 3), np.nan)
    results = [TrackResult(k, "initializing", np.full(40, np.nan), [], nan, nan, np.zeros(25), nan) for k in range(5)]
    with pytest.raises(VmocapError, match="no tracked frame"):
        reconstruct(results, PipelineConfig.of(offline=True))


def test_offline_identification_from_confident_markers() -> None:
    """offline_identify_quantile: each keypoint keeps the markers whose weight reaches that
    quantile of its own weights; unweighted (never seen) markers are dropped; 0 keeps all."""
    from vmocap_core.method.config import ConfigError
    from vmocap_core.method.offline import confident

    rng = np.random.default_rng(0)
    markers = rng.normal(size=(100, 25, 3))
    weights = np.tile(np.linspace(0.1, 1.0, 100)[:, None], (1, 25))
    weights[:, 3] *= 10  # another keypoint's scale: its own quantile
    weights[:50, 7] = 0.0  # half of keypoint 7 unseen: the quantile of the seen half
    weights[:, 9] = 0.0  # never seen
    kept = np.isfinite(confident(markers, weights, 0.75)).all(axis=2)
    assert kept[:, 0].sum() == 25 and kept[:, 3].sum() == 25 and kept[75:, 0].all()
    assert kept[:, 7].sum() == 13 and kept[87:, 7].all()
    assert not kept[:, 9].any()
    assert confident(markers, weights, 0.0) is markers
    with pytest.raises(ConfigError):
        PipelineConfig.from_dict({"offline_identify_quantile": 1.0})


def test_offline_segments_bridge_a_few_uncertain_frame_sets_only() -> None:
    """offline_bridge_frames: up to that many frame sets in a row that the images disagreed with
    ("uncertain") stay inside one segment; a longer run, another status or missing frame sets
    (a stamp jump) still end it."""
    from vmocap_core.method.offline import segments

    stamps = np.arange(20, dtype=np.int64) * 16_666_667
    tracked = np.ones(20, bool)
    tracked[[5, 10, 11, 12, 13]] = False
    uncertain = ~tracked
    assert segments(stamps, tracked) == [slice(0, 5), slice(6, 10), slice(14, 20)]
    assert segments(stamps, tracked, uncertain, 3) == [slice(0, 10), slice(14, 20)]
    assert segments(stamps, tracked, uncertain, 4) == [slice(0, 20)]
    lost = uncertain.copy()
    lost[5] = False  # lost, not uncertain: the tracker started over there
    assert segments(stamps, tracked, lost, 3) == [slice(0, 5), slice(6, 10), slice(14, 20)]
    jumped = stamps.copy()
    jumped[6:] += 100_000_000  # frame sets missing after the uncertain one
    assert segments(jumped, tracked, uncertain, 3) == [slice(0, 5), slice(6, 10), slice(14, 20)]


def test_offline_keeps_a_bridged_uncertain_frame_set_a_gap(walk) -> None:
    """One uncertain frame set inside a track: its neighbours are tracked and smoothed as one
    segment, the frame set itself is output as it came (uncertain, nothing interpolated). Split
    there (offline_bridge_frames 0), the second segment starts afresh: the keypoints jump (81 mm
    beyond the true motion on this clip) where bridged they move with the body (7 mm)."""
    from vmocap_core.method.offline import reconstruct
    from vmocap_core.method.pipeline import Pipeline
    from vmocap_core.pcm.synthetic import SyntheticPcmSource, benchmark_rig

    rig = benchmark_rig(np.nanmean(walk.positions[:, 0], axis=0))
    src = SyntheticPcmSource(rig, walk.positions, walk.present, seed=0)
    tracker = Pipeline(rig, PipelineConfig.of(fps=RATE_HZ))
    live = [tracker.step(src.render(t)).skeleton for t in range(len(walk.positions))]
    k = next(t for t in range(60, len(live)) if live[t - 1].status == live[t].status == live[t + 1].status == "tracking")
    live[k] = dataclasses.replace(live[k], status="uncertain")
    truth = np.linalg.norm(walk.positions[k + 1] - walk.positions[k - 1], axis=1)
    steps = {}
    for bridge in (0, 3):
        out = reconstruct(live, PipelineConfig.of(fps=RATE_HZ, offline=True, offline_bridge_frames=bridge).skeleton)
        assert out[k].status == "uncertain" and out[k - 1].status == out[k + 1].status == "tracking", bridge
        assert out[k] is live[k]
        steps[bridge] = np.nanmax(np.linalg.norm(out[k + 1].keypoints - out[k - 1].keypoints, axis=1) - truth)
    assert steps[3] < 0.02 and steps[0] > 2 * steps[3], steps
