"""Several people from the CNN (our extension; the paper tracks one person): one pipeline per
person, one CNN call per frame set.

Each tracked person's crops follow their own skeleton (the paper's feedback, III-B), so each
lattice search reads maps of its own person. The detector runs on images with the tracked
bodies' silhouettes greyed (`hidden`): every frame set while someone found is not initialized yet (their
crops come from it), every wait_search_s while someone lost waits (their last crops held in
between), and every `detect_every_s` while fewer than `max_people` are tracked, to find people
who walked in (`_search`: cheap whole-image looks, a closer look where needed). A detection
that a tracked person's pelvis projects onto is theirs; the others are grouped across cameras
(pcm/choice.py: hip centres triangulated from two cameras that project onto a detection in
both) into new people, the one seen by the most cameras first. The crops of everyone go
through the landmark model together (one batched call per frame set). A view says nothing of
a person's keypoints that another tracked body covers there (occlusion.py; the marker stage
does the same for keypoints outside its image).

People end when they have had no skeleton for `end_after_s` (left the room, or lost and not
found again near where they were), or when their skeleton lies on another person's (two tracks
converged on one body: the younger one ends). The skeletons identified for people who left
are kept for `remember_s`: a newcomer whose first fit has one's link lengths is that person
come back and is tracked at once (skeleton_stage.py, REMEMBERED_LENGTHS), without the
identification phase; they get a new id. Nothing here reads ground truth.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numpy as np

from ..cameras.projection import Rig, binning_affine
from ..errors import VmocapError
from ..keypoints import INDEX, KEYPOINTS
from ..pcm.choice import AGREE_FRACTION, choose_subject, detection_arrays
from ..pcm.crops import BODY_FRACTION, Crops
from ..pcm.detector import Detection
from ..pcm.views import PcmViews
from .config import PipelineConfig
from .landmarks import resolve
from .occlusion import hidden_keypoints, others_greyed, without_hidden
from .pipeline import FrameResult, Pipeline
from .prediction import BodyPredictor
from .results import seed_of, skeleton_of
from .skeleton import Skeleton

PELVIS = INDEX["pelvis"]
SearchKind = Literal["waiting", "newcomers", "counting"]  # what a detector search is for (_search)


class PeopleError(VmocapError):
    """A setting the multi-person tracker cannot work with."""


@dataclass
class PeopleConfig:
    max_people: int = 2  # people tracked at once; more in view are counted, not tracked
    detect_every_s: float = 0.5  # while fewer are tracked: the detector looks for newcomers this often
    count_every_s: float = 2.0  # while max_people are tracked: it counts the people left out this often (0: never)
    end_after_s: float = 1.0  # a person without a skeleton for this long is ended
    reacquire_m: float = 1.0  # a lost person is found again within this of their last hip centre
    same_body_m: float = 0.15  # two skeletons whose keypoints lie this close (median): one body
    hold_s: float = 0.25  # before their skeleton: a camera that lost a person's detection keeps its last crop this long
    wait_search_s: float = 0.1  # while someone waits for crops (found, lost): the detector runs this often
    closer_every: int = 4  # every this many searches for newcomers look closer in every camera (_search)
    remember_s: float = 60.0  # an ended person's skeleton is kept this long: if they come back, no new identification
    # a person's track (identified, or found again) is output once this many frame sets agreed
    # with its skeleton (SkeletonConfig.check_confirm_frames, the larger of the two): with other
    # bodies about, a first fit may lean on one of them or on a body half up off the floor
    confirm_frames: int = 3

    def __post_init__(self) -> None:
        if int(self.max_people) < 1:
            raise PeopleError(f"max_people must be at least 1, got {self.max_people}")
        if min(self.detect_every_s, self.count_every_s) < 0:
            raise PeopleError("detect_every_s and count_every_s must be >= 0")
        if int(self.confirm_frames) < 0:
            raise PeopleError(f"confirm_frames must be >= 0, got {self.confirm_frames}")


@dataclass
class Person:
    """One tracked person: `number` counts people in order of appearance (0, 1, ...); the
    outputs give them REP-155 ids."""

    number: int
    pipeline: Pipeline
    seed: np.ndarray  # (3,) their hip centre when last seen: where to look for them when lost
    seen_ns: int  # stamp of their last frame set with a skeleton (or of their detection)
    born_ns: int = 0  # stamp of the frame set they were found in (seen_ns stays it until their first skeleton)
    last: FrameResult | None = None
    held: dict[int, tuple[int, Any]] = field(default_factory=dict)  # camera -> (stamp, detector crop) before a skeleton

    @property
    def status(self) -> str:
        return "initializing" if self.last is None else self.last.status


@dataclass
class PeopleFrame:
    """One frame set: every person's result (people ended in it are not among them) and the
    people the detector saw but nobody tracks (per camera)."""

    stamp_ns: int
    people: list[Person]
    untracked: np.ndarray  # (C,) detections per camera nobody's skeleton explains, at the last look (-1: none yet)
    ended: list[int] = field(default_factory=list)  # numbers of the people ended in this frame set
    left_out: int = 0  # people two cameras see whom nobody tracks for want of a slot, at the last look

    @property
    def first(self) -> Person | None:
        """The person found first among those with a result: the one on the subject topics."""
        return min((p for p in self.people if p.last is not None), key=lambda p: p.number, default=None)

    @property
    def others_in_view(self) -> int:
        """The most detections nobody tracked explains in one camera at the detector's last
        look (0: none, or not looked yet)."""
        return int(max(self.untracked.max(initial=0), 0))


def _concat(crops: Sequence[Crops]) -> Crops:
    return Crops(np.concatenate([c.camera for c in crops]), np.concatenate([c.center for c in crops]),
                 np.concatenate([c.side for c in crops]), np.concatenate([c.rotation for c in crops]),
                 np.concatenate([c.valid for c in crops if c.valid is not None]))


def explained(rig: Rig, found: Sequence[Sequence[Detection]], pelvises: np.ndarray) -> list[list[Detection]]:
    """Per camera, the detections no tracked person (pelvises (P, 3)) projects onto: the
    detection's hip within AGREE_FRACTION of its hip-to-head length of a projected pelvis
    (pcm/choice.py's rule for one person's detections in two cameras)."""
    if len(pelvises) == 0:
        return [list(d) for d in found]
    uv, front = rig.project(np.asarray(pelvises, dtype=np.float64))  # (C, P, 2), (C, P)
    out: list[list[Detection]] = []
    for c, (dets, hips, reach) in enumerate(zip(found, *detection_arrays(found)[:2])):
        if not dets:
            out.append([])
            continue
        dist = np.linalg.norm(hips[:, None] - uv[c][None], axis=-1)  # (n, P)
        taken = (front[c][None] & (dist < AGREE_FRACTION * np.maximum(reach[:, None], 1e-6))).any(axis=1)
        out.append([d for d, t in zip(dets, taken) if not t])
    return out


def hidden(rig: Rig, images: Sequence[np.ndarray | None], skeletons: np.ndarray) -> list:
    """The images with each skeleton's ((P, 25, 3) keypoints) silhouette greyed
    (occlusion.others_greyed): the person detector finds the most prominent people of an image
    and misses a smaller one beside them (the BlazePose detector is a one-person model), so the
    people already tracked are taken out of the search for others. Their silhouettes, not their
    boxes: from most cameras a person standing beside a tracked one lies inside that one's box."""
    if len(skeletons) == 0:
        return list(images)
    greyed = others_greyed(rig, images, skeletons, [None])
    return [greyed.get((0, c), im) for c, im in enumerate(images)]


