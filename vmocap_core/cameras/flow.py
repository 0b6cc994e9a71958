"""Flow control between the cameras and the CNN: frame sets the CNN could not take are not sent.

When the CNN is slower than the cameras, the PCM node keeps only the newest frame set and drops
the others; but each dropped frame set was still converted, sent (over DDS in the processes
layout: ~9 MB a frame set for 4 cameras at 1024x768) and received, on the cores the CNN needs.
`InFlight` lets the camera node send a frame set only while fewer than `limit` frame sets are
between it and the end of the CNN (the PCM node's NS/pcm/done says which frame set it finished),
so an overloaded graph spends its cores on the frame sets it processes: the newest wins at the
source, nothing queues, latency stays bounded. The decision is per frame set: every camera's
frame of one instant (stamps within half a period) is sent or skipped alike.

A second frame set in flight keeps the CNN busy while the first one's results travel (the
throughput of `limit` 2), but sent at once it would wait there for a whole CNN run, which
doubles the latency under overload. So a frame set beyond the first is sent only from one
period before the CNN is expected to be free (its time per frame set measured from the `done`
answers): it waits at most a period, and the camera's next frame would come too late to keep
the CNN busy.
"""

from __future__ import annotations

import statistics
import threading
from collections import deque


def applies(cnn_answers: bool, local_takers: list[str], remote_takers: list[str]) -> bool:
    """Whether flow control applies to a camera node's images: a PCM node reports what it finished
    (`cnn_answers`), and the images reach only PCM nodes (names vmocap_pcm*) in other processes
    (`remote_takers`). A recorder or viewer of the images gets every frame; a PCM node in the
    camera's own process (`local_takers`) takes them for free and keeps the newest itself, which
    gives fresher frame sets than holding them back here."""
    return (cnn_answers and not local_takers and bool(remote_takers)
            and all(n.startswith("vmocap_pcm") for n in remote_takers))


OVERLOAD_MARGIN = 1.2  # CnnPace.behind: the CNN's time per frame set over this many arrival intervals


class CnnPace:
    """The PCM node's view of whether its CNN keeps up: the recent intervals between frame
    sets' arrivals and the CNN's recent times per frame set (the last 9 of each)."""

    def __init__(self) -> None:
        self.arrivals: deque[float] = deque(maxlen=9)
        self.cnn_times: deque[float] = deque(maxlen=9)
        self._last_arrival: float | None = None

    def arrived(self, now_s: float) -> None:
        if self._last_arrival is not None:
            self.arrivals.append(now_s - self._last_arrival)
        self._last_arrival = now_s

    def finished(self, seconds: float) -> None:
        self.cnn_times.append(seconds)

    def newest_only(self, waiting: int, capacity: int) -> bool:
        """Whether to take only the newest of the `waiting` frame sets (a queue of `capacity`):
        when the CNN is slower than they come it never catches up, so an older frame set taken
        first only ages the output by the periods between them (and the newer one then waits a
        whole CNN run); a CNN that is faster on the whole takes them in order and catches up
        after a slow frame set, without dropping it. Only while the queue is full (dropping
        already): a slow start (the detector's first runs) with room left is caught up in order.
        Arrivals, not the cameras' nominal rate: a replay paced slower than recorded is no
        overload; and a margin, so that a CNN about as fast as the frame sets come keeps taking
        them all."""
        return (1 < waiting and capacity <= waiting and len(self.cnn_times) >= 3 and len(self.arrivals) >= 3
                and statistics.fmean(self.cnn_times) > OVERLOAD_MARGIN * statistics.fmean(self.arrivals))


class InFlight:
    """Thread-safe; shared by the camera threads of one node. `admit` decides (once per frame
    set) whether a frame goes out, `done` is called with the stamp of each frame set the CNN
    finished. A frame set sent but never finished (dropped downstream, no CNN running) stops
    counting after `stale_s`."""

    def __init__(self, limit: int, period_s: float, stale_s: float = 1.0) -> None:
        if limit < 1:
            raise ValueError("at least one frame set must be allowed in flight")
        self.limit = int(limit)
        self.period_s = float(period_s)
        self.tol_ns = int(0.5 * period_s * 1e9)
        self.stale_s = float(stale_s)
        self._lock = threading.Lock()
        self._sent: deque[tuple[int, float]] = deque()  # (stamp, monotonic time sent), oldest first
        self._decided: deque[tuple[int, bool]] = deque(maxlen=64)  # recent frame sets and their decision
        self.skipped = 0  # frame sets not sent (counted once per frame set)
        self.sent = 0
        self._service: deque[float] = deque(maxlen=9)  # the CNN's recent times per frame set (s)
        self._last_done = float("-inf")  # monotonic time of the last answer

    def admit(self, stamp_ns: int, now_s: float) -> bool:
        with self._lock:
            for s, ok in reversed(self._decided):  # another camera's frame of a frame set decided already
                if abs(s - stamp_ns) <= self.tol_ns:
                    return ok
            while self._sent and now_s - self._sent[0][1] > self.stale_s:
                self._sent.popleft()
            ok = len(self._sent) < self.limit
            if ok and self._sent and self._service:  # the CNN is busy until about free_at
                free_at = max(self._sent[0][1], self._last_done) + len(self._sent) * statistics.median(self._service)
                ok = now_s >= free_at - self.period_s
            if ok:
                self._sent.append((int(stamp_ns), now_s))
                self.sent += 1
            else:
                self.skipped += 1
            self._decided.append((int(stamp_ns), ok))
            return ok

    def done(self, stamp_ns: int, now_s: float) -> None:
        """The CNN finished the frame set stamped `stamp_ns` (answer received at monotonic
        `now_s`): it and older ones are out of flight."""
        with self._lock:
            finished = None
            while self._sent and self._sent[0][0] <= stamp_ns + self.tol_ns:
                finished = self._sent.popleft()
            if finished is not None and abs(finished[0] - stamp_ns) <= self.tol_ns:
                # its time in the CNN: from when it was sent, or from the answer before if it waited
                self._service.append(now_s - max(finished[1], self._last_done))
            self._last_done = now_s

    @property
    def in_flight(self) -> int:
        return len(self._sent)
