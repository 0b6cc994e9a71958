"""vmocap_skeleton: weighted IK, low-pass filter and second IK (paper II-E, II-F). NS/markers ->
NS/joint_states, NS/keypoints, NS/skeleton and the feedback NS/feedback."""

from __future__ import annotations

import time
from typing import Any

from vmocap_core import graph_config
from vmocap_core.method.held import lengths_word
from vmocap_core.outputs.messages import CLOUD, markers_from_message, result_messages

from ..subject import hri_outputs, skeleton_outputs
from ..transport import Transport
from .base import STREAM_DEPTH, InitWatch, VmocapNode

DISAGREE_WARN_S = 3.0  # the WARN naming disagreeing keypoints and cameras stays this long after the last such frame set


class SkeletonNode(VmocapNode):
    """NS/markers -> SkeletonStage (IK, IIR, second IK) -> NS/joint_states, NS/keypoints,
    NS/skeleton and the feedback NS/feedback."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_skeleton") -> None:
        super().__init__(name, config, overrides, transport)
        from vmocap_core.method.skeleton_stage import SkeletonStage

        self.stage = SkeletonStage(config.skeleton_config(name, self.p))
        self.pubs = {}
        for topic, ty in ((self.topics.feedback, CLOUD), (self.topics.joint_states, "sensor_msgs/msg/JointState"),
                          (self.topics.keypoints, CLOUD), (self.topics.skeleton, "visualization_msgs/msg/MarkerArray")):
            fb = topic == self.topics.feedback
            self.pubs[topic] = self.publisher(ty, topic, depth=50 if fb else STREAM_DEPTH, latched=fb)
        self.subject, extra = skeleton_outputs(self)  # robot_description, root_pose, TF
        self.pubs.update(extra)
        self.hri = hri_outputs(self, self.subject, self.pubs)  # REP-155 bodies; None: off or no hri_msgs (WARN)
        self.subscribe(CLOUD, self.topics.markers, self._on_markers, depth=self.p["queue_depth"], latched=True)
        self.counts = {"frames": 0, "tracking": 0, "uncertain": 0}
        self.last_status = "initializing"
        self.init_watch = InitWatch(self.p["init_warn_s"], config.stage_config("vmocap_markers").init_max_reprojection_px,
                                    self.rig.names if self.rig is not None else None)

    def _on_markers(self, msg: dict) -> None:
        t0 = time.perf_counter()
        markers = markers_from_message(msg)
        result = self.stage.step(markers)
        self.init_watch.update(self, result.status, markers, self.stage.init_problem)
        self._check_images(result.status)
        # feedback, then joint_states; outputs nobody subscribes to are not even built
        pubs = self.pubs
        for topic, _ty, out in result_messages(self.topics, result, subject=self.subject,
                                               wanted=lambda topic: topic in pubs and pubs[topic].wanted()):
            if topic in pubs:
                pubs[topic](out)
        if self.hri is not None:
            self.hri(result)
        self.counts["frames"] += 1
        self.counts["tracking"] += result.status == "tracking"
        self.counts["uncertain"] += result.status == "uncertain"
        self.last_status = result.status
        self.proc.add(1e3 * (time.perf_counter() - t0))
        self.record_age(result.stamp_ns)

    def _check_images(self, status: str) -> None:
        """WARN (held DISAGREE_WARN_S) while the skeleton disagrees with the images: which
        keypoints, which cameras (consistency.py); joint_states stop meanwhile."""
        names = self.rig.names if self.rig is not None else [f"camera {c}" for c in range(32)]
        text = self.stage.warning(status, names)
        if text is not None:
            self.warn_for("images", text, DISAGREE_WARN_S)

    def status(self) -> dict[str, Any]:
        last = self.stage.verdict.last
        return dict(self.counts, status=self.last_status,
                    agreement="-" if last is None else f"{last.agreement:.2f}",
                    link_lengths=lengths_word(self.stage),
                    body_id=(self.hri.core.body_id if self.hri is not None else None) or "-")
