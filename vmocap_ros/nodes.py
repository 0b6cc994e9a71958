"""The vmocap nodes: thin rclpy shells around vmocap_core (parameters, topics, conversion,
one call into the core per message). Messages travel as CDR bytes (rclpy raw subscriptions,
publish(bytes)) and are converted with vmocap_core.bag.messages, the same code the offline
pipeline uses: graph and `vmocap process` compute from identical inputs.
"""

from __future__ import annotations

import functools
import heapq
import itertools
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter

from vmocap_core import graph_config
from vmocap_core.bag import cdr
from vmocap_core.bag import messages as M
from vmocap_core.errors import VmocapError
from vmocap_core.process import (
    CLOUD, DIAG, IMAGE, INFO, PcmAssembler, TrackerPipeline, channel_keypoints, feedback_of,
    markers_from_message, markers_message, result_messages,
)
from vmocap_core.sources.clock import LoopedStamps, PlaybackClock
from vmocap_core.sync import ApproximateSync

from .common import Topics, declare, msg_class, qos
from .subject import recorded_outputs, recorder_tf, skeleton_outputs

STREAM_DEPTH = 10  # images, PCMs, markers: reliable, keep last 10


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
        return {"p50": f"{np.percentile(a, 50):.3f}", "p95": f"{np.percentile(a, 95):.3f}", "n": str(len(a))}


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


BUS = LocalBus()


class Output:
    """One output topic of a node; calling it publishes a message dict. In-process nodes
    (LocalBus) get the dict itself; over DDS it goes as CDR bytes, encoded only when a DDS
    reader matched, except on a transient-local (latched) topic of a node without local bus:
    kept for readers that match later. Volatile samples without a reader go nowhere, so their
    encoding is skipped (the MarkerArray alone costs ~0.4 ms). `prepare` + `send` split the
    work: a recorded camera frame is encoded while it waits for its due time."""

    __slots__ = ("type_name", "topic", "pub", "latched", "local")

    def __init__(self, type_name: str, topic: str, pub: Any, latched: bool) -> None:
        self.type_name, self.topic, self.pub, self.latched = type_name, topic, pub, latched
        self.local = BUS.enabled  # our nodes in this process subscribe locally, not over DDS

    def dds_wanted(self) -> bool:
        return (self.latched and not self.local) or self.pub.get_subscription_count() > 0

    def wanted(self) -> bool:
        """Does anyone take this topic (a local node or a DDS reader)? Else skip building it."""
        return bool(self.local and BUS.subscribers.get(self.topic)) or self.dds_wanted()

    def prepare(self, msg: dict) -> tuple[dict, bytes | None]:
        return msg, (cdr.encode(self.type_name, msg) if self.dds_wanted() else None)

    def send(self, prepared: tuple[dict, bytes | None]) -> None:
        msg, data = prepared
        if self.local:
            BUS.publish(self.topic, msg)
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


DUE = DueQueue()


