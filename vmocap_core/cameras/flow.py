"""Flow control between the cameras and the CNN: frame sets the CNN could not take are not sent.

When the CNN is slower than the cameras, the PCM node keeps only the newest frame set and drops
the others; but each dropped frame set was still converted, sent (over DDS in the processes
layout: ~9 MB a frame set for 4 cameras at 1024x768) and received, on the cores the CNN needs.
`InFlight` lets the camera node send a frame set only while fewer than `limit` frame sets are
between it and the end of the CNN (the PCM node's NS/pcm/done says which frame set it finished),
so an overloaded graph spends its cores on the frame sets it processes: the newest wins at the
source, nothing queues, latency stays bounded. The decision is per frame set: every camera's
frame of one instant (stamps within half a period) is sent or skipped alike.
"""

from __future__ import annotations

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


class InFlight:
    """Thread-safe; shared by the camera threads of one node. `admit` decides (once per frame
    set) whether a frame goes out, `done` is called with the stamp of each frame set the CNN
    finished. A frame set sent but never finished (dropped downstream, no CNN running) stops
    counting after `stale_s`."""

    def __init__(self, limit: int, period_s: float, stale_s: float = 1.0) -> None:
        if limit < 1:
            raise ValueError("at least one frame set must be allowed in flight")
        self.limit = int(limit)
        self.tol_ns = int(0.5 * period_s * 1e9)
        self.stale_s = float(stale_s)
        self._lock = threading.Lock()
        self._sent: deque[tuple[int, float]] = deque()  # (stamp, monotonic time sent), oldest first
        self._decided: deque[tuple[int, bool]] = deque(maxlen=64)  # recent frame sets and their decision
        self.skipped = 0  # frame sets not sent (counted once per frame set)
        self.sent = 0

    def admit(self, stamp_ns: int, now_s: float) -> bool:
        with self._lock:
            for s, ok in reversed(self._decided):  # another camera's frame of a frame set decided already
                if abs(s - stamp_ns) <= self.tol_ns:
                    return ok
            while self._sent and now_s - self._sent[0][1] > self.stale_s:
                self._sent.popleft()
            ok = len(self._sent) < self.limit
            if ok:
                self._sent.append((int(stamp_ns), now_s))
                self.sent += 1
            else:
                self.skipped += 1
            self._decided.append((int(stamp_ns), ok))
            return ok

    def done(self, stamp_ns: int) -> None:
        """The CNN finished the frame set stamped `stamp_ns`: it and older ones are out of flight."""
        with self._lock:
            while self._sent and self._sent[0][0] <= stamp_ns + self.tol_ns:
                self._sent.popleft()

    @property
    def in_flight(self) -> int:
        return len(self._sent)
