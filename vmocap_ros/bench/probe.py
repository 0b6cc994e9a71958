"""The probe of the node-graph benchmarks and the figures drawn from what it records.

`Probe` is a node in the benchmark's own process that receives the graph's small outputs and the
nodes' /diagnostics; `latency`, `missing_periods`, `node_age` and `callback_cpu` turn those
records into the reported figures (graph.py, soak.py, faults.py).
"""

from __future__ import annotations

import time

import numpy as np


class Probe:
    """Records (receive wall time, capture stamp) of the graph's outputs and the nodes'
    /diagnostics. A measurement must not change what it measures: a node encodes and sends a
    topic over DDS only when a DDS reader matched, so the probe subscribes to the small
    outputs a controller takes (joint_states, keypoints) and, with the player feed, to the
    player's camera_info (the player pays for that); per-stage ages come from the nodes' own
    diagnostics (each node's `age`: capture stamp -> end of its processing)."""

    def __init__(self, rclpy, cameras: list[str], input_topic: bool) -> None:
        from vmocap_core.bag import cdr

        from ..common import Topics, msg_class, qos

        self.rclpy = rclpy
        self.node = rclpy.create_node("vmocap_bench_probe")
        t = Topics("/vmocap")
        self.samples: dict[str, list[tuple[int, int]]] = {k: [] for k in ("transport", "joint_states", "keypoints")}
        self.diag: dict[str, list[tuple[int, dict[str, str]]]] = {}  # node -> (monotonic ns, values)
        self.recording = False
        self.min_stamp = 0  # ignore outputs of frames captured before the current mode started
        # ignore /diagnostics sent before the last clear(all_=True): the previous mode's graph's
        # last reports can still wait in the reader's queue and mix its counts into this mode's
        self.diag_since = 0

        def stamp_of(data: bytes) -> int:
            import struct

            sec, nsec = struct.unpack_from("<iI", data, 4)
            return sec * 1_000_000_000 + nsec

        def sub(kind: str, ty: str, topic: str, latched: bool = False) -> None:
            def cb(data: bytes) -> None:
                if self.recording:
                    st = stamp_of(data)
                    if st >= self.min_stamp:
                        self.samples[kind].append((time.time_ns(), st))

            self.node.create_subscription(msg_class(ty), topic, cb, qos(50, latched=latched), raw=True)

        if input_topic:
            sub("transport", "sensor_msgs/msg/CameraInfo", t.camera_info(cameras[0]))
        sub("joint_states", "sensor_msgs/msg/JointState", t.joint_states)
        sub("keypoints", "sensor_msgs/msg/PointCloud2", t.keypoints)

        def on_diag(data: bytes) -> None:
            d = cdr.decode("diagnostic_msgs/msg/DiagnosticArray", data)
            sent = d["header"]["stamp"]
            if sent["sec"] * 1_000_000_000 + sent["nanosec"] < self.diag_since:
                return
            for s in d["status"]:
                vals = {v["key"]: v["value"] for v in s["values"]}
                if "cpu_s" in vals:
                    self.diag.setdefault(s["name"], []).append((time.monotonic_ns(), vals))

        self.node.create_subscription(msg_class("diagnostic_msgs/msg/DiagnosticArray"), "/diagnostics", on_diag, qos(50), raw=True)
        from ..run_node import make_executor

        self.executor = make_executor()  # the probe shares the CPU with the graph: keep it cheap
        self.executor.add_node(self.node)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)

    def spin_until(self, done, timeout_s: float) -> bool:
        """Spin until `done()` is true or `timeout_s` passed; whether it came true."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() >= deadline:
                return False
            self.spin_for(0.1)
        return True

    def clear(self, all_: bool = False) -> None:
        for v in self.samples.values():
            v.clear()
        if all_:
            self.diag.clear()
            self.diag_since = time.time_ns()

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown()
        self.node.destroy_node()


def latency(samples: list[tuple[int, int]]) -> dict[str, float]:
    if not samples:
        return {"p50": float("nan"), "p95": float("nan"), "n": 0}
    a = np.array([(r - s) / 1e6 for r, s in samples])
    return {"p50": round(float(np.percentile(a, 50)), 2), "p95": round(float(np.percentile(a, 95)), 2), "n": int(a.size)}


def in_window(diag: list[tuple[int, dict[str, str]]], t0: int, t1: int) -> list[dict[str, str]]:
    return [v for t, v in diag if t0 <= t <= t1]


def callback_cpu(diag: list[tuple[int, dict[str, str]]], t0: int, t1: int) -> float:
    pts = [(t, float(v["cpu_s"])) for t, v in diag if t0 <= t <= t1]
    if len(pts) < 2:
        return float("nan")
    (ta, ca), (tb, cb) = pts[0], pts[-1]
    return round(100.0 * (cb - ca) / ((tb - ta) / 1e9), 1)


def node_age(vals: dict[str, str] | None) -> dict[str, float]:
    """A node's own latency figure (capture stamp -> end of its processing, over its last
    300 frame sets) from its diagnostics."""
    if not vals or "age_ms_p50" not in vals:
        return {"p50": float("nan"), "p95": float("nan"), "n": 0}
    return {"p50": round(float(vals["age_ms_p50"]), 2), "p95": round(float(vals["age_ms_p95"]), 2), "n": int(vals["age_ms_n"])}


def missing_periods(stamps: list[int], period_ns: float) -> int:
    """Frame sets missing between the first and the last of evenly spaced stamps (the camera
    node stamps the frame set due at epoch + k periods)."""
    s = np.unique(np.asarray(stamps, dtype=np.int64))
    if s.size < 2:
        return 0
    return int(np.maximum(np.rint(np.diff(s) / period_ns) - 1, 0).sum())
