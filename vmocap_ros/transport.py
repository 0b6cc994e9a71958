"""How the nodes of one process hand messages to each other, and when a recorded frame goes out.

A `Transport` belongs to one process (made by run_node.spin_nodes, passed to every node it
creates): its `LocalBus` delivers a message published by one of our nodes to our other nodes
of the process as the dict itself (no CDR, no DDS); its `DueQueue` lets the spin loop send
recorded camera frames at their due time. `Output` is one output topic of a node.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections import deque
from typing import Any, Callable

from vmocap_core.bag import cdr


class LocalBus:
    """All-nodes-in-one-process delivery (`vmocap launch --single-process`): a message published
    by one of our nodes reaches our other nodes in this process as the dict itself (no CDR,
    no DDS), queued and handed over by the spin loop after the current callback returns. It is
    still published over DDS when anyone else (recorder, RViz, a controller) subscribes.
    Subscriptions are decided in `finalize()`, once every node exists: a topic published by a
    node of this process is taken locally, any other topic over DDS."""

    def __init__(self) -> None:
        self.enabled = False
        self.publishers: set[str] = set()
        self.subscribers: dict[str, list[Callable[[dict], None]]] = {}
        self.subscriber_nodes: dict[str, list[str]] = {}  # topic -> names of the local nodes taking it
        self.pending: deque = deque()
        # a message published from another thread (the camera node's readers) wakes the spin
        # loop's executor at once (`wake`, set by the spin loop); poll_s is only a fallback
        self.poll_s = 0.1
        self.wake: Callable[[], None] | None = None
        self.spin_thread = threading.get_ident()
        self._wake_pending = False

    def publish(self, topic: str, msg: dict) -> None:
        subs = self.subscribers.get(topic)
        if not subs:
            return
        for cb in subs:
            self.pending.append((cb, msg))
        if self.wake is not None and not self._wake_pending and threading.get_ident() != self.spin_thread:
            self._wake_pending = True  # one wake-up per drain, not per message
            self.wake()

    def drain(self, max_s: float = 0.0) -> bool:
        """Hand over the messages queued so far, and those the callbacks queue meanwhile (a
        frame set's way from node to node) for up to max_s seconds: the executor's timers and
        DDS events wait meanwhile (a spin_once between two hand-overs costs ~70 us). True
        when messages are left."""
        end = time.monotonic() + max_s
        while True:
            self._wake_pending = False  # before counting: a message queued after this wakes again
            n = len(self.pending)
            for _ in range(n):
                cb, msg = self.pending.popleft()
                cb(msg)
            if not self.pending or time.monotonic() >= end:
                return bool(self.pending)


class Output:
    """One output topic of a node; calling it publishes a message dict. In-process nodes
    (LocalBus) get the dict itself; over DDS it goes as CDR bytes, encoded only when a DDS
    reader matched, except on a transient-local (latched) topic of a node without local bus, and
    on a latched description (depth 1: robot_description, /tf_static, a body's urdf) of any
    node: kept for readers that match later (RViz, a ROS4HRI listener opening a new body). Volatile samples without a reader go nowhere, so their
    encoding is skipped (the MarkerArray alone costs ~0.4 ms). `prepare` + `send` split the
    work: a recorded camera frame is encoded while it waits for its due time."""

    __slots__ = ("type_name", "topic", "pub", "latched", "local", "bus", "kept")

    def __init__(self, type_name: str, topic: str, pub: Any, latched: bool, bus: LocalBus, depth: int = 10) -> None:
        self.type_name, self.topic, self.pub, self.latched, self.bus = type_name, topic, pub, latched, bus
        self.local = bus.enabled  # our nodes in this process subscribe locally, not over DDS
        # latched streams (feedback, markers, lockstep heatmaps) are latched for our own nodes:
        # with them in this process, nothing else needs their samples kept
        self.kept = latched and (not self.local or depth == 1)

    def dds_wanted(self) -> bool:
        return self.kept or self.pub.get_subscription_count() > 0

    def wanted(self) -> bool:
        """Does anyone take this topic (a local node or a DDS reader)? Else skip building it."""
        return bool(self.local and self.bus.subscribers.get(self.topic)) or self.dds_wanted()

    def prepare(self, msg: dict) -> tuple[dict, bytes | None]:
        return msg, (cdr.encode(self.type_name, msg) if self.dds_wanted() else None)

    def send(self, prepared: tuple[dict, bytes | None]) -> None:
        msg, data = prepared
        if self.local:
            self.bus.publish(self.topic, msg)
        if data is not None:
            self.pub.publish(data)

    def __call__(self, msg: dict) -> None:
        self.send(self.prepare(msg))


class DueQueue:
    """Publications due at a monotonic time, made by the spin loop (run_node.spin_nodes) when
    they are due: a recorded camera's frames, prepared (and CDR-encoded) by its reader thread
    beforehand, go out in one burst per instant from the thread that handles them next, instead
    of every camera's reader thread waking at the same instant and queueing for the GIL (the
    last of 4 cameras went out ~2 ms late on 2 cores). Without a spin loop (`wake` None) the
    reader threads publish themselves."""

    def __init__(self) -> None:
        self._heap: list = []
        self._lock = threading.Lock()
        self._seq = itertools.count()
        self.wake: Callable[[], None] | None = None  # set by the spin loop
        self._sleep_until = float("inf")
        self._when_idle: list[tuple[float, Callable[[], None]]] = []

    def when_idle(self, fn: Callable[[], None], at_latest: float) -> None:
        """Call fn once the spin loop has nothing left to hand over, or at the monotonic time
        at_latest at the latest (checked between callbacks). From the spin loop's thread only."""
        self._when_idle.append((at_latest, fn))

    def run_idle(self, idle: bool) -> None:
        if not self._when_idle:
            return
        now = time.monotonic()
        waiting = []
        for at_latest, fn in self._when_idle:
            if idle or at_latest <= now:
                fn()
            else:
                waiting.append((at_latest, fn))
        self._when_idle = waiting

    def put(self, due: float, send: Callable[[], None]) -> None:
        with self._lock:
            heapq.heappush(self._heap, (due, next(self._seq), send))
            wake = due < self._sleep_until
            if wake:
                self._sleep_until = due
        if wake and self.wake is not None:
            self.wake()

    def run_due(self, poll_s: float) -> float:
        """Send what is due; the time (s) the spin loop may sleep before the next is due."""
        while True:
            with self._lock:
                now = time.monotonic()
                if not self._heap or self._heap[0][0] > now:
                    wait = min(poll_s, self._heap[0][0] - now) if self._heap else poll_s
                    self._sleep_until = now + wait
                    return wait
                send = heapq.heappop(self._heap)[2]
            send()


class Transport:
    """The in-process bus and due queue shared by the nodes of one process."""

    def __init__(self, local: bool = False) -> None:
        self.bus = LocalBus()
        self.bus.enabled = local
        self.due = DueQueue()
