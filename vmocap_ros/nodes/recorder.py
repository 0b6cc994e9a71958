"""vmocap_recorder: topics -> MCAP (CDR bytes as received)."""

from __future__ import annotations

import threading
import time
from typing import Any

from vmocap_core import graph_config
from vmocap_core.errors import VmocapError

from ..common import msg_class, qos
from ..transport import Transport
from .base import VmocapNode


class RecorderNode(VmocapNode):
    """Topics -> MCAP (CDR bytes as received). The file is complete and renamed from .partial
    when the node is closed (Ctrl-C/SIGTERM of the launcher or `vmocap record`)."""

    needs_rig = False

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_recorder") -> None:
        super().__init__(name, config, overrides, transport)
        from vmocap_core.bag import BagWriter

        if not self.p["output"]:
            raise VmocapError("vmocap_recorder: parameter 'output' (an .mcap path) is required")
        self.writer = BagWriter(self.p["output"], compression=self.p["compression"]).open()
        self.known = self.topics.outputs()
        self.wanted = list(self.p["topics"]) or list(self.known)
        self.subscribed: set[str] = set()
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
                        self.writer.write(topic, ty, data, self.get_clock().now().nanoseconds)
                self.cpu_s += time.thread_time() - t0

            self.create_subscription(msg_class(ty), topic, cb, qos(100), raw=True)
            self.subscribed.add(topic)

    def status(self) -> dict[str, Any]:
        return {"messages": self.writer.count if self.writer else 0, "topics": sorted(self.subscribed)}

    def close(self) -> None:
        with self.lock:
            if self.writer is not None:
                self.writer.close()
                self.get_logger().info(f"wrote {self.writer.count} messages to {self.writer.path}")
                self.writer = None
