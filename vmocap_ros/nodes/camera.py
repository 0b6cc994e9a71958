"""vmocap_camera: camera ingest. Frames of a FrameSource per camera (bag, video, Aravis, V4L2)
-> NS/CAM/image_raw + NS/CAM/camera_info, recorded frames sent at their due time, images
reduced `binning` times when the graph's binning says so."""

from __future__ import annotations

import functools
import threading
import time
from typing import Any

from vmocap_core import graph_config
from vmocap_core.bag import messages as M
from vmocap_core.cameras.bag import bin_image, check_binning
from vmocap_core.cameras.clock import LoopedStamps, PlaybackClock
from vmocap_core.cameras.flow import InFlight, applies
from vmocap_core.cameras.lockstep import LockstepGate
from vmocap_core.cameras.start import StartGate
from vmocap_core.errors import VmocapError
from vmocap_core.outputs.messages import CLOUD, HEADER, IMAGE, INFO

from ..shm_link import ShmOut
from ..transport import Output, Transport
from .base import VmocapNode

STALL_S = 2.0  # a live camera that delivers nothing for this long (but is not lost) is WARNed about


class CameraNode(VmocapNode):
    """Frames of a FrameSource per camera -> NS/CAM/image_raw + NS/CAM/camera_info."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_camera") -> None:
        super().__init__(name, config, overrides, transport)
        if self.rig is None:
            raise VmocapError("vmocap_camera needs a rig")
        self.binning = self.p["binning"]
        check_binning(self.binning)
        self._stop = threading.Event()
        # lockstep: recorded frame sets go out as the graph answers them, not by the clock
        self._gate = LockstepGate(self.p["lockstep_timeout_ms"] / 1e3) if self.p["lockstep"] else None
        self._playback = PlaybackClock(0.0 if self._gate else self.p["rate"], self.p["restamp"])
        # live (and replays as live): frame sets the CNN has no room for are not sent
        self._flow = InFlight(self.p["max_in_flight"], 1.0 / self.p["fps"]) if self.p["max_in_flight"] and not self._gate else None
        self._flow_on = False  # set by _check_flow: a PCM node answers, and only PCM nodes take the images
        # under flow control, frames go to PCM nodes of this machine through shared memory
        self._shm: dict[str, ShmOut] = {}
        self._image_topics: list[str] = []
        self._matched = threading.Event()
        self._threads = []
        self.published = {c.name: 0 for c in self.rig}
        self.late_dropped = {c.name: 0 for c in self.rig}  # restamped replay: frames a period late, skipped
        self.wrong_size = {c.name: 0 for c in self.rig}  # frames of another size than the rig's calibration
        self.disconnects = {c.name: 0 for c in self.rig}
        self.reconnects = {c.name: 0 for c in self.rig}
        self.last_frame = {c.name: time.monotonic() for c in self.rig}  # when each camera last delivered
        self._live: set[str] = set()
        for cam in self.rig:
            src = self._make_source(cam.name)
            src.open()
            if getattr(src, "live", False):
                self._live.add(cam.name)
            pub_img = self.publisher(IMAGE, self.topics.image(cam.name))
            pub_info = self.publisher(INFO, self.topics.camera_info(cam.name))
            if self._flow is not None and self.p["shm_images"]:
                self._shm[cam.name] = ShmOut(self, self.topics.image(cam.name))
            self._image_topics.append(self.topics.image(cam.name))
            th = threading.Thread(target=self._run, args=(src, cam, pub_img, pub_info), daemon=True)
            self._threads.append((th, src))
        if self._gate is not None:
            self.subscribe(CLOUD, self.topics.feedback, lambda m: self._gate.answered(M.stamp_ns(m)), depth=50, latched=True)
        if self._flow is not None:
            self.subscribe(HEADER, self.topics.pcm_done, lambda m: self._flow.done(M.stamp_ns(m["stamp"]), time.monotonic()), depth=10)
            self.create_timer(0.5, self._check_flow)
        for th, _ in self._threads:
            th.start()
        self._start = StartGate(time.monotonic(), self.p["wait_subscribers"])
        self._matched_timer = self.create_timer(0.05, self._check_matched)
        self._check_matched()

    def _check_matched(self) -> None:
        """Recorded sources start once their readers are there (cameras/start.py): one of our
        nodes in this process or a matched DDS reader per image topic, and every `wait_topics`
        topic has a subscriber."""
        if self._matched.is_set():
            return
        matched = [bool(self.count_subscribers(t) + len(self.transport.bus.subscribers.get(t, ()))) for t in self._image_topics]
        note = self._start.update(time.monotonic(), matched, all(self.count_subscribers(t) for t in self.p["wait_topics"]))
        if note is not None:
            if self._flow is not None:  # decided before the first frame set, not up to 0.5 s into the replay
                self._check_flow()
            self._matched.set()
            self._matched_timer.cancel()
            self.get_logger().info("playing" + note)

    def _make_source(self, camera: str):
        kind, uri = self.p["source"], self.p["uri"]
        if kind == "bag":
            from vmocap_core.cameras.bag import BagFrameSource

            return BagFrameSource(uri, camera, topic=self.topics.image(camera), start_offset_s=self.p["start_offset"],
                                  loop=self.p["loop"], binning=self.binning, recover=self.p["recover"])
        import importlib

        try:
            factory = importlib.import_module("vmocap_core.cameras").make_source
        except (ImportError, AttributeError):
            raise VmocapError(f"camera source {kind!r} is not available (vmocap_core.cameras.make_source missing)") from None
        return factory(kind, uri, camera)

    def _run(self, src, cam, pub_img: Output, pub_info: Output) -> None:
        stamps = LoopedStamps()
        slot = threading.Semaphore(1)  # one frame of this camera waits for its time, the next is read meanwhile
        last_due: float | None = None
        seen = cam.binned(self.binning)  # the size its images are published at
        prev_due: float | None = None  # due time of the frame read before (sent or not)
        while not self._stop.is_set():
            try:
                frame = src.read(timeout=0.5)
            except VmocapError as exc:
                if getattr(src, "live", False):  # reported and retried; the thread ends when given up
                    if self._reconnect(src, cam.name, str(exc)):
                        self.last_frame[cam.name] = time.monotonic()
                        continue
                    return
                self.errors[f"camera:{cam.name}"] = str(exc)  # this camera's thread ends: ERROR
                self.get_logger().error(str(exc))
                return
            bad = getattr(src, "bad_frames", 0)
            if bad:
                self.problems[f"frames:{cam.name}"] = f"{cam.name}: {bad} frames skipped ({src.last_error})"
            damaged = getattr(src, "damaged", None)
            if damaged:  # recover: a damaged recording played without its damaged chunks
                self.problems[f"damaged:{cam.name}"] = f"{cam.name}: {len(damaged)} damaged chunks skipped (recover): {damaged[0]}"
            if frame is None:
                if src.exhausted:
                    return
                continue
            self.last_frame[cam.name] = time.monotonic()
            h, w = frame.image.shape[:2]
            if self.binning > 1 and (w, h) == (cam.width, cam.height):  # a source of full frames (live cameras)
                frame.image = bin_image(frame.image, self.binning)
                h, w = frame.image.shape[:2]
            if (w, h) != (seen.width, seen.height):  # published as it is; vmocap_pcm does not use it
                self.wrong_size[cam.name] += 1
                self.warn_for(f"size:{cam.name}", f"{cam.name}: frames of {w}x{h}, the rig is calibrated at "
                              f"{cam.width}x{cam.height}" + (f" (binning {self.binning}: {seen.width}x{seen.height})" if self.binning > 1 else "")
                              + f" ({self.wrong_size[cam.name]} frames)")
            if not getattr(src, "live", False) and not self._matched.is_set():
                while not self._matched.wait(0.05):
                    if self._stop.is_set():
                        return
            stamp, due = self._playback.schedule(stamps(frame.stamp_ns), time.monotonic(), time.time_ns())
            # the message refers to the frame's pixels (sources never reuse a frame's array)
            img, info = M.image_msg(frame.image, stamp, cam.name, copy=False), M.camera_info_msg(cam, stamp, binning=self.binning)
            if due is None:
                if self._playback.restamp:
                    img["header"] = info["header"] = M.header(time.time_ns(), cam.name)
                prepared = (pub_img.prepare(img), pub_info.prepare(info))
                if self._gate is not None and cam.name not in self._live and not self._gate.enter(stamp, self._stop):
                    return
                self._send(cam.name, *prepared, pub_img, pub_info)
                continue
            # a recorded frame is converted (and encoded for DDS readers) while it waits for its
            # time; under flow control most frame sets are not sent, so their images are encoded
            # in _send once admitted (an encode of 4 images costs ~2 ms of the CNN's core)
            prepared = ((img, None) if self._flow_on else pub_img.prepare(img), pub_info.prepare(info))
            while not slot.acquire(timeout=0.1):  # the previous frame of this camera is still due
                if self._stop.is_set():
                    return
            period, prev_due = (due - prev_due if prev_due is not None else 0.0), due
            if self._playback.superseded(due, period, time.monotonic()):  # replayed as live: skipped
                slot.release()
                self.late_dropped[cam.name] += 1
                continue
            if self.transport.due.wake is not None:  # the spin loop sends it when due, and frees the slot
                period = due - last_due if last_due is not None else 0.0
                last_due = due
                self.transport.due.put(due, functools.partial(self._send_due, cam.name, prepared, pub_img, pub_info, slot, due + 0.5 * period))
                continue
            delay = due - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            self._send(cam.name, *prepared, pub_img, pub_info)
            slot.release()

    def _reconnect(self, src, cam: str, error: str) -> bool:
        """A live camera that failed (unplugged, power lost, network down): reported, then
        reopened every reconnect_s seconds, at most reconnect_attempts times. True once it
        delivers again (a WARN stays for a while after), False when given up or stopping."""
        self.disconnects[cam] += 1
        t0, attempts = time.monotonic(), self.p["reconnect_attempts"]
        self.get_logger().warning(f"{cam}: disconnected ({error}); reopening every {self.p['reconnect_s']} s")
        for k in range(1, attempts + 1):
            self.problems[f"camera:{cam}"] = (f"{cam}: disconnected ({error}); reconnecting, attempt {k} of {attempts}")
            if self._stop.wait(self.p["reconnect_s"]):
                return False
            try:
                src.close()
                src.open()
            except VmocapError as exc:
                error = str(exc)
                continue
            self.reconnects[cam] += 1
            self.problems.pop(f"camera:{cam}", None)
            msg = f"{cam}: reconnected after {time.monotonic() - t0:.1f} s ({self.disconnects[cam]} disconnections)"
            self.get_logger().warning(msg)
            self.warn_for(f"reconnected:{cam}", msg)
            return True
        self.get_logger().error(f"{cam}: given up after {attempts} reconnection attempts")
        self.problems.pop(f"camera:{cam}", None)
        self.errors[f"camera:{cam}"] = f"{cam}: disconnected, given up after {attempts} attempts ({error})"
        return False

    def _send_due(self, cam: str, prepared: tuple, pub_img: Output, pub_info: Output, slot: threading.Semaphore,
                  release_at: float) -> None:
        self._send(cam, *prepared, pub_img, pub_info)
        # this camera's reader thread reads its next frame once the graph is done with this
        # frame set (or half a period later): woken meanwhile, it would take the GIL from it
        self.transport.due.when_idle(slot.release, release_at)

    def _check_flow(self) -> None:
        """Who takes the images and whether a PCM node answers: flow.applies decides."""
        bus, done = self.transport.bus, self.topics.pcm_done
        answered = done in bus.publishers or self.count_publishers(done) > 0
        local = [n for t in self._image_topics for n in bus.subscriber_nodes.get(t, [])]
        remote = [i.node_name for t in self._image_topics for i in self.get_subscriptions_info_by_topic(t)]
        self._flow_on = applies(answered, local, remote)
        for out in self._shm.values():
            out.check()

    def _send(self, cam: str, img: tuple, info: tuple, pub_img: Output, pub_info: Output) -> None:
        if self._flow_on and self._flow is not None and not self._flow.admit(M.stamp_ns(img[0]), time.monotonic()):
            return  # the CNN is busy with newer-than-useful work: this frame set is not sent
        shm = self._shm.get(cam)
        if self._flow_on and shm is not None and shm.on:  # the pixels into shared memory, a reference over DDS
            shm.send(img[0])
        else:
            if img[1] is None:  # deferred (above) or no DDS reader when prepared
                img = pub_img.prepare(img[0])
            pub_img.send(img)
        pub_info.send(info)
        self.published[cam] += 1
        self.record_age(M.stamp_ns(img[0]))  # how late the frame went out

    def status(self) -> dict[str, Any]:
        # checked here, at 1 Hz, not by the camera's reader thread: that may be the one stuck
        now = time.monotonic()
        for cam in self._live:
            quiet = now - self.last_frame[cam]
            key = f"camera:{cam}"  # disconnected or given up: said already
            if quiet > STALL_S and key not in self.problems and key not in self.errors:  # connected, but nothing comes
                self.warn_for(f"stalled:{cam}", f"{cam}: no frame for {quiet:.1f} s (connected)")
        self.watch_dropped(sum(self.late_dropped.values()), "frames dropped (a period late)")
        out = {"published": self.published, "late_dropped": self.late_dropped, "wrong_size": self.wrong_size,
               "disconnects": self.disconnects, "reconnects": self.reconnects}
        if self._flow is not None:
            out["flow"] = {"on": self._flow_on, "sent": self._flow.sent, "skipped": self._flow.skipped,
                           "in_flight": self._flow.in_flight,
                           "shared_memory": self._flow_on and bool(self._shm) and all(o.on for o in self._shm.values())}
        if self._gate is not None:
            if self._gate.timeouts:
                self.warn_for("lockstep", f"lockstep: {self._gate.timeouts} frame sets got no feedback within "
                              f"{self._gate.timeout_s:g} s (no person in any view, or a node not running)")
            out["lockstep"] = {"answered": self._gate.answered_count, "timeouts": self._gate.timeouts}
        return out

    def close(self) -> None:
        self._stop.set()
        for th, src in self._threads:
            th.join(timeout=2.0)
            src.close()
        for out in self._shm.values():
            out.close()