class PeopleTracker:
    """Up to `people.max_people` people through one BlazePose PCM source (pcm.pipeline.BlazePosePcm:
    `detect_people`, `crops_from_skeleton`, `landmark`); `step(images,
    stamp_ns)` per frame set (module doc)."""

    def __init__(self, rig: Rig, pcm: Any, config: PipelineConfig | None = None, people: PeopleConfig | None = None,
                 landmarks: str = "blazepose", crop_prediction: str = "rigid", binning: int = 1) -> None:
        self.rig, self.pcm = rig, pcm
        # binning > 1: the images come reduced that many times (REP 104) and `pcm` works on the
        # rig as they show it; the detections are read with that rig, and the views' affines
        # are returned for full-resolution pixels, so the pipelines keep the rig and its bounds
        self.seen = rig.binned(binning) if binning > 1 else rig
        self._to_binned = binning_affine(binning) if binning > 1 else None
        cfg = config or PipelineConfig()
        self.people_config = people or PeopleConfig()
        confirm = max(cfg.skeleton.check_confirm_frames, int(self.people_config.confirm_frames))
        # no re-acquisition of a weak keypoint at its maps' strongest peaks (MarkerStage._reacquire):
        # with others in the room those peaks are as likely theirs, and a triangulation of two
        # bodies' peaks lands on neither; a lost person is found again by the detector instead
        self.config = cfg.replace(landmarks=resolve(cfg.skeleton.landmarks, landmarks), check_confirm_frames=confirm,
                                  reacquire_weight=0.0)
        self.crop_prediction = crop_prediction
        self.people: list[Person] = []
        self._next = 0
        self._last_detection_ns: int | None = None
        self._searches = 0  # searches for newcomers so far
        self._untracked = np.full(len(rig), -1)  # per camera, the detections nobody tracks at the last look
        self._left_out = 0  # people (seen by two cameras) not tracked for want of a slot, at the last look
        self._remembered: list[tuple[int, Skeleton]] = []  # (stamp ended, identified skeleton) of people who left

    def _new_person(self, seed: np.ndarray, stamp_ns: int) -> Person:
        pipe = Pipeline(self.rig, self.config)
        pipe.predictor = BodyPredictor(enabled=self.crop_prediction == "rigid")
        keep = self.people_config.remember_s * 1e9
        self._remembered = [(t, sk) for t, sk in self._remembered if 0 <= stamp_ns - t <= keep]
        pipe.skeleton.known = [sk for _, sk in self._remembered]
        p = Person(self._next, pipe, np.asarray(seed, dtype=np.float64), stamp_ns, stamp_ns)
        self._next += 1
        self.people.append(p)
        return p

    def _search_due(self, stamp_ns: int, waiting: list[Person]) -> SearchKind | None:
        """Which search this frame set runs (_search), if any: "waiting" every frame set while
        someone found is not initialized yet, every wait_search_s while someone lost waits (their
        last detector crops are held in between: a full search costs several frame periods);
        "newcomers" every detect_every_s while fewer than max_people are tracked; "counting"
        every count_every_s while max_people are (who is left out)."""
        cfg = self.people_config
        kind: SearchKind
        if waiting:
            # a person found and not yet initialized gets fresh detections every frame set: the
            # initialization triangulates consecutive frame sets of a body that may walk fast
            kind, every = "waiting", 0.0 if any(p.seen_ns == p.born_ns for p in waiting) else cfg.wait_search_s
        elif len(self.people) < cfg.max_people:
            kind, every = "newcomers", cfg.detect_every_s
        elif cfg.count_every_s > 0:
            kind, every = "counting", cfg.count_every_s
        else:
            return None
        last = self._last_detection_ns
        return kind if last is None or not 0 <= stamp_ns - last < every * 1e9 else None

    def _crops(self, p: Person, index: np.ndarray, found: Sequence[Sequence[Detection]], have: np.ndarray,
               stamp_ns: int) -> Crops:
        """A person's detector crops (MediaPipe's rule, rotated already): this frame set's
        detection per camera (index (C,), -1: none), else the camera's last one for hold_s. In
        one camera a person crossing another is often not found, or found as one with them,
        for a few frame sets, and the initialization needs consecutive ones."""
        for c in range(len(found)):
            if index[c] >= 0:
                p.held[c] = (stamp_ns, found[c][index[c]].crop())
        hold = self.people_config.hold_s * 1e9
        cams = [c for c, (t, _) in sorted(p.held.items()) if have[c] and 0 <= stamp_ns - t <= hold]
        return Crops.from_rectangles(cams, [p.held[c][1] for c in cams])

    def step(self, images: Sequence[np.ndarray | None], stamp_ns: int) -> PeopleFrame:
        cfg = self.people_config
        have = np.array([im is not None for im in images], dtype=bool)
        crops: dict[int, Crops] = {}
        tracked: dict[int, np.ndarray] = {}
        for p in self.people:
            kp = skeleton_of(p.pipeline.predictor.predict(stamp_ns))
            if kp is not None:
                tracked[p.number] = kp
                c = self.pcm.crops_from_skeleton(kp, turned_fraction=BODY_FRACTION)
                crops[p.number] = c.select(have[c.camera])
        waiting = [p for p in self.people if p.number not in tracked]
        search = self._search_due(stamp_ns, waiting)
        if search is not None:
            self._last_detection_ns = stamp_ns
            skeletons = np.array(list(tracked.values())).reshape(-1, len(KEYPOINTS), 3)
            pelvises = skeletons[:, PELVIS]
            pelvises = pelvises[np.isfinite(pelvises).all(axis=1)]
            left = self._search(images, skeletons, pelvises, search)
            # the lost first (near where they were), then newcomers, the best seen first
            for p in waiting:
                choice = choose_subject(self.seen, left, p.seed)
                point = choice.point
                near = point is not None and np.linalg.norm(point - p.seed) <= cfg.reacquire_m
                crops[p.number] = self._crops(p, choice.index if near else np.full(len(self.rig), -1), left, have,
                                              stamp_ns)
                if near and point is not None:
                    left = explained(self.seen, left, point[None])
                    if p.seen_ns == p.born_ns:  # not initialized yet: follow their detections
                        p.seed = point
            while len(self.people) < cfg.max_people:
                choice = choose_subject(self.seen, left, None)
                if choice.point is None:
                    break
                p = self._new_person(choice.point, stamp_ns)
                crops[p.number] = self._crops(p, choice.index, left, have, stamp_ns)
                left = explained(self.seen, left, choice.point[None])
            self._untracked = np.array([len(d) for d in left])
            self._left_out = self._people_in(left)
        for p in waiting:  # between searches: their held detector crops
            if p.number not in crops:
                crops[p.number] = self._crops(p, np.full(len(self.rig), -1), [[] for _ in self.rig], have, stamp_ns)
        pcm = self._infer(images, crops, tracked, stamp_ns)
        order = [n for n in tracked if n in pcm]
        if len(order) > 1:  # a view says nothing of a person's keypoints another body covers
            covered = hidden_keypoints(self.rig, np.stack([tracked[n] for n in order]))
            pcm.update({n: without_hidden(pcm[n], h) for n, h in zip(order, covered)})
        for p in self.people:
            own = pcm.get(p.number)
            p.last = p.pipeline.step(own if own is not None else PcmViews.empty(len(KEYPOINTS), self.pcm.landmark.map_size,
                                                                               stamp_ns))
            body, seed = skeleton_of(p.pipeline.feedback), seed_of(p.pipeline.feedback)
            if body is not None:
                p.seed, p.seen_ns = body[PELVIS].copy(), stamp_ns
                p.held.clear()
            elif seed is not None:  # their track slid onto another body: look where they were heading
                p.seed = seed
        ended = self._end(stamp_ns)
        return PeopleFrame(stamp_ns, list(self.people), self._untracked.copy(), ended, self._left_out)

    def _people_in(self, found: list[list[Detection]]) -> int:
        """How many people the detections make, grouped across cameras as newcomers are."""
        n = 0
        for _ in range(sum(len(d) for d in found)):  # each person takes at least one detection
            point = choose_subject(self.seen, found, None).point
            if point is None:
                break
            n += 1
            found = explained(self.seen, found, point[None])
        return n

    def _search(self, images: Sequence[np.ndarray | None], skeletons: np.ndarray, pelvises: np.ndarray,
                kind: SearchKind) -> list[list[Detection]]:
        """Per camera, the detections no tracked person explains, with the tracked bodies hidden.
        For someone "waiting": every look of detect_people. For "newcomers": the
        whole images, and the closer look only in the cameras that found nobody while another
        one found someone (a newcomer in the room is seen whole by some camera; the closer look
        in every camera of an empty room costs 110 ms against 4 x 4 ms), and in every camera on
        every closer_every-th search (a person small in every view: far, or a low-resolution
        rig); no turned look (a lying newcomer is found when they get up). "counting" the people
        left out (every slot taken): as for newcomers, but never every camera's closer look,
        which costs more than a frame period."""
        shown = hidden(self.seen, images, skeletons)
        if kind == "waiting":
            return explained(self.seen, self.pcm.detect_people(shown), pelvises)
        thorough = kind == "newcomers" and self._searches % self.people_config.closer_every == 0  # the first search too
        if kind == "newcomers":
            self._searches += 1
        left = explained(self.seen, self.pcm.detect_people(shown, turned=thorough, closer=thorough), pelvises)
        empty = [c for c, d in enumerate(left) if not d and shown[c] is not None]
        if not thorough and empty and len(empty) < sum(im is not None for im in shown):
            again = self.pcm.detect_people([shown[c] if c in empty else None for c in range(len(shown))], turned=False)
            closer = explained(self.seen, again, pelvises)
            left = [closer[c] if c in empty else d for c, d in enumerate(left)]
        return left

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

    def _end(self, stamp_ns: int) -> list[int]:
        cfg = self.people_config
        gone = {p.number for p in self.people if not 0 <= stamp_ns - p.seen_ns <= cfg.end_after_s * 1e9}
        self._remembered += [(stamp_ns, p.pipeline.skeleton.identified) for p in self.people
                             if p.number in gone and p.pipeline.skeleton.identified is not None]
        # two skeletons on one body (a track that jumped to its neighbour): the younger ends
        fed = [(p.number, skeleton_of(p.pipeline.feedback)) for p in self.people if p.number not in gone]
        bodies = [(n, kp) for n, kp in fed if kp is not None]
        for i, (na, a) in enumerate(bodies):
            for nb, b in bodies[i + 1:]:
                d = np.linalg.norm(a - b, axis=1)
                if np.isfinite(d).any() and float(np.nanmedian(d)) < cfg.same_body_m:
                    gone.add(max(na, nb))
        self.people = [p for p in self.people if p.number not in gone]
        return sorted(gone)
