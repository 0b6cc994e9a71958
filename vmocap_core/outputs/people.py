"""ROS4HRI (REP-155) outputs of several tracked people, without ROS.

Each person of method/people_tracker.py is a body with its own id (hri.HriOutputs per person,
the ids drawn from one set, so no two bodies share one): `/humans/bodies/tracked` lists every
body tracked in the frame set (one message, an empty list when nobody is), and each body has
its `urdf` and `joint_states` as for one subject, plus its keypoints (the same PointCloud2 as
`NS/keypoints`) on `NS/bodies/<id>/keypoints`. An ended person's topics close RETIRE_S after
their end, as a single subject's do. With `tf`, each body's /tf (`body_<id>`, its suffixed
segments) as for one subject, and one /tf_static holding every body's fixed frames with the
graph's own (`subject`, streams.SubjectOutputs): /tf_static is latched with depth 1, so a
message per body would leave a late listener only the last body's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bag import messages as M
from ..graph_config import Topics
from .hri import GRACE_S, IDS_LIST, RETIRE_S, TRACKED, Channel, HriFrame, HriOutputs, body_channels
from .messages import CLOUD
from .streams import SubjectOutputs
from .tf import TF_TYPE, Transforms, tf_message


def keypoints_topic(namespace: str, body_id: str) -> str:
    return f"{namespace}/bodies/{body_id}/keypoints"


class PeopleOutputs:
    """`step(frame)` of a PeopleFrame -> the HriFrame (topics to open, messages, topics to close)."""

    def __init__(self, namespace: str = Topics().ns, seed: int | None = None, grace_s: float = GRACE_S,
                 retire_s: float = RETIRE_S, subject: SubjectOutputs | None = None, tf: bool = False) -> None:
        self.namespace, self.seed, self.grace_s, self.retire_s = namespace, seed, grace_s, retire_s
        self.subject, self.tf = subject, tf
        self._fixed: dict[int, Transforms] = {}  # person number -> their body's fixed frames
        self._used: set[str] = set()
        self._bodies: dict[int, HriOutputs] = {}
        self._closing: dict[str, int] = {}  # id of an ended person -> stamp of their end

    def body_id(self, number: int) -> str | None:
        hri = self._bodies.get(number)
        return None if hri is None else hri.body_id

    def _channels(self, body_id: str) -> list[Channel]:
        return body_channels(body_id) + [Channel(keypoints_topic(self.namespace, body_id), CLOUD, False)]

    def step(self, frame: Any, wanted: Any = None) -> HriFrame:
        """wanted(topic): False where nobody listens (messages not built; the tracked list always is)."""
        t = frame.stamp_ns
        out = HriFrame()
        ids: list[str] = []
        described = False  # a body's fixed frames are new: /tf_static again, with everyone's
        for p in frame.people:
            if p.last is None:
                continue
            hri = self._bodies.get(p.number)
            if hri is None:
                seed = None if self.seed is None else self.seed + p.number
                hri = self._bodies[p.number] = HriOutputs(None, tf=self.tf, seed=seed, grace_s=self.grace_s,
                                                          retire_s=self.retire_s, used=self._used)
            result = p.last.skeleton
            f = hri.step(result, wanted)
            body = hri.body_id
            if f.opened and body is not None:  # a new id: its channels, ours included
                out.opened += self._channels(body)
            out.closed += [c.topic for i in f.retired for c in self._channels(i)]  # ours included
            out.messages += [m for m in f.messages if m[0] not in (TRACKED, Topics.tf_static)]
            if any(m[0] == Topics.tf_static for m in f.messages) and hri.fixed_frames is not None:
                self._fixed[p.number] = hri.fixed_frames
                described = True
            if body is not None and result.status == "tracking":
                ids.append(body)
                topic = keypoints_topic(self.namespace, body)
                if wanted is None or wanted(topic):
                    out.messages.append((topic, CLOUD, M.keypoint_cloud(t, result.keypoints,
                                                                        np.nan_to_num(result.confidence, nan=0.0))))
        if described:
            static = Transforms.concat(list(self._fixed.values()))
            if self.subject is not None:  # the graph's own fixed frames in the same message
                self.subject.extra_static = static
                static = self.subject.static(t)
            out.messages.append((Topics.tf_static, TF_TYPE, tf_message(t, static)))
        for n in frame.ended:  # people the tracker ended: their id ends now, the topics later
            self._fixed.pop(n, None)
            hri = self._bodies.pop(n, None)
            if hri is not None and hri.body_id is not None:
                self._closing[hri.body_id] = t
        gone = [i for i, end in self._closing.items() if not 0 <= t - end <= self.retire_s * 1e9]
        for i in gone:
            del self._closing[i]
            out.closed += [c.topic for c in self._channels(i)]
        out.messages.append((TRACKED, IDS_LIST, {"header": M.header(t), "ids": ids}))
        return out
