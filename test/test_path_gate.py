"""The path gate (vmocap_core/method/path_gate.py) on hip-centre paths with known answers."""

import numpy as np

from vmocap_core.method.path_gate import PathGate

RATE = 60.0
WALK = np.array([-1.0, 0.0, 0.0])  # m/s along -x, hips 0.9 m high
OTHER = np.array([-0.25, 0.4, 0.9])  # a person standing 0.4 m beside the walker's line


def _ns(k: int) -> int:
    return int(round(k / RATE * 1e9))


def _walker(k: int) -> np.ndarray:
    return np.array([0.0, 0.0, 0.9]) + WALK * k / RATE


def _confirmed_walk(gate: PathGate, frames: int, pulled: int) -> None:
    """`frames` confirmed frame sets of the walker, the last `pulled` of them already drawn
    towards the other person (the check reads the skeleton fed back one frame set late)."""
    for k in range(frames):
        p = _walker(k)
        j = k - (frames - pulled) + 1
        if j > 0:
            p = p + (OTHER - p) * 0.08 * j
        gate.add(_ns(k), p)


def test_a_track_back_on_the_person_beside_is_strayed_and_the_seed_is_on_the_walk():
    """The walker is tracked for 0.5 s, the last 9 confirmed frame sets (0.15 s) slide towards
    a person standing beside, the views disagree; 0.3 s later the track comes back on that
    person. The points confirmed just before the doubt are dropped, so the expectation stays on
    the walk: the gate says "strayed" with a seed near the walker, and a track back on the
    walker passes."""
    frames, pulled, back = 30, 9, 18
    k = frames + back
    expected = {}
    for doubt in (True, False):
        gate = PathGate(max_m=0.3, horizon_s=0.4)
        _confirmed_walk(gate, frames, pulled)
        if doubt:
            gate.doubt(_ns(frames))
        expected[doubt] = gate.expected(_ns(k))
        if doubt:
            seed = gate.strayed(_ns(k), OTHER)
            assert seed is not None and np.linalg.norm(seed[:2] - _walker(k)[:2]) < 0.1, seed
            assert gate.strayed(_ns(k), _walker(k)) is None
    # kept, the pulled points bend the expectation towards the other person
    off = {d: np.linalg.norm(e[:2] - _walker(k)[:2]) for d, e in expected.items()}
    assert off[False] > off[True] + 0.05, off


def test_the_hip_centre_rising_or_falling_is_not_another_body():
    """A jump or a fall moves the hip centre 0.6 m vertically while the views disagree: the
    same body. Only a horizontal move that far is another body."""
    gate = PathGate(max_m=0.3, horizon_s=0.4)
    _confirmed_walk(gate, 30, 0)
    gate.doubt(_ns(30))
    k = 50
    assert gate.strayed(_ns(k), _walker(k) + [0.0, 0.0, 0.6]) is None
    assert gate.strayed(_ns(k), _walker(k) - [0.0, 0.0, 0.6]) is None
    assert gate.strayed(_ns(k), _walker(k) + [0.0, 0.6, 0.0]) is not None


def test_the_expectation_keeps_a_short_window_and_two_points():
    """Only the last WINDOW_S of confirmed points are kept, and doubt never leaves fewer than two:
    the expectation of a walker that turned follows the new heading, and a doubt right after a
    start still has a velocity."""
    gate = PathGate(max_m=0.3, horizon_s=0.4, window_s=0.25)
    for k in range(60):  # 0.5 s along +y, then 0.5 s along -x
        p = np.array([0.0, k / RATE, 0.9]) if k < 30 else np.array([-(k - 29) / RATE, 29 / RATE, 0.9])
        gate.add(_ns(k), p)
    exp = gate.expected(_ns(59 + 12))
    assert abs(exp[0] - (-(59 + 12 - 29) / RATE)) < 0.02 and abs(exp[1] - 29 / RATE) < 0.02, exp
    start = PathGate(max_m=0.3, horizon_s=0.4)
    for k in range(3):
        start.add(_ns(k), _walker(k))
    start.doubt(_ns(3))
    assert len(start._path) == 2
    assert np.linalg.norm(start.expected(_ns(3)) - _walker(3)) < 0.02


def test_the_place_the_subject_can_be_grows_once_the_path_is_old():
    """An overloaded graph keeps few frame sets: a track back 1.4 s after the last confirmed
    one may find a walker that turned aside 0.6 m from where it was heading. Within the
    horizon the same 0.6 m is another body; past it, the bound grows at a brisk walk."""
    gate = PathGate(max_m=0.3, horizon_s=0.4)
    _confirmed_walk(gate, 30, 0)
    gate.doubt(_ns(30))
    for back_s, strays in ((0.3, True), (1.4, False)):
        k = 29 + int(round(back_s * RATE))
        exp = gate.expected(_ns(k))
        assert exp is not None
        turned = exp + [0.0, 0.6, 0.0]  # walked off to the side
        assert (gate.strayed(_ns(k), turned) is not None) is strays, back_s
    one = PathGate(max_m=0.3, horizon_s=0.4)
    one.add(_ns(0), _walker(0))
    assert one.bound(_ns(24)) == 0.3 and abs(one.bound(_ns(84)) - (0.3 + 1.5 * 1.0)) < 1e-6


def test_a_walker_who_stops_is_not_strayed_but_a_body_beside_the_stop_is():
    """A walker stops in front of someone (face to face, a hand-over) while the views
    disagree: the track comes back where they stopped, 0.37 m short of where their velocity
    would have carried them. That is the subject; 0.4 m to the side of it is not."""
    gate = PathGate(max_m=0.3, horizon_s=0.4)
    _confirmed_walk(gate, 30, 0)
    gate.doubt(_ns(30))
    k = 30 + 18
    stop = _walker(26)  # stopped as the views began to disagree
    assert np.linalg.norm(gate.expected(_ns(k))[:2] - stop[:2]) > 0.35
    assert gate.strayed(_ns(k), stop) is None
    assert gate.strayed(_ns(k), stop + [0.0, 0.4, 0.0]) is not None
    assert gate.strayed(_ns(k), stop - WALK * 0.4) is not None  # back the way they came