class VmocapNode(Node):
    """Base: validated parameters (declared with descriptions/ranges), raw pub/sub helpers,
    CPU accounting, a 1 Hz /diagnostics status."""

    needs_rig = True

    def __init__(self, name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__(name)
        self.p = config.node_params(name, overrides)
        declare(self, [q for q in graph_config.params_of(name) if q.name != "use_sim_time"], self.p)
        if self.p["use_sim_time"]:
            self.set_parameters([Parameter("use_sim_time", Parameter.Type.BOOL, True)])
        self.config = config
        self.topics = Topics(self.p["namespace"])
        self.rig = None
        if self.p["rig"] and self.needs_rig:
            from vmocap_core.rig_io import load_rig

            rig = load_rig(self.p["rig"])
            self.rig = rig.subset(self.p["cameras"]) if self.p["cameras"] else rig
        self.cpu_s = 0.0
        self.proc = Stat()
        self.age = Stat()  # capture stamp -> end of processing, ms (wall clock)
        self.problems: dict[str, str] = {}
        self._pending_subs: list = []
        self._dds_pubs: dict[str, Any] = {}  # topic -> rclpy publisher, for matched-subscriber counts
        self._diag = self.create_publisher(msg_class(DIAG), Topics.diagnostics, qos(10))
        self.create_timer(1.0, self._publish_diagnostics)

    # -- raw messages --------------------------------------------------------------------
    def publisher(self, type_name: str, topic: str, depth: int = STREAM_DEPTH, latched: bool = False) -> "Output":
        pub = self.create_publisher(msg_class(type_name), topic, qos(depth, latched=latched))
        self._dds_pubs[topic] = pub
        if BUS.enabled:
            BUS.publishers.add(topic)
        return Output(type_name, topic, pub, latched)

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
        if not BUS.enabled:
            self.finalize()

    def finalize(self) -> None:
        """Create the subscriptions: local for topics a node of this process publishes."""
        subs, self._pending_subs = self._pending_subs, []
        for type_name, topic, guarded, depth, latched in subs:
            if BUS.enabled and topic in BUS.publishers:
                BUS.subscribers.setdefault(topic, []).append(guarded)
                continue
            # images and heatmaps: numpy views into the received bytes (no further copy)
            copy = type_name != IMAGE
            self.create_subscription(msg_class(type_name), topic,
                                     lambda data, g=guarded, t=type_name, c=copy: g(cdr.decode(t, data, copy=c)),
                                     qos(depth, latched=latched), raw=True)

    # -- diagnostics ---------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        return {}

    def _publish_diagnostics(self) -> None:
        values = {"cpu_s": f"{self.cpu_s:.4f}"}
        values.update({f"proc_ms_{k}": v for k, v in self.proc.summary().items()})
        values.update({f"age_ms_{k}": v for k, v in self.age.summary().items()})
        values.update({k: str(v) for k, v in self.status().items()})
        # matched DDS subscribers per output: volatile outputs published before a subscriber
        # matched are gone, so whoever records or controls can check it is connected
        values.update({f"subscribers:{t}": str(pub.get_subscription_count()) for t, pub in self._dds_pubs.items()})
        level = 1 if self.problems else 0
        message = "; ".join(sorted(self.problems.values()))[:500] or "ok"
        self._diag.publish(cdr.encode(DIAG, M.diagnostics_msg(time.time_ns(), [(level, self.get_name(), message, values)])))

    def close(self) -> None:
        """Flush outputs (the recorder closes its bag); called before the node is destroyed."""


class CameraNode(VmocapNode):
    """Frames of a FrameSource per camera -> NS/CAM/image_raw + NS/CAM/camera_info."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__("vmocap_camera", config, overrides)
        if self.rig is None:
            raise VmocapError("vmocap_camera needs a rig")
        self._stop = threading.Event()
        self._playback = PlaybackClock(self.p["rate"], self.p["restamp"])
        self._image_topics: list[str] = []
        self._matched = threading.Event()
        self._first_match: float | None = None
        self._threads = []
        self.published = {c.name: 0 for c in self.rig}
        self.late_dropped = {c.name: 0 for c in self.rig}  # restamped replay: frames a period late, skipped
        for cam in self.rig:
            src = self._make_source(cam.name)
            src.open()
            pub_img = self.publisher(IMAGE, self.topics.image(cam.name))
            pub_info = self.publisher(INFO, self.topics.camera_info(cam.name))
            self._image_topics.append(self.topics.image(cam.name))
            th = threading.Thread(target=self._run, args=(src, cam, pub_img, pub_info), daemon=True)
            self._threads.append((th, src))
        for th, _ in self._threads:
            th.start()
        self._wait_end = time.monotonic() + self.p["wait_subscribers"]
        self._matched_timer = self.create_timer(0.05, self._check_matched)
        self._check_matched()

    def _check_matched(self) -> None:
        """Recorded sources start 0.2 s after an image topic has a subscriber (one of our nodes
        in this process or a matched DDS reader; the 0.2 s let a subscriber's other topics
        match too), at most wait_subscribers seconds after start-up: frames published before
        the PCM node has matched would be lost."""
        if self._matched.is_set():
            return
        now = time.monotonic()
        if self._first_match is None and any(self.count_subscribers(t) + len(BUS.subscribers.get(t, ()))
                                             for t in self._image_topics):
            self._first_match = now
        if (self._first_match is not None and now >= self._first_match + 0.2) or now >= self._wait_end:
            self._matched.set()
            self._matched_timer.cancel()
            self.get_logger().info("playing" + (" (no subscriber yet)" if self._first_match is None else ""))

    def _make_source(self, camera: str):
        kind, uri = self.p["source"], self.p["uri"]
        if kind == "bag":
            from vmocap_core.sources.bag import BagFrameSource

            return BagFrameSource(uri, camera, topic=self.topics.image(camera), start_offset_s=self.p["start_offset"], loop=self.p["loop"])
        import importlib

        try:
            factory = getattr(importlib.import_module("vmocap_core.sources"), "make_source")
        except (ImportError, AttributeError):
            raise VmocapError(f"camera source {kind!r} is not available (vmocap_core.sources.make_source missing)") from None
        return factory(kind, uri, camera)

    def _run(self, src, cam, pub_img: Output, pub_info: Output) -> None:
        stamps = LoopedStamps()
        slot = threading.Semaphore(1)  # one frame of this camera waits for its time, the next is read meanwhile
        last_due: float | None = None
        prev_due: float | None = None  # due time of the frame read before (sent or not)
        while not self._stop.is_set():
            try:
                frame = src.read(timeout=0.5)
            except VmocapError as exc:
                self.problems[f"camera:{cam.name}"] = str(exc)
                self.get_logger().error(str(exc))
                return
            bad = getattr(src, "bad_frames", 0)
            if bad:
                self.problems[f"frames:{cam.name}"] = f"{cam.name}: {bad} frames skipped ({src.last_error})"
            if frame is None:
                if src.exhausted:
                    return
                continue
            if not getattr(src, "live", False) and not self._matched.is_set():
                while not self._matched.wait(0.05):
                    if self._stop.is_set():
                        return
            stamp, due = self._playback.schedule(stamps(frame.stamp_ns), time.monotonic(), time.time_ns())
            # the message refers to the frame's pixels (sources never reuse a frame's array)
            img, info = M.image_msg(frame.image, stamp, cam.name, copy=False), M.camera_info_msg(cam, stamp)
            if due is None:
                if self._playback.restamp:
                    img["header"] = info["header"] = M.header(time.time_ns(), cam.name)
                self._send(cam.name, pub_img.prepare(img), pub_info.prepare(info), pub_img, pub_info)
                continue
            # a recorded frame is converted (and encoded for DDS readers) while it waits for its time
            prepared = (pub_img.prepare(img), pub_info.prepare(info))
            while not slot.acquire(timeout=0.1):  # the previous frame of this camera is still due
                if self._stop.is_set():
                    return
            period, prev_due = (due - prev_due if prev_due is not None else 0.0), due
            if self._playback.superseded(due, period, time.monotonic()):  # replayed as live: skipped
                slot.release()
                self.late_dropped[cam.name] += 1
                continue
            if DUE.wake is not None:  # the spin loop sends it when due, and frees the slot
                period = due - last_due if last_due is not None else 0.0
                last_due = due
                DUE.put(due, functools.partial(self._send_due, cam.name, prepared, pub_img, pub_info, slot, due + 0.5 * period))
                continue
            delay = due - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            self._send(cam.name, *prepared, pub_img, pub_info)
            slot.release()

    def _send_due(self, cam: str, prepared: tuple, pub_img: Output, pub_info: Output, slot: threading.Semaphore,
                  release_at: float) -> None:
        self._send(cam, *prepared, pub_img, pub_info)
        # this camera's reader thread reads its next frame once the graph is done with this
        # frame set (or half a period later): woken meanwhile, it would take the GIL from it
        DUE.when_idle(slot.release, release_at)

    def _send(self, cam: str, img: tuple, info: tuple, pub_img: Output, pub_info: Output) -> None:
        pub_img.send(img)
        pub_info.send(info)
        self.published[cam] += 1
        self.age.add((time.time_ns() - M.stamp_ns(img[0])) / 1e6)  # how late the frame went out

    def status(self) -> dict[str, Any]:
        return {"published": self.published, "late_dropped": self.late_dropped}

    def close(self) -> None:
        self._stop.set()
        for th, src in self._threads:
            th.join(timeout=2.0)
            src.close()


class PcmNode(VmocapNode):
    """Synchronized camera images -> PCM heatmaps per view (NS/pcm/VIEW/heatmaps + camera_info)."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__("vmocap_pcm", config, overrides)
        if self.rig is None:
            raise VmocapError("vmocap_pcm needs a rig")
        p = self.p
        names = self.rig.names
        self.sync: ApproximateSync[np.ndarray] = ApproximateSync(
            names, int(p["sync_tolerance_ms"] * 1e6), p["min_cameras"], int(p["silent_after_ms"] * 1e6))
        self.provider = self._make_provider()
        self.feedback: np.ndarray | None = None
        self.info_mismatch: dict[str, str] = {}
        self._info_seen: dict[str, tuple] = {}  # camera -> the CameraInfo last compared with the rig
        self._pubs: dict[str, tuple[Output, Output]] = {}
        for name in names:
            self.subscribe(IMAGE, self.topics.image(name), lambda m, n=name: self._on_image(n, m), depth=p["queue_depth"])
            self.subscribe(INFO, self.topics.camera_info(name), lambda m, n=name: self._on_info(n, m))
        self.subscribe(CLOUD, self.topics.feedback, self._on_feedback, depth=50, latched=True)
        # one view per camera exists from the start (publishers created late would lose their
        # first messages while discovery matches them); extra views (CAM_1...) come on demand
        for name in names:
            self._pubs[name] = (self.publisher(IMAGE, self.topics.pcm(name)), self.publisher(INFO, self.topics.pcm_info(name)))
        self.frames = 0
        self.sets: deque = deque()
        self.counts = {"queue_dropped": 0, "feedback_timeouts": 0}
        self.wait = p["feedback_wait_ms"] / 1e3
        self.awaiting: int | None = None
        self.awaiting_since = 0.0
        if self.wait > 0:
            self.create_timer(min(0.02, self.wait / 2), self._check_timeout)

    def _make_provider(self):
        from vmocap_core.process import BagPcmProvider, SyntheticPcmProvider

        kind, model = self.p["source"], self.p["model"]
        if kind == "synthetic":
            fps = self.config.tracker_dict(self.config.node_params("vmocap_skeleton")).get("fps", 30.0)
            return SyntheticPcmProvider(self.rig, model, fps)
        if model.endswith(".mcap"):
            return BagPcmProvider(model, self.rig, channel_keypoints(self.p["pcm_keypoints"]), self.p["namespace"])
        from vmocap_core.process import make_model_provider  # the CNN (vmocap_core.pcm)

        provider = make_model_provider(model, self.rig, self.p["rotation"], self.p["threads"])
        expected = list(channel_keypoints(self.p["pcm_keypoints"]))
        if list(provider.pcm.landmark.keypoints) != expected:
            raise VmocapError(f"pcm_keypoints of the config do not match the model's channels "
                              f"({len(provider.pcm.landmark.keypoints)} channels; for BlazePose leave pcm_keypoints empty)")
        return provider

    def _on_info(self, cam: str, msg: dict) -> None:
        # a camera sends the same CameraInfo every frame: compare with the rig only when it changed
        seen = (msg["width"], msg["height"], msg["distortion_model"], np.asarray(msg["k"]).tobytes(), np.asarray(msg["d"]).tobytes())
        if self._info_seen.get(cam) == seen:
            return
        self._info_seen[cam] = seen
        problem = M.camera_info_mismatch(msg, self.rig[cam])
        if problem and cam not in self.info_mismatch:
            self.get_logger().warning(problem + " (the rig is used)")
        if problem:
            self.info_mismatch[cam] = problem
            self.problems[f"info:{cam}"] = problem

    def _on_feedback(self, msg: dict) -> None:
        self.feedback = M.cloud_keypoints(msg)[0]
        if self.awaiting is not None and M.stamp_ns(msg) == self.awaiting:
            self.awaiting = None
            self._pump()

    def _on_image(self, cam: str, msg: dict) -> None:
        t = M.stamp_ns(msg)
        for fs in self.sync.add(cam, t, M.image_array(msg)):
            self.sets.append(fs)
            if len(self.sets) > self.p["queue_depth"]:
                self.sets.popleft()
                self.counts["queue_dropped"] += 1
        self._pump()

    def _check_timeout(self) -> None:
        if self.awaiting is not None and time.monotonic() - self.awaiting_since > self.wait:
            self.counts["feedback_timeouts"] += 1
            self.problems["feedback"] = f"no skeleton feedback within {self.wait * 1e3:.0f} ms ({self.counts['feedback_timeouts']}x)"
            self.awaiting = None
            self._pump()

    def _pump(self) -> None:
        """Frame sets in order; with feedback_wait_ms > 0 frame t waits for the skeleton of the
        frame before it (crops from t-1, as offline), otherwise the latest skeleton is used."""
        while self.sets and self.awaiting is None:
            fs = self.sets.popleft()
            t0 = time.perf_counter()
            cams = [n for n in self.rig.names if n in fs.items]
            idx = np.array([self.rig.names.index(n) for n in cams])
            fb = self.feedback if self.p["use_feedback"] else None
            pcm = self.provider.infer([fs.items[n] for n in cams], idx, fs.stamp_ns, fb)
            if self.wait > 0 and self.p["use_feedback"]:
                self.awaiting, self.awaiting_since = fs.stamp_ns, time.monotonic()
            seen: dict[str, int] = {}
            # without a DDS reader of the heatmaps (all nodes in one process), our vmocap_markers
            # gets the maps themselves: no interleaving into Image data and back (~1 ms a set)
            data = any(pi.dds_wanted() for pi, _ in self._pubs.values())
            for img, info in M.pcm_msgs(pcm, self.rig, data=data):
                cam_name = img["header"]["frame_id"]
                k = seen.get(cam_name, 0)
                seen[cam_name] = k + 1
                view = cam_name if k == 0 else f"{cam_name}_{k}"
                if view not in self._pubs:
                    self._pubs[view] = (self.publisher(IMAGE, self.topics.pcm(view)), self.publisher(INFO, self.topics.pcm_info(view)))
                pi, pc = self._pubs[view]
                pc(info)
                if data:
                    pi(img)
                else:
                    pi.send((img, None))  # to our nodes only
            if pcm.n_views == 0 and self.awaiting is not None:
                self.awaiting = None  # nothing published: no skeleton will answer this frame
            self.frames += 1
            self.proc.add(1e3 * (time.perf_counter() - t0))
            self.age.add((time.time_ns() - fs.stamp_ns) / 1e6)

    def status(self) -> dict[str, Any]:
        st = self.sync.stats()
        return dict(self.counts, frames=self.frames, pcm=self.provider.name, sync=st.as_dict(), silent=list(st.silent),
                    queued=len(self.sets))


class MarkersNode(VmocapNode):
    """PCM views -> frame sets -> MarkerStage (lattice search) -> NS/markers. The lattice of
    frame t waits for the skeleton of frame t-1 (NS/feedback) so results are deterministic."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__("vmocap_markers", config, overrides)
        if self.rig is None:
            raise VmocapError("vmocap_markers needs a rig")
        p = self.p
        views = p["views"] or self.rig.names
        self.asm = PcmAssembler(self.rig, views, channel_keypoints(p["pcm_keypoints"]),
                                int(p["sync_tolerance_ms"] * 1e6), p["min_cameras"], int(p["silent_after_ms"] * 1e6))
        self.pipe = TrackerPipeline(self.rig, config.tracker_dict(p))
        self.stage = self.pipe.markers
        self.queue: deque = deque()
        self.awaiting: int | None = None
        self.awaiting_since = 0.0
        self.timeout = p["feedback_timeout_ms"] / 1e3
        self.counts = {"frames": 0, "queue_dropped": 0, "feedback_timeouts": 0}
        # markers and feedback are transient-local: a frame processed before the other node's
        # subscription matched (start-up) is still delivered, keeping the chain deterministic
        self.pub = self.publisher(CLOUD, self.topics.markers, depth=p["queue_depth"], latched=True)
        for v in views:
            self.subscribe(IMAGE, self.topics.pcm(v), lambda m, v=v: self._enqueue(self.asm.add_image(v, m)), depth=p["queue_depth"])
            self.subscribe(INFO, self.topics.pcm_info(v), lambda m, v=v: self._enqueue(self.asm.add_info(v, m)), depth=p["queue_depth"])
        self.subscribe(CLOUD, self.topics.feedback, self._on_feedback, depth=50, latched=True)
        if self.timeout > 0:
            self.create_timer(min(0.02, self.timeout / 2), self._check_timeout)

    def _enqueue(self, pcms: list) -> None:
        for pcm in pcms:
            self.queue.append(pcm)
            if len(self.queue) > self.p["queue_depth"]:
                self.queue.popleft()
                self.counts["queue_dropped"] += 1
        self._pump()

    def _pump(self) -> None:
        while self.queue and (self.awaiting is None or self.timeout == 0):
            pcm = self.queue.popleft()
            t0 = time.perf_counter()
            markers = self.stage.step(pcm)
            if self.timeout > 0:  # before publishing: the feedback may come back at once
                self.awaiting, self.awaiting_since = pcm.stamp_ns, time.monotonic()
            self.pub(markers_message(markers))
            self.counts["frames"] += 1
            self.proc.add(1e3 * (time.perf_counter() - t0))
            self.age.add((time.time_ns() - pcm.stamp_ns) / 1e6)

    def _on_feedback(self, msg: dict) -> None:
        t = M.stamp_ns(msg)
        if self.timeout > 0 and t != self.awaiting:
            return  # late feedback of a frame we stopped waiting for
        self.stage.feedback(M.cloud_keypoints(msg)[0])
        self.awaiting = None
        self._pump()

    def _check_timeout(self) -> None:
        if self.awaiting is not None and time.monotonic() - self.awaiting_since > self.timeout:
            self.counts["feedback_timeouts"] += 1
            self.problems["feedback"] = f"no skeleton feedback within {self.timeout * 1e3:.0f} ms ({self.counts['feedback_timeouts']}x)"
            self.stage.feedback(None)  # re-initialize rather than search around a stale skeleton
            self.awaiting = None
            self._pump()

    def status(self) -> dict[str, Any]:
        st = self.asm.sync.stats()
        return dict(self.counts, queued=len(self.queue), sync=st.as_dict(), silent=list(st.silent),
                    rejected_frame_sets=self.asm.bad_views)


class SkeletonNode(VmocapNode):
    """NS/markers -> SkeletonStage (IK, IIR, second IK) -> NS/joint_states, NS/keypoints,
    NS/skeleton and the feedback NS/feedback."""

    needs_rig = False

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__("vmocap_skeleton", config, overrides)
        from vmocap_core.tracker import SkeletonStage, TrackerConfig

        self.stage = SkeletonStage(TrackerConfig.from_dict(config.tracker_dict(self.p)))
        self.pubs = {}
        for topic, ty in ((self.topics.feedback, CLOUD), (self.topics.joint_states, "sensor_msgs/msg/JointState"),
                          (self.topics.keypoints, CLOUD), (self.topics.skeleton, "visualization_msgs/msg/MarkerArray")):
            fb = topic == self.topics.feedback
            self.pubs[topic] = self.publisher(ty, topic, depth=50 if fb else STREAM_DEPTH, latched=fb)
        self.subject, extra = skeleton_outputs(self)  # robot_description, root_pose, TF
        self.pubs.update(extra)
        self.subscribe(CLOUD, self.topics.markers, self._on_markers, depth=self.p["queue_depth"], latched=True)
        self.counts = {"frames": 0, "tracking": 0}
        self.last_status = "initializing"

    def _on_markers(self, msg: dict) -> None:
        t0 = time.perf_counter()
        result = self.stage.step(markers_from_message(msg))
        # feedback, then joint_states; outputs nobody subscribes to are not even built
        pubs = self.pubs
        for topic, _ty, out in result_messages(self.topics, result, subject=self.subject,
                                               wanted=lambda topic: topic in pubs and pubs[topic].wanted()):
            if topic in pubs:
                pubs[topic](out)
        self.counts["frames"] += 1
        self.counts["tracking"] += result.status == "tracking"
        self.last_status = result.status
        self.proc.add(1e3 * (time.perf_counter() - t0))
        self.age.add((time.time_ns() - result.stamp_ns) / 1e6)

    def status(self) -> dict[str, Any]:
        return dict(self.counts, status=self.last_status)


class RecorderNode(VmocapNode):
    """Topics -> MCAP (CDR bytes as received). The file is complete and renamed from .partial
    when the node is closed (Ctrl-C/SIGTERM of the launcher or `vmocap record`)."""

    needs_rig = False

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> None:
        super().__init__("vmocap_recorder", config, overrides)
        from vmocap_core.bag import BagWriter

        if not self.p["output"]:
            raise VmocapError("vmocap_recorder: parameter 'output' (an .mcap path) is required")
        self.writer = BagWriter(self.p["output"], compression=self.p["compression"]).open()
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


NODES: dict[str, type[VmocapNode]] = {
    "vmocap_camera": CameraNode,
    "vmocap_pcm": PcmNode,
    "vmocap_markers": MarkersNode,
    "vmocap_skeleton": SkeletonNode,
    "vmocap_recorder": RecorderNode,
}


def create(name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> VmocapNode:
    return NODES[name](config, overrides)
