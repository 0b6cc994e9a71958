"""The topic names of the node graph under its namespace (docs/graph.md)."""

from __future__ import annotations


class Topics:
    """Topic names of the graph under a namespace (see docs/graph.md)."""

    def __init__(self, namespace: str = "/vmocap") -> None:
        self.ns = "/" + namespace.strip("/") if namespace.strip("/") else ""

    def slot(self, k: int) -> "Topics":
        """Several people (max_people > 1): the topics of slot k's person between vmocap_pcm,
        vmocap_markers and vmocap_skeleton, under NS/people/slotK (pcm/VIEW/heatmaps, markers, feedback)."""
        return Topics(f"{self.ns}/people/slot{k}")

    def image(self, cam: str) -> str:
        return f"{self.ns}/{cam}/image_raw"

    def camera_info(self, cam: str) -> str:
        return f"{self.ns}/{cam}/camera_info"

    def pcm(self, view: str) -> str:
        return f"{self.ns}/pcm/{view}/heatmaps"

    def pcm_info(self, view: str) -> str:
        return f"{self.ns}/pcm/{view}/camera_info"

    @property
    def pcm_done(self) -> str:
        """The stamp of each frame set the PCM node finished (std_msgs/Header): flow control."""
        return f"{self.ns}/pcm/done"

    def pcm_keypoints(self, cam: str) -> str:
        """A camera's 2D keypoints (the PCM centroids in its image), published on demand."""
        return f"{self.ns}/pcm/{cam}/keypoints"

    @property
    def markers(self) -> str:
        return f"{self.ns}/markers"

    @property
    def feedback(self) -> str:
        return f"{self.ns}/feedback"

    @property
    def joint_states(self) -> str:
        return f"{self.ns}/joint_states"

    @property
    def keypoints(self) -> str:
        return f"{self.ns}/keypoints"

    @property
    def skeleton(self) -> str:
        return f"{self.ns}/skeleton"

    @property
    def robot_description(self) -> str:
        return f"{self.ns}/robot_description"

    @property
    def root_pose(self) -> str:
        return f"{self.ns}/root_pose"

    diagnostics = "/diagnostics"
    clock = "/clock"
    tf = "/tf"
    tf_static = "/tf_static"

    def outputs(self) -> dict[str, str]:
        """The graph's output topics and their types (what the recorder takes by default)."""
        return {
            self.joint_states: "sensor_msgs/msg/JointState",
            self.root_pose: "geometry_msgs/msg/PoseStamped",
            self.robot_description: "std_msgs/msg/String",
            self.keypoints: "sensor_msgs/msg/PointCloud2",
            self.markers: "sensor_msgs/msg/PointCloud2",
            self.skeleton: "visualization_msgs/msg/MarkerArray",
            self.diagnostics: "diagnostic_msgs/msg/DiagnosticArray",
        }
