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
