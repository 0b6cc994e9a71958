"""vmocap_markers: the lattice search (paper II-D). PCM views -> frame sets -> MarkerStage -> NS/markers."""

from __future__ import annotations

import functools
import time
from collections import deque
from typing import Any

import numpy as np

from vmocap_core import graph_config
from vmocap_core.bag import messages as M
from vmocap_core.cameras.sync import frames_missing
from vmocap_core.errors import VmocapError
from vmocap_core.method.camera_check import BlindCameras, EpipolarCheck, OddCamera, camera_residuals
from vmocap_core.method.markers import MarkerStage
from vmocap_core.method.time_offsets import TimingCheck
from vmocap_core.outputs.messages import CLOUD, IMAGE, INFO, markers_message
from vmocap_core.pcm.assembly import PcmAssembler, channel_keypoints

from ..shm_link import ShmIn
from ..transport import Transport
from .base import InitWatch, VmocapNode

CAMERA_CHECK_EVERY = 10  # frame sets between per-camera residual and heatmap checks (~0.3 ms each)
EPIPOLAR_EVERY = 3  # frame sets between epipolar samples (~0.3 ms each; enough samples in a few seconds)
HEATMAP_WARN_S = 5.0  # a corrupted-heatmap or blind-camera WARN stays this long after the last observation
BLIND_WARN_S = 1.0  # a camera without any heatmap this long while the others track: WARN


class Stream:
    """One person's way through the node: their views' heatmaps assembled into frame sets, the
    frame sets queued while the lattice search waits for the previous one's feedback, the stage
    and the markers' publisher. One for the subject; with several people one per slot."""

    def __init__(self, asm: PcmAssembler, stage: Any, pub: Any, topics: Any) -> None:
        self.asm, self.stage, self.pub, self.topics = asm, stage, pub, topics
        self.queue: deque = deque()
        self.awaiting: int | None = None
        self.awaiting_since = 0.0
        self.last_stamp: int | None = None


