"""Several people, the stages after the CNN: one marker stage and one skeleton stage per person
(the paper's lattice search, first IK, filter and second IK, each on its own person's heatmaps).

`MarkerSlot` is what vmocap_markers runs per slot with max_people > 1, `PeopleSkeletons` what
vmocap_skeleton runs; people_tracker.py composes both with people_look.py offline. The skeleton
side ends people by the rule the CNN's side applies too (people_config.ended_people), and keeps
the skeletons identified for people who ended for `remember_s`: a newcomer whose first fit has
one's link lengths is that person come back and is tracked at once (skeleton_stage.py,
REMEMBERED_LENGTHS), without the identification phase; they get a new id. A marker two people
found in one place is one body part of either: neither IK uses it (contested.py).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Iterable

import numpy as np

from ..cameras.projection import Rig
from ..pcm.views import PcmViews
from .config import MarkersConfig, SkeletonConfig
from .contested import contested
from .markers import MarkerStage
from .people_config import PeopleConfig, ended_people
from .results import Markers, TrackResult, feedback_of, nan_markers, skeleton_of
from .skeleton import Skeleton
from .skeleton_stage import SkeletonStage


class MarkerSlot:
    """The marker stage of whoever sits in one slot (PcmViews.person; people_look.py), a new one
    for each new person; a free slot (person -1) gives no markers. vmocap_markers runs one per
    slot; offline, people_tracker.py does."""

    def __init__(self, rig: Rig, config: MarkersConfig | None = None, reacquire: bool = False) -> None:
        # no re-acquisition of a weak keypoint at its maps' strongest peaks (MarkerStage._reacquire)
        # where the maps come from the CNN and another tracked person is about: their peaks are
        # then as likely the other's, and a triangulation of two bodies' peaks lands on neither.
        # A person tracked alone (PcmViews.company 0) keeps it, as the one-subject pipeline does:
        # without it, a limb that slid onto an untracked body beside them (a person whose track
        # just ended) stayed there while the rest of the body walked away. Maps drawn from the
        # person's own detections alone (multiperson.py) keep it always (`reacquire`). Whoever's
        # maps they are, they are read as drawn, not mirrored (mirror.py): at hug distance the
        # other body's limbs lie where this one's mirrored limbs would (and Shelf lost PCP with it).
        config = (config or MarkersConfig()).replace(unmirror_ratio=0.0)
        self.rig, self.alone_config = rig, config
        self.config = config if reacquire else config.replace(reacquire_weight=0.0)
        self.person = -1
        self.stage: MarkerStage | None = None

    def step(self, pcm: PcmViews) -> Markers:
        if pcm.person != self.person:
            self.person = pcm.person
            self.stage = MarkerStage(self.rig, self.config) if pcm.person >= 0 else None
        if self.stage is None:
            return nan_markers(pcm.stamp_ns)
        self.stage.config = self.alone_config if pcm.company == 0 else self.config
        return self.stage.step(pcm)

    def feedback(self, keypoints: np.ndarray | None) -> None:
        """The first-IK keypoints of this slot's person for the frame set just processed."""
        if self.stage is not None:
            self.stage.feedback(keypoints)


class PeopleSkeletons:
    """One skeleton stage per person; `step(stamp_ns, markers)` with every tracked person's
    markers of a frame set -> their results and the people who ended in it (module doc)."""

    def __init__(self, config: SkeletonConfig | None = None, people: PeopleConfig | None = None) -> None:
        self.people = people or PeopleConfig()
        # a track is output once confirm_frames agreed with it (or check_confirm_frames, the larger):
        # with other bodies about, a first fit may lean on one of them
        config = config or SkeletonConfig()
        self.config = config.replace(check_confirm_frames=max(config.check_confirm_frames, int(self.people.confirm_frames)))
        self._over: set[int] = set()  # people ended here: their markers, should the CNN's side still send some, are nobody's
        self.stages: dict[int, SkeletonStage] = {}
        self.seen_ns: dict[int, int] = {}  # person -> stamp of their last frame set with a skeleton (first: found)
        self.bodies: dict[int, np.ndarray | None] = {}  # person -> their last fed-back skeleton
        self._remembered: list[tuple[int, Skeleton]] = []  # (stamp ended, identified skeleton) of people who left
        self.subject: int | None = None  # the person on the subject topics (None: nobody now)
        self._subject_body: Skeleton | None = None  # their identified skeleton: who the subject is

    def _stage(self, number: int, stamp_ns: int) -> SkeletonStage:
        stage = self.stages.get(number)
        if stage is None:
            stage = self.stages[number] = SkeletonStage(self.config)
            stage.known = self._remembered_at(stamp_ns)
            self.seen_ns[number] = stamp_ns
        return stage

    def _remembered_at(self, stamp_ns: int) -> list[Skeleton]:
        """The identified skeletons of the people who ended within `remember_s` (older ones forgotten)."""
        keep = self.people.remember_s * 1e9
        self._remembered = [(t, sk) for t, sk in self._remembered if 0 <= stamp_ns - t <= keep]
        return [sk for _, sk in self._remembered]

    def _uncontested(self, markers: dict[int, Markers]) -> dict[int, Markers]:
        """Each person's markers without those another person found in the same place (contested.py)."""
        both = contested(markers, self.people.contested_m)
        return {n: replace(m, weights=np.where(both[n], 0.0, m.weights), contested=both[n]) if both[n].any() else m
                for n, m in markers.items()}

    def step(self, stamp_ns: int, markers: dict[int, Markers], gone: Iterable[int] = ()) -> tuple[dict[int, TrackResult], list[int]]:
        """The results of the people whose `markers` came (in their order; a person without
        markers in a frame set keeps their stage as it was) and the numbers of those ended now:
        by the end rule, or in `gone` (the CNN's side ended them first)."""
        results = {}
        markers = {n: m for n, m in markers.items() if n not in self._over}
        if self.people.contested_m > 0 and len(markers) > 1:
            markers = self._uncontested(markers)
        for n, m in markers.items():
            results[n] = r = self._stage(n, stamp_ns).step(m)
            self.bodies[n] = body = skeleton_of(feedback_of(r))
            if body is not None:
                self.seen_ns[n] = stamp_ns
        timed_out, merged = ended_people(stamp_ns, self.seen_ns, self.bodies, self.people)
        gone = timed_out | (set(gone) & set(self.stages))
        for n in sorted(gone):
            identified = self.stages[n].identified
            if identified is not None:
                self._remembered.append((stamp_ns, identified))
        ended = sorted(gone | merged)
        self._over.update(ended)
        for n in ended:
            self.stages.pop(n)
            self.seen_ns.pop(n, None)
            self.bodies.pop(n, None)
        self._choose_subject(stamp_ns, [n for n in results if n not in ended])
        return results, ended

    def _choose_subject(self, stamp_ns: int, stepped: list[int]) -> None:
        """The subject topics carry the first person found, and stay with them: once their link
        lengths are identified, a track of theirs that ended is waited for (their remembered
        skeleton recognized in a newcomer, `remember_s`) rather than handed to whoever else has a
        body, which a controller on the subject topics would take for the subject. Without an
        identified skeleton to wait for, the first found of those stepped in this frame set."""
        n = self.subject
        if n is not None and n in self.stages:
            if self.stages[n].identified is not None:
                self._subject_body = self.stages[n].identified
            return
        body = self._subject_body
        if body is not None and any(sk is body for sk in self._remembered_at(stamp_ns)):
            self.subject = next((m for m, st in sorted(self.stages.items()) if st.identified is body), None)
            return
        self._subject_body = None
        self.subject = min(stepped, default=None)
