"""A motion clip rendered into an MCAP recording: per frame and camera a bgr8 Image
(NS/CAM/image_raw) and its CameraInfo (NS/CAM/camera_info), plus the clip's keypoints on
TRUTH_TOPIC (PointCloud2 of the 25 KEYPOINTS, NaN where the clip has none). Recordings are
cached by a content hash of everything that determines their bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from ...bag import BagReader, BagWriter
from ...bag import messages as M
from ...cameras.projection import Camera, Rig
from ...graph_config import Topics
from ...keypoints import KEYPOINTS
from ...motion import Motion, extend, load_motion, resample
from .body import SHAPES, Body, load_body
from .pose import clip_joints, segment_transforms, skin
from .scene import Appearance, SceneRenderer

TRUTH_TOPIC = "/vmocap/truth/keypoints"
RENDER_VERSION = 2  # bump when the rendered bytes change for the same inputs
T0_NS = 1_000_000_000_000


@dataclass
class ClipSpec:
    """What one rendering depends on."""

    path: Path
    frames: int
    rate_hz: float
    seed: int
    variant: int = 0  # 0: the clip's own body and look; k > 0: the k-th next shape, another look

    def shape(self) -> str:
        """Body shape of the clip: cycles through SHAPES by clip name (all shapes over the set);
        variant k takes the k-th shape after that one."""
        names = sorted(SHAPES)
        return names[(zlib.crc32(self.path.stem.encode()) + self.seed + self.variant) % len(names)]

    def rng_seed(self) -> int:
        # variant 0 keeps the key it had before variants existed: the same bytes as before
        tail = f":{self.variant}" if self.variant else ""
        return zlib.crc32(f"{self.path.stem}:{self.seed}{tail}".encode())

    def label(self) -> str:
        """The clip's name, with the shape for variants (report rows, output files)."""
        return self.path.stem if self.variant == 0 else f"{self.path.stem}-{self.shape()}"


def scale_rig(rig: Rig, factor: float) -> Rig:
    """The rig with images scaled by `factor` (intrinsics to match; OpenCV pixel centres)."""
    if factor == 1.0:
        return rig
    cams = []
    for c in rig:
        w, h = int(round(c.width * factor)), int(round(c.height * factor))
        sx, sy = w / c.width, h / c.height
        S = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])
        cams.append(Camera(c.name, S @ c.K, c.dist, c.R, c.t, w, h))
    return Rig(cams)


def prepare_motion(spec: ClipSpec) -> Motion:
    """The clip at the rig rate, played forward/backward to `frames`, its mean pelvis moved
    onto the rig's centre (as the synthetic benchmark centres its rig on the clip)."""
    m = resample(load_motion(spec.path), spec.rate_hz)
    m = extend(m, spec.frames / spec.rate_hz)
    pos = m.positions[: spec.frames].copy()
    pos[..., :2] -= np.nanmean(pos[:, KEYPOINTS.index("pelvis"), :2], axis=0)
    return Motion(m.name, pos, m.present, m.fps)


def cache_key(spec: ClipSpec, rig: Rig) -> str:
    h = hashlib.sha256()
    h.update(Path(spec.path).read_bytes())
    key = {"frames": spec.frames, "rate": spec.rate_hz, "seed": spec.seed, "v": RENDER_VERSION}
    if spec.variant:  # variant 0 keeps its old key (and cached file)
        key["variant"] = spec.variant
    h.update(json.dumps(key).encode())
    for c in rig:
        h.update(c.name.encode())
        for a in (c.K, c.dist, c.R, c.t, np.array([c.width, c.height], float)):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def posed_bodies(body: Body, positions: np.ndarray) -> Callable[[], Iterator[np.ndarray]]:
    """A function giving the posed vertices of `body` at each frame of `positions` (T, 25, 3),
    one at a time (skinning again per pass): memory does not grow with the clip."""
    A, b = segment_transforms(body, clip_joints(positions, KEYPOINTS))
    return lambda: (skin(body, A[t], b[t]) for t in range(len(A)))


def clip_scene(spec: ClipSpec, rig: Rig) -> tuple[Motion, Callable[[], Iterator[np.ndarray]], SceneRenderer]:
    """The clip's motion, its posed body (posed_bodies) and the scene with that body, its look
    and room (the box not yet fitted)."""
    motion = prepare_motion(spec)
    body = load_body(spec.shape())
    posed = posed_bodies(body, motion.positions)
    lowest = np.array([v[:, 2].min() for v in posed()])
    # the floor under the soles: at z = 0 unless the body lies lower (then it sinks into it less)
    floor_z = float(min(0.0, np.percentile(lowest, 5)))
    rng = np.random.default_rng(spec.rng_seed())
    return motion, posed, SceneRenderer(rig, body, Appearance.draw(rng), spec.rng_seed(), floor_z)


def render_recording(spec: ClipSpec, rig: Rig, cache_dir: Path, progress: bool = True) -> Path:
    """Render (or find in the cache) the recording of one clip; returns its path."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    out = cache_dir / f"{spec.label()}_{cache_key(spec, rig)}.mcap"
    if out.exists():
        return out
    motion, posed, scene = clip_scene(spec, rig)
    scene.fit_box(posed())
    write_rendered(out, scene, ((v, ()) for v in posed()), spec.rate_hz, [(TRUTH_TOPIC, motion.positions)],
                   spec.label(), progress)
    return out


def write_rendered(out: Path, scene: SceneRenderer, frames: Iterable[tuple[np.ndarray, Sequence[np.ndarray]]],
                   rate_hz: float, truths: Sequence[tuple[str, np.ndarray]], label: str, progress: bool) -> None:
    """Render `frames` ((posed subject, posed others) per frame) through `scene` into the MCAP
    `out`: per frame every camera's CameraInfo and Image, then each truth topic's keypoints
    (truths: (topic, (T, 25, 3))). Written to a scratch file renamed at the end: `out` is
    complete or absent. Closes the scene."""
    from tqdm import tqdm

    topics = Topics()
    rig = scene.rig
    n = len(truths[0][1])
    # this process's own scratch file: two benches rendering the same clip into one cache at once
    # each write their own (a shared name had one truncate the other's file mid-write, and a
    # mixture of the two went into the cache); the last rename wins, both complete and equal
    tmp = out.with_name(f"{out.stem}.{os.getpid()}.part")
    try:
        with BagWriter(tmp, compression="zstd", overwrite=True) as w:
            for k, (verts, others) in enumerate(tqdm(frames, total=n, desc=f"render {label}", unit="frame",
                                                     disable=not progress, file=sys.stderr, leave=False)):
                t = T0_NS + int(round(k * 1e9 / rate_hz))
                for cam, img in zip(rig, scene.render(verts, others)):
                    w.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, t), t)
                    w.write(topics.image(cam.name), "sensor_msgs/msg/Image", M.image_msg(img, t, cam.name), t)
                for topic, positions in truths:
                    w.write(topic, "sensor_msgs/msg/PointCloud2", M.keypoint_cloud(t, positions[k]), t)
    finally:
        scene.close()
    tmp.replace(out)


def read_truth(path: Path, topic: str = TRUTH_TOPIC) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (T,), keypoints (T, 25, 3)) of a recording's truth topic."""
    stamps, pts = [], []
    with BagReader(path) as r:
        for m in r.messages([topic]):
            d = m.decode()
            P, _, _ = M.cloud_keypoints(d)
            stamps.append(M.stamp_ns(d))
            pts.append(P if P is not None else np.full((len(KEYPOINTS), 3), np.nan))
    return np.asarray(stamps, dtype=np.int64), np.asarray(pts)
