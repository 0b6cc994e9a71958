"""Several people, the CNN's side (vmocap_pcm with max_people > 1, and the offline
people_tracker.py): who is in view, and each tracked person's heatmaps, one CNN call per frame set.

Each tracked person's crops follow their own fed-back skeleton (the paper's feedback, III-B), so
each lattice search reads maps of its own person. The detector runs on images with the tracked
bodies' silhouettes greyed (`hidden`): every frame set while someone found is not initialized yet
(their crops come from it), every wait_search_s while someone lost waits (their last crops held in
between), and every `detect_every_s` while fewer than `max_people` are tracked, to find people who
walked in (`_plan`: cheap whole-image looks, a closer look where needed), with glances (the
whole images only) every `glance_every_s` in between; in a free-running graph beside the frame
sets (`beside`, pcm/background.py), otherwise in the frame set's own time. A detection that a
tracked person's pelvis projects onto is theirs; the others are grouped across cameras
(pcm/choice.py: hip centres triangulated from two cameras that project onto a detection in both)
into new people, the one seen by the most cameras first. People found who have no skeleton yet
are greyed over their detections for a second look in the same search (`detections_greyed`):
the detector draws the most prominent person of an image, and two people in view from the start
were otherwise found one after the other's initialization. The crops of everyone go through the
landmark model together. A view says nothing of a person's keypoints that another tracked body
covers there (occlusion.py).

Every person sits in a slot (0 .. max_people - 1) while tracked: in the node graph each slot has
its own heatmap, markers and feedback topics, and the marker and skeleton nodes run one stage per
slot. Nothing here reads ground truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Sequence

import numpy as np

from ..cameras.projection import Rig, binning_affine
from ..keypoints import INDEX, KEYPOINTS
from ..pcm.background import Background
from ..pcm.choice import choose_subject
from ..pcm.crops import BODY_FRACTION, Crops
from ..pcm.detector import Detection, PoseDetector
from ..pcm.peaks import camera_keypoints
from ..pcm.views import PcmViews
from .occlusion import hidden_keypoints, others_greyed, without_hidden
from .people_config import PeopleConfig, ended_people
from .people_search import Search, SearchKind, detections_greyed, explained, found_again, people_in, run_search
from .prediction import BodyPredictor
from .results import seed_of, skeleton_of

PELVIS = INDEX["pelvis"]
HIPS = [INDEX["left_hip"], INDEX["right_hip"]]
FOLLOW_MIN_WEIGHT = 0.5  # a hip's heatmap peak a crop follows (_follow): seen, not guessed
# nice of the thread that searches beside the frame sets: below the frame sets, which must not
# wait, but not the census' lowest, which a saturated CPU starves (a newcomer would never be found)
SEARCH_NICE = 10


@dataclass
class Seat:
    """A person as the CNN's side knows them: `number` counts people in order of appearance
    (0, 1, ...; the outputs give them REP-155 ids), `slot` is theirs while they are tracked."""

    number: int
    slot: int
    predictor: BodyPredictor  # their fed-back skeleton, extrapolated to the frame set (their crops)
    seed: np.ndarray  # (3,) their hip centre when last seen: where to look for them when lost
    seen_ns: int  # stamp of their last frame set with a skeleton (or of their detection)
    body: np.ndarray | None = None  # their last fed-back skeleton (None: none, or a seed)
    fed_ns: int = -1  # stamp of their last feedback (a latched topic may bring an older one again)
    held: dict[int, tuple[int, Any]] = field(default_factory=dict)  # camera -> (stamp, detector crop) before a skeleton
    had_body: bool = False  # a skeleton was fed back for them once (False: found, not initialized yet)


@dataclass
class Look:
    """One frame set's look: every seated person's heatmaps (no views: nothing to crop them
    from), in the order they were found, and the people the detector saw but nobody tracks."""

    stamp_ns: int
    views: dict[int, PcmViews]  # person number -> their heatmaps (PcmViews.person is the number)
    slots: dict[int, int]  # person number -> slot
    untracked: np.ndarray  # (C,) detections per camera nobody's skeleton explains, at the last look (-1: none yet)
    left_out: int = 0  # people two cameras see whom nobody tracks for want of a slot, at the last look


@dataclass
class _Now:
    """The frame set a search is planned at or its finds are given out at (PeopleLook.step)."""

    images: Sequence[np.ndarray | None]
    stamp_ns: int
    have: np.ndarray  # (C,) cameras with an image
    tracked: dict[int, np.ndarray]  # person number -> their skeleton (25, 3) predicted to this frame set
    waiting: list[Seat]  # the seated people without one
    crops: dict[int, Crops]  # person number -> their crops so far

    @cached_property
    def skeletons(self) -> np.ndarray:
        return np.array(list(self.tracked.values())).reshape(-1, len(KEYPOINTS), 3)

    @cached_property
    def pelvises(self) -> np.ndarray:
        p = self.skeletons[:, PELVIS]
        return p[np.isfinite(p).all(axis=1)]


def _concat(crops: Sequence[Crops]) -> Crops:
    return Crops(np.concatenate([c.camera for c in crops]), np.concatenate([c.center for c in crops]),
                 np.concatenate([c.side for c in crops]), np.concatenate([c.rotation for c in crops]),
                 np.concatenate([c.valid for c in crops if c.valid is not None]))


class PeopleLook:
    """Up to `people.max_people` people through one BlazePose PCM source (pcm.pipeline.BlazePosePcm:
    `detect_people`, `crops_from_skeleton`, `landmark`): `step(images, stamp_ns)` per frame set,
    then each person's `feedback`, and `end` for the people who ended (module doc)."""

    def __init__(self, rig: Rig, pcm: Any, people: PeopleConfig | None = None, crop_prediction: str = "rigid",
                 binning: int = 1, beside: bool = False) -> None:
        self.rig, self.pcm = rig, pcm
        # binning > 1: the images come reduced that many times (REP 104) and `pcm` works on the
        # rig as they show it; the detections are read with that rig, and the views' affines
        # are returned for full-resolution pixels, so the stages keep the rig and its bounds
        self.seen = rig.binned(binning) if binning > 1 else rig
        self._to_binned = binning_affine(binning) if binning > 1 else None
        self.config = people or PeopleConfig()
        self.crop_prediction = crop_prediction
        self.seats: list[Seat] = []
        self._next = 0
        self._last_detection_ns: int | None = None  # the last search's stamp
        self._last_full_ns: int | None = None  # the last search's that was no glance (_search_due)
        self._searches = 0  # searches for newcomers so far
        self._greyed: frozenset[int] = frozenset()  # the people hidden at the last search that looked closer everywhere
        self._untracked = np.full(len(rig), -1)  # per camera, the detections nobody tracks at the last full look
        self._left_out = 0  # people (seen by two cameras) not tracked for want of a slot, at the last full look
        self._newly_tracked = False  # someone got their first skeleton since the last search for newcomers
        # beside: the searches run beside the frame sets (a free-running graph: a search costs
        # several frame periods, which every tracked person's frame sets would otherwise wait
        # for), on copies of the images of the frame set they were due at; their finds are given
        # out at the first frame set after they end. Otherwise in the frame set's own time
        # (offline, lockstep: the same result on every machine)
        self._beside: Background[Search] | None = None
        if beside:
            self._beside = Background("vmocap-people-search", pcm.new_detector, self._search_beside, SEARCH_NICE)

    def _search_beside(self, detector: PoseDetector, search: Search) -> list[list[Detection]]:
        return run_search(self.seen, detector.find_people, search)

    def wait_search(self, timeout: float | None = None) -> bool:
        """Until no search runs beside the frame sets; False when the timeout came first."""
        return True if self._beside is None else self._beside.wait(timeout)

    @property
    def search_error(self) -> str:
        """Why the last search beside the frame sets failed ("" none)."""
        return "" if self._beside is None else self._beside.error

    def close(self) -> None:
        if self._beside is not None:
            self._beside.close()

    def feedback(self, number: int, stamp_ns: int, feedback: np.ndarray | None, tracking: bool = True) -> None:
        """A person's fed-back skeleton of the frame set stamped `stamp_ns` (results.feedback_of):
        their next crops follow it, output or not (`tracking`: the graph's feedback does not say);
        a seed (their track slid onto another body) is where to look."""
        seat = next((s for s in self.seats if s.number == number), None)
        if seat is None or stamp_ns < seat.fed_ns:
            return
        seat.fed_ns = stamp_ns
        seat.predictor.update(stamp_ns, feedback)
        seat.body, seed = skeleton_of(feedback), seed_of(feedback)
        if seat.body is not None:
            if not seat.had_body:  # their first skeleton: the next frame set searches (_search_due)
                seat.had_body = self._newly_tracked = True
            seat.seed, seat.seen_ns = seat.body[PELVIS].copy(), stamp_ns
            seat.held.clear()
        elif seed is not None:
            seat.seed = seed

    def ended(self, stamp_ns: int) -> set[int]:
        """The people who end at `stamp_ns` by what was fed back (people_config.ended_people)."""
        gone, merged = ended_people(stamp_ns, {s.number: s.seen_ns for s in self.seats},
                                    {s.number: s.body for s in self.seats}, self.config)
        return gone | merged

    def end(self, numbers: Sequence[int] | set[int]) -> None:
        """These people are no longer looked for: their slots are free."""
        self.seats = [s for s in self.seats if s.number not in numbers]

    def _new_seat(self, seed: np.ndarray, stamp_ns: int) -> Seat:
        taken = {s.slot for s in self.seats}
        slot = next(k for k in range(self.config.max_people) if k not in taken)
        s = Seat(self._next, slot, BodyPredictor(enabled=self.crop_prediction == "rigid"),
                 np.asarray(seed, dtype=np.float64), stamp_ns)
        self._next += 1
        self.seats.append(s)
        return s

    def _search_due(self, stamp_ns: int, waiting: list[Seat]) -> SearchKind | None:
        """Which search this frame set runs (_plan), if any: "waiting" every frame set while
        someone found is not initialized yet, every wait_search_s while someone lost waits (their
        last detector crops are held in between: a full search costs several frame periods);
        "newcomers" every detect_every_s while fewer than max_people are tracked, and at once
        when someone got their first skeleton (greyed from then on, they no longer hide whom
        the one-person detector missed beside them), and a "glance" every glance_every_s in
        between; "counting" every count_every_s while max_people are (who is left out)."""
        cfg = self.config

        def due(last: int | None, every: float) -> bool:
            return last is None or not 0 <= stamp_ns - last < every * 1e9

        if waiting:
            # a person found and not yet initialized gets fresh detections every frame set: the
            # initialization triangulates consecutive frame sets of a body that may walk fast
            every = 0.0 if any(not s.had_body for s in waiting) else cfg.wait_search_s
            return "waiting" if due(self._last_detection_ns, every) else None
        if len(self.seats) < cfg.max_people:
            if self._newly_tracked or due(self._last_full_ns, cfg.detect_every_s):
                self._newly_tracked = False
                return "newcomers"
            # someone walking in is seen whole by two cameras well before the next full search
            # comes: without glances their wait for a body would be up to detect_every_s plus their
            # initialization; a glance costs a fraction of a full search (no closer look)
            if due(self._last_detection_ns, cfg.glance_every_s):
                return "glance"
            return None
        if cfg.count_every_s > 0 and due(self._last_full_ns, cfg.count_every_s):
            return "counting"
        return None

    def _crops(self, s: Seat, index: np.ndarray, found: Sequence[Sequence[Detection]], have: np.ndarray,
               stamp_ns: int) -> Crops:
        """A person's detector crops (MediaPipe's rule, rotated already): this frame set's
        detection per camera (index (C,), -1: none), else the camera's last one for hold_s. In
        one camera a person crossing another is often not found, or found as one with them,
        for a few frame sets, and the initialization needs consecutive ones."""
        for c in range(len(found)):
            if index[c] >= 0:
                s.held[c] = (stamp_ns, found[c][index[c]].crop())
        hold = self.config.hold_s * 1e9
        cams = [c for c, (t, _) in sorted(s.held.items()) if have[c] and 0 <= stamp_ns - t <= hold]
        return Crops.from_rectangles(cams, [s.held[c][1] for c in cams])

    def step(self, images: Sequence[np.ndarray | None], stamp_ns: int) -> Look:
        have = np.array([im is not None for im in images], dtype=bool)
        crops: dict[int, Crops] = {}
        tracked: dict[int, np.ndarray] = {}
        for s in self.seats:
            kp = skeleton_of(s.predictor.predict(stamp_ns))
            if kp is not None:
                tracked[s.number] = kp
                c = self.pcm.crops_from_skeleton(kp, turned_fraction=BODY_FRACTION)
                crops[s.number] = c.select(have[c.camera])
        waiting = [s for s in self.seats if s.number not in tracked]
        now = _Now(images, stamp_ns, have, tracked, waiting, crops)
        if self._beside is None:
            search = self._plan(now)
            while search is not None:  # a search, then perhaps a second look ("again")
                search = self._found(search, run_search(self.seen, self.pcm.detect_people, search), now)
        else:
            done = self._beside.take()
            if done is not None:
                again = self._found(*done, now)
                if again is not None:
                    self._beside.offer(again)
            if self._beside.idle:
                search = self._plan(now)
                if search is not None:
                    self._beside.offer(search)
        for s in waiting:  # between searches: their held detector crops
            if s.number not in crops:
                crops[s.number] = self._crops(s, np.full(len(self.rig), -1), [[] for _ in self.rig], have, stamp_ns)
        pcm = self._infer(images, crops, tracked, stamp_ns)
        for s in waiting:
            if not s.had_body and s.number in pcm:
                self._follow(s, pcm[s.number], stamp_ns)
        order = [n for n in tracked if n in pcm]
        if len(order) > 1:  # a view says nothing of a person's keypoints another body covers
            covered = hidden_keypoints(self.rig, np.stack([tracked[n] for n in order]))
            pcm.update({n: without_hidden(pcm[n], h) for n, h in zip(order, covered)})
        views = {}
        for s in self.seats:
            own = pcm.get(s.number)
            if own is None:
                own = PcmViews.empty(len(KEYPOINTS), self.pcm.landmark.map_size, stamp_ns)
            company = len(tracked) - (s.number in tracked)  # the others with a skeleton (MarkerSlot)
            views[s.number] = dataclasses.replace(own, person=s.number, company=company)
        return Look(stamp_ns, views, {s.number: s.slot for s in self.seats}, self._untracked.copy(), self._left_out)

    def _follow(self, s: Seat, views: PcmViews, stamp_ns: int) -> None:
        """Before their skeleton, a person's held detector crops follow their hips as the
        landmark model sees them in the crops (MediaPipe's tracking: a detection once, then the
        landmarks place the next crop), where both hips are seen well and stay inside the crop:
        the initialization needs consecutive frame sets of crops on them, and a search (several
        frame periods beside a free-running graph's frame sets) finds them only now and then."""
        uv, w = camera_keypoints(views, len(self.rig))  # full-resolution pixels
        hips = uv[:, HIPS].mean(axis=1)  # (C, 2)
        if self._to_binned is not None:  # the crops are in the pixels the detector saw
            hips = hips @ self._to_binned[:2, :2].T + self._to_binned[:2, 2]
        seen = np.all(w[:, HIPS] >= FOLLOW_MIN_WEIGHT, axis=1)
        for c, (t, (centre, side, rotation)) in list(s.held.items()):
            if seen[c] and t < stamp_ns and np.linalg.norm(hips[c] - centre) < side / 2:
                s.held[c] = (stamp_ns, (hips[c].copy(), side, rotation))

    def _place(self, left: list[list[Detection]], waiting: list[Seat], crops: dict[int, Crops], have: np.ndarray,
               stamp_ns: int) -> tuple[list[list[Detection]], list[list[Detection]], np.ndarray, list[Seat]]:
        """A search's detections given out: to each waiting person the detections near where they
        were (their crops; where none, their last ones held), then to new seats, the best seen
        first. -> the detections left, per camera those given out, the (P, 3) hip centres of
        those given them, the waiting people given none."""
        cfg = self.config
        placed: list[list[Detection]] = [[] for _ in left]
        unplaced, points = [], []

        def give(index: np.ndarray, point: np.ndarray) -> list[list[Detection]]:
            for c, i in enumerate(index):
                if i >= 0:
                    placed[c].append(left[c][i])
            points.append(point)
            return explained(self.seen, left, point[None])

        for s in waiting:  # the lost first (near where they were), then newcomers
            choice = choose_subject(self.seen, left, s.seed)
            point = choice.point
            near = point is not None and np.linalg.norm(point - s.seed) <= cfg.reacquire_m
            crops[s.number] = self._crops(s, choice.index if near else np.full(len(self.rig), -1), left, have, stamp_ns)
            if near and point is not None:
                left = give(choice.index, point)
                if not s.had_body:  # not initialized yet: follow their detections
                    s.seed = point
            else:
                unplaced.append(s)
        while len(self.seats) < cfg.max_people:
            choice = choose_subject(self.seen, left, None)
            if choice.point is None:
                break
            s = self._new_seat(choice.point, stamp_ns)
            crops[s.number] = self._crops(s, choice.index, left, have, stamp_ns)
            left = give(choice.index, choice.point)
        return left, placed, np.array(points).reshape(-1, 3), unplaced

    def _plan(self, now: _Now) -> Search | None:
        """The search due at this frame set (_search_due), if any, and how closely it looks. For
        someone "waiting": every look of detect_people. For "newcomers": the whole images, and
        the closer look only in the cameras that found nobody while another one found someone (a
        newcomer in the room is seen whole by some camera; the closer look in every camera of an
        empty room costs 110 ms against 4 x 4 ms), and in every camera on every closer_every-th
        search (a person small in every view: far, or a low-resolution rig), with a turned look
        too (a lying newcomer); and the closer look in every camera in the first search after
        someone tracked is hidden who was not at the last such look (the detector, a one-person
        model, drew the most prominent person of an image and missed a smaller one beside them).
        "glance": the whole images only. "counting" the people left out (every slot taken): as
        for newcomers, but never every camera's closer look, which costs more than a frame period."""
        stamp_ns = now.stamp_ns
        kind = self._search_due(stamp_ns, now.waiting)
        if kind is None:
            return None
        self._last_detection_ns = stamp_ns
        if kind != "glance":
            self._last_full_ns = stamp_ns
        skeletons, pelvises, images = now.skeletons, now.pelvises, list(now.images)
        if self._beside is not None:  # the frame's buffer may be reused (shared memory) once the frame set is done
            images = [None if im is None else np.array(im, copy=True) for im in images]
        if kind == "waiting":
            return Search(kind, stamp_ns, list(images), skeletons, pelvises, turned=True, closer=True)
        if kind == "glance":
            return Search(kind, stamp_ns, list(images), skeletons, pelvises, turned=False, closer=False)
        greyed = frozenset(now.tracked)
        periodic = kind == "newcomers" and self._searches % self.config.closer_every == 0  # the first search too
        thorough = periodic or (kind == "newcomers" and not greyed <= self._greyed)
        if kind == "newcomers":
            self._searches += 1
        if thorough:
            self._greyed = greyed
        return Search(kind, stamp_ns, list(images), skeletons, pelvises, turned=periodic, closer=thorough,
                      fill=not thorough)

    def _found(self, search: Search, left: list[list[Detection]], now: _Now) -> Search | None:
        """A search's detections given out at the frame set stamped stamp_ns (_place) -> the
        second look it calls for, if any: the detector, a one-person model, draws the most
        prominent person of an image and misses a farther or smaller one, so before those just
        found have a skeleton to grey it looks once more with their detections greyed, for whom
        they hid ("again", closer but not turned)."""
        waiting, crops, have, stamp_ns = now.waiting, now.crops, now.have, now.stamp_ns
        if search.stamp_ns != stamp_ns:  # made at an earlier frame set: where are they now?
            left = found_again(self.seen, self.pcm.detector, now.images, now.skeletons, now.pelvises, left,
                               search.placed if search.kind == "again" else None)
        if search.kind == "again":
            left = self._place(left, [s for s in waiting if s.number in search.unplaced], crops, have, stamp_ns)[0]
            self._count(left)
            return None
        left, placed, points, unplaced = self._place(left, waiting, crops, have, stamp_ns)
        again = any(not s.had_body for s in unplaced) or \
            (search.kind == "newcomers" and len(self.seats) < self.config.max_people)
        if search.kind != "glance" and again and any(placed):  # on this frame set: `placed` are in it
            shown = [im if placed[c] else None for c, im in enumerate(detections_greyed(now.images, placed))]
            if self._beside is not None:
                shown = [None if im is None else np.array(im, copy=True) for im in shown]
            return Search("again", stamp_ns, shown, now.skeletons, np.concatenate([now.pelvises, points]),
                          turned=False, closer=True, first=left, placed=placed,
                          unplaced=frozenset(s.number for s in unplaced))
        if search.kind != "glance":
            self._count(left)
        return None

    def _count(self, left: list[list[Detection]]) -> None:
        """What the diagnostics say: the full looks' counts of whom nobody tracks."""
        self._untracked = np.array([len(d) for d in left])
        self._left_out = people_in(self.seen, left)

    def _infer(self, images: Sequence[np.ndarray | None], crops: dict[int, Crops], tracked: dict[int, np.ndarray],
               stamp_ns: int) -> dict[int, PcmViews]:
        """Everyone's crops through the landmark model at once, split back per person. Where
        other tracked bodies overlap a person's in a view, that person's crop is cut from a copy
        of the image with the others greyed (occlusion.others_greyed): the landmark model reads
        one body per crop."""
        order = [n for n, c in crops.items() if len(c)]
        if not order:
            return {}
        shown, parts = list(images), []
        if tracked:
            numbers = list(tracked)
            greyed = others_greyed(self.seen, images, np.stack([tracked[n] for n in numbers]),
                                   [numbers.index(n) if n in tracked else None for n in order])
            at = {key: len(shown) + k for k, key in enumerate(greyed)}
            shown += list(greyed.values())
            for i, n in enumerate(order):  # the greyed copies as extra images, then the rig's cameras again
                cam = crops[n].camera
                parts.append(dataclasses.replace(crops[n], camera=np.array([at.get((i, int(c)), int(c)) for c in cam])))
        else:
            parts = [crops[n] for n in order]
        views = self.pcm.landmark.infer(shown, _concat(parts), stamp_ns)
        views = dataclasses.replace(views, camera=np.concatenate([crops[n].camera for n in order]))
        if self._to_binned is not None:  # binned pixel -> map, composed with full pixel -> binned pixel
            views.image_to_map = views.image_to_map @ self._to_binned
        owner = np.concatenate([np.full(len(crops[n]), n) for n in order])
        return {n: views.select(owner == n) for n in order}
