"""Lockstep replay (cameras/lockstep.py): the camera threads of one node send frame set t+1 only
once the graph answered frame set t, or the timeout passed."""

from __future__ import annotations

import threading
import time

import pytest

from vmocap_core.cameras.lockstep import LockstepGate


def _camera(gate: LockstepGate, stamps: list[int], sent: list[tuple[int, float]], stop: threading.Event) -> threading.Thread:
    def run() -> None:
        for s in stamps:
            if not gate.enter(s, stop):
                return
            sent.append((s, time.monotonic()))
    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_each_frame_set_waits_for_the_answer_to_the_one_before():
    gate, stop, sent = LockstepGate(5.0), threading.Event(), []
    cams = [_camera(gate, [10, 20, 30], sent, stop) for _ in range(4)]
    time.sleep(0.2)
    assert sorted(s for s, _ in sent) == [10] * 4  # every camera's frame of the first set, nothing newer
    gate.answered(5)  # an older frame set's feedback releases nothing
    time.sleep(0.1)
    assert len(sent) == 4
    t_answer = time.monotonic()
    gate.answered(10)
    time.sleep(0.2)
    assert sorted(s for s, _ in sent) == [10] * 4 + [20] * 4
    assert min(t for s, t in sent if s == 20) >= t_answer
    gate.answered(20)
    for th in cams:
        th.join(2.0)
    assert [s for s, _ in sent].count(30) == 4 and gate.answered_count == 2 and gate.timeouts == 0


def test_an_unanswered_frame_set_releases_the_next_after_the_timeout_and_stop_ends_a_wait():
    gate, stop, sent = LockstepGate(0.3), threading.Event(), []
    th = _camera(gate, [1, 2], sent, stop)
    th.join(2.0)
    assert [s for s, _ in sent] == [1, 2] and gate.timeouts == 1
    assert sent[1][1] - sent[0][1] >= 0.29

    gate2, stop2, sent2 = LockstepGate(60.0), threading.Event(), []
    th2 = _camera(gate2, [1, 2], sent2, stop2)
    time.sleep(0.2)
    stop2.set()
    th2.join(1.0)
    assert not th2.is_alive() and [s for s, _ in sent2] == [1]


def test_timeout_must_be_positive():
    with pytest.raises(ValueError):
        LockstepGate(0.0)


def test_in_flight_sends_a_frame_set_only_while_the_cnn_has_room():
    from vmocap_core.cameras.flow import InFlight

    period = 1 / 30
    f = InFlight(2, period, stale_s=1.0)
    t = [int(1e9 + k * period * 1e9) for k in range(6)]
    # frame set 0 and 1 go out, each camera's frame alike (stamps a few ms apart)
    assert f.admit(t[0], 0.0) and f.admit(t[0] + 2_000_000, 0.001)
    assert f.admit(t[1], 0.033) and f.admit(t[1] - 3_000_000, 0.034)
    # frame set 2: two in flight, not sent, on every camera
    assert not f.admit(t[2], 0.066) and not f.admit(t[2] + 1_000_000, 0.067)
    assert (f.sent, f.skipped, f.in_flight) == (2, 1, 2)
    f.done(t[0])  # the CNN finished frame set 0: room for the next one
    assert f.admit(t[3], 0.1) and f.in_flight == 2
    f.done(t[3])  # a later frame set finished: everything before it is out of flight too
    assert f.in_flight == 0
    # a frame set nobody finishes (no CNN running) stops counting after stale_s
    assert f.admit(t[4], 0.2) and f.admit(t[5], 0.25)
    assert not f.admit(t[5] + int(period * 1e9), 0.3)
    assert f.admit(t[5] + int(2 * period * 1e9), 1.3)
    with pytest.raises(ValueError):
        InFlight(0, period)
