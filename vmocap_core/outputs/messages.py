"""The graph's output messages of a frame: what vmocap_markers and vmocap_skeleton publish and
what `vmocap process` writes, built by the same functions."""

from __future__ import annotations

import json
from typing import Any, Callable, Iterator

import numpy as np

from ..bag import BagWriter
from ..bag import messages as M
from ..export.session import SUBJECT_STATUS
from ..graph_config import Topics
from ..keypoints import KEYPOINTS
from ..method.consistency import ViewCheck
from ..method.results import Markers, feedback_of
from .streams import SubjectOutputs

IMAGE = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"
CLOUD = "sensor_msgs/msg/PointCloud2"
JOINTS = "sensor_msgs/msg/JointState"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTICS_PERIOD_S = 1.0  # every node reports its status on /diagnostics this often

HEADER = "std_msgs/msg/Header"  # a bare stamp: vmocap_pcm's NS/pcm/done


def markers_message(markers: Markers) -> dict:
    residual = markers.residual_px if markers.residual_px is not None else np.full(len(KEYPOINTS), np.nan)
    check = None
    if markers.check is not None:
        c = markers.check
        check = (c.confidence, c.disagree, np.zeros(len(KEYPOINTS), np.uint32) if c.agree is None else c.agree)
    return M.keypoint_cloud(markers.stamp_ns, markers.positions, markers.weights, markers.kind, residual, markers.cameras,
                            check=check, others=markers.others, inside=markers.inside, person=markers.person)


def markers_from_message(msg: dict) -> Markers:
    """Inverse of `markers_message` (the cloud carries positions, weights, kind and the check)."""
    P, S, kind = M.cloud_keypoints(msg)
    if P is None:
        P = np.full((len(KEYPOINTS), 3), np.nan)
    residual, cameras = M.cloud_marker_extras(msg)
    check = M.cloud_marker_check(msg)
    return Markers(M.stamp_ns(msg), P, S, kind, residual_px=residual, cameras=cameras,
                   check=None if check is None else ViewCheck(*check), others=M.cloud_marker_others(msg),
                   inside=M.cloud_marker_inside(msg), person=M.cloud_marker_person(msg))


def result_messages(topics: Topics, result: Any, wanted: Callable[[str], bool] | None = None,
                    subject: Any = None) -> Iterator[tuple[str, str, dict]]:
    """(topic, type, message) of one TrackResult in publishing order: the feedback first (the
    lattice search of the next frame waits for it), then, with a `subject`
    (outputs.streams.SubjectOutputs), robot_description and /tf_static when the skeleton is
    new, then joint_states (what controllers wait for; the URDF's joints), root_pose, /tf,
    keypoints and the MarkerArray. Each message is built when it is taken, and not at all where
    `wanted(topic)` is False (nobody listens)."""
    from . import streams
    from .urdf import base_pose, joint_positions

    t = result.stamp_ns
    tracking = result.status == "tracking"
    want = wanted or (lambda topic: True)
    if want(topics.feedback):
        yield topics.feedback, CLOUD, M.keypoint_cloud(result.feedback_stamp, feedback_of(result))
    if subject is not None:
        yield from subject.start(topics, t)
        if tracking:
            yield from subject.description(topics, t, result.dims)
    if tracking:
        positions, base = joint_positions(result.q), base_pose(result.q)
        if want(topics.joint_states):
            yield topics.joint_states, JOINTS, streams.joint_state(t, positions)
        if want(topics.root_pose):
            yield topics.root_pose, streams.POSE, streams.root_pose(t, base)
        if subject is not None and want(topics.tf):
            yield subject.tf(topics, t, positions, base)
    if want(topics.keypoints):
        yield topics.keypoints, CLOUD, M.keypoint_cloud(t, result.keypoints if tracking else None,
                                                        np.nan_to_num(result.confidence, nan=0.0))
    if want(topics.skeleton):
        yield topics.skeleton, MARKER_ARRAY, M.skeleton_markers(t, result.keypoints if tracking else None)


def write_results(writer: BagWriter, topics: Topics, result, stamp_ns: int, subject: SubjectOutputs | None) -> None:
    """A TrackResult's output messages (not the internal feedback) into a bag at its stamp."""
    for topic, ty, msg in result_messages(topics, result, wanted=lambda topic: topic != topics.feedback, subject=subject):
        if topic in (topics.robot_description, topics.tf_static):
            writer.add_topic(topic, ty, latched=True)
        writer.write(topic, ty, msg, stamp_ns)


def subject_message(stamp_ns: int, dims: Any) -> dict:
    return M.diagnostics_msg(stamp_ns, [(0, SUBJECT_STATUS, "body dimensions (m)", {"dims": json.dumps(dims.to_dict())})])
