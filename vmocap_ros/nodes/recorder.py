"""vmocap_recorder: topics -> MCAP (CDR bytes as received)."""

from __future__ import annotations

import threading
import time
from typing import Any

from vmocap_core import graph_config
from vmocap_core.bag import cdr
from vmocap_core.errors import VmocapError

from ..common import msg_class, qos
from ..subject import recorded_outputs, recorder_tf
from ..transport import Transport
from .base import VmocapNode


def keep_partial(output: str) -> str:
    """Move OUTPUT.partial, which only a killed recorder leaves, out of the way of a new
    recording (OUT.mcap -> OUT.killed1.mcap.partial, .killed2 ...); "" when there was none."""
    from pathlib import Path

    from vmocap_core.bag.writer import PARTIAL_SUFFIX

    out = Path(output)
    partial = out.with_name(out.name + PARTIAL_SUFFIX)
    if not partial.exists():
        return ""
    k = 1
    while (keep := out.with_name(f"{out.stem}.killed{k}{out.suffix}{PARTIAL_SUFFIX}")).exists():
        k += 1
    partial.rename(keep)
    return str(keep)


class RecorderNode(VmocapNode):
    """Topics -> MCAP (CDR bytes as received). The file is complete and renamed from .partial
    when the node is closed (Ctrl-C/SIGTERM of the launcher or `vmocap record`)."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_recorder") -> None:
        super().__init__(name, config, overrides, transport)
        from vmocap_core.bag import BagWriter

        if not self.p["output"]:
            raise VmocapError("vmocap_recorder: parameter 'output' (an .mcap path) is required")
        self.kept = keep_partial(self.p["output"])
        if self.kept:  # a recorder of this output was killed (and restarted by the launcher)
            msg = f"a killed recorder's file was kept as {self.kept} (`vmocap process --recover` reads it)"
            self.get_logger().warning(msg)
            self.warn_for("kept", msg, hold_s=30.0)
        # small chunks: on SIGKILL only the chunk being filled is lost (`--recover` reads the rest)
        self.writer = BagWriter(self.p["output"], compression=self.p["compression"], chunk_size=self.p["chunk_kb"] << 10,
                                overwrite=self.p["overwrite"]).open()
        self.known = recorded_outputs(self.topics)
        self.wanted = list(self.p["topics"]) or list(self.known)
        self.subscribed: set[str] = set()
        self.tf = recorder_tf(self)  # /tf and /tf_static derived from our outputs
        self.lock = threading.Lock()
        self._discover()
        self.create_timer(0.5, self._discover)

    def _discover(self) -> None:
        types = dict(self.known)
        for name, tys in self.get_topic_names_and_types():
            if tys:
                types.setdefault(name, tys[0])
        for topic in self.wanted:
            if topic in self.subscribed or topic not in types:
                continue
            ty = types[topic]
            try:
                self.writer.add_topic(topic, ty, qos_depth=100)
            except VmocapError as exc:  # a type vmocap's CDR codec does not know
                self.problems[topic] = f"not recorded: {exc}"
                self.subscribed.add(topic)
                continue

            def cb(data: bytes, topic: str = topic, ty: str = ty) -> None:
                t0 = time.thread_time()
                with self.lock:
                    if self.writer is not None:
                        now = self.get_clock().now().nanoseconds
                        self.writer.write(topic, ty, data, now)
                        if self.tf is not None:
                            self._write_tf(topic, ty, data, now)
                self.cpu_s += time.thread_time() - t0

            latched = topic in (self.topics.robot_description, self.topics.tf_static)
            if latched:
                self.writer.add_topic(topic, ty, latched=True)
            self.create_subscription(msg_class(ty), topic, cb, qos(1 if latched else 100, latched=latched), raw=True)
            self.subscribed.add(topic)

    def _write_tf(self, topic: str, ty: str, data: bytes, now: int) -> None:
        if topic not in (self.topics.robot_description, self.topics.joint_states, self.topics.root_pose):
            return
        try:
            derived = self.tf.add(topic, cdr.decode(ty, data))
        except VmocapError as exc:
            self.problems["tf"] = f"no TF derived: {exc}"
            return
        for t, tty, msg in derived:
            if t == self.topics.tf_static:
                self.writer.add_topic(t, tty, latched=True)
            self.writer.write(t, tty, msg, now)

    def status(self) -> dict[str, Any]:
        return {"messages": self.writer.count if self.writer else 0, "topics": sorted(self.subscribed)}

    def close(self) -> None:
        with self.lock:
            if self.writer is not None:
                self.writer.close()
                self.get_logger().info(f"wrote {self.writer.count} messages to {self.writer.path}")
                self.writer = None
