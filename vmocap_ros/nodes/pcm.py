"""vmocap_pcm: PCM inference. Synchronized camera images -> the CNN (vmocap_core.pcm) -> heatmaps
per view (NS/pcm/VIEW/heatmaps + camera_info); crops and rotation from the fed-back skeleton."""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from vmocap_core import graph_config
from vmocap_core.bag import heatmaps
from vmocap_core.bag import messages as M
from vmocap_core.cameras.bag import check_binning
from vmocap_core.cameras.flow import CnnPace
from vmocap_core.cameras.sync import ApproximateSync
from vmocap_core.errors import VmocapError
from vmocap_core.method.camera_check import image_problem
from vmocap_core.method.prediction import BodyPredictor
from vmocap_core.outputs.messages import CLOUD, HEADER, IMAGE, INFO
from vmocap_core.pcm.assembly import channel_keypoints
from vmocap_core.pcm.peaks import camera_keypoints
from vmocap_core.pcm.views import blank_views

from ..common import Topics
from ..shm_link import ShmIn, ShmOut
from ..transport import Output, Transport
from .base import VmocapNode


class PcmNode(VmocapNode):
    """Synchronized camera images -> PCM heatmaps per view (NS/pcm/VIEW/heatmaps + camera_info)."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_pcm") -> None:
        super().__init__(name, config, overrides, transport)
        if self.rig is None:
            raise VmocapError("vmocap_pcm needs a rig")
        p = self.p
        check_binning(p["binning"])
        self.seen = self.rig.binned(p["binning"])  # the cameras as their images come (REP 104 binning)
        names = self.rig.names
        self.sync: ApproximateSync[np.ndarray] = ApproximateSync(
            names, int(p["sync_tolerance_ms"] * 1e6), p["min_cameras"], int(p["silent_after_ms"] * 1e6))
        self.provider = self._make_provider()
        # the crops follow the feedback extrapolated to each frame set (method/prediction.py)
        self.predictor = BodyPredictor.for_provider(self.provider)
        self.info_mismatch: dict[str, str] = {}
        self._info_seen: dict[str, tuple] = {}  # camera -> the CameraInfo last compared with the rig
        self._pubs: dict[str, tuple[Output, Output]] = {}
        for name in names:
            self.subscribe(IMAGE, self.topics.image(name), lambda m, n=name: self._on_image(n, m), depth=max(2, p["queue_depth"]))
            self.subscribe(INFO, self.topics.camera_info(name), lambda m, n=name: self._on_info(n, m))
        # frames of a camera node in another process of this machine come through shared memory
        self._shm_in = ShmIn(self) if p["shm_images"] else None
        if self._shm_in is not None:
            for name in names:
                self._shm_in.subscribe(self.topics.image(name), name, lambda m, n=name: self._on_image(n, m),
                                       depth=max(2, p["queue_depth"]))
        self._subscribe_feedback()
        # one view per camera exists from the start (publishers created late would lose their
        # first messages while discovery matches them); extra views (CAM_1...) come on demand
        # in lockstep the heatmaps are transient-local, as markers and feedback are: a view the
        # markers node matched late still gets its first heatmaps (one lost one stalls the loop)
        self._latched = bool(p["lockstep"])
        # heatmaps for vmocap_markers nodes of this machine through shared memory (not in lockstep:
        # a reference read late by a transient-local reader could find its slot written again)
        self._hm_shm: dict[str, ShmOut] = {}
        for topics in self._heatmap_topics():
            for name in names:
                self._pubs[topics.pcm(name)] = self._view_publishers(topics, name)
        if self._hm_shm:
            self.create_timer(0.5, self._check_shm)
        self._kp_pubs = {name: self.publisher(CLOUD, self.topics.pcm_keypoints(name)) for name in names}
        self._done = self.publisher(HEADER, self.topics.pcm_done)  # vmocap_camera's flow control
        self.frames = 0
        self.sets: deque = deque()
        self.counts = {"queue_dropped": 0, "feedback_timeouts": 0}
        self.bad_images = {n: 0 for n in names}  # images not given to the CNN (wrong size, no contrast)
        self.wait = p["feedback_wait_ms"] / 1e3
        self.awaiting: int | None = None
        self.awaiting_since = 0.0
        if self.wait > 0:
            self.create_timer(min(0.02, self.wait / 2), self._check_timeout)
        self.pace = CnnPace()  # whether the CNN keeps up with the frame sets
        self.busy = False  # a frame set is in the inference thread
        self.worker = ThreadPoolExecutor(1, thread_name_prefix=self.get_name()) if p["inference_thread"] else None

    def _check_shm(self) -> None:
        for out in self._hm_shm.values():
            out.check()

    def _subscribe_feedback(self) -> None:
        self.subscribe(CLOUD, self.topics.feedback, self._on_feedback, depth=50, latched=True)

    def _heatmap_topics(self) -> list[Topics]:
        """Where the heatmaps go: the graph's namespace (several people: one per slot)."""
        return [self.topics]

    def _view_publishers(self, topics: Topics, view: str) -> tuple[Output, Output]:
        if self.p["shm_images"] and not self._latched:
            self._hm_shm[topics.pcm(view)] = ShmOut(self, topics.pcm(view))
        return (self.publisher(IMAGE, topics.pcm(view), latched=self._latched),
                self.publisher(INFO, topics.pcm_info(view), latched=self._latched))

    def _make_provider(self):
        from vmocap_core.pcm.providers import BagPcmProvider, SyntheticPcmProvider

        kind, model = self.p["source"], self.p["model"]
        if kind == "synthetic":
            return SyntheticPcmProvider(self.rig, model, self.p["fps"])
        if model.endswith(".mcap"):
            return BagPcmProvider(model, self.rig, channel_keypoints(self.p["pcm_keypoints"]), self.p["namespace"])
        from vmocap_core.pcm.providers import make_model_provider  # the CNN

        # the census of others in view runs beside the frame sets, on CPU they leave over (pcm/census.py)
        provider = make_model_provider(model, self.rig, self.p["rotation"], self.p["threads"], self.p["binning"],
                                       self.p["crop_prediction"], self.p["census_every"], census_background=True)
        provider.warm_up()  # before READY: the first frame set would wait for it
        from vmocap_core.pcm import selfcheck

        check = selfcheck.last_verdict()
        if check is not None and check.warning:  # a failing self-check: running, but on the slower float model
            self.problems["cnn"] = check.warning
        expected = list(channel_keypoints(self.p["pcm_keypoints"]))
        if list(provider.pcm.landmark.keypoints) != expected:
            raise VmocapError(f"pcm_keypoints of the config do not match the model's channels "
                              f"({len(provider.pcm.landmark.keypoints)} channels; for BlazePose leave pcm_keypoints empty)")
        return provider

    def _on_info(self, cam: str, msg: dict) -> None:
        # a camera sends the same CameraInfo every frame: compare with the rig only when it changed
        seen = (msg["width"], msg["height"], msg.get("binning_x"), msg["distortion_model"], np.asarray(msg["k"]).tobytes(),
                np.asarray(msg["d"]).tobytes())
        if self._info_seen.get(cam) == seen:
            return
        self._info_seen[cam] = seen
        problem = M.camera_info_mismatch(msg, self.rig[cam], binning=self.p["binning"])
        if problem and cam not in self.info_mismatch:
            self.get_logger().warning(problem + " (the rig is used)")
        if problem:
            self.info_mismatch[cam] = problem
            self.problems[f"info:{cam}"] = problem

    def _on_feedback(self, msg: dict) -> None:
        self.predictor.update(M.stamp_ns(msg), M.cloud_keypoints(msg)[0])
        if self.awaiting is not None and M.stamp_ns(msg) == self.awaiting:
            self.awaiting = None
            self._pump()

    def _on_image(self, cam: str, msg: dict) -> None:
        t = M.stamp_ns(msg)
        for fs in self.sync.add(cam, t, M.image_array(msg)):
            self.pace.arrived(time.monotonic())
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
        frame before it (crops from t-1, as offline), otherwise the latest skeleton is used.
        With inference_thread the CNN runs beside the spin loop (onnxruntime releases the GIL),
        so camera frames, markers and skeleton of the previous frame set go on meanwhile."""
        while self.sets and self.awaiting is None and not self.busy:
            if self.wait == 0 and self.pace.newest_only(len(self.sets), self.p["queue_depth"]):
                while len(self.sets) > 1:  # live and overloaded: the older ones would only add latency
                    self.sets.popleft()
                    self.counts["queue_dropped"] += 1
            fs = self.sets.popleft()
            cams = [n for n in self.rig.names if n in fs.items and self._usable(n, fs.items[n])]
            fb = self.predictor.predict(fs.stamp_ns) if self.p["use_feedback"] else None
            if self.wait > 0 and self.p["use_feedback"]:
                self._await_feedback(fs.stamp_ns)
            # without a DDS reader of the heatmaps (all nodes in one process), our vmocap_markers
            # gets the maps themselves: no interleaving into Image data and back (~1 ms a set)
            data = any(pi.dds_wanted() for pi, _ in self._pubs.values())
            if self.worker is None or self.transport.due.wake is None:  # no spin loop to hand back to
                self._publish(fs, data, *self._infer(fs, cams, fb, data))
                continue
            self.busy = True
            self.worker.submit(self._infer_in_thread, fs, cams, fb, data)

    def _await_feedback(self, stamp_ns: int) -> None:
        self.awaiting, self.awaiting_since = stamp_ns, time.monotonic()

    def _infer(self, fs: Any, cams: list[str], fb: np.ndarray | None, data: bool) -> tuple[Any, list, float]:
        """The CNN on the usable cameras' images; the others get blank views (see blank_views).
        The messages: (heatmap topic, Image, CameraInfo) per view."""
        t0 = time.perf_counter()
        idx = np.array([self.rig.names.index(n) for n in cams])
        pcm = self.provider.infer([fs.items[n] for n in cams], idx, fs.stamp_ns, fb)
        unused = [self.rig.names.index(n) for n in fs.items if n not in cams]
        if unused and pcm.n_views:
            pcm = blank_views(pcm, unused)
        msgs = heatmaps.pcm_msgs(pcm, self.rig, data=data)
        names = heatmaps.view_names(pcm, self.rig)
        return pcm, [(self.topics, v, img, info) for v, (img, info) in zip(names, msgs)], time.perf_counter() - t0

    def _infer_in_thread(self, fs: Any, cams: list[str], fb: np.ndarray | None, data: bool) -> None:
        try:
            out = self._infer(fs, cams, fb, data)
        except Exception as exc:  # noqa: BLE001 - reported by the spin loop, the node goes on
            error = exc
            self.transport.due.put(time.monotonic(), lambda: self._failed(error))
            return
        self.transport.due.put(time.monotonic(), lambda: self._publish(fs, data, *out))

    def _failed(self, exc: Exception) -> None:
        self.busy = False
        self.awaiting = None
        self.errors["inference"] = f"PCM inference failed: {exc}"
        self.get_logger().error(self.errors["inference"])
        self._pump()

    def _publish(self, fs: Any, data: bool, pcm: Any, msgs: list, seconds: float) -> None:
        """In the spin loop's thread: the frame set's heatmaps out, then the next frame set in."""
        t0 = time.perf_counter()
        for topics, view, img, info in msgs:
            topic = topics.pcm(view)
            if topic not in self._pubs:
                self._pubs[topic] = self._view_publishers(topics, view)
            pi, pc = self._pubs[topic]
            pc(info)
            shm = self._hm_shm.get(topic)
            if data and shm is not None and shm.on:  # the maps into shared memory, a reference over DDS
                shm.send(img)
            elif data:
                pi(img)
            else:
                pi.send((img, None))  # to our nodes only
        self._publish_keypoints(pcm, fs.items, fs.stamp_ns)
        self._done(M.header(fs.stamp_ns, ",".join(fs.items)))
        if not msgs and self.awaiting is not None:
            self.awaiting = None  # nothing published: no skeleton will answer this frame
        self.errors.pop("inference", None)
        self.pace.finished(seconds)
        self.frames += 1
        self.proc.add(1e3 * (seconds + time.perf_counter() - t0))
        self.record_age(fs.stamp_ns)
        self.busy = False
        self._pump()

    def _publish_keypoints(self, pcm: Any, cams: Any, stamp_ns: int) -> None:
        """Each camera's 2D keypoints, for whoever subscribes (a viewer, a recording that needs
        the detections but not the 1.7 MB of heatmaps per frame set)."""
        wanted = [n for n in cams if self._kp_pubs[n].wanted()]
        if not wanted:
            return
        uv, w = camera_keypoints(pcm, len(self.rig))
        for n in wanted:
            c = self.rig.names.index(n)
            self._kp_pubs[n](M.image_keypoints_msg(stamp_ns, n, uv[c], w[c]))

    def close(self) -> None:
        if self._shm_in is not None:
            self._shm_in.close()
        for out in self._hm_shm.values():
            out.close()
        if self.worker is not None:
            self.worker.shutdown(wait=True, cancel_futures=True)
        if hasattr(self.provider, "close"):
            self.provider.close()
        super().close()

    def _usable(self, cam: str, image: np.ndarray) -> bool:
        """False (and a WARN naming the camera, held WARN_HOLD_S) for an image the CNN must not
        get: another size than the rig's calibration, or no contrast (all black / white). The
        camera then has no view in this frame set, as a camera without a frame; the others go on."""
        c = self.seen[cam]
        problem = image_problem(image, c.width, c.height)
        if not problem:
            return True
        self.bad_images[cam] += 1
        self.warn_for(f"image:{cam}", f"{cam}: {problem}: not used ({self.bad_images[cam]} frames so far)")
        return False

    def status(self) -> dict[str, Any]:
        st = self.sync.stats()
        self.watch_late(st.late)
        self.watch_silent(st.silent)
        self.watch_dropped(self.counts["queue_dropped"])
        # people besides the subject, per camera, from the CNN's detector (vmocap_core.pcm.choice)
        others = self.provider.others_in_view() if hasattr(self.provider, "others_in_view") else {}
        census = getattr(getattr(self.provider, "pcm", None), "census", None)
        if census is not None and census.error:
            self.warn_for("census", f"the look for others in view failed: {census.error}")
        return dict(self.counts, frames=self.frames, bad_images=self.bad_images, pcm=self.provider.name, sync=st.as_dict(), silent=list(st.silent),
                    queued=len(self.sets), precision=getattr(self.provider, "precision", "n/a"),
                    precision_reason=getattr(self.provider, "precision_reason", "n/a"),
                    shared_memory=self._shm_in.status() if self._shm_in is not None else "off",
                    heatmaps_shared_memory=bool(self._hm_shm) and all(o.on for o in self._hm_shm.values()),
                    others_in_view=max(others.values(), default=0),
                    others_in_view_by_camera=", ".join(f"{n}: {k}" for n, k in others.items() if k) or "none",
                    others_in_view_looks=census.looks if census is not None else 0)
