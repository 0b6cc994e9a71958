"""Others in view while tracking (issue 32, item 1): the detector looks at one camera at a time
for people besides the subject, so that the diagnostics can say someone else is there.

While tracking, the crops come from the skeleton and the detector does not run. One look (the
whole image, then the closer pass around a small person) can cost more than a frame period on
2 cores, so looks made inside the frame set had to be rare, and a person standing beside the
subject for a few seconds was often not reported. In the background a look runs in a thread of
its own at the lowest CPU priority, on a copy of one camera's image and the subject's pelvis at
that instant: frame sets never wait for it, a look offered while the last one runs is skipped,
and on a saturated CPU the looks come less often. The crops and heatmaps never depend on it.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..cameras.projection import Rig
from .background import Background
from .choice import others_near
from .detector import Detection, PoseDetector

LOWEST_PRIORITY = 19  # nice of the background look's thread: CPU the frame sets leave over
EVERY = 15  # frame sets between looks (the graph's census_every): each of 4 cameras about once a second at 60 Hz
# A count is as old as its camera's last look: with a look at some camera older than this
# (a camera without frames, a saturated CPU, census off) the census does not know who is in view.
STALE_S = 3.0

Find = Callable[[Sequence[np.ndarray | None]], list[list[Detection]]]


class Census:
    """others (C,): per camera, the people besides the subject at the last look at it;
    `count(stamp_ns)`: the most in any camera, -1 when a camera's look is stale.

    every: a look is offered every that many `offer` calls (0: never), the cameras in turn.
    background: looks run in a low-priority thread with a detector of their own (`make_detector`);
    otherwise inside `offer` with `find` (deterministic: offline runs and tests)."""

    def __init__(self, rig: Rig, every: int, find: Find, background: bool = False,
                 make_detector: Callable[[], PoseDetector] | None = None) -> None:
        if background and make_detector is None:
            raise ValueError("a background census needs make_detector (a detector of its own)")
        self.rig = rig
        self.every = int(every)
        self.others = np.zeros(len(rig), dtype=int)
        self._previous = np.zeros(len(rig), dtype=int)  # per camera, what the look before the last saw
        self._looked_ns = np.full(len(rig), np.iinfo(np.int64).min // 2, dtype=np.int64)  # capture stamp of each camera's last look
        self.looks = 0  # looks finished
        self._find = find
        self._count = 0
        self._turn = 0
        self._thread: Background[tuple[int, np.ndarray, np.ndarray, int]] | None = None
        if background and make_detector is not None:
            self._thread = Background("vmocap-census", make_detector, self._look_with, LOWEST_PRIORITY)

    @property
    def error(self) -> str:
        """Why the last background look failed ("" none)."""
        return "" if self._thread is None else self._thread.error

    def found(self, others: np.ndarray, stamp_ns: int = 0) -> None:
        """(C,) counts of a detector run on every camera made elsewhere (initialization) on the
        frame set captured at stamp_ns."""
        self.others[:] = others
        self._previous[:] = others
        self._looked_ns[:] = stamp_ns

    def count(self, stamp_ns: int) -> int:
        """People besides the subject in any camera at the frame set captured at stamp_ns, -1
        (unknown) when some camera's last look is over STALE_S before it."""
        if stamp_ns - int(self._looked_ns.min()) > STALE_S * 1e9:
            return -1
        return int(self.others.max(initial=0))

    def offer(self, images: Sequence[np.ndarray | None], pelvis: np.ndarray, stamp_ns: int = 0) -> None:
        """A tracked frame set (images in rig order, None: no frame) with the subject's pelvis (3,),
        captured at stamp_ns."""
        if self.every <= 0:
            return
        self._count += 1
        have = [c for c, im in enumerate(images) if im is not None]
        if self._count % self.every or not have:
            return
        c = have[self._turn % len(have)]
        if self._thread is None:
            self._turn += 1
            self._look(c, images[c], pelvis, stamp_ns, self._find)
            return
        # the frame's buffer may be reused (shared memory) once the frame set is done; a look
        # offered while the last one runs is skipped and the camera keeps its turn
        if self._thread.offer((c, np.array(images[c], copy=True), np.array(pelvis, dtype=np.float64), int(stamp_ns))):
            self._turn += 1

    def _look_with(self, detector: PoseDetector, job: tuple[int, np.ndarray, np.ndarray, int]) -> None:
        c, image, pelvis, stamp_ns = job
        self._look(c, image, pelvis, stamp_ns, lambda images: detector.find_people(images, turned=False))

    def _look(self, c: int, image: np.ndarray, pelvis: np.ndarray, stamp_ns: int, find: Find) -> None:
        # The detector merges two people who stand close (one box): a look at the person beside
        # the subject missed them 4 times in 10. So a camera's count is the larger of its last two
        # looks: someone who left is cleared one look later.
        seen = others_near(self.rig, c, find([image])[0], pelvis)
        self.others[c] = max(seen, self._previous[c])
        self._previous[c] = seen
        self._looked_ns[c] = stamp_ns
        self.looks += 1

    def wait(self, timeout: float | None = None) -> bool:
        """Until no look runs (background); False when the timeout came first."""
        return True if self._thread is None else self._thread.wait(timeout)

    def close(self, timeout: float = 5.0) -> None:
        """Ends the background thread after the look it runs (background.Background.close)."""
        if self._thread is not None:
            self._thread.close(timeout)
