"""The vmocap nodes, one file per node, in the method's order: camera ingest -> PCM inference
-> lattice search (markers) -> IK + filter (skeleton) -> recorder. With max_people > 1 the PCM
and skeleton nodes are their several-people kinds (pcm_people.py, skeleton_people.py) and the
markers node runs a stage per person. Each is a thin rclpy shell: parameters, publishers and
subscriptions, one call into vmocap_core per message."""

from __future__ import annotations

from typing import Any

from vmocap_core import graph_config

from ..transport import Transport
from .base import VmocapNode
from .camera import CameraNode
from .markers import MarkersNode
from .pcm import PcmNode
from .pcm_people import PeoplePcmNode
from .recorder import RecorderNode
from .skeleton import SkeletonNode
from .skeleton_people import PeopleSkeletonNode

# max_people > 1 (under /**): everyone in view
PEOPLE_NODES: dict[str, type[VmocapNode]] = {"vmocap_pcm": PeoplePcmNode, "vmocap_skeleton": PeopleSkeletonNode}
NODES: dict[str, type[VmocapNode]] = {
    "vmocap_camera": CameraNode,
    "vmocap_pcm": PcmNode,
    "vmocap_markers": MarkersNode,
    "vmocap_skeleton": SkeletonNode,
    "vmocap_recorder": RecorderNode,
}


def create(name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
           transport: Transport | None = None) -> VmocapNode:
    """The node called `name`: a node type's name, or an instance of one (`vmocap_pcm_cam0`:
    graph_config.node_type)."""
    kind = graph_config.node_type(name)
    people = kind in PEOPLE_NODES and config.node_params(name, overrides)["max_people"] > 1
    return (PEOPLE_NODES if people else NODES)[kind](config, overrides, transport, name)
