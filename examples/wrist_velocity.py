"""A controller-side example: a separate ROS 2 process that takes vmocap's outputs the way a
robot controller would and computes the wrist velocities in the world frame.

Subscribes (namespace /vmocap by default):
- `robot_description` (std_msgs/String, transient local): the subject's URDF, loaded with
  Pinocchio's URDF parser; rebuilt when the subject is re-identified.
- `joint_states` (sensor_msgs/JointState, the URDF's joints) and `root_pose`
  (geometry_msgs/PoseStamped, world -> pelvis), paired by stamp: forward kinematics of the
  frames `kp_left_wrist` / `kp_right_wrist` gives their positions in the world frame; the
  velocity is the difference quotient of consecutive frames.
- `keypoints` (sensor_msgs/PointCloud2): published for every frame, empty while no subject is
  tracked, so its stamps are the graph's frame clock. A subject is *lost* when that clock runs
  more than `--stale-ms` ahead of the last joint state: the controller must then stop using the
  last pose (a velocity is never taken across such a gap).

Run: `python examples/wrist_velocity.py --output wrists.jsonl` (Ctrl-C stops it); each line
is one JSON record: {"stamp_ns", "event": "velocity", "left", "right"} in m/s, or
{"stamp_ns", "event": "lost" | "found"}.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from typing import Any, TextIO

import numpy as np

WRISTS = ("kp_left_wrist", "kp_right_wrist")


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class WristVelocity:
    """The controller's logic without ROS: feed it messages' contents, it returns records."""

    def __init__(self, stale_ns: int = 200_000_000) -> None:
        self.stale_ns = stale_ns
        self.model: Any = None
        self._pending: dict[int, dict[str, Any]] = {}
        self._last: tuple[int, np.ndarray] | None = None  # (stamp, wrist positions (2, 3))
        self.last_state_ns: int | None = None
        self.lost = False

    def on_description(self, xml: str) -> None:
        import pinocchio as pin

        self.model = pin.buildModelFromXML(xml)
        self.data = self.model.createData()
        self.frames = [self.model.getFrameId(f) for f in WRISTS]
        self._last = None  # other link lengths: do not differentiate across the change

    def wrists(self, names: list[str], positions: np.ndarray, t: np.ndarray, quat: np.ndarray) -> np.ndarray:
        """World positions (2, 3) of the wrists at a joint state and base pose."""
        import pinocchio as pin

        q = np.zeros(self.model.nq)
        for n, v in zip(names, positions):
            q[self.model.joints[self.model.getJointId(n)].idx_q] = v
        pin.framesForwardKinematics(self.model, self.data, q)
        R = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
        return np.array([R @ self.data.oMf[f].translation + t for f in self.frames])

    def on_state(self, stamp: int, kind: str, value: Any) -> list[dict]:
        """kind "joints": (names, positions); kind "pose": (t (3,), quat x y z w (4,))."""
        entry = self._pending.setdefault(stamp, {})
        entry[kind] = value
        if len(entry) < 2 or self.model is None:
            return []
        del self._pending[stamp]
        for old in [s for s in self._pending if s < stamp]:
            del self._pending[old]
        out = []
        if self.lost:
            self.lost = False
            out.append({"stamp_ns": stamp, "event": "found"})
        p = self.wrists(*entry["joints"], *entry["pose"])
        if self._last is not None and 0 < stamp - self._last[0] <= self.stale_ns:
            v = (p - self._last[1]) / ((stamp - self._last[0]) * 1e-9)
            out.append({"stamp_ns": stamp, "event": "velocity", "left": v[0].tolist(), "right": v[1].tolist()})
        self._last = (stamp, p)
        self.last_state_ns = stamp
        return out

    def on_frame_clock(self, stamp: int) -> list[dict]:
        """A frame of the graph (keypoints stamp): is the last joint state stale?"""
        if self.last_state_ns is None or self.lost or stamp - self.last_state_ns <= self.stale_ns:
            return []
        self.lost = True
        self._last = None
        return [{"stamp_ns": stamp, "event": "lost"}]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--namespace", default="/vmocap")
    ap.add_argument("--stale-ms", type=float, default=200.0, help="lost when the frame clock is this far past the last joint state")
    ap.add_argument("--output", default="-", help="JSON lines file ('-': standard output)")
    args = ap.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import String

    from rclpy.signals import SignalHandlerOptions

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)  # Ctrl-C handled below
    node = rclpy.create_node("wrist_velocity")
    ctl = WristVelocity(int(args.stale_ms * 1e6))
    out: TextIO = sys.stdout if args.output == "-" else open(args.output, "w")

    def emit(records: list[dict]) -> None:
        for r in records:
            out.write(json.dumps(r) + "\n")
        out.flush()

    ns = "/" + args.namespace.strip("/")
    stream = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, f"{ns}/robot_description", lambda m: ctl.on_description(m.data), latched)
    node.create_subscription(JointState, f"{ns}/joint_states", lambda m: emit(
        ctl.on_state(stamp_ns(m.header), "joints", (list(m.name), np.asarray(m.position)))), stream)
    node.create_subscription(PoseStamped, f"{ns}/root_pose", lambda m: emit(ctl.on_state(stamp_ns(m.header), "pose", (
        np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z]),
        np.array([m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w])))), stream)
    node.create_subscription(PointCloud2, f"{ns}/keypoints", lambda m: emit(ctl.on_frame_clock(stamp_ns(m.header))), stream)
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    print("READY wrist_velocity", flush=True)
    connected = False
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
        if not connected and all(node.count_publishers(f"{ns}/{t}") for t in ("joint_states", "root_pose", "keypoints")):
            connected = True
            print("CONNECTED to the vmocap outputs", flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    if out is not sys.stdout:
        out.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
