"""The vmocap nodes: thin rclpy shells around vmocap_core (parameters, topics, conversion,
one call into the core per message). Messages travel as CDR bytes (rclpy raw subscriptions,
publish(bytes)) and are converted with vmocap_core.bag.messages, the same code the offline
pipeline uses: graph and `vmocap process` compute from identical inputs.
"""

from __future__ import annotations

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
        # a node publishing from its own threads (the camera node's readers) sets this: the spin
        # loop then wakes every poll_s to hand those messages over (executors cannot be woken
        # from another thread without a guard condition, which the EventsExecutor lacks)
        self.poll_s = 0.1

    def publish(self, topic: str, msg: dict) -> None:
        for cb in self.subscribers.get(topic, ()):
            self.pending.append((cb, msg))

    def drain(self) -> int:
        """Hand over the messages queued so far (not those queued meanwhile: a producer thread
        faster than the consumers must not starve the executor's timers and DDS events)."""
        n = len(self.pending)
        for _ in range(n):
            cb, msg = self.pending.popleft()
            cb(msg)
        return n


BUS = LocalBus()


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
    def publisher(self, type_name: str, topic: str, depth: int = STREAM_DEPTH, latched: bool = False) -> Callable[[dict], None]:
        pub = self.create_publisher(msg_class(type_name), topic, qos(depth, latched=latched))
        self._dds_pubs[topic] = pub
        if not BUS.enabled:
            if latched:  # transient local: kept for subscribers that match later
                return lambda msg: pub.publish(cdr.encode(type_name, msg))

            def publish_volatile(msg: dict) -> None:
                # volatile: a sample without a matched reader goes nowhere; skip its encoding
                # (e.g. the MarkerArray skeleton, 1.5 ms, when no RViz is listening)
                if pub.get_subscription_count() > 0:
                    pub.publish(cdr.encode(type_name, msg))

            return publish_volatile
        BUS.publishers.add(topic)

        def publish(msg: dict) -> None:
            BUS.publish(topic, msg)
            # over DDS only when someone outside this process's nodes subscribes (our own
            # nodes take it locally and have no DDS subscription on this topic)
            if pub.get_subscription_count() > 0:
                pub.publish(cdr.encode(type_name, msg))

        return publish

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
        if BUS.enabled:
            BUS.poll_s = 0.002  # frames come from the reader threads: hand them over within 2 ms
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

    def _run(self, src, cam, pub_img, pub_info) -> None:
        stamps = LoopedStamps()
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
            # a recorded frame is converted while it waits for its time, and goes out on time
            img, info = M.image_msg(frame.image, stamp, cam.name), M.camera_info_msg(cam, stamp)
            if due is not None:
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            elif self._playback.restamp:
                img["header"] = info["header"] = M.header(time.time_ns(), cam.name)
            pub_img(img)
            pub_info(info)
            self.published[cam.name] += 1

    def status(self) -> dict[str, Any]:
        return {"published": self.published}

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
        self._pubs: dict[str, tuple[Callable, Callable]] = {}
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
            for img, info in M.pcm_msgs(pcm, self.rig):
                cam_name = img["header"]["frame_id"]
                k = seen.get(cam_name, 0)
                seen[cam_name] = k + 1
                view = cam_name if k == 0 else f"{cam_name}_{k}"
                if view not in self._pubs:
                    self._pubs[view] = (self.publisher(IMAGE, self.topics.pcm(view)), self.publisher(INFO, self.topics.pcm_info(view)))
                pi, pc = self._pubs[view]
                pc(info)
                pi(img)
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
        self.subscribe(CLOUD, self.topics.markers, self._on_markers, depth=self.p["queue_depth"], latched=True)
        self.counts = {"frames": 0, "tracking": 0}
        self.last_status = "initializing"

    def _on_markers(self, msg: dict) -> None:
        t0 = time.perf_counter()
        result = self.stage.step(markers_from_message(msg))
        for topic, _ty, out in result_messages(self.topics, result):
            self.pubs[topic](out)
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


NODES: dict[str, type[VmocapNode]] = {
    "vmocap_camera": CameraNode,
    "vmocap_pcm": PcmNode,
    "vmocap_markers": MarkersNode,
    "vmocap_skeleton": SkeletonNode,
    "vmocap_recorder": RecorderNode,
}


def create(name: str, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None) -> VmocapNode:
    return NODES[name](config, overrides)
