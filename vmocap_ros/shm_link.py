"""Large messages between our nodes of one machine through shared memory (cameras/shm.py).

An `ShmOut` is the side channel of one Image topic (`TOPIC/shm`): while every reader of TOPIC
also reads TOPIC/shm, the node writes the pixels into its ring and publishes only a reference
there; otherwise the message goes on TOPIC as before. An `ShmIn` takes the references of a
node's topics, copies the pixels out and hands the message on as if it came on TOPIC; when it
cannot reach the memory (another machine, another PID namespace) it stops taking them, so the
sender goes back to TOPIC.
"""

from __future__ import annotations

from typing import Any, Callable

from vmocap_core.cameras.shm import FrameReader, FrameRing, ShmUnavailable
from vmocap_core.outputs.messages import IMAGE

from .transport import Output


def shm_topic(topic: str) -> str:
    return f"{topic}/shm"


class ShmOut:
    """The shared-memory side channel of one Image output of `node` (a VmocapNode)."""

    def __init__(self, node: Any, topic: str) -> None:
        self.node, self.topic = node, topic
        self.pub: Output = node.publisher(IMAGE, shm_topic(topic))
        self.ring: FrameRing | None = None
        self.on = False  # set by check()

    def check(self) -> bool:
        """On while TOPIC has readers and every one of them also takes the references."""
        readers = self._readers(self.topic)
        self.on = bool(readers) and readers <= self._readers(shm_topic(self.topic))
        return self.on

    def _readers(self, topic: str) -> set[tuple[str, str]]:
        return {(i.node_namespace, i.node_name) for i in self.node.get_subscriptions_info_by_topic(topic)}

    def send(self, msg: dict) -> None:
        """The message's pixels into the ring, the reference out (call only while `on`)."""
        data = msg["data"]
        n = memoryview(data).nbytes
        if self.ring is None or self.ring.capacity < n:  # the first message, or a larger one
            if self.ring is not None:
                self.ring.close()
            self.ring = FrameRing(n, name="vmocap-" + self.topic.strip("/").replace("/", "-"))
        self.pub(dict(msg, data=self.ring.write(data)))

    def close(self) -> None:
        if self.ring is not None:
            self.ring.close()


class ShmIn:
    """Takes the references of Image topics of `node` and hands each message, its pixels
    copied out, to the topic's callback."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self.reader: FrameReader | None = FrameReader()
        self.topics: list[str] = []
        self.received = 0
        self.off = ""  # why the references are not taken

    def subscribe(self, topic: str, key: str, cb: Callable[[dict], None], depth: int) -> None:
        self.topics.append(shm_topic(topic))
        self.node.subscribe(IMAGE, shm_topic(topic), lambda m: self._on(key, m, cb), depth=depth)

    def _on(self, key: str, msg: dict, cb: Callable[[dict], None]) -> None:
        if self.reader is None:
            return
        try:
            data = self.reader.read(key, msg["data"])
        except ShmUnavailable as exc:
            self.off = str(exc)
            self.node.get_logger().info(f"over DDS, not shared memory: {exc}")
            for t in self.topics:
                self.node.drop_subscription(t)
            self.close()
            return
        if data is not None:
            self.received += 1
            cb(dict(msg, data=data))

    def status(self) -> Any:
        if self.reader is None:
            return f"off: {self.off}" if self.off else "off"
        return {"received": self.received, "overwritten": self.reader.overwritten, "gone": self.reader.gone}

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
            self.reader = None
