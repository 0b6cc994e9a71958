"""Approximate-time synchronization of N camera streams (message_filters has no wheel here).

Frames are matched by capture stamp: a frame set takes, per camera, the frame closest to a
pivot stamp within `tolerance_ns`. Time is driven by the data (the newest stamp seen), not the
wall clock, so the result is deterministic for a given arrival order.

- Complete sets are emitted as soon as the last camera's frame arrives.
- A camera that has already delivered a frame later than pivot + tolerance cannot complete the
  set any more: the set is emitted without it if at least `min_cameras` take part ("partial"),
  otherwise dropped.
- A camera that delivered nothing for `silent_after_ns` (in stamp time) while another camera went
  on delivering is *silent*: sets no longer wait for it; it is reported in `stats()` and becomes
  active again with its next frame. "Went on" is measured to the newest stamp some camera has
  followed with another frame: after a gap in every stream (a recording with a gap, cameras
  restarted together) the first camera back does not make the others silent, so the first frame
  set after the gap is matched, not dropped.
- Duplicated stamps (same camera, same stamp) are dropped and counted; frames that arrive out of
  order are inserted in stamp order, or dropped as late when a set at or after their stamp was
  already emitted.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import Any, Generic, Sequence, TypeVar

T = TypeVar("T")


@dataclass
class FrameSet(Generic[T]):
    """Frames of several cameras taken at (about) the same time."""

    stamp_ns: int  # the earliest stamp in the set (the pivot)
    items: dict[str, T]  # camera name -> item, only the cameras that take part
    stamps: dict[str, int]  # camera name -> its frame's own stamp
    missing: tuple[str, ...] = ()  # cameras without a frame in this set

    @property
    def complete(self) -> bool:
        return not self.missing


@dataclass
class SyncStats:
    complete: int = 0
    partial: int = 0
    dropped_sets: int = 0  # pivots that could not gather min_cameras frames
    dropped_frames: dict[str, int] = field(default_factory=dict)  # unmatched frames per camera
    duplicates: dict[str, int] = field(default_factory=dict)
    late: dict[str, int] = field(default_factory=dict)
    missing: dict[str, int] = field(default_factory=dict)  # sets emitted without this camera
    silent: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {
            "complete": self.complete,
            "partial": self.partial,
            "dropped_sets": self.dropped_sets,
            "dropped_frames": dict(self.dropped_frames),
            "duplicates": dict(self.duplicates),
            "late": dict(self.late),
            "missing": dict(self.missing),
            "silent": list(self.silent),
        }


class ApproximateSync(Generic[T]):
    """Match frames of the cameras `names` by stamp (see the module docstring)."""

    def __init__(
        self,
        names: Sequence[str],
        tolerance_ns: int,
        min_cameras: int = 2,
        silent_after_ns: int = 500_000_000,
        max_queue: int = 30,
    ) -> None:
        if len(set(names)) != len(names) or not names:
            raise ValueError(f"camera names must be unique and non-empty: {list(names)}")
        if tolerance_ns < 0:
            raise ValueError("tolerance_ns must be >= 0")
        self.names = list(names)
        self.tolerance_ns = int(tolerance_ns)
        self.min_cameras = max(1, min(int(min_cameras), len(names)))
        self.silent_after_ns = int(silent_after_ns)
        self.max_queue = int(max_queue)
        self._stamps: dict[str, list[int]] = {n: [] for n in names}
        self._items: dict[str, list[T]] = {n: [] for n in names}
        self._newest: dict[str, int | None] = {n: None for n in names}
        self._before_newest: dict[str, int | None] = {n: None for n in names}  # each camera's newest stamp but one
        self._emitted_until: int | None = None  # stamp of the last emitted/dropped pivot
        self._last_members: set[str] = set()  # cameras that took part in that set
        self._first: int | None = None  # first stamp seen
        z = {n: 0 for n in names}
        self._stats = SyncStats(dropped_frames=dict(z), duplicates=dict(z), late=dict(z), missing=dict(z))

    # ------------------------------------------------------------------------------ input
    def add(self, name: str, stamp_ns: int, item: T) -> list[FrameSet[T]]:
        """Add one frame; returns the frame sets that became ready (oldest first)."""
        if name not in self._stamps:
            raise KeyError(f"unknown camera {name!r}; expected one of {self.names}")
        stamp_ns = int(stamp_ns)
        st = self._stats
        # a frame, even a late one, proves the camera is alive (not silent)
        if self._first is None:
            self._first = stamp_ns
        newest = self._newest[name]
        if newest is None or stamp_ns > newest:
            self._before_newest[name], self._newest[name] = newest, stamp_ns
        last = self._emitted_until
        if last is not None and (
            stamp_ns <= last or (name not in self._last_members and stamp_ns <= last + self.tolerance_ns)
        ):
            # its set was already emitted (or dropped): too late to take part
            st.late[name] += 1
            return []
        stamps = self._stamps[name]
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            st.duplicates[name] += 1
            return []
        stamps.insert(i, stamp_ns)
        self._items[name].insert(i, item)
        return self._drain()

    def flush(self) -> list[FrameSet[T]]:
        """At the end of a recording: emit what can still be matched, drop the rest."""
        out = []
        while any(self._stamps.values()):
            fs = self._try_pivot(final=True)
            if fs is not None and fs is not _DROPPED:
                out.append(fs)
        return out

    def stats(self) -> SyncStats:
        self._stats.silent = tuple(self._silent())
        return self._stats

    # ------------------------------------------------------------------------------ logic
    def _now(self) -> int | None:
        """The newest stamp some camera has delivered another frame after (its stream went on)."""
        seen = [s for s in self._before_newest.values() if s is not None]
        return max(seen) if seen else None

    def _silent(self) -> list[str]:
        now = self._now()
        if now is None:
            return []
        # a camera that never delivered counts from the first stamp any camera delivered
        first = self._first if self._first is not None else now
        return [
            n for n in self.names
            if (t if (t := self._newest[n]) is not None else first) < now - self.silent_after_ns
            and not self._stamps[n]
        ]

    def _drain(self) -> list[FrameSet[T]]:
        out: list[FrameSet[T]] = []
        while True:
            fs = self._try_pivot(final=False)
            if fs is None:
                return out
            if fs is not _DROPPED:
                out.append(fs)

    def _try_pivot(self, final: bool):
        heads = [(s[0], n) for n, s in self._stamps.items() if s]
        if not heads:
            return None
        pivot = min(heads)[0]
        tol = self.tolerance_ns
        silent = set(self._silent())
        chosen: dict[str, int] = {}
        waiting = False
        for n in self.names:
            stamps = self._stamps[n]
            # closest frame within tolerance of the pivot (queues are sorted)
            j = bisect.bisect_left(stamps, pivot - tol)
            best = None
            while j < len(stamps) and stamps[j] <= pivot + tol:
                if best is None or abs(stamps[j] - pivot) < abs(stamps[best] - pivot):
                    best = j
                j += 1
            if best is not None:
                # a later frame might still arrive closer to the pivot only if the camera has
                # not yet delivered anything past pivot + tol
                chosen[n] = best
                continue
            newest = self._newest[n]
            can_still_come = n not in silent and (newest is None or newest <= pivot + tol)
            if can_still_come and not final:
                waiting = True
        overflow = max(len(s) for s in self._stamps.values()) > self.max_queue
        if waiting and not overflow:
            return None
        self._emitted_until = pivot
        if len(chosen) < self.min_cameras:
            # drop the pivot frame(s): the oldest frame of each camera at the pivot
            for n in self.names:
                s = self._stamps[n]
                if s and s[0] == pivot:
                    s.pop(0)
                    self._items[n].pop(0)
                    self._stats.dropped_frames[n] += 1
            self._stats.dropped_sets += 1
            self._last_members = set()
            return _DROPPED
        items, stamps_out = {}, {}
        for n, j in chosen.items():
            # frames older than the chosen one can never be matched any more
            self._stats.dropped_frames[n] += j
            stamps_out[n] = self._stamps[n][j]
            items[n] = self._items[n][j]
            del self._stamps[n][: j + 1]
            del self._items[n][: j + 1]
        missing = tuple(n for n in self.names if n not in chosen)
        self._last_members = set(chosen)
        for n in missing:
            self._stats.missing[n] += 1
        if missing:
            self._stats.partial += 1
        else:
            self._stats.complete += 1
        return FrameSet(stamp_ns=pivot, items=items, stamps=stamps_out, missing=missing)


_DROPPED: Any = object()


LATE_WARN = 5  # late frames of one camera within one diagnostics period that make it a problem


def lagging(before: dict[str, int], now: dict[str, int], threshold: int = LATE_WARN) -> dict[str, int]:
    """Cameras whose `late` count (SyncStats.late) grew by at least `threshold` since `before`:
    their frames keep arriving after their frame set was emitted, so they are never used (a
    clock or stamps behind the others by more than the tolerance, or a source that stalls)."""
    return {n: c - before.get(n, 0) for n, c in now.items() if c - before.get(n, 0) >= threshold}


def frames_missing(prev_ns: int | None, stamp_ns: int, fps: float) -> int:
    """Frame periods skipped between two consecutive frame sets' capture stamps at `fps`: 0 when
    they are one period apart (up to 1.5), none for the first set or a stamp going back (a loop)."""
    if prev_ns is None or stamp_ns <= prev_ns:
        return 0
    return max(0, int(round((stamp_ns - prev_ns) * fps / 1e9)) - 1)
