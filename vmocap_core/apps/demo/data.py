"""The demo's data: the Pose2Sim videos (their Qualisys calibration is read by
calibration.reference.load_qualisys), the videos as an MCAP bag, and that bag's synchronized
frame sets."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ...cameras.bag import bin_image, decode_compressed
from ...cameras.projection import Rig
from ...errors import SourceError, VmocapError

FPS = 60.0


def log(msg: str) -> None:
    print(f"vmocap demo: {msg}", file=sys.stderr, flush=True)


def video_paths(demo: Path) -> dict[str, Path]:
    vids = sorted((demo / "videos").glob("cam*.mp4"))
    if not vids:
        raise VmocapError(f"{demo}/videos: no cam*.mp4")
    return {p.stem: p for p in vids}


def video_sizes(videos: dict[str, Path]) -> dict[str, tuple[int, int]]:
    import cv2

    out = {}
    for name, p in videos.items():
        cap = cv2.VideoCapture(str(p))
        out[name] = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        cap.release()
    return out


# ------------------------------------------------------------------------------ videos -> bag
def videos_to_bag(videos: dict[str, Path], rig: Rig, bag: Path, max_frames: int | None = None, quality: int = 90,
                  raw: bool = False, overwrite: bool = False) -> int:
    """Write the synchronized videos as JPEG CompressedImage + CameraInfo per camera
    (stamp = frame index / 60 fps). Returns the number of frame sets. raw=True writes
    sensor_msgs/Image (bgr8) on NS/CAM/image_raw instead (about 25 MB per frame set before
    the bag's zstd compression; the camera node reads either). An existing `bag` is replaced
    only with `overwrite`, and only once the new one is complete (BagWriter)."""
    import cv2
    from tqdm import tqdm

    from ...bag import BagWriter
    from ...bag import messages as M
    from ...graph_config import Topics

    topics = Topics()
    caps = {c.name: cv2.VideoCapture(str(videos[c.name])) for c in rig}
    n = min(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) for cap in caps.values())
    if max_frames:
        n = min(n, max_frames)
    written = 0
    with BagWriter(bag, compression="zstd" if raw else "none", overwrite=overwrite, inputs=videos.values()) as writer:
        for f in tqdm(range(n), desc="videos -> bag", unit="frame", file=sys.stderr):
            ns = int(round(f * 1e9 / FPS))
            frames = {}
            for name, cap in caps.items():
                ok, img = cap.read()
                if not ok:
                    break
                frames[name] = img
            if len(frames) < len(caps):
                break
            for cam in rig:
                if raw:
                    writer.write(topics.image(cam.name), "sensor_msgs/msg/Image", M.image_msg(frames[cam.name], ns, cam.name), ns)
                    writer.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, ns), ns)
                    continue
                ok, jpg = cv2.imencode(".jpg", frames[cam.name], [cv2.IMWRITE_JPEG_QUALITY, quality])
                writer.write(topics.image(cam.name) + "/compressed", "sensor_msgs/msg/CompressedImage",
                             {"header": M.header(ns, cam.name), "format": "jpeg", "data": jpg.tobytes()}, ns)
                writer.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, ns), ns)
            written += 1
    for cap in caps.values():
        cap.release()
    return written


def bag_frame_sets(bag: Path, rig: Rig, binning: int = 1):
    """(stamp_ns, images in rig order) of the bag's camera images (JPEG CompressedImage, or raw
    Image), by stamp; reduced `binning` times (cameras.bag.decode_compressed / bin_image)."""
    from ...bag import BagReader
    from ...bag import messages as M
    from ...graph_config import Topics

    topics = Topics()
    pending: dict[int, dict[int, np.ndarray]] = {}
    with BagReader(bag) as reader:
        want = {}
        for i, c in enumerate(rig):
            raw = topics.image(c.name)
            want[raw + "/compressed" if raw + "/compressed" in reader.topics else raw] = i
        missing = [t for t in want if t not in reader.topics]
        if missing:
            raise VmocapError(f"{bag}: no topics {missing}")
        for m in reader.messages(list(want)):
            msg = m.decode()
            ns = M.stamp_ns(msg)
            if m.topic.endswith("/compressed"):
                try:
                    img = decode_compressed(msg, binning)
                except SourceError as exc:
                    raise VmocapError(f"{bag}: undecodable image on {m.topic} at {ns} ns ({exc})") from None
            else:
                img = bin_image(M.image_array(msg), binning)
            pending.setdefault(ns, {})[want[m.topic]] = img
            if len(pending[ns]) == len(rig):
                imgs = pending.pop(ns)
                yield ns, [imgs[i] for i in range(len(rig))]


def _count_frame_sets(bag: Path, rig: Rig, raw: bool = False) -> int:
    from ...bag import BagReader
    from ...errors import BagError
    from ...graph_config import Topics

    suffix = "" if raw else "/compressed"
    try:
        with BagReader(bag) as reader:
            return min(reader.message_counts.get(Topics().image(c.name) + suffix, 0) for c in rig)
    except BagError:
        return -1


def _video_frames(videos: dict[str, Path]) -> int:
    import cv2

    counts = []
    for p in videos.values():
        cap = cv2.VideoCapture(str(p))
        counts.append(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        cap.release()
    return min(counts)
