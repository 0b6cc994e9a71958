"""The crops' body prediction (method/prediction.py): a body turning over is predicted where it
will be, nothing is extrapolated from stale or missing feedback."""

import numpy as np

from vmocap_core.method.prediction import MAX_GAP_S, BodyPredictor, rigid_motion, rotation_power
from vmocap_core.method.rotation import trunk_tilt
from vmocap_core.pcm.synthetic import benchmark_rig

MS = 1_000_000


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _body() -> np.ndarray:
    rng = np.random.default_rng(3)
    kp = rng.normal(scale=0.25, size=(25, 3)) + [0.0, 0.0, 1.0]
    kp[0], kp[1] = [0.0, 0.0, 0.9], [0.0, 0.0, 1.4]  # pelvis below neck: upright
    return kp


def _turned(kp: np.ndarray, angle: float, shift: float) -> np.ndarray:
    """The body turned about its centroid's x axis (a backflip's rotation) and moved along y."""
    c = kp.mean(axis=0)
    return (kp - c) @ _rot_x(angle).T + c + [0.0, shift, 0.0]


def test_rigid_motion_and_its_power_recover_a_turn():
    kp = _body()
    R, ca, cb = rigid_motion(kp, _turned(kp, 0.3, 0.05))
    assert np.allclose(R, _rot_x(0.3), atol=1e-9)
    assert np.allclose(cb - ca, [0.0, 0.05, 0.0], atol=1e-9)
    assert np.allclose(rotation_power(R, 2.0), _rot_x(0.6), atol=1e-9)
    assert np.allclose(rotation_power(R, 10.0, max_angle=np.radians(60)), _rot_x(np.radians(60)), atol=1e-9)


def test_a_body_turning_over_is_predicted_at_the_next_frame_set():
    """A backflip's 360 degrees in 0.6 s at 30 Hz: 20 degrees a frame set; the crop's tilt from the
    last skeleton lags that much in every camera, the prediction's much less (2 periods ahead:
    an overloaded graph that skipped a frame set)."""
    kp = _body()
    rig = benchmark_rig(kp[0])
    step = np.radians(20.0)
    p = BodyPredictor()
    p.update(0, kp)
    p.update(33 * MS, _turned(kp, step, 0.02))
    for ahead, t in ((1, 66 * MS), (2, 99 * MS)):
        truth = _turned(kp, (1 + ahead) * step, 0.02 * (1 + ahead))
        pred = p.predict(t)
        lag = np.abs(np.angle(np.exp(1j * (trunk_tilt(rig, _turned(kp, step, 0.02)) - trunk_tilt(rig, truth)))))
        err = np.abs(np.angle(np.exp(1j * (trunk_tilt(rig, pred) - trunk_tilt(rig, truth)))))
        assert err.max() < 0.1 * lag.max(), (ahead, np.degrees(err), np.degrees(lag))
        assert np.abs(pred - truth).max() < 0.02


def test_no_extrapolation_from_stale_missing_or_single_feedback():
    kp = _body()
    p = BodyPredictor()
    assert p.predict(0) is None
    p.update(0, kp)
    assert np.array_equal(p.predict(33 * MS), kp)  # one feedback: no velocity
    p.update(int((MAX_GAP_S + 0.1) * 1e9), _turned(kp, 0.2, 0.0))  # too long after the one before
    assert np.array_equal(p.predict(int((MAX_GAP_S + 0.2) * 1e9)), _turned(kp, 0.2, 0.0))
    p.update(int((MAX_GAP_S + 0.13) * 1e9), None)  # lost: start again
    assert p.predict(int(1e9)) is None
    off = BodyPredictor(enabled=False)
    off.update(0, kp)
    off.update(33 * MS, _turned(kp, 0.2, 0.0))
    assert np.array_equal(off.predict(66 * MS), _turned(kp, 0.2, 0.0))


def test_the_same_feedback_again_does_not_erase_the_velocity():
    """The feedback topic is latched: a re-delivered message must not make the two last equal."""
    kp = _body()
    p = BodyPredictor()
    p.update(0, kp)
    p.update(33 * MS, _turned(kp, 0.2, 0.0))
    p.update(33 * MS, _turned(kp, 0.2, 0.0))
    p.update(10 * MS, kp)  # older: ignored
    assert np.allclose(p.predict(66 * MS), _turned(kp, 0.4, 0.0), atol=1e-9)
