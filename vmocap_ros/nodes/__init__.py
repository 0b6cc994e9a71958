"""The vmocap nodes, one file per node, in the method's order: camera ingest -> PCM inference
-> lattice search (markers) -> IK + filter (skeleton) -> recorder; several people: camera ->
people (all of it per person, method/people_tracker.py) -> recorder. Each is a thin rclpy
shell: parameters, publishers and subscriptions, one call into vmocap_core per message."""

from __future__ import annotations

from typing import Any

from vmocap_core import graph_config

from ..transport import Transport
from .base import VmocapNode
from .camera import CameraNode
from .markers import MarkersNode
from .pcm import PcmNode
from .people import PeopleNode
from .recorder import RecorderNode
from .skeleton import SkeletonNode

NODES: dict[str, type[VmocapNode]] = {
    "vmocap_camera": CameraNode,
    "vmocap_pcm": PcmNode,
    "vmocap_markers": MarkersNode,
    "vmocap_skeleton": SkeletonNode,
    "vmocap_people": PeopleNode,
    "vmocap_recorder": RecorderNode,
}


def create(name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
           transport: Transport | None = None) -> VmocapNode:
    """The node called `name`: a node type's name, or an instance of one (`vmocap_pcm_cam0`:
    graph_config.node_type)."""
    return NODES[graph_config.node_type(name)](config, overrides, transport, name)
