"""The subject's ROS outputs frame by frame: what the skeleton node (and `vmocap process`)
publishes besides the tracker's own messages, and the TF a recorder derives from them.

Order within a tracked frame (process.result_messages): `robot_description` and `/tf_static`
when the subject's skeleton is new (first identification or a re-identification with other
link lengths), then `joint_states` (the URDF's joints), `root_pose` and `/tf`. So a listener
always has the description a joint state refers to before that joint state.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ..bag import messages as M
from ..cameras.projection import Rig
from ..graph_config import Topics
from ..method.skeleton import BodyDimensions
from .tf import TF_TYPE, Transforms, UrdfKinematics, base_transform, camera_transforms, tf_message
from .urdf import JOINT_NAMES, SubjectModel

STRING = "std_msgs/msg/String"
POSE = "geometry_msgs/msg/PoseStamped"
JOINTS = "sensor_msgs/msg/JointState"


def joint_state(stamp_ns: int, positions: np.ndarray) -> dict:
    """JointState of the URDF's 34 joints (`urdf.joint_positions` of the model's 40 DOF)."""
    return M.joint_state_msg(stamp_ns, JOINT_NAMES, positions)


def root_pose(stamp_ns: int, base: tuple[np.ndarray, np.ndarray]) -> dict:
    """PoseStamped of the pelvis (the floating base, `urdf.base_pose`) in the world frame."""
    t, q = base
    return {"header": M.header(stamp_ns, M.WORLD_FRAME),
            "pose": {"position": dict(zip("xyz", map(float, t))), "orientation": dict(zip("xyzw", map(float, q)))}}


def pose_of(msg: dict) -> tuple[np.ndarray, np.ndarray]:
    p, o = msg["pose"]["position"], msg["pose"]["orientation"]
    return np.array([p[k] for k in "xyz"], float), np.array([o[k] for k in "xyzw"], float)


class SubjectOutputs:
    """robot_description, /tf_static and /tf of the tracked subject (one per node or run)."""

    def __init__(self, rig: Rig | None = None) -> None:
        self.cameras = camera_transforms(rig) if rig is not None and len(rig) else None
        self.dims: BodyDimensions | None = None
        self.model: SubjectModel | None = None
        self.kinematics: UrdfKinematics | None = None
        self.descriptions = 0
        self.started = False
        self.extra_static: Transforms | None = None  # more fixed frames of the graph (hri.HriOutputs: the body's)

    def start(self, topics: Topics, stamp_ns: int) -> Iterator[tuple[str, str, dict]]:
        """/tf_static of the cameras, once, before any subject is described."""
        if not self.started:
            self.started = True
            if self.cameras is not None:
                yield topics.tf_static, TF_TYPE, tf_message(stamp_ns, self.cameras)

    def static(self, stamp_ns: int) -> Transforms:
        parts = [p for p in (self.cameras, self.kinematics.static_transforms() if self.kinematics else None, self.extra_static)
                 if p is not None]
        return Transforms.concat(parts) if parts else Transforms([], [], np.zeros((0, 3)), np.zeros((0, 4)))

    def description(self, topics: Topics, stamp_ns: int, dims: BodyDimensions | None) -> Iterator[tuple[str, str, dict]]:
        """robot_description and /tf_static, when `dims` is a skeleton not yet described."""
        if dims is None or dims == self.dims:
            return
        self.dims, self.model = dims, SubjectModel(dims)
        xml = self.model.to_xml()
        self.kinematics = UrdfKinematics(xml)
        self.descriptions += 1
        yield topics.robot_description, STRING, {"data": xml}
        yield topics.tf_static, TF_TYPE, tf_message(stamp_ns, self.static(stamp_ns))

    def tf(self, topics: Topics, stamp_ns: int, positions: np.ndarray, base: tuple[np.ndarray, np.ndarray]) -> tuple[str, str, dict]:
        """/tf of one frame from `urdf.joint_positions` and `urdf.base_pose` of its 40 DOF."""
        assert self.kinematics is not None, "description() first"
        body = self.kinematics.transforms(JOINT_NAMES, positions)
        return topics.tf, TF_TYPE, tf_message(stamp_ns, Transforms.concat([base_transform(*base), body]))


class TfFromStates:
    """What a recorder adds to a bag of our outputs when it cannot receive TF itself: /tf from
    each (joint_states, root_pose) pair of one stamp and the latest robot_description, and
    /tf_static (cameras of `rig`, keypoint frames) with every robot_description."""

    def __init__(self, topics: Topics, rig: Rig | None = None) -> None:
        self.topics = topics
        self.cameras = camera_transforms(rig) if rig is not None and len(rig) else None
        self.kinematics: UrdfKinematics | None = None
        self._pending: dict[int, dict[str, dict]] = {}

    def add(self, topic: str, msg: dict) -> list[tuple[str, str, dict]]:
        """(topic, type, message) to write after the message of `topic` arrived."""
        t = self.topics
        if topic == t.robot_description:
            self.kinematics = UrdfKinematics(msg["data"])
            parts = [p for p in (self.cameras, self.kinematics.static_transforms()) if p is not None]
            return [(t.tf_static, TF_TYPE, tf_message(0, Transforms.concat(parts)))]
        if topic not in (t.joint_states, t.root_pose):
            return []
        stamp = M.stamp_ns(msg)
        entry = self._pending.setdefault(stamp, {})
        entry[topic] = msg
        if len(entry) < 2 or self.kinematics is None:
            for old in [s for s in self._pending if s < stamp - 2_000_000_000]:  # never completed
                del self._pending[old]
            return []
        del self._pending[stamp]
        js, pose = entry[t.joint_states], entry[t.root_pose]
        body = self.kinematics.transforms(js["name"], np.asarray(js["position"]))
        return [(t.tf, TF_TYPE, tf_message(stamp, Transforms.concat([base_transform(*pose_of(pose)), body])))]
