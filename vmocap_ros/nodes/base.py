"""The base of every vmocap node: validated parameters, raw publishers and subscriptions
(CDR bytes over DDS, dicts between our nodes of one process), CPU accounting and a 1 Hz
/diagnostics status. Messages are converted with vmocap_core.bag.messages, the same code the
offline pipeline uses: graph and `vmocap process` compute from identical inputs."""

from __future__ import annotations

import time
from collections import deque
from typing import Any, Callable

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter

from vmocap_core import graph_config
from vmocap_core.bag import cdr
from vmocap_core.bag import messages as M
from vmocap_core.cameras.sync import lagging
from vmocap_core.errors import VmocapError
from vmocap_core.outputs.messages import DIAG, DIAGNOSTICS_PERIOD_S, IMAGE

from ..common import Topics, declare, msg_class, qos
from ..transport import Output, Transport

STREAM_DEPTH = 10  # images, PCMs, markers: reliable, keep last 10
AGE_WINDOW_NS = 3600 * 10**9  # a stamp further than this from the node's clock is on another clock
WARN_HOLD_S = 5.0  # a WARN of a passing fault (warn_for) stays this long after its last occurrence


def age_problem(now_ns: int, stamp_ns: int) -> str:
    """Why (now - stamp) is no latency ("" when it is one)."""
    if abs(now_ns - stamp_ns) <= AGE_WINDOW_NS:
        return ""
    return (f"n/a: frame stamps are {abs(now_ns - stamp_ns) / 3.6e12:.0f} h from this node's clock (a recording "
            "replayed without restamp; set restamp, or use_sim_time with `vmocap play`, for ages)")


class Stat:
    """Rolling window of durations (ms)."""

    def __init__(self, n: int = 300) -> None:
        self.v: deque[float] = deque(maxlen=n)

    def add(self, ms: float) -> None:
        self.v.append(ms)

    def summary(self) -> dict[str, str]:
        if not self.v:
            return {}
        a = np.fromiter(self.v, float)
        return {"p50": f"{np.percentile(a, 50):.3f}", "p95": f"{np.percentile(a, 95):.3f}", "mean": f"{a.mean():.3f}",
                "n": str(len(a))}



