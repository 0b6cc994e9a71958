"""The subject's ROS outputs on the node side (logic in vmocap_core.outputs): the skeleton
node's extra publishers, and the TF a recorder derives when /tf cannot travel over DDS.

tf2_msgs has no PyPI wheel: without it (the default install) no node can publish or
subscribe /tf; the skeleton node then publishes root_pose and robot_description only, and the
recorder writes /tf and /tf_static into its MCAP from them (vmocap_core.outputs.streams).
With tf2_msgs importable (a ROS 2 install), /tf and /tf_static go over DDS as well, unless
VMOCAP_TF_DDS=off (the recorder then derives them, as without tf2_msgs)."""

from __future__ import annotations

import os
from typing import Any

from vmocap_core.outputs.streams import POSE, STRING, SubjectOutputs, TfFromStates
from vmocap_core.outputs.tf import TF_TYPE

TF_DEPTH = 100


def tf_available() -> bool:
    if os.environ.get("VMOCAP_TF_DDS", "auto") == "off":
        return False
    try:
        import tf2_msgs.msg  # noqa: F401
    except ImportError:
        return False
    return True


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
