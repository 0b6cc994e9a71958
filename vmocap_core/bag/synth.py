"""Synthetic bags for tests and benchmarks: a rig watching a motion clip, as MCAP topics.

Per frame and camera: CameraInfo (NS/CAM/camera_info), optionally a bgr8 Image
(NS/CAM/image_raw), and the synthetic PCM of the view (NS/pcm/CAM/heatmaps + camera_info,
vmocap_core.pcm.synthetic's noise model). Capture stamps start at `t0_ns`, one per 1/fps.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..cameras.projection import Rig
from ..graph_config import Topics
from . import heatmaps
from . import messages as M
from .writer import BagWriter

if TYPE_CHECKING:
    from ..pcm.synthetic import NoiseModel


def write_synthetic_bag(
    path: str | Path,
    rig: Rig,
    positions: np.ndarray,
    present: np.ndarray,
    n_frames: int,
    fps: float = 30.0,
    stride: int = 16,
    images: bool = False,
    pcm: bool = True,
    namespace: str = "/vmocap",
    t0_ns: int = 1_000_000_000_000,
    seed: int = 0,
    compression: str = "none",
    noise: NoiseModel | None = None,
) -> Path:
    """noise: the heatmaps' noise model (default: the benchmark's, at this stride)."""
    from ..pcm.synthetic import NoiseModel, SyntheticPcmSource

    topics = Topics(namespace)
    src = SyntheticPcmSource(rig, positions, present, seed=seed, noise=noise or NoiseModel(stride=stride), fps=fps)
    rng = np.random.default_rng(seed)
    # one random texture per camera; frames differ by a cheap roll so bytes change
    textures = [rng.integers(0, 255, (c.height, c.width, 3), dtype=np.uint8) for c in rig] if images else []
    with BagWriter(path, compression=compression, overwrite=True) as w:  # scratch data: rewritten freely
        for k in range(n_frames):
            t = t0_ns + int(round(k * 1e9 / fps))
            views = src.render(src.looped(k)) if pcm else None
            for i, cam in enumerate(rig):
                w.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, t), t)
                if images:
                    img = np.roll(textures[i], k, axis=1)
                    w.write(topics.image(cam.name), "sensor_msgs/msg/Image", M.image_msg(img, t, cam.name), t)
            if views is not None:
                views.stamp_ns = t
                for (pcm_img, info), v in zip(heatmaps.pcm_msgs(views, rig), range(views.n_views)):
                    name = rig[int(views.camera[v])].name
                    w.write(topics.pcm(name), "sensor_msgs/msg/Image", pcm_img, t)
                    w.write(topics.pcm_info(name), "sensor_msgs/msg/CameraInfo", info, t)
    return Path(path)