class VmocapNode(Node):
    """Base: validated parameters (declared with descriptions/ranges), raw pub/sub helpers,
    CPU accounting, a 1 Hz /diagnostics status."""


    def __init__(self, name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None) -> None:
        super().__init__(name)
        self.transport = transport or Transport()
        self.p = config.node_params(name, overrides)
        declare(self, [q for q in graph_config.params_of(name) if q.name != "use_sim_time"], self.p)
        if self.p["use_sim_time"]:
            self.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        self.config = config
        self.topics = Topics(self.p["namespace"])
        self.rig = None
        if self.p["rig"]:  # nodes that can run without one (skeleton, recorder) use it for names and frames
            from vmocap_core.cameras.rig_file import load_rig

            rig = load_rig(self.p["rig"])
            self.rig = rig.subset(self.p["cameras"]) if self.p["cameras"] else rig
        self.cpu_s = 0.0
        self.proc = Stat()
        self.age = Stat()  # capture stamp -> end of processing, ms (this node's clock)
        self.age_note = ""
        self._frames_done = 0  # frame sets processed, for the achieved rate in the diagnostics
        self._late_before: dict[str, int] = {}
        self._rate_mark = (time.monotonic(), 0)
        self.problems: dict[str, str] = {}  # WARN: the node works, with a problem the message names
        self.errors: dict[str, str] = {}  # ERROR: a part of the node has stopped doing its job
        self._dropped_before = 0
        self._held: dict[str, float] = {}  # problem key -> monotonic time its WARN ends (warn_for)
        self._pending_subs: list = []
        self._dds_pubs: dict[str, Any] = {}  # topic -> rclpy publisher, for matched-subscriber counts
        self._dds_subs: dict[str, Any] = {}  # topic -> rclpy subscription (drop_subscription)
        self._diag = self.create_publisher(msg_class(DIAG), Topics.diagnostics, qos(10))
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)

    # -- raw messages --------------------------------------------------------------------
    def publisher(self, type_name: str, topic: str, depth: int = STREAM_DEPTH, latched: bool = False) -> "Output":
        pub = self.create_publisher(msg_class(type_name), topic, qos(depth, latched=latched))
        self._dds_pubs[topic] = pub
        bus = self.transport.bus
        if bus.enabled:
            bus.publishers.add(topic)
        return Output(type_name, topic, pub, latched, bus, depth)

    def drop_publisher(self, out: "Output") -> None:
        """Destroy an output made by `publisher` (a topic of a body that is gone)."""
        self._dds_pubs.pop(out.topic, None)
        self.transport.bus.publishers.discard(out.topic)
        self.destroy_publisher(out.pub)

    def subscribe(self, type_name: str, topic: str, cb: Callable[[dict], None], depth: int = STREAM_DEPTH,
                  latched: bool = False) -> None:
        def guarded(msg: dict) -> None:
            t0 = time.thread_time()
            try:
                cb(msg)
            except VmocapError as exc:
                self.problems[topic] = str(exc)
                self.get_logger().error(f"{topic}: {exc}", throttle_duration_sec=5.0)
            finally:
                self.cpu_s += time.thread_time() - t0

        self._pending_subs.append((type_name, topic, guarded, depth, latched))
        if not self.transport.bus.enabled:
            self.finalize()

    def finalize(self) -> None:
        """Create the subscriptions: local for topics a node of this process publishes."""
        subs, self._pending_subs = self._pending_subs, []
        bus = self.transport.bus
        for type_name, topic, guarded, depth, latched in subs:
            if bus.enabled and topic in bus.publishers:
                bus.subscribers.setdefault(topic, []).append(guarded)
                bus.subscriber_nodes.setdefault(topic, []).append(self.get_name())
                continue
            # images and heatmaps: numpy views into the received bytes (no further copy)
            copy = type_name != IMAGE
            self._dds_subs[topic] = self.create_subscription(
                msg_class(type_name), topic, lambda data, g=guarded, t=type_name, c=copy: g(cdr.decode(t, data, copy=c)),
                qos(depth, latched=latched), raw=True)

    def drop_subscription(self, topic: str) -> None:
        """Stop taking a topic subscribed over DDS by `subscribe` (its publishers see one reader less)."""
        sub = self._dds_subs.pop(topic, None)
        if sub is not None:
            self.destroy_subscription(sub)

    # -- diagnostics ---------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        return {}

    def watch_late(self, late: dict[str, int]) -> None:
        """WARN naming cameras whose frames keep coming too late to be used (sync.lagging);
        called with SyncStats.late once per diagnostics period."""
        grown = lagging(self._late_before, late)
        self._late_before = dict(late)
        if grown:
            self.problems["late"] = ("frames of " + ", ".join(f"{n} ({k} in the last period)" for n, k in grown.items())
                                     + " arrive after their frame set went out and are not used: stamps behind the "
                                     "other cameras (clock offset) or a stalling source")
        else:
            self.problems.pop("late", None)

    def watch_silent(self, silent: list[str] | tuple[str, ...], what: str = "camera") -> None:
        """WARN naming the cameras (views) the synchronizer calls silent: nothing from them for
        silent_after_ms of the others' stamps, so frame sets go on without them."""
        if silent:
            self.problems["silent"] = (f"silent {what}{'s' if len(silent) > 1 else ''}: {', '.join(silent)} (nothing for "
                                       f"{self.p['silent_after_ms']:.0f} ms while the others deliver; going on without)")
        else:
            self.problems.pop("silent", None)

    def watch_dropped(self, dropped: int, what: str = "frame sets dropped") -> None:
        """WARN (held WARN_HOLD_S) when the node lost input in the last diagnostics period: it
        (or a stage before it) falls behind (the achieved rate is rate_hz)."""
        grown, self._dropped_before = dropped - self._dropped_before, dropped
        if grown > 0:
            p50 = self.proc.summary().get("p50", "n/a")
            self.warn_for("falling_behind", f"falling behind: {grown} {what} in the last second ({dropped} in all; "
                                            f"processing p50 {p50} ms per frame set)")

    def warn_for(self, key: str, text: str, hold_s: float = WARN_HOLD_S) -> None:
        """A WARN of a passing fault (a bad frame, a short disconnection): kept on /diagnostics
        for `hold_s` after its last occurrence, so a 1 Hz status cannot miss it, then cleared."""
        self.problems[key] = text
        self._held[key] = time.monotonic() + hold_s

    def record_age(self, stamp_ns: int) -> None:
        """Capture stamp -> now on this node's clock (sim time under use_sim_time). Stamps of a
        recording replayed without restamp are on no clock of this machine: no figure then."""
        self._frames_done += 1
        now = self.get_clock().now().nanoseconds
        problem = age_problem(now, stamp_ns)
        if problem:
            self.age_note = problem
            return
        self.age.add((now - stamp_ns) / 1e6)

    def _publish_diagnostics(self) -> None:
        values = {"cpu_s": f"{self.cpu_s:.4f}"}
        values.update({f"proc_ms_{k}": v for k, v in self.proc.summary().items()})
        values.update({f"age_ms_{k}": v for k, v in self.age.summary().items()})
        if self.age_note:
            values["age_ms"] = self.age_note
        t, n = time.monotonic(), self._frames_done
        values["rate_hz"] = f"{(n - self._rate_mark[1]) / max(t - self._rate_mark[0], 1e-9):.2f}"  # achieved, last period
        self._rate_mark = (t, n)
        values.update({k: str(v) for k, v in self.status().items()})
        for key, until in list(self._held.items()):
            if t > until:
                del self._held[key]
                self.problems.pop(key, None)
        # matched DDS subscribers per output: volatile outputs published before a subscriber
        # matched are gone, so whoever records or controls can check it is connected
        values.update({f"subscribers:{t}": str(pub.get_subscription_count()) for t, pub in self._dds_pubs.items()})
        problems, errors = dict(self.problems), dict(self.errors)  # camera threads add to them meanwhile
        level = 2 if errors else 1 if problems else 0
        message = "; ".join([*sorted(errors.values()), *sorted(problems.values())])[:500] or "ok"
        self._diag.publish(cdr.encode(DIAG, M.diagnostics_msg(time.time_ns(), [(level, self.get_name(), message, values)])))

    def close(self) -> None:
        """Flush outputs (the recorder closes its bag); called before the node is destroyed."""


class InitWatch:
    """A node's WARN while no subject is initialized for longer than `warn_s` of capture time,
    with the reason from the virtual markers (init_report.py)."""

    def __init__(self, warn_s: float, bound_px: float, camera_names: list[str] | None) -> None:
        self.warn_ns, self.bound_px, self.camera_names = int(warn_s * 1e9), bound_px, camera_names
        self.since_ns: int | None = None

    def update(self, node: VmocapNode, status: str, markers: Any, problem: str | None = None,
               min_presence: float | None = None) -> None:
        from vmocap_core.method.init_report import not_initialized_reason

        if status not in ("initializing", "lost", "none"):
            self.since_ns = None
            node.problems.pop("initializing", None)
            return
        self.since_ns = markers.stamp_ns if self.since_ns is None else self.since_ns
        waited = markers.stamp_ns - self.since_ns
        if self.warn_ns and waited >= self.warn_ns:
            names = self.camera_names or [f"camera {c}" for c in range(32)]
            why = not_initialized_reason(markers, names, self.bound_px, problem, min_presence)
            node.problems["initializing"] = f"no subject initialized for {waited / 1e9:.1f} s: {why}"
