"""N camera sources run together: frame sets matched by stamp, a sync report, a software
trigger that fires every camera at once, and survival of a camera that disconnects.

Live sources (`source.live`) are each read by their own thread into a short queue; frame
sets are formed from the queues by stamp (within `tolerance_ns`). Recordings are read in
lock step (they are synchronized by construction). A live camera whose `read`/`open` raises
SourceError is reported (`events`, `on_event`), left out of the frame sets while it is
away, and reopened every `reconnect_s` seconds; the other cameras keep running.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import SourceError
from .base import Frame, FrameSource


@dataclass
class FrameSet:
    """Frames of one instant: `frames[name]`; `missing` lists cameras without a frame."""

    stamp_ns: int  # median stamp of the frames
    frames: dict[str, Frame]
    missing: list[str] = field(default_factory=list)

    @property
    def spread_ns(self) -> int:
        s = [f.stamp_ns for f in self.frames.values()]
        return int(max(s) - min(s)) if s else 0


@dataclass
class _CamState:
    source: FrameSource
    queue: collections.deque = field(default_factory=lambda: collections.deque(maxlen=8))
    connected: bool = False
    frames: int = 0
    overflow: int = 0  # frames pushed out of the queue before use
    unmatched: int = 0  # frames dropped because no partner frame existed in the other cameras
    gaps: int = 0  # frames missing according to the stamps (period known)
    disconnects: int = 0
    reconnects: int = 0
    stamps: list[int] = field(default_factory=list)
    last_error: str = ""


class SourceRig:
    """Start N sources together and deliver synchronized FrameSets.

    tolerance_ns: frames of one set lie within this of each other (default: half the
    expected period `period_ns`, else 5 ms). trigger_mode: `read_set` fires `trigger()` on
    every source at once (all threads released by one barrier) before collecting a set.
    calibration: a vmocap Rig; `start` raises SourceError when a camera's image size differs
    from the size it was calibrated at.
    """

    def __init__(self, sources: list[FrameSource], period_ns: int | None = None, tolerance_ns: int | None = None,
                 trigger_mode: bool = False, reconnect_s: float = 1.0, queue_len: int = 8,
                 on_event: Callable[[str, str], None] | None = None, calibration=None) -> None:
        names = [s.name for s in sources]
        if len(set(names)) != len(names):
            raise SourceError(f"camera names must be unique: {names}")
        if not sources:
            raise SourceError("a rig needs at least one source")
        if trigger_mode:
            lacking = [s.name for s in sources if not s.software_trigger]
            if lacking:
                raise SourceError(f"software trigger mode: cameras {lacking} have no software trigger")
        self.sources = sources
        self.period_ns = period_ns
        self.tolerance_ns = tolerance_ns or (period_ns // 2 if period_ns else 5_000_000)
        self.trigger_mode = trigger_mode
        self.reconnect_s = reconnect_s
        self.on_event = on_event
        self.calibration = calibration  # a vmocap Rig: image sizes must match its calibration
        self.events: list[tuple[float, str, str]] = []
        self._state = {s.name: _CamState(s, collections.deque(maxlen=queue_len)) for s in sources}
        self._live = any(s.live for s in sources)
        self._lock = threading.Condition()
        self._running = False
        self._threads: list[threading.Thread] = []
        self._sets = 0
        self._spreads: list[int] = []
        self._incomplete_sets = 0
        self._t_start = 0.0

    # ------------------------------------------------------------------ life cycle
    def start(self) -> "SourceRig":
        """Open every source (a live camera that fails to open is retried in the background)."""
        errors = []
        for name, st in self._state.items():
            try:
                st.source.open()
                st.connected = True
            except SourceError as exc:
                if not st.source.live:
                    errors.append(str(exc))
                else:
                    self._event(name, f"not connected: {exc}")
        if errors:
            self.stop()
            raise SourceError("; ".join(errors))
        if self.calibration is not None:
            self._check_sizes()
        self._running = True
        self._t_start = time.monotonic()
        if self._live:
            for st in self._state.values():
                t = threading.Thread(target=self._worker, args=(st,), name=f"cam-{st.source.name}", daemon=True)
                t.start()
                self._threads.append(t)
        return self

    def _check_sizes(self) -> None:
        rig = self.calibration
        known = [(n, st.source.size) for n, st in self._state.items() if st.source.size is not None and n in rig.names]
        try:
            rig.subset([n for n, _ in known]).check_sizes([s for _, s in known])
        except ValueError as exc:
            self.stop()
            raise SourceError(str(exc)) from None

    def stop(self) -> None:
        self._running = False
        with self._lock:
            self._lock.notify_all()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        for st in self._state.values():
            try:
                st.source.close()
            except SourceError:
                pass
            st.connected = False

    def __enter__(self) -> "SourceRig":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def names(self) -> list[str]:
        return list(self._state)

    @property
    def connected(self) -> dict[str, bool]:
        return {n: st.connected for n, st in self._state.items()}

    def _event(self, camera: str, what: str) -> None:
        self.events.append((time.time(), camera, what))
        if self.on_event is not None:
            self.on_event(camera, what)

    # ------------------------------------------------------------------ live workers
    def _worker(self, st: _CamState) -> None:
        src = st.source
        while self._running:
            if not st.connected:
                time.sleep(self.reconnect_s)
                if not self._running:
                    break
                try:
                    src.close()
                    src.open()
                except SourceError as exc:
                    st.last_error = str(exc)
                    continue
                st.connected = True
                st.reconnects += 1
                self._event(src.name, "reconnected")
                continue
            try:
                frame = src.read(timeout=0.1)
            except SourceError as exc:
                st.connected = False
                st.disconnects += 1
                st.last_error = str(exc)
                self._event(src.name, f"disconnected: {exc}")
                with self._lock:
                    st.queue.clear()
                    self._lock.notify_all()
                continue
            if frame is None:
                continue
            with self._lock:
                if len(st.queue) == st.queue.maxlen:
                    st.overflow += 1
                st.queue.append(frame)
                self._note(st, frame)
                self._lock.notify_all()

    def _note(self, st: _CamState, frame: Frame) -> None:
        st.frames += 1
        if st.stamps and self.period_ns:
            gap = (frame.stamp_ns - st.stamps[-1]) / self.period_ns
            if gap > 1.5:
                st.gaps += int(round(gap)) - 1
        st.stamps.append(frame.stamp_ns)
        if len(st.stamps) > 10000:
            del st.stamps[:5000]

    # ------------------------------------------------------------------ frame sets
    def trigger(self) -> None:
        """Fire every connected camera's software trigger at once: one thread per camera,
        released together by a barrier, so the spread is thread wake-up time, not N calls."""
        srcs = [s for s in self.sources if self._state[s.name].connected]
        if not srcs:
            return
        barrier = threading.Barrier(len(srcs))
        errors: list[tuple[str, str]] = []

        def fire(src: FrameSource) -> None:
            try:
                barrier.wait(timeout=1.0)
                src.trigger()
            except (SourceError, threading.BrokenBarrierError) as exc:
                errors.append((src.name, str(exc)))

        threads = [threading.Thread(target=fire, args=(s,)) for s in srcs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for name, e in errors:
            self._event(name, f"trigger failed: {e}")

    def read_set(self, timeout: float = 1.0) -> FrameSet | None:
        """The next synchronized frame set, or None (timeout, or a recording ended)."""
        if not self._running:
            raise SourceError("rig not started")
        if self.trigger_mode:
            self.trigger()
        if not self._live:
            return self._read_lockstep(timeout)
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._running:
                fs = self._match()
                if fs is not None:
                    return fs
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._lock.wait(left)
        return None

    def _read_lockstep(self, timeout: float) -> FrameSet | None:
        """Recordings: read on demand, dropping frames of cameras that started earlier (by
        stamp) until the heads agree; None when a recording ends."""
        while True:
            for st in self._state.values():
                if not st.queue:
                    f = st.source.read(timeout)
                    if f is None:
                        return None
                    self._note(st, f)
                    st.queue.append(f)
            fs = self._match()
            if fs is not None:
                return fs

    def _match(self) -> FrameSet | None:
        """Form a set from the queue heads when all connected cameras agree within tolerance;
        drop heads that are too old to ever get partners (counted as unmatched)."""
        active = [st for st in self._state.values() if st.connected]
        if not active or any(not st.queue for st in active):
            return None
        while True:
            heads = [st.queue[0].stamp_ns for st in active]
            newest = max(heads)
            stale = [st for st, h in zip(active, heads) if newest - h > self.tolerance_ns]
            if not stale:
                break
            for st in stale:
                st.queue.popleft()
                st.unmatched += 1
            if any(not st.queue for st in active):
                return None
        frames = {st.source.name: st.queue.popleft() for st in active}
        missing = [n for n, st in self._state.items() if not st.connected]
        return self._emit(frames, missing)

    def _emit(self, frames: dict[str, Frame], missing: list[str]) -> FrameSet:
        stamp = int(np.median([f.stamp_ns for f in frames.values()]))
        fs = FrameSet(stamp, frames, missing)
        self._sets += 1
        self._incomplete_sets += int(bool(missing))
        self._spreads.append(fs.spread_ns)
        if len(self._spreads) > 10000:
            del self._spreads[:5000]
        return fs

    # ------------------------------------------------------------------ report
    def report(self) -> dict:
        """Per camera rate, frames, drops, disconnects; stamp spread within the frame sets."""
        cams = {}
        for name, st in self._state.items():
            s = np.asarray(st.stamps[-1000:], dtype=np.int64)
            rate = float((len(s) - 1) / ((s[-1] - s[0]) * 1e-9)) if len(s) > 1 and s[-1] > s[0] else 0.0
            cams[name] = {
                "connected": st.connected, "frames": st.frames, "rate_hz": rate, "gaps": st.gaps,
                "overflow": st.overflow, "unmatched": st.unmatched, "disconnects": st.disconnects,
                "reconnects": st.reconnects, **{f"source_{k}": v for k, v in st.source.stats().items()},
            }
        sp = np.asarray(self._spreads, dtype=np.float64) * 1e-6
        return {
            "sets": self._sets, "incomplete_sets": self._incomplete_sets,
            "spread_ms_mean": float(sp.mean()) if sp.size else 0.0,
            "spread_ms_max": float(sp.max()) if sp.size else 0.0,
            "tolerance_ms": self.tolerance_ns * 1e-6, "cameras": cams,
        }

    def format_report(self) -> str:
        r = self.report()
        lines = [f"{r['sets']} frame sets ({r['incomplete_sets']} incomplete), stamp spread mean "
                 f"{r['spread_ms_mean']:.3f} ms, max {r['spread_ms_max']:.3f} ms (tolerance {r['tolerance_ms']:.1f} ms)"]
        for n, c in r["cameras"].items():
            lines.append(f"  {n}: {c['rate_hz']:.2f} Hz, {c['frames']} frames, gaps {c['gaps']}, overflow {c['overflow']}, "
                         f"unmatched {c['unmatched']}, disconnects {c['disconnects']}/{c['reconnects']} reconnected"
                         + ("" if c["connected"] else "  [DISCONNECTED]"))
        return "\n".join(lines)
