"""`vmocap process --max-people N`: the multi-person tracker (method/people_tracker.py) over a
recording's image frame sets, every person's REP-155 outputs (outputs/people.py) into the bag;
process.py writes the first person's results on the subject topics as for one subject."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bag import BagWriter
from ..cameras.projection import Rig
from ..errors import BagError
from ..method.config import PipelineConfig
from ..method.pipeline import FrameResult, ImageSet, Pipeline


class PeopleSteps:
    """The tracker and its outputs; `step` takes one ImageSet, writes the bodies' messages and
    returns the first person's FrameResult (None: nobody has one)."""

    def __init__(self, tracker: Any, outputs: Any) -> None:
        self.tracker, self.outputs = tracker, outputs

    @classmethod
    def over(cls, pipe: Pipeline, rig: Rig, config: PipelineConfig, max_people: int, namespace: str) -> "PeopleSteps":
        """Over the pipeline's CNN (BlazePose's detector and landmark model)."""
        from ..method.people_tracker import PeopleConfig, PeopleTracker
        from ..outputs.people import PeopleOutputs

        source: Any = pipe.pcm
        if source is None or not hasattr(getattr(source, "pcm", None), "detect_people"):
            raise BagError("several people (max_people > 1) need the BlazePose CNN on camera images")
        if getattr(source, "binning", 1) != 1:
            raise BagError("several people (max_people > 1) with --binning: not supported yet")
        tracker = PeopleTracker(rig, source.pcm, config, PeopleConfig(max_people=max_people),
                                landmarks=getattr(source, "landmarks", "auto"),
                                crop_prediction=getattr(source, "crop_prediction", "rigid"))
        return cls(tracker, PeopleOutputs(namespace))

    def step(self, frame: ImageSet, writer: BagWriter, stats: dict[str, Any]) -> FrameResult | None:
        images: list[np.ndarray | None] = [None] * len(self.tracker.rig)
        for c, image in zip(frame.cameras, frame.images):
            images[int(c)] = image
        people = self.tracker.step(images, frame.stamp_ns)
        hri = self.outputs.step(people)
        for ch in hri.opened:
            writer.add_topic(ch.topic, ch.type, latched=ch.latched)
        for topic, ty, msg in hri.messages:
            writer.write(topic, ty, msg, frame.stamp_ns)
        tracked = sum(p.status == "tracking" for p in people.people)
        stats["people_max"] = max(stats.get("people_max", 0), tracked)
        stats["people_ended"] = stats.get("people_ended", 0) + len(people.ended)
        first = people.first
        return None if first is None else first.last