class MarkersNode(VmocapNode):
    """PCM views -> frame sets -> MarkerStage (lattice search) -> NS/markers. The lattice of
    frame t waits for the skeleton of frame t-1 (NS/feedback) so results are deterministic.
    With max_people > 1 (under /**): one stage per slot (method/people_stages.MarkerSlot), each
    on its slot's topics (NS/people/slotK/...), the subject's checks of the cameras left out."""

    def __init__(self, config: graph_config.GraphConfig, overrides: dict[str, Any] | None = None,
                 transport: Transport | None = None, name: str = "vmocap_markers") -> None:
        super().__init__(name, config, overrides, transport)
        if self.rig is None:
            raise VmocapError("vmocap_markers needs a rig")
        p = self.p
        views = p["views"] or self.rig.names
        stage_config = config.stage_config(name, p)
        self.timeout = p["feedback_timeout_ms"] / 1e3
        self.counts = {"frames": 0, "queue_dropped": 0, "missing": 0, "feedback_timeouts": 0}
        self.mirrored = np.zeros(len(self.rig), dtype=np.int64)  # per camera: frame sets its maps were read mirrored
        latched = bool(p["lockstep"])  # as vmocap_pcm publishes them in lockstep
        # from a vmocap_pcm in another process of this machine the maps come through shared memory
        self._shm_in = ShmIn(self) if p["shm_images"] and not latched else None
        self.people = p["max_people"] > 1
        if self.people:
            from vmocap_core.method.people_stages import MarkerSlot

            places = [(self.topics.slot(k), MarkerSlot(self.rig, stage_config)) for k in range(p["max_people"])]
        else:
            places = [(self.topics, MarkerStage(self.rig, stage_config))]
        self.streams = []
        for topics, stage in places:
            asm = PcmAssembler(self.rig, views, channel_keypoints(p["pcm_keypoints"]), int(p["sync_tolerance_ms"] * 1e6),
                               p["min_cameras"], int(p["silent_after_ms"] * 1e6))
            # markers and feedback are transient-local: a frame processed before the other node's
            # subscription matched (start-up) is still delivered, keeping the chain deterministic
            pub = self.publisher(CLOUD, topics.markers, depth=p["queue_depth"], latched=True)
            self.streams.append(Stream(asm, stage, pub, topics))
        self.subject = self.streams[0]
        self.stage = self.subject.stage
        self.asm = self.subject.asm
        self.init_watch = InitWatch(p["init_warn_s"], stage_config.init_max_reprojection_px, self.rig.names)
        self.presence: dict[str, float] = {}  # CNN presence per camera, last triangulated frame set
        self.cameras = OddCamera()  # per-camera reprojection residuals while tracking
        self.epipolar = EpipolarCheck(self.rig)  # per-pair epipolar offsets while tracking
        self.blind = BlindCameras(BLIND_WARN_S)  # cameras without any heatmap while tracking
        # cameras out of step (a probe a minute while tracking; the epipolar WARN says it too)
        self.timing = TimingCheck(self.rig, p["fps"])
        for st in self.streams:
            for v in views:
                on_maps = functools.partial(self._on_maps, st, v)
                self.subscribe(IMAGE, st.topics.pcm(v), on_maps, depth=p["queue_depth"], latched=latched)
                if self._shm_in is not None:
                    self._shm_in.subscribe(st.topics.pcm(v), v, on_maps, depth=p["queue_depth"])
                self.subscribe(INFO, st.topics.pcm_info(v), functools.partial(self._on_info, st, v), depth=p["queue_depth"],
                               latched=latched)
            self.subscribe(CLOUD, st.topics.feedback, functools.partial(self._on_feedback, st), depth=50, latched=True)
        if self.timeout > 0:
            self.create_timer(min(0.02, self.timeout / 2), self._check_timeout)

    def _on_maps(self, st: Stream, view: str, msg: dict) -> None:
        self._enqueue(st, st.asm.add_image(view, msg))

    def _on_info(self, st: Stream, view: str, msg: dict) -> None:
        self._enqueue(st, st.asm.add_info(view, msg))

    def _enqueue(self, st: Stream, pcms: list) -> None:
        for pcm in pcms:
            st.queue.append(pcm)
            if len(st.queue) > self.p["queue_depth"]:
                st.queue.popleft()
                self.counts["queue_dropped"] += 1
        self._pump(st)

    def _pump(self, st: Stream) -> None:
        while st.queue and (st.awaiting is None or self.timeout == 0):
            pcm = st.queue.popleft()
            t0 = time.perf_counter()
            # frame sets lost anywhere before the tracker (DDS queues, the PCM node, a camera);
            # every slot answers every frame set: the first one's count for the frame sets
            first = st is self.subject
            if first:
                self.counts["missing"] += frames_missing(st.last_stamp, pcm.stamp_ns, self.p["fps"])
            st.last_stamp = pcm.stamp_ns
            markers = st.stage.step(pcm)
            if self.timeout > 0:  # before publishing: the feedback may come back at once
                st.awaiting, st.awaiting_since = pcm.stamp_ns, time.monotonic()
            st.pub(markers_message(markers))
            self.proc.add(1e3 * (time.perf_counter() - t0))
            if first:
                self.counts["frames"] += 1
                self.record_age(pcm.stamp_ns)
            if not self.people:
                self._check_subject(pcm, markers)

    def _check_subject(self, pcm: Any, markers: Any) -> None:
        """The subject's frame set against the cameras: initialization, presence, timing, epipolar
        geometry, heatmaps, residuals, blind cameras (each a WARN naming what it found)."""
        self.init_watch.update(self, "tracking" if markers.kind == "lattice" else "initializing", markers)
        self.mirrored += (markers.mirrored >> np.arange(self.mirrored.size)) & 1
        if markers.presence:
            self.presence = markers.presence
        if markers.kind == "lattice":
            self.timing.request(time.monotonic())
            self.timing.add(pcm)
        if markers.kind == "lattice" and self.counts["frames"] % EPIPOLAR_EVERY == 0:
            self._check_epipolar(pcm)
        # every frame set: a camera's blind spell is timed from its first frame set, not from the
        # next check (sampled every 10th, a panel covering a view for 1.2 s was timed 1.0-1.17 s)
        self._check_blind(pcm, markers.kind == "lattice")
        if self.counts["frames"] % CAMERA_CHECK_EVERY == 0:
            self._check_heatmaps(pcm)
            if markers.kind == "lattice":
                self._check_cameras(pcm, markers.positions)
            self._check_timing()

    def _check_heatmaps(self, pcm: Any) -> None:
        """WARN (for HEATMAP_WARN_S) when heatmaps arrive with values the lattice search has to
        clean up (NaN, Inf, negative, above 1): a broken CNN or transport must not pass silently."""
        bad = pcm.corrupted()
        if bad:
            names = ", ".join(f"{self.rig[c].name} ({n} values)" for c, n in sorted(bad.items()))
            self.warn_for("heatmaps", f"heatmaps not finite or outside [0, 1] from {names}: cleaned, affected keypoints "
                          "dropped", HEATMAP_WARN_S)

    def _check_blind(self, pcm: Any, tracking: bool) -> None:
        """WARN naming a camera that has given no heatmap for BLIND_WARN_S while the others
        track the person (a covered or turned camera, or a CNN failing for it, which the
        tracker otherwise survives silently on the remaining views)."""
        # capture time, not wall time: a recording replayed slower or faster is judged by the scene's seconds
        long_blind = self.blind.update(pcm, tracking, pcm.stamp_ns * 1e-9)
        if long_blind:
            names = ", ".join(f"{self.rig[c].name} ({s:.1f} s)" for c, s in long_blind.items())
            self.warn_for("blind", f"no heatmap from {names} while the other cameras track the person: covered, "
                          "turned away, or its CNN failing", HEATMAP_WARN_S)

    def _check_cameras(self, pcm: Any, positions: np.ndarray) -> None:
        """After the markers went out: per-camera residuals, and a WARN naming a camera that
        disagrees with the others (camera_check.py)."""
        self.cameras.add(camera_residuals(self.rig, pcm, positions))
        odd = self.cameras.odd()
        if odd is None:
            self.problems.pop("camera", None)
            return
        name, px, others = odd
        self.problems["camera"] = (f"{name} disagrees with the other cameras: its heatmap peaks lie {px:.0f} px from the "
                                   f"markers' projections (the others {others:.0f} px): moved or turned since calibration?")

    def _check_timing(self) -> None:
        """WARN naming the cameras the last time-offset probe found out of step (one probe a
        minute while tracking, time_offsets.TimingCheck), until a later probe finds them in step."""
        text = self.timing.warning()
        if text:
            self.problems["timing"] = text
        else:
            self.problems.pop("timing", None)

    def _check_epipolar(self, pcm: Any) -> None:
        """WARN naming a camera whose keypoints lie off the others' epipolar lines by a constant
        (camera_check.EpipolarCheck): moved or turned since calibration, or a view the CNN biases."""
        self.epipolar.add(pcm)
        odd = self.epipolar.odd()
        if odd is None:
            self.problems.pop("epipolar", None)
            return
        name, mrad, others = odd
        px = mrad * 1e-3 * float(self.rig[name].K[0, 0])
        self.problems["epipolar"] = (f"{name} disagrees with the other cameras' epipolar geometry: its keypoints lie "
                                     f"{mrad:.1f} mrad ({px:.0f} px) off their epipolar lines on average (the other pairs "
                                     f"{others:.1f} mrad): moved or turned since calibration, out of step, or this view's "
                                     "keypoints biased?" + self.timing.note(name))

    def close(self) -> None:
        self.timing.close()
        if self._shm_in is not None:
            self._shm_in.close()
        super().close()

    def _on_feedback(self, st: Stream, msg: dict) -> None:
        t = M.stamp_ns(msg)
        if self.timeout > 0 and t != st.awaiting:
            return  # late feedback of a frame we stopped waiting for
        st.stage.feedback(M.cloud_keypoints(msg)[0])
        st.awaiting = None
        self._pump(st)

    def _check_timeout(self) -> None:
        for st in self.streams:
            if st.awaiting is not None and time.monotonic() - st.awaiting_since > self.timeout:
                self.counts["feedback_timeouts"] += 1
                self.problems["feedback"] = (f"no skeleton feedback within {self.timeout * 1e3:.0f} ms "
                                             f"({self.counts['feedback_timeouts']}x)")
                st.stage.feedback(None)  # re-initialize rather than search around a stale skeleton
                st.awaiting = None
                self._pump(st)

    def status(self) -> dict[str, Any]:
        st = self.asm.sync.stats()  # the subject's (several people: slot 0's) views
        self.watch_late(st.late)
        self.watch_silent(st.silent, "view")
        # `missing` includes the frame sets dropped from our own queue
        self.watch_dropped(self.counts["missing"], f"frame sets dropped or missing (stamps further apart than 1/{self.p['fps']:g} s)")
        return dict(self.counts, queued=sum(len(s.queue) for s in self.streams), sync=st.as_dict(), silent=list(st.silent),
                    rejected_frame_sets=sum(s.asm.bad_views for s in self.streams),
                    shared_memory=self._shm_in.status() if self._shm_in is not None else "off", presence={k: round(v, 3) for k, v in self.presence.items()},
                    **{f"residual_px:{k}": round(v, 1) for k, v in self.cameras.medians().items()},
                    **{f"mirrored:{c.name}": int(n) for c, n in zip(self.rig, self.mirrored) if n})

