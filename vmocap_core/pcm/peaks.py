"""Per-camera 2D keypoints from PcmViews (for triangulation at initialization and for checks).

A camera may have several views (the paper's rotation variant: upright view for the upper
body, rotated view for the lower body); each keypoint is taken from the view that is valid for
it (the highest-scoring one if several are). Views whose presence is below `min_presence` say
nothing: heatmaps peak at ~0.5 even without a person.
"""

from __future__ import annotations

import numpy as np

from ..keypoints import KEYPOINTS
from .views import PcmViews


def camera_keypoints(
    pv: PcmViews, n_cameras: int, min_presence: float = 0.5, threshold: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """(C, 25, 2) image pixels in KEYPOINTS order (PCM centroids, II-C) and (C, 25) weights
    (peak values; 0 = not observed), ready for `triangulation.triangulate(rig, uv, w)`."""
    uv_v, w_v = pv.centroids(threshold)  # (V, J, 2), (V, J)
    w_v = np.where(pv.valid & (pv.presence[:, None] >= min_presence), w_v, 0.0)
    J = len(KEYPOINTS)
    uv = np.full((n_cameras, J, 2), np.nan)
    w = np.zeros((n_cameras, J))
    if pv.n_views == 0:
        return uv, w
    # best view per (camera, keypoint): scatter the views in ascending weight order so the
    # strongest one is written last (numpy: the last of repeated indices wins)
    order = np.argsort(w_v, axis=0, kind="stable")  # (V, J)
    vv = order.ravel()
    jj = np.broadcast_to(np.arange(w_v.shape[1])[None], w_v.shape).ravel()
    keep = w_v[vv, jj] > 0
    cam, kp = pv.camera[vv[keep]], pv.keypoints[jj[keep]]
    uv[cam, kp] = uv_v[vv[keep], jj[keep]]
    w[cam, kp] = w_v[vv[keep], jj[keep]]
    return uv, w
