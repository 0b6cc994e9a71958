"""`vmocap process --max-people N`: the multi-person tracker (method/people_tracker.py) over a
recording's image frame sets, every person's REP-155 outputs (outputs/people.py) into the bag;
process.py writes the first person's results on the subject topics as for one subject.

With `--offline` the live pass keeps every frame set's people instead of writing them; then each
person's own results go through the whole-recording pass (method/offline.py: their skeleton
identified over all their frames, smoothed without lag), and the outputs are written from those,
frame set by frame set, as the live pass would have written them."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Iterator

import numpy as np

from ..bag import BagWriter
from ..cameras.projection import Rig
from ..errors import BagError
from ..method.config import PipelineConfig
from ..method.pipeline import FrameResult, ImageSet, Pipeline
from ..method.results import FEEDBACK_STATUSES, TrackResult
from ..pcm.views import PcmViews


class PeopleSteps:
    """The tracker and its outputs; `step` takes one ImageSet, writes the bodies' messages (or,
    offline, keeps the frame set for `offline`) and returns the first person's FrameResult
    (None: nobody has one)."""

    def __init__(self, tracker: Any, outputs: Any, offline: bool = False) -> None:
        self.tracker, self.outputs, self.offline = tracker, outputs, offline
        self.kept: list[Any] = []  # offline: every frame set's PeopleFrame, its people's maps dropped

    @classmethod
    def over(cls, pipe: Pipeline, rig: Rig, config: PipelineConfig, max_people: int, namespace: str,
             offline: bool = False) -> "PeopleSteps":
        """Over the pipeline's CNN (BlazePose's detector and landmark model)."""
        from ..method.people_config import PeopleConfig
        from ..method.people_tracker import PeopleTracker
        from ..outputs.people import PeopleOutputs

        source: Any = pipe.pcm
        if source is None or not hasattr(getattr(source, "pcm", None), "detect_people"):
            raise BagError("several people (max_people > 1) need the BlazePose CNN on camera images")
        tracker = PeopleTracker(rig, source.pcm, config, PeopleConfig(max_people=max_people),
                                landmarks=getattr(source, "landmarks", "auto"),
                                crop_prediction=getattr(source, "crop_prediction", "rigid"),
                                binning=getattr(source, "binning", 1))
        return cls(tracker, PeopleOutputs(namespace), offline)

    def step(self, frame: ImageSet, writer: BagWriter, stats: dict[str, Any]) -> FrameResult | None:
        images: list[np.ndarray | None] = [None] * len(self.tracker.rig)
        for c, image in zip(frame.cameras, frame.images):
            images[int(c)] = image
        people = self.tracker.step(images, frame.stamp_ns)
        if self.offline:
            # the maps are the bulk of a result (2 MB a frame set) and the whole-recording pass
            # reads only the skeleton stage's results
            self.kept.append(replace(people, people=[replace(p, last=_without_maps(p.last)) for p in people.people]))
        else:
            self._write(people, writer)
        tracked = sum(p.status == "tracking" for p in people.people)
        stats["people_max"] = max(stats.get("people_max", 0), tracked)
        stats["people_ended"] = stats.get("people_ended", 0) + len(people.ended)
        first = people.first
        return None if first is None else first.last

    def _write(self, people: Any, writer: BagWriter) -> None:
        hri = self.outputs.step(people)
        for ch in hri.opened:
            writer.add_topic(ch.topic, ch.type, latched=ch.latched)
        for topic, ty, msg in hri.messages:
            writer.write(topic, ty, msg, people.stamp_ns)

    @property
    def followed(self) -> bool:
        """Offline: someone's live pass got as far as the skeleton (enough for the whole-recording pass)."""
        return any(p.last is not None and p.last.status in FEEDBACK_STATUSES for f in self.kept for p in f.people)

    def reconstruct(self, config: PipelineConfig, writer: BagWriter, stats: dict[str, Any],
                    progress: bool = False) -> Iterator[FrameResult | None]:
        """Offline: each person's whole-recording pass, then every kept frame set's bodies
        written from it; yields each frame set's first person's result (None: nobody)."""
        from ..method.offline import OfflineError, identify_and_reconstruct

        lives: dict[int, list[TrackResult]] = {}
        for f in self.kept:
            for p in f.people:
                if p.last is not None:
                    lives.setdefault(p.number, []).append(p.last.skeleton)
        done: dict[int, dict[int, TrackResult]] = {}
        never: list[int] = []
        for number, results in lives.items():
            try:
                out, _ = identify_and_reconstruct(results, config.skeleton, progress=progress)
            except OfflineError:  # never tracked: their live results (no output) stand
                never.append(number)
                continue
            done[number] = {r.stamp_ns: r for r in out}
        stats["people_offline"] = {"reconstructed": len(done), "never_tracked": len(never)}
        for f in self.kept:
            people = []
            for p in f.people:
                new = None if p.last is None else done.get(p.number, {}).get(p.last.stamp_ns)
                people.append(p if new is None else replace(p, last=replace(p.last, skeleton=new)))
            frame = replace(f, people=people)
            self._write(frame, writer)
            first = frame.first
            yield None if first is None else first.last


def _without_maps(res: FrameResult | None) -> FrameResult | None:
    if res is None:
        return None
    return replace(res, pcm=PcmViews.empty(len(res.pcm.keypoints), 1, res.stamp_ns))
