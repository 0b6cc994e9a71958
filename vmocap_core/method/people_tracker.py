"""Several people from the CNN (our extension; the paper tracks one person), offline: the CNN's
side (people_look.py: who is in view, each person's heatmaps from one CNN call per frame set)
and one marker and skeleton stage per person (people_stages.py), composed frame set by frame
set as the node graph composes them in vmocap_pcm, vmocap_markers and vmocap_skeleton with
max_people > 1, each person's feedback going back to their own lattice search and crops.

    images --PeopleLook--> {person: PcmViews} --MarkerSlot each--> {person: Markers}
       ^                                         --PeopleSkeletons--> {person: TrackResult}, ended
       '-------- each person's first-IK keypoints of frame t-1 ------------'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..cameras.projection import Rig
from .config import PipelineConfig
from .landmarks import resolve
from .people_config import PeopleConfig
from .people_look import PeopleLook
from .people_stages import MarkerSlot, PeopleSkeletons
from .pipeline import FrameResult
from .results import TrackResult, feedback_of


@dataclass
class Person:
    """One tracked person: `number` counts people in order of appearance (0, 1, ...); the
    outputs give them REP-155 ids."""

    number: int
    last: FrameResult | None = None

    @property
    def status(self) -> str:
        return "initializing" if self.last is None else self.last.status

    @property
    def result(self) -> TrackResult | None:
        """Their skeleton stage's result of the frame set (None: none yet)."""
        return None if self.last is None else self.last.skeleton

    @property
    def feedback(self) -> np.ndarray | None:
        """What their next frame set's crops and lattice search start from (results.feedback_of)."""
        return None if self.last is None else self.last.feedback


@dataclass
class PeopleFrame:
    """One frame set: the result of every person stepped in it (people ended in it are not among
    them) and the people the detector saw but nobody tracks (per camera)."""

    stamp_ns: int
    people: list[Person]
    untracked: np.ndarray  # (C,) detections per camera nobody's skeleton explains, at the last look (-1: none yet)
    ended: list[int] = field(default_factory=list)  # numbers of the people ended in this frame set
    left_out: int = 0  # people two cameras see whom nobody tracks for want of a slot, at the last look
    subject: int | None = None  # the number of the person on the subject topics (PeopleSkeletons.subject)

    @property
    def first(self) -> Person | None:
        """The one on the subject topics, when stepped in this frame set with a result."""
        return next((p for p in self.people if p.number == self.subject and p.last is not None), None)

    @property
    def others_in_view(self) -> int:
        """The most detections nobody tracked explains in one camera at the detector's last
        look (0: none, or not looked yet)."""
        return int(max(self.untracked.max(initial=0), 0))


class PeopleTracker:
    """Up to `people.max_people` people through one BlazePose PCM source (pcm.pipeline.BlazePosePcm),
    or through another look (`look`: multiperson.DetectionsLook, people from 2D detections);
    `step(images, stamp_ns)` per frame set (module doc)."""

    def __init__(self, rig: Rig, pcm: Any, config: PipelineConfig | None = None, people: PeopleConfig | None = None,
                 landmarks: str = "blazepose", crop_prediction: str = "rigid", binning: int = 1, look: Any = None) -> None:
        self.rig, self.pcm = rig, pcm
        self.people_config = people or PeopleConfig()
        cfg = config or PipelineConfig()  # the CNN's keypoints are its landmarks, not joint centres
        self.config = cfg.replace(landmarks=resolve(cfg.skeleton.landmarks, landmarks))
        self.look = look if look is not None else PeopleLook(rig, pcm, self.people_config, crop_prediction, binning)
        reacquire = bool(getattr(self.look, "own_maps", False))  # maps of the person's own detections alone
        self.slots = [MarkerSlot(rig, self.config.markers, reacquire) for _ in range(self.people_config.max_people)]
        self.skeletons = PeopleSkeletons(self.config.skeleton, self.people_config)
        self.people: dict[int, Person] = {}

    @property
    def seen(self) -> Rig:
        """The rig as the images show it (binned)."""
        return self.look.seen

    def step(self, images: Sequence[Any], stamp_ns: int) -> PeopleFrame:
        """One frame set (the look's input: images, or 2D people per view): the people the look
        gives heatmaps for are stepped; the others keep their stages as they were."""
        look = self.look.step(images, stamp_ns)
        markers = {n: self.slots[look.slots[n]].step(views) for n, views in look.views.items()}
        results, ended = self.skeletons.step(stamp_ns, markers)
        for n, result in results.items():
            fb = feedback_of(result)
            self.slots[look.slots[n]].feedback(fb)
            self.look.feedback(n, result.feedback_stamp, fb, result.status == "tracking")
            person = self.people.setdefault(n, Person(n))
            person.last = FrameResult(look.views[n], markers[n], result, fb)
        self.look.end(ended)
        for n in ended:
            self.people.pop(n, None)
        stepped = [p for n, p in self.people.items() if n in results]
        return PeopleFrame(stamp_ns, stepped, look.untracked, ended, look.left_out, self.skeletons.subject)
