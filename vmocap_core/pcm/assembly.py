"""Heatmap messages -> frame sets of PcmViews: what vmocap_markers does with its subscriptions,
and what `vmocap process` does with a bag's PCM topics."""

from __future__ import annotations

from typing import Iterable

import numpy as np

from ..bag import heatmaps
from ..bag import messages as M
from ..cameras.projection import Rig
from ..cameras.sync import ApproximateSync
from ..errors import BagError, HeatmapError
from ..graph_config import Topics
from ..keypoints import KEYPOINTS, indices
from .views import PcmViews

IMAGE = "sensor_msgs/msg/Image"


def channel_keypoints(names: Iterable[str]) -> np.ndarray:
    names = list(names)
    return indices(names) if names else np.arange(len(KEYPOINTS))


class PcmAssembler:
    """Pairs each view's heatmap Image with its CameraInfo (same stamp) and synchronizes the
    views into frame sets. `add_*` return the PcmViews that became complete."""

    def __init__(self, rig: Rig, views: list[str], keypoints: np.ndarray, tolerance_ns: int = 1_000_000,
                 min_views: int = 2, silent_after_ns: int = 500_000_000) -> None:
        self.rig = rig
        self.views = list(views)
        self.keypoints = np.asarray(keypoints)
        self.sync: ApproximateSync[tuple[dict, dict]] = ApproximateSync(
            self.views, tolerance_ns, min_cameras=min_views, silent_after_ns=silent_after_ns, max_queue=60)
        self._half: dict[str, dict[int, tuple[str, dict]]] = {v: {} for v in self.views}
        self.bad_views = 0
        self.last_error = ""

    def _add(self, view: str, kind: str, msg: dict) -> list[PcmViews]:
        t = M.stamp_ns(msg)
        pending = self._half[view]
        other = pending.pop(t, None)
        if other is None:
            pending[t] = (kind, msg)
            if len(pending) > 60:  # a partner that never comes: forget the oldest
                pending.pop(min(pending))
            return []
        if other[0] == kind:  # duplicate of the same half: keep the newer one
            pending[t] = (kind, msg)
            return []
        pair = (msg, other[1]) if kind == "image" else (other[1], msg)
        return self._frame_sets(self.sync.add(view, t, pair))

    def add_image(self, view: str, msg: dict) -> list[PcmViews]:
        return self._add(view, "image", msg)

    def add_info(self, view: str, msg: dict) -> list[PcmViews]:
        return self._add(view, "info", msg)

    def flush(self) -> list[PcmViews]:
        return self._frame_sets(self.sync.flush())

    def _frame_sets(self, sets: list) -> list[PcmViews]:
        out = []
        for fs in sets:
            pairs = [fs.items[v] for v in self.views if v in fs.items]
            try:
                pcm = heatmaps.pcm_views(pairs, self.rig, self.keypoints)
            except (HeatmapError, BagError) as exc:
                self.bad_views += 1
                self.last_error = str(exc)
                continue
            pcm.stamp_ns = fs.stamp_ns
            out.append(pcm)
        return out


def pcm_topics(bag_topics: dict[str, str], topics: Topics, views: list[str] | None) -> list[str]:
    """View names of the PCM topics present in a bag."""
    prefix = f"{topics.ns}/pcm/"
    found = sorted(
        t[len(prefix): -len("/heatmaps")] for t, ty in bag_topics.items()
        if t.startswith(prefix) and t.endswith("/heatmaps") and ty == IMAGE
    )
    if views:
        missing = [v for v in views if v not in found]
        if missing:
            raise BagError(f"the bag has no PCM topics for views {missing} (found {found})")
        return list(views)
    return found
