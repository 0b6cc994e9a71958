"""vmocap_people: everyone in view (max_people under /**). Synchronized camera images -> the
multi-person tracker (vmocap_core.method.people_tracker: the CNN's detector and landmark model,
one markers + skeleton pipeline per person) -> each person a REP-155 body, the first one found
also on the subject topics (NS/joint_states, NS/keypoints, robot_description ...)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from vmocap_core import graph_config
from vmocap_core.bag import messages as M
from vmocap_core.cameras.bag import check_binning
from vmocap_core.cameras.sync import ApproximateSync
from vmocap_core.errors import VmocapError
from vmocap_core.method.camera_check import image_problem
from vmocap_core.outputs.messages import CLOUD, HEADER, IMAGE, result_messages

from ..shm_link import ShmIn
from ..subject import hri_outputs, skeleton_outputs
from ..transport import Transport
from .base import STREAM_DEPTH, VmocapNode


class PeopleNode(VmocapNode):
    """Camera images -> PeopleTracker -> the subject topics (first person) and REP-155 bodies."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_people") -> None:
        super().__init__(name, config, overrides, transport)
        from vmocap_core.method.people_config import PeopleConfig
        from vmocap_core.method.people_tracker import PeopleTracker
        from vmocap_core.outputs.people import PeopleOutputs
        from vmocap_core.pcm.providers import make_model_provider

        if self.rig is None:
            raise VmocapError("vmocap_people needs a rig")
        p = self.p
        check_binning(p["binning"])
        names = self.rig.names
        self.sync: ApproximateSync[np.ndarray] = ApproximateSync(
            names, int(p["sync_tolerance_ms"] * 1e6), p["min_cameras"], int(p["silent_after_ms"] * 1e6))
        provider = make_model_provider(p["model"], self.rig, p["rotation"], p["threads"], p["binning"], p["crop_prediction"])
        provider.warm_up()  # before READY: the first frame set would wait for it
        self.pcm_name = provider.name
        self.tracker = PeopleTracker(
            self.rig, provider.pcm, config.pipeline_config(),
            PeopleConfig(max_people=p["max_people"], detect_every_s=p["detect_every_s"], count_every_s=p["count_every_s"],
                         end_after_s=p["end_after_s"], remember_s=p["remember_s"],
                         confirm_frames=p["confirm_frames"]),
            landmarks=provider.landmarks, crop_prediction=p["crop_prediction"], binning=p["binning"])
        for cam in names:
            self.subscribe(IMAGE, self.topics.image(cam), lambda m, n=cam: self._on_image(n, m), depth=max(2, p["queue_depth"]))
        self._shm_in = ShmIn(self) if p["shm_images"] else None
        if self._shm_in is not None:
            for cam in names:
                self._shm_in.subscribe(self.topics.image(cam), cam, lambda m, n=cam: self._on_image(n, m),
                                       depth=max(2, p["queue_depth"]))
        t = self.topics
        # the feedback carries each frame set's stamp: lockstep's answer (cameras/lockstep.py)
        self.pubs = {t.feedback: self.publisher(CLOUD, t.feedback, depth=50, latched=True)}
        for topic, ty in ((t.joint_states, "sensor_msgs/msg/JointState"), (t.keypoints, CLOUD),
                          (t.skeleton, "visualization_msgs/msg/MarkerArray")):
            self.pubs[topic] = self.publisher(ty, topic, depth=STREAM_DEPTH)
        self.subject, extra = skeleton_outputs(self)
        self.pubs.update(extra)
        self.hri = hri_outputs(self, None, self.pubs, PeopleOutputs(t.ns, subject=self.subject, tf=t.tf in self.pubs))
        self._done = self.publisher(HEADER, t.pcm_done)  # vmocap_camera's flow control
        self.sets: list = []
        self.busy = False
        self.worker = ThreadPoolExecutor(1, thread_name_prefix=name) if p["inference_thread"] else None
        self.counts = {"frames": 0, "queue_dropped": 0, "bad_images": 0}
        self.last: Any = None  # the last PeopleFrame

    def _on_image(self, cam: str, msg: dict) -> None:
        for fs in self.sync.add(cam, M.stamp_ns(msg), M.image_array(msg)):
            self.sets.append(fs)
        self._pump()

    def _pump(self) -> None:
        """The newest frame set when the tracker is free (the older ones would only add latency)."""
        if self.busy or not self.sets:
            return
        if self.p["lockstep"]:
            fs = self.sets.pop(0)
        else:
            fs = self.sets[-1]
            self.counts["queue_dropped"] += len(self.sets) - 1
            self.sets.clear()
        images: list[np.ndarray | None] = [None] * len(self.rig)
        for c, cam in enumerate(self.rig.names):
            im = fs.items.get(cam)
            if im is not None and not image_problem(im, self.tracker.seen[cam].width, self.tracker.seen[cam].height):
                images[c] = im
            elif im is not None:
                self.counts["bad_images"] += 1
        if self.worker is None or self.transport.due.wake is None:
            self._publish(fs.stamp_ns, *self._step(images, fs.stamp_ns))
            return
        self.busy = True
        self.worker.submit(self._step_in_thread, images, fs.stamp_ns)

    def _step(self, images: list, stamp_ns: int) -> tuple[Any, float]:
        t0 = time.perf_counter()
        return self.tracker.step(images, stamp_ns), time.perf_counter() - t0

    def _step_in_thread(self, images: list, stamp_ns: int) -> None:
        try:
            out = self._step(images, stamp_ns)
        except Exception as exc:  # noqa: BLE001 - reported by the spin loop, the node goes on
            error = exc
            self.transport.due.put(time.monotonic(), lambda: self._failed(error))
            return
        self.transport.due.put(time.monotonic(), lambda: self._publish(stamp_ns, *out))

    def _failed(self, exc: Exception) -> None:
        self.busy = False
        self.errors["tracker"] = f"people tracker failed: {exc}"
        self.get_logger().error(self.errors["tracker"])
        self._pump()

    def _publish(self, stamp_ns: int, frame: Any, seconds: float) -> None:
        """In the spin loop's thread: the first person on the subject topics, every body, the
        frame set's answer (feedback, done), then the next frame set in."""
        t0 = time.perf_counter()
        pubs = self.pubs
        first = frame.first
        if first is not None:
            for topic, _ty, out in result_messages(self.topics, first.last.skeleton, subject=self.subject,
                                                   wanted=lambda tp: tp in pubs and tp != self.topics.feedback
                                                   and pubs[tp].wanted()):
                if topic in pubs:
                    pubs[topic](out)
        feedback = None if first is None else first.feedback
        pubs[self.topics.feedback](M.keypoint_cloud(stamp_ns, feedback))
        if self.hri is not None:
            self.hri(frame)
        self._done(M.header(stamp_ns, ",".join(self.rig.names)))
        self.last = frame
        self.counts["frames"] += 1
        self.errors.pop("tracker", None)
        if frame.left_out:
            self.warn_for("people", f"{frame.left_out} more people in view than max_people {self.p['max_people']} tracks "
                                    "(those found first are tracked)")
        self.proc.add(1e3 * (seconds + time.perf_counter() - t0))
        self.record_age(stamp_ns)
        self.busy = False
        self._pump()

    def status(self) -> dict[str, Any]:
        st = self.sync.stats()
        self.watch_late(st.late)
        self.watch_silent(st.silent)
        self.watch_dropped(self.counts["queue_dropped"])
        frame = self.last
        people = [] if frame is None else frame.people
        ids = [self.hri.core.body_id(p.number) for p in people] if self.hri is not None else []
        return dict(self.counts, pcm=self.pcm_name, max_people=self.p["max_people"],
                    people=len(people), tracking=sum(p.status == "tracking" for p in people),
                    statuses=", ".join(f"{i or p.number}: {p.status}" for p, i in zip(people, ids or [None] * len(people)))
                    or "nobody", untracked_in_view=0 if frame is None else frame.others_in_view,
                    left_out=0 if frame is None else frame.left_out,
                    sync=st.as_dict())

    def close(self) -> None:
        if self._shm_in is not None:
            self._shm_in.close()
        if self.worker is not None:
            self.worker.shutdown(wait=True, cancel_futures=True)
        super().close()
