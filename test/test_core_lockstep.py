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
    t = [int(1e9 + k * period * 1e9) for k in range(12)]
    # frame set 0 and 1 go out, each camera's frame alike (stamps a few ms apart)
    assert f.admit(t[0], 0.0) and f.admit(t[0] + 2_000_000, 0.001)
    assert f.admit(t[1], 0.033) and f.admit(t[1] - 3_000_000, 0.034)
    # frame set 2: two in flight, not sent, on every camera
    assert not f.admit(t[2], 0.066) and not f.admit(t[2] + 1_000_000, 0.067)
    assert (f.sent, f.skipped, f.in_flight) == (2, 1, 2)
    f.done(t[0], 0.09)  # the CNN finished frame set 0 in 0.09 s: it should finish frame set 1 at 0.18
    assert not f.admit(t[3], 0.1)  # room, but it would wait there 0.08 s
    assert f.admit(t[4], 0.15) and f.in_flight == 2  # from a period before 0.18
    f.done(t[4], 0.25)  # a later frame set finished: everything before it is out of flight too
    assert f.in_flight == 0
    assert f.admit(t[8], 0.27) and f.admit(t[9], 0.34)  # the CNN's time is 0.095 s: free at 0.365
    assert not f.admit(t[10], 0.37)
    # frame sets nobody finishes (no CNN running) stop counting after stale_s
    assert f.admit(t[11], 1.4)
    with pytest.raises(ValueError):
        InFlight(0, period)


def test_in_flight_sends_the_second_frame_set_just_before_the_cnn_is_free():
    """A CNN that takes 0.1 s a frame set, frames every 1/60 s: after the first answers the
    second frame set goes out only from one period before the CNN is expected to be free, so
    it waits there at most a period instead of a whole CNN run."""
    from vmocap_core.cameras.flow import InFlight

    period, cnn = 1 / 60, 0.1
    f = InFlight(2, period, stale_s=1.0)
    waits = []  # how long each frame set waited for the CNN
    queue: list[tuple[int, float]] = []  # sent, not yet in the CNN: (stamp, sent at)
    running: tuple[int, float] | None = None  # (stamp, finishes at)
    for k in range(240):
        now = k * period
        while running is not None and running[1] <= now:  # the CNN answers, then takes the next
            end = running[1]
            f.done(running[0], end)
            running = None
            if queue:
                s, sent_at = queue.pop(0)
                waits.append(end - sent_at)
                running = (s, end + cnn)
        stamp = int(1e9 + k * period * 1e9)
        if f.admit(stamp, now):
            if running is None:
                waits.append(0.0)
                running = (stamp, now + cnn)
            else:
                queue.append((stamp, now))
    late = waits[3:]  # once the CNN's time is known
    assert max(late) <= period + 1e-9, late
    done_sets = len(waits)
    assert done_sets >= 0.9 * 240 * period / cnn  # the CNN stays busy: about 40 frame sets in 4 s
