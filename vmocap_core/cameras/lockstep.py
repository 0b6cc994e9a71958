"""Lockstep replay: a recorded frame set goes out once the graph has answered the one before.

The paper's loop is causal: the lattice search and the CNN's crops of frame t start from the
skeleton of frame t-1. Played at a fixed rate, a graph slower than the recording drops frame
sets (newest wins), so its output depends on the machine. In lockstep the camera node sends
frame set t+1 when the skeleton's feedback for frame set t arrived (the feedback carries its
frame set's stamp), so every frame set is processed, in order, at whatever speed this machine
has: the graph's output equals `vmocap process` on the same recording. A frame set nobody
answers (no person in any view, a node down) releases the next one after `timeout_s`.
"""

from __future__ import annotations

import threading
import time


class LockstepGate:
    """Shared by the camera threads of one node (thread-safe). Frames of the frame set in
    flight (and older ones) pass; a newer frame waits until `answered` is called with a stamp
    at least the one in flight, or `timeout_s` passed (counted in `timeouts`)."""

    def __init__(self, timeout_s: float) -> None:
        if timeout_s <= 0:
            raise ValueError("lockstep timeout must be positive")
        self.timeout_s = float(timeout_s)
        self._cond = threading.Condition()
        self._in_flight: int | None = None  # stamp of the frame set sent and not yet answered
        self._since = 0.0
        self.answered_count = 0
        self.timeouts = 0

    def enter(self, stamp_ns: int, stop: threading.Event | None = None) -> bool:
        """Block until a frame stamped `stamp_ns` may go out; False when `stop` was set."""
        with self._cond:
            while True:
                if self._in_flight is None:
                    self._in_flight, self._since = int(stamp_ns), time.monotonic()
                    return True
                if stamp_ns <= self._in_flight:  # another camera's frame of the set in flight
                    return True
                left = self._since + self.timeout_s - time.monotonic()
                if left <= 0:
                    self.timeouts += 1
                    self._in_flight = None
                    continue
                if stop is not None and stop.is_set():
                    return False
                self._cond.wait(min(left, 0.1))

    def answered(self, stamp_ns: int) -> None:
        """The graph is done with the frame set stamped `stamp_ns` (or a later one)."""
        with self._cond:
            if self._in_flight is not None and stamp_ns >= self._in_flight:
                self._in_flight = None
                self.answered_count += 1
                self._cond.notify_all()
