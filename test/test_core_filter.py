"""The IIR low-pass filter, metrics, motions."""

from __future__ import annotations

import numpy as np
import pytest

from vmocap_core.apps.metrics import acceleration_error, bone_length_std, jitter, summarize, table_one
from vmocap_core.errors import MotionFileError
from vmocap_core.keypoints import INDEX
from vmocap_core.method.iir import LowPassFilter
from vmocap_core.motion import extend, load_motion, resample


def test_butterworth_frequency_response():
    f = LowPassFilter(2, 6.0, 60.0)
    h = f.frequency_response(np.array([0.1, 6.0, 20.0]))
    assert h[0] == pytest.approx(1.0, abs=1e-3)
    assert h[1] == pytest.approx(1 / np.sqrt(2), abs=1e-3)  # -3 dB at the cutoff
    assert h[2] < 0.1
    # The per-sample filter realizes that response: a 20 Hz sine is attenuated accordingly.
    t = np.arange(600) / 60.0
    x = np.sin(2 * np.pi * 20.0 * t)
    y = np.array([f(v) for v in x])
    assert np.abs(y[300:]).max() == pytest.approx(h[2], rel=0.05)


def test_filter_starts_in_steady_state_and_works_on_arrays():
    f = LowPassFilter(4, 5.0, 60.0)
    x = np.full((25, 3), 2.5)
    for _ in range(3):
        assert np.allclose(f(x), x)


def test_lag_compensation_removes_the_delay_on_ramps():
    plain = LowPassFilter(2, 4.0, 60.0)
    lead = LowPassFilter(2, 4.0, 60.0, lag_compensation=True)
    ramp = np.arange(300) / 60.0  # 1 m/s
    yp = np.array([plain(v) for v in ramp])
    yl = np.array([lead(v) for v in ramp])
    assert abs(ramp[-1] - yp[-1]) == pytest.approx(plain.group_delay_s(), rel=0.05)
    assert abs(ramp[-1] - yl[-1]) < 1e-6
    assert lead.frequency_response(np.array([0.0]))[0] == pytest.approx(1.0)


def test_invalid_filter_settings():
    with pytest.raises(ValueError):
        LowPassFilter(2, 40.0, 60.0)
    with pytest.raises(ValueError):
        LowPassFilter(0, 4.0, 60.0)


def test_metrics_on_hand_computed_cases():
    gt = np.zeros((2, 25, 3))
    pred = gt.copy()
    pred[:, INDEX["neck"], 0] = 0.04  # 40 mm
    pred[:, INDEX["left_knee"], 2] = 0.12  # 120 mm
    scored = np.zeros(25, bool)
    scored[[INDEX["neck"], INDEX["left_knee"], INDEX["pelvis"]]] = True
    t = table_one(pred, gt, scored)
    assert t["mpjpe_mm"] == pytest.approx((40 + 120 + 0) / 3)
    assert t["pck50"] == pytest.approx(200 / 3)
    assert t["pck100"] == pytest.approx(200 / 3)
    assert t["pck150"] == pytest.approx(100.0)
    assert t["groups"]["upper_body"]["mpjpe_mm"] == pytest.approx(40)
    assert t["groups"]["lower_body"]["mpjpe_mm"] == pytest.approx(60)
    assert t["groups"]["head"] is None
    assert summarize(np.full((3, 2), np.nan))["mpjpe_mm"] is None


def test_bone_length_std_and_jitter():
    kp = np.zeros((4, 25, 3))
    kp[:, INDEX["left_elbow"], 0] = [0.3, 0.3, 0.5, 0.5]  # upper arm 0.3 then 0.5 -> std 0.1
    assert bone_length_std(kp, {"ua": ("left_shoulder", "left_elbow")}) == pytest.approx(0.1)
    p = np.zeros((5, 1, 3))
    p[:, 0, 0] = 0.5 * 2.0 * (np.arange(5) / 10.0) ** 2  # constant 2 m/s^2 at 10 Hz
    assert jitter(p, 10.0) == pytest.approx(2.0)
    # the acceleration error ignores what the truth does itself and a constant offset ...
    assert acceleration_error(p + 0.05, p, 10.0) == pytest.approx(0.0)
    # ... and counts a one-frame spike e as |e|, |-2e|, |e| (m/s^2 x fps^2) over the three triples it is in
    q = p.copy()
    q[2, 0, 1] += 0.01
    assert acceleration_error(q, p, 10.0) == pytest.approx((1 + 2 + 1) / 3)
    q[3] = np.nan  # triples with an unknown frame are left out: only frames 0-2 remain
    assert acceleration_error(q, p, 10.0) == pytest.approx(1.0)


