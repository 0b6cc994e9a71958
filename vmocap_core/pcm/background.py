"""Detector work beside the frame sets: one job at a time in a thread of its own, at a lower CPU
priority, with a detector of its own (loaded by the first job, in that thread). A job offered
while one runs, or while the last one's result waits to be taken, is refused: the caller offers
again later, so frame sets never wait for a detector (the census of others in view, census.py; the people look's searches in a free-running
graph, method/people_look.py)."""

from __future__ import annotations

import os
import threading
from typing import Any, Callable, Generic, TypeVar

Job = TypeVar("Job")


class Background(Generic[Job]):
    """`offer(job)` runs `work(detector, job)` in the thread (False: refused, see `idle`); `take()`
    gives the last finished job and what work returned (unless None), once; `error` says why the
    last job failed ("" none). make_detector: called once, in the thread."""

    def __init__(self, name: str, make_detector: Callable[[], Any], work: Callable[[Any, Job], Any],
                 nice: int) -> None:
        self.name, self.nice = name, int(nice)
        self._make, self._work = make_detector, work
        self._job: Job | None = None
        self._done: tuple[Job, Any] | None = None
        self._cv = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.error = ""

    @property
    def idle(self) -> bool:
        """No job runs and no result waits: a job offered now is taken."""
        with self._cv:
            return self._job is None and self._done is None and not self._closed

    def offer(self, job: Job) -> bool:
        with self._cv:
            if self._job is not None or self._done is not None or self._closed:
                return False
            self._job = job
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
                self._thread.start()
            self._cv.notify()
            return True

    def take(self) -> tuple[Job, Any] | None:
        with self._cv:
            done, self._done = self._done, None
            return done

    def _run(self) -> None:
        try:  # this thread only (Linux: a thread id is a process id for setpriority)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.nice)
        except (AttributeError, OSError):
            pass  # not Linux, or not allowed: it still never blocks a frame set
        detector = None
        while True:
            with self._cv:
                while self._job is None and not self._closed:
                    self._cv.wait()
                job = self._job
                if self._closed or job is None:
                    return
            result = None
            try:
                detector = detector if detector is not None else self._make()
                result = self._work(detector, job)
                self.error = ""
            except Exception as exc:  # a diagnostic, never the frame sets' failure
                self.error = f"{type(exc).__name__}: {exc}"
            finally:
                with self._cv:
                    if not self.error and result is not None:
                        self._done = (job, result)
                    self._job = None
                    self._cv.notify_all()

    def wait(self, timeout: float | None = None) -> bool:
        """Until no job runs; False when the timeout came first."""
        with self._cv:
            return self._cv.wait_for(lambda: self._job is None, timeout)

    def close(self, timeout: float = 5.0) -> None:
        """Ends the thread after the job it runs (if any; on a saturated CPU a low-priority job can
        take long: a daemon thread, it is not waited for beyond timeout)."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
