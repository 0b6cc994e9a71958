"""vmocap_skeleton with max_people > 1: everyone in view. Each slot's markers
(NS/people/slotK/markers) -> one skeleton stage per person (vmocap_core.method.people_stages:
weighted IK, low-pass filter, second IK) -> each person a REP-155 body, the first one found
also on the subject topics (NS/joint_states, NS/keypoints, robot_description ...); each slot's
feedback back to its crops and lattice search, then NS/feedback (the frame set's answer)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vmocap_core import graph_config
from vmocap_core.bag import messages as M
from vmocap_core.keypoints import KEYPOINTS
from vmocap_core.method.held import lengths_word
from vmocap_core.outputs.messages import CLOUD, markers_from_message, result_messages

from ..subject import hri_outputs, skeleton_outputs
from ..transport import Transport
from .base import STREAM_DEPTH, VmocapNode

PENDING_KEPT = 20  # frame sets waiting for their other slots' markers; older ones are dropped (counted)


class PeopleSkeletonNode(VmocapNode):
    """Every slot's markers of a frame set -> PeopleSkeletons -> bodies, subject topics, feedback."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_skeleton") -> None:
        super().__init__(name, config, overrides, transport)
        from vmocap_core.method.people_config import PeopleConfig
        from vmocap_core.method.people_stages import PeopleSkeletons
        from vmocap_core.outputs.people import PeopleOutputs

        p = self.p
        self.slots = range(p["max_people"])
        self.skeletons = PeopleSkeletons(config.skeleton_config(name, p), PeopleConfig(
            max_people=p["max_people"], end_after_s=p["end_after_s"], remember_s=p["remember_s"],
            confirm_frames=p["confirm_frames"], contested_m=p["contested_m"]))
        t = self.topics
        self.pubs = {t.slot(k).feedback: self.publisher(CLOUD, t.slot(k).feedback, depth=50, latched=True)
                     for k in self.slots}
        # the frame set's answer (lockstep, cameras/lockstep.py): the first person's feedback
        self.pubs[t.feedback] = self.publisher(CLOUD, t.feedback, depth=50, latched=True)
        for topic, ty in ((t.joint_states, "sensor_msgs/msg/JointState"), (t.keypoints, CLOUD),
                          (t.skeleton, "visualization_msgs/msg/MarkerArray")):
            self.pubs[topic] = self.publisher(ty, topic, depth=STREAM_DEPTH)
        self.subject, extra = skeleton_outputs(self)
        self.pubs.update(extra)
        self.hri = hri_outputs(self, None, self.pubs, PeopleOutputs(t.ns, subject=self.subject, tf=t.tf in self.pubs))
        for k in self.slots:
            self.subscribe(CLOUD, t.slot(k).markers, lambda m, k=k: self._on_markers(k, m), depth=p["queue_depth"],
                           latched=True)
        self.pending: dict[int, dict[int, Any]] = {}  # frame set stamp -> slot -> Markers
        self.seated: dict[int, int] = {}  # slot -> the person in it at the last frame set
        self.counts = {"frames": 0, "incomplete": 0}
        self.last: Any = None  # the last PeopleFrame

    def _on_markers(self, slot: int, msg: dict) -> None:
        markers = markers_from_message(msg)
        got = self.pending.setdefault(markers.stamp_ns, {})
        got[slot] = markers
        if len(got) < len(self.slots):
            return
        for stamp in [s for s in self.pending if s < markers.stamp_ns]:  # older ones will not be completed
            del self.pending[stamp]
            self.counts["incomplete"] += 1
        self._step(markers.stamp_ns, self.pending.pop(markers.stamp_ns))
        while len(self.pending) > PENDING_KEPT:
            self.pending.pop(min(self.pending))
            self.counts["incomplete"] += 1

    def _step(self, stamp_ns: int, by_slot: dict[int, Any]) -> None:
        """One frame set: every person's stage, each slot's feedback, then the outputs."""
        from vmocap_core.method.people_tracker import PeopleFrame, Person
        from vmocap_core.method.pipeline import FrameResult
        from vmocap_core.method.results import feedback_of
        from vmocap_core.pcm.views import PcmViews

        t0 = time.perf_counter()
        markers = {m.person: m for _, m in sorted(by_slot.items()) if m.person >= 0}
        # a slot whose person changed: vmocap_pcm ended them (by the rule applied here too, or first)
        gone = [n for k, n in self.seated.items() if n >= 0 and by_slot[k].person != n]
        self.seated = {k: m.person for k, m in by_slot.items()}
        results, ended = self.skeletons.step(stamp_ns, markers, gone)
        people = []
        for k, m in sorted(by_slot.items()):
            r = results.get(m.person)
            fb = None if r is None else feedback_of(r)
            self.pubs[self.topics.slot(k).feedback](M.keypoint_cloud(stamp_ns if r is None else r.feedback_stamp, fb))
            if r is not None and m.person not in ended:
                people.append(Person(m.person, FrameResult(PcmViews.empty(len(KEYPOINTS), 1, stamp_ns), m, r, fb)))
        frame = PeopleFrame(stamp_ns, sorted(people, key=lambda p: p.number), np.full(len(self.rig or []), -1), ended,
                            subject=self.skeletons.subject)
        first = frame.first
        pubs = self.pubs
        if first is not None and first.result is not None:
            for topic, _ty, out in result_messages(self.topics, first.result, subject=self.subject,
                                                   wanted=lambda tp: tp in pubs and tp != self.topics.feedback
                                                   and pubs[tp].wanted()):
                if topic in pubs:
                    pubs[topic](out)
        pubs[self.topics.feedback](M.keypoint_cloud(stamp_ns, None if first is None else first.feedback))
        if self.hri is not None:
            self.hri(frame)
        self.last = frame
        self.counts["frames"] += 1
        self.proc.add(1e3 * (time.perf_counter() - t0))
        self.record_age(stamp_ns)

    def status(self) -> dict[str, Any]:
        if self.counts["incomplete"]:
            self.watch_dropped(self.counts["incomplete"], "frame sets without every slot's markers")
        people = [] if self.last is None else self.last.people
        # each person by body id (their number without the REP-155 outputs)
        named = [((self.hri.core.body_id(p.number) if self.hri is not None else None) or p.number, p) for p in people]
        stages = self.skeletons.stages
        return dict(self.counts, max_people=self.p["max_people"], people=len(people),
                    tracking=sum(p.status == "tracking" for p in people),
                    statuses=", ".join(f"{n}: {p.status}" for n, p in named) or "nobody",
                    link_lengths=", ".join(f"{n}: {lengths_word(stages[p.number])}" for n, p in named
                                           if p.number in stages) or "-")