def test_motion_files(tmp_path):
    from vmocap_core.apps.bench.accuracy import default_motions

    files = default_motions()
    assert any(f.stem == "cartwheel" for f in files)
    m = load_motion(next(f for f in files if f.stem == "cartwheel"))
    assert m.is_inverted()
    r = extend(resample(m, 60.0), 4.0)
    assert r.fps == 60.0 and r.n_frames >= 240
    bad = tmp_path / "bad.npz"
    np.savez(bad, joints=np.zeros((5, 3)), names=np.array(["neck"]), fps=30.0)
    with pytest.raises(MotionFileError):
        load_motion(bad)
    only = tmp_path / "partial.npz"
    np.savez(only, joints=np.zeros((5, 2, 3)), names=np.array(["neck", "unknown_part"]), fps=30.0)
    assert load_motion(only).present.sum() == 1


def test_one_euro_smooths_still_keypoints_and_follows_fast_ones():
    """Two keypoints: one still with 5 mm noise, one moving at 3 m/s. The still one's noise is
    more than halved; the moving one trails far less than a fixed first-order filter at
    min_cutoff would make it (its cutoff rose with its speed)."""
    from vmocap_core.method.one_euro import OneEuroFilter

    rate, n = 60.0, 240
    rng = np.random.default_rng(0)
    t = np.arange(n) / rate
    still = rng.normal(0.0, 0.005, (n, 3))
    fast = np.stack([3.0 * t, np.zeros(n), np.zeros(n)], axis=1)
    f = OneEuroFilter(1.0, 10.0, rate, 2.0)
    fixed = OneEuroFilter(1.0, 0.0, rate, 2.0)  # beta 0: a plain first-order low-pass at 1 Hz
    out = np.array([f(np.stack([a, b])) for a, b in zip(still, fast)])
    ref = np.array([fixed(np.stack([a, b])) for a, b in zip(still, fast)])
    tail = slice(60, None)
    # noise reduced (its own jitter raises the cutoff a little: about twice the fixed filter's)
    assert np.std(out[tail, 0]) < 0.5 * np.std(still[tail])
    lag = np.abs(out[tail, 1, 0] - fast[tail, 0]).mean()
    assert lag < 0.1 * np.abs(ref[tail, 1, 0] - fast[tail, 0]).mean()  # ~0.5 m behind at 1 Hz; ours a few cm


def test_one_euro_constant_input_nan_restart_and_bad_parameters():
    from vmocap_core.method.one_euro import OneEuroFilter

    f = OneEuroFilter(1.0, 10.0, 60.0)
    x = np.array([[0.1, 0.2, 1.0], [0.5, -0.3, 1.2]])
    for _ in range(5):
        assert np.array_equal(f(x), x)
    y = x.copy()
    y[1] = np.nan
    assert np.isnan(f(y)[1]).all() and np.isfinite(f(y)[0]).all()
    z = x + [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    assert np.array_equal(f(z)[1], z[1])  # a keypoint back after NaN restarts at its sample
    for bad in ((0.0, 10.0, 60.0), (1.0, -1.0, 60.0), (31.0, 1.0, 60.0)):
        with pytest.raises(ValueError):
            OneEuroFilter(*bad)


def test_one_euro_follows_the_real_interval_of_skipped_samples() -> None:
    """A 60 Hz filter fed every second sample with dt = 1/30 s behaves as a 30 Hz filter: a
    graph that skips frame sets does not see them as a jump."""
    from vmocap_core.method.one_euro import OneEuroFilter

    t = np.arange(0, 2, 1 / 60)
    x = np.stack([np.sin(3 * t), 0.5 * t, np.cos(2 * t)], -1)[:, None]  # (T, 1, 3)
    fast, slow = OneEuroFilter(1.0, 10.0, 60.0), OneEuroFilter(1.0, 10.0, 30.0)
    a = np.array([fast(xi, dt=1 / 30) for xi in x[::2]])
    b = np.array([slow(xi) for xi in x[::2]])
    assert np.allclose(a, b, atol=1e-12)
    plain = OneEuroFilter(1.0, 10.0, 60.0)
    c = np.array([plain(xi) for xi in x[::2]])
    assert np.abs(c - b).max() > 1e-3, "without dt the skipped samples filter differently"
