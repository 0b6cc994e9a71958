"""vmocap_pcm with max_people > 1: everyone in view. Synchronized camera images -> the people
look (vmocap_core.method.people_look: BlazePose's detector finds the people, every tracked
person's crops through the landmark model in one call) -> each person's heatmaps on their slot's
topics (NS/people/slotK/pcm/VIEW/heatmaps + camera_info); their crops follow the skeleton fed back on
NS/people/slotK/feedback."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vmocap_core.bag import heatmaps
from vmocap_core.bag import messages as M
from vmocap_core.errors import VmocapError
from vmocap_core.keypoints import KEYPOINTS
from vmocap_core.outputs.messages import CLOUD
from vmocap_core.pcm.blazepose import views_per_camera
from vmocap_core.pcm.views import PcmViews

from ..common import Topics
from .pcm import PcmNode

SEATED_KEPT = 100  # frame sets whose slots are remembered: a slot's feedback names its frame set, not its person


class PeoplePcmNode(PcmNode):
    """Synchronized camera images -> every tracked person's heatmaps, slot by slot (module doc)."""

    def _make_provider(self):
        """The CNN, and the look over it (PcmNode.__init__ asks for the provider first)."""
        from vmocap_core.method.people_config import PeopleConfig
        from vmocap_core.method.people_look import PeopleLook
        from vmocap_core.pcm.providers import make_model_provider

        p = self.p
        if p["source"] != "model" or p["model"] not in ("blazepose", "blazepose-lite"):
            raise VmocapError(f"max_people {p['max_people']}: vmocap_pcm needs model blazepose or blazepose-lite (its "
                              f"person detector finds the people), not {p['model'] or p['source']!r}")
        # no census beside the frame sets: the look's own searches count the people in view
        provider = make_model_provider(p["model"], self.rig, p["rotation"], p["threads"], p["binning"],
                                       p["crop_prediction"], census_every=0)
        provider.warm_up()  # before READY: the first frame set would wait for it
        self.look = PeopleLook(self.rig, provider.pcm, PeopleConfig(
            max_people=p["max_people"], detect_every_s=p["detect_every_s"], glance_every_s=p["glance_every_s"],
            count_every_s=p["count_every_s"], end_after_s=p["end_after_s"]), p["crop_prediction"], p["binning"],
            # free-running, the detector searches beside the frame sets; in lockstep in their own time
            beside=p["feedback_wait_ms"] == 0)
        self.seated: dict[int, dict[int, int]] = {}  # frame set stamp -> slot -> person number
        self.fed: list[tuple[int, dict]] = []  # slot feedback not yet given to the look (it may be looking)
        self.pending: set[int] = set()  # slots whose feedback of the awaited frame set has not come
        self.last_look: Any = None
        self.looked_ns: int | None = None  # the stamp of the last frame set looked at
        return provider

    def _subscribe_feedback(self) -> None:
        for k in range(self.p["max_people"]):
            self.subscribe(CLOUD, self.topics.slot(k).feedback, lambda m, k=k: self._on_slot_feedback(k, m), depth=50,
                           latched=True)

    def _heatmap_topics(self) -> list[Topics]:
        return [self.topics.slot(k) for k in range(self.p["max_people"])]

    def _on_slot_feedback(self, slot: int, msg: dict) -> None:
        self.fed.append((slot, msg))
        t = M.stamp_ns(msg)
        if self.awaiting == t:
            self.pending.discard(slot)
            if not self.pending:
                self.awaiting = None
        self._pump()

    def _take_feedback(self) -> None:
        """The slots' feedback into the look, between two looks (the look runs in a thread of its own)."""
        for slot, msg in self.fed:
            t = M.stamp_ns(msg)
            number = self.seated.get(t, {}).get(slot)
            if number is not None:
                self.look.feedback(number, t, M.cloud_keypoints(msg)[0])
        self.fed.clear()

    def _pump(self) -> None:
        if not self.busy:
            self._take_feedback()
        super()._pump()

    def _await_feedback(self, stamp_ns: int) -> None:
        super()._await_feedback(stamp_ns)
        self.pending = set(range(self.p["max_people"]))

    def _infer(self, fs: Any, cams: list[str], fb: np.ndarray | None, data: bool) -> tuple[Any, list, float]:
        """The people who ended at the last frame set (by what was fed back; vmocap_skeleton
        applies the same rule) leave their slots, then the look; every slot's heatmaps, padded
        to the expected views (a free slot: every view stands for none)."""
        t0 = time.perf_counter()
        images: list[np.ndarray | None] = [None] * len(self.rig)
        for n in cams:
            images[self.rig.names.index(n)] = fs.items[n]
        if self.looked_ns is not None:
            self.look.end(self.look.ended(self.looked_ns))
        look = self.look.step(images, fs.stamp_ns)
        self.looked_ns = fs.stamp_ns
        by_slot = {slot: n for n, slot in look.slots.items()}
        self.seated[fs.stamp_ns] = by_slot
        while len(self.seated) > SEATED_KEPT:
            self.seated.pop(next(iter(self.seated)))
        names = heatmaps.rig_view_names(self.rig, views_per_camera(self.p["rotation"]))
        free = PcmViews.empty(len(KEYPOINTS), self.look.pcm.landmark.map_size, fs.stamp_ns)
        msgs = []
        for k in range(self.p["max_people"]):
            views = heatmaps.padded(look.views[by_slot[k]] if k in by_slot else free, self.rig, names)
            msgs += [(self.topics.slot(k), v, img, info)
                     for v, (img, info) in zip(heatmaps.view_names(views, self.rig), heatmaps.pcm_msgs(views, self.rig, data))]
        return look, msgs, time.perf_counter() - t0

    def _publish(self, fs: Any, data: bool, look: Any, msgs: list, seconds: float) -> None:
        self.last_look = look
        super()._publish(fs, data, look, msgs, seconds)

    def _publish_keypoints(self, pcm: Any, cams: Any, stamp_ns: int) -> None:
        """Each camera's 2D keypoints are one person's: not published with several."""

    def close(self) -> None:
        self.look.close()
        super().close()

    def status(self) -> dict[str, Any]:
        out = super().status()
        if self.look.search_error:
            self.warn_for("search", f"the detector's search for people failed: {self.look.search_error}")
        look = self.last_look
        if look is not None and look.left_out:
            self.warn_for("people", f"{look.left_out} more people in view than max_people {self.p['max_people']} "
                                    "tracks (those found first are tracked)")
        out.update(max_people=self.p["max_people"], people=len(self.look.seats),
                   slots=", ".join(f"{s.slot}: {s.number}" for s in self.look.seats) or "none",
                   untracked_in_view=0 if look is None else int(max(look.untracked.max(initial=0), 0)),
                   left_out=0 if look is None else look.left_out)
        return out
