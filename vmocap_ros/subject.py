"""The subject's ROS outputs on the node side (logic in vmocap_core.outputs): the skeleton
node's extra publishers, its ROS4HRI (REP-155) publishers, and the TF a recorder derives when
/tf cannot travel over DDS.

tf2_msgs has no PyPI wheel: without it (the default install) no node can publish or
subscribe /tf; the skeleton node then publishes root_pose and robot_description only, and the
recorder writes /tf and /tf_static into its MCAP from them (vmocap_core.outputs.streams).
With tf2_msgs importable (a ROS 2 install), /tf and /tf_static go over DDS as well, unless
VMOCAP_TF_DDS=off (the recorder then derives them, as without tf2_msgs). hri_msgs has no
wheel either: without it the skeleton node runs without the ROS4HRI outputs and says so on
/diagnostics (WARN)."""

from __future__ import annotations

import os
from typing import Any

from vmocap_core.outputs.hri import IDS_LIST, TRACKED, HriOutputs
from vmocap_core.outputs.streams import POSE, STRING, SubjectOutputs, TfFromStates
from vmocap_core.outputs.tf import TF_TYPE

TF_DEPTH = 100
HRI_DEPTH = 10  # /humans/bodies/tracked and each body's joint_states: reliable, keep last 10
BUILD_MSGS = "bash scripts/build_ros_msgs.sh"


def tf_available() -> bool:
    if os.environ.get("VMOCAP_TF_DDS", "auto") == "off":
        return False
    try:
        import tf2_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


def hri_available() -> bool:
    try:
        import hri_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


class HriPublishers:
    """The skeleton node's ROS4HRI outputs (vmocap_core.outputs.hri): /humans/bodies/tracked
    (reliable, volatile: what libhri's listener subscribes with), per body id its urdf
    (transient local) and joint_states, opened when the id appears and destroyed when the core
    retires it; /tf and /tf_static through the node's own publishers."""

    def __init__(self, node: Any, subject: SubjectOutputs | None, shared: dict[str, Any], core: Any = None) -> None:
        self.node, self.shared = node, shared
        # core: the subject's HriOutputs, or outputs.people.PeopleOutputs for several people
        self.core = core if core is not None else HriOutputs(subject, tf=node.topics.tf in shared)
        self.pubs = {TRACKED: node.publisher(IDS_LIST, TRACKED, depth=HRI_DEPTH)}

    def __call__(self, result: Any) -> None:
        frame = self.core.step(result, wanted=self._wanted)
        for ch in frame.opened:
            self.pubs[ch.topic] = self.node.publisher(ch.type, ch.topic, depth=1 if ch.latched else HRI_DEPTH,
                                                      latched=ch.latched)
        for topic, _ty, msg in frame.messages:
            (self.pubs.get(topic) or self.shared[topic])(msg)
        for topic in frame.closed:
            self.node.drop_publisher(self.pubs.pop(topic))

    def _wanted(self, topic: str) -> bool:
        pub = self.pubs.get(topic) or self.shared.get(topic)
        return pub is not None and pub.wanted()


def hri_outputs(node: Any, subject: SubjectOutputs | None, shared: dict[str, Any], core: Any = None) -> HriPublishers | None:
    """The node's HriPublishers when its `hri` parameter asks for them and hri_msgs imports;
    without hri_msgs a WARN naming the build command (none when `hri` is false)."""
    if not node.p["hri"]:
        return None
    if not hri_available():
        node.problems["hri"] = (f"no ROS4HRI outputs (/humans/bodies/...): hri_msgs is not installed; build it with "
                                f"`{BUILD_MSGS}`, or set hri: false")
        return None
    return HriPublishers(node, subject, shared, core)


def skeleton_outputs(node: Any) -> tuple[SubjectOutputs, dict[str, Any]]:
    """SubjectOutputs of a skeleton node and its extra publishers by topic."""
    t = node.topics
    pubs = {t.root_pose: node.publisher(POSE, t.root_pose),
            t.robot_description: node.publisher(STRING, t.robot_description, depth=1, latched=True)}
    if tf_available():
        pubs[t.tf] = node.publisher(TF_TYPE, t.tf, depth=TF_DEPTH)
        pubs[t.tf_static] = node.publisher(TF_TYPE, t.tf_static, depth=1, latched=True)
    return SubjectOutputs(node.rig), pubs


def recorded_outputs(topics: Any) -> dict[str, str]:
    """The graph outputs a recorder takes by default: with /tf and /tf_static when they travel."""
    out = topics.outputs()
    if tf_available():
        out.update({topics.tf: TF_TYPE, topics.tf_static: TF_TYPE})
    return out


def recorder_tf(node: Any) -> TfFromStates | None:
    """The recorder's TF source when /tf does not travel over DDS (None when it does)."""
    return None if tf_available() else TfFromStates(node.topics, node.rig)
