"""A camera source reading one camera's images from a rosbag2 MCAP file (raw
sensor_msgs/Image, or sensor_msgs/CompressedImage decoded to BGR)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import numpy as np

from ..bag import BagReader, cdr
from ..bag import messages as M
from ..errors import BagError, SourceError
from .base import Frame, FrameSource

COMPRESSED = "sensor_msgs/msg/CompressedImage"


class BagFrameSource(FrameSource):
    """Frames of `camera` from the Image topic `topic` (default /vmocap/CAMERA/image_raw).
    When the bag has no such topic but `topic`/compressed of type sensor_msgs/CompressedImage
    (JPEG/PNG, as image_transport records it), that one is read and each frame decoded to a
    BGR image; a frame that does not decode is skipped and counted in `bad_frames`.

    binning > 1: frames come reduced that many times (JPEGs decoded directly at that size, raw
    images block-averaged: bin_image), for a camera node publishing binned images.

    Recorded: `read` returns frames as fast as asked (pacing is the caller's: see
    vmocap_ros' camera node); `exhausted` turns True at the end unless `loop`.
    """

    def __init__(self, path: str | Path, camera: str, topic: str | None = None, start_offset_s: float = 0.0,
                 loop: bool = False, recover: bool = False, binning: int = 1) -> None:
        self.path = Path(path)
        self.name = camera
        self.topic = topic or f"/vmocap/{camera}/image_raw"
        self.start_offset_ns = int(start_offset_s * 1e9)
        self.loop = loop
        self.recover = recover
        check_binning(binning)
        self.binning = binning
        self._reader: BagReader | None = None
        self._it: Iterator | None = None
        self._done = False
        self._seq = 0
        self.compressed = False
        self.bad_frames = 0
        self.last_error = ""

    def open(self) -> None:
        try:
            self._reader = BagReader(self.path, recover=self.recover).open()
        except BagError as exc:
            raise SourceError(f"camera {self.name}: {exc}") from None
        alt = self.topic + "/compressed"
        if self.topic not in self._reader.topics and self._reader.topics.get(alt) == COMPRESSED:
            self.topic = alt
        self.compressed = self._reader.topics.get(self.topic) == COMPRESSED
        if self.compressed:  # each camera decodes in a thread of its own (vmocap_camera)
            single_threaded_opencv()
        if self.topic not in self._reader.topics:
            topics = sorted(self._reader.topics)
            self.close()
            raise SourceError(f"camera {self.name}: {self.path} has no topic {self.topic} (topics: {topics})")
        self._restart()

    def _restart(self) -> None:
        assert self._reader is not None
        start = self._reader.start_ns + self.start_offset_ns if self.start_offset_ns else None
        # zero copy: an uncompressed bag's image is a view into the memory-mapped file until the
        # camera node copies it into its message
        self._it = iter(self._reader.messages([self.topic], start_ns=start, zero_copy=True))

    @property
    def damaged(self) -> list[str]:
        """recover: the damaged chunks skipped so far, what and where each was (the reader's
        list, read each frame by the camera node: not copied)."""
        return self._reader.damaged_chunks if self._reader is not None else []

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        self._it = None

    @property
    def exhausted(self) -> bool:
        return self._done

    def read(self, timeout: float = 1.0) -> Frame | None:
        if self._it is None:
            raise SourceError(f"camera {self.name}: source not open")
        restarted = False
        while True:
            try:
                m = next(self._it)
            except StopIteration:
                if not self.loop or restarted:  # restarted: nothing usable in the whole bag
                    self._done = True
                    return None
                self._restart()
                restarted = True
                continue
            except BagError as exc:
                raise SourceError(f"camera {self.name}: {exc}") from None
            try:
                msg = cdr.decode(m.type, m.data, copy=False)
                image = decode_compressed(msg, self.binning) if self.compressed else bin_image(M.image_array(msg), self.binning)
            except (BagError, SourceError) as exc:
                self.bad_frames += 1
                self.last_error = f"camera {self.name}: {exc}"
                continue
            self._seq += 1
            return Frame(self.name, M.stamp_ns(msg), image, self._seq)


def single_threaded_opencv() -> None:
    """OpenCV's own worker threads off, process-wide, where our threads decode images side by
    side: its workers wait actively for work, and beside a second decoding thread (and the
    CNN's threads) they took twice the CPU for the same JPEGs."""
    import cv2

    cv2.setNumThreads(1)


# Niceness of threads that decode images ahead of the CNN (offline): such decoding only fills
# the cores while the CNN -> tracker chain waits; at equal priority it preempts a CNN thread and
# the frame set's call waits for its slower half.
DECODE_AHEAD_NICE = 10


def decode_ahead_priority() -> None:
    """Lower the calling thread's priority by DECODE_AHEAD_NICE (Linux: nice is per thread);
    left as it is where the platform does not allow it."""
    try:
        os.nice(DECODE_AHEAD_NICE)
    except OSError:
        pass


# cv2.imread flag per binning: JPEGs are decoded directly at the reduced size (DCT scaling,
# ~3x cheaper at 2 on 1088x1920 frames); other formats are decoded whole and block-averaged
# (OpenCV's reduced PNG decoding is not a block mean at 4).
REDUCED = {1: "IMREAD_COLOR", 2: "IMREAD_REDUCED_COLOR_2", 4: "IMREAD_REDUCED_COLOR_4", 8: "IMREAD_REDUCED_COLOR_8"}


def decode_compressed(msg: dict, binning: int = 1) -> np.ndarray:
    """sensor_msgs/CompressedImage (JPEG, PNG, ...) -> BGR uint8 image, reduced `binning`
    times (1, 2, 4 or 8; projection.Camera.binned gives the matching camera)."""
    import cv2

    check_binning(binning)
    data = np.frombuffer(msg["data"], dtype=np.uint8)
    jpeg = bytes(data[:2]) == b"\xff\xd8"
    img = cv2.imdecode(data, getattr(cv2, REDUCED[binning] if jpeg else "IMREAD_COLOR")) if data.size else None
    if img is None:
        raise SourceError(f"compressed image ({msg.get('format') or 'unknown format'}, {data.size} bytes) does not decode")
    return img if jpeg else bin_image(img, binning)


def bin_image(image: np.ndarray, binning: int) -> np.ndarray:
    """An image reduced `binning` times by averaging binning x binning blocks (REP 104 binning,
    the geometry of projection.Camera.binned; the size rounds up as libjpeg's reduced decoding
    does, a partial last block filled by repeating the edge)."""
    import cv2

    check_binning(binning)
    if binning == 1:
        return image
    h, w = image.shape[:2]
    H, W = -(-h // binning), -(-w // binning)
    if (H * binning, W * binning) != (h, w):
        image = cv2.copyMakeBorder(image, 0, H * binning - h, 0, W * binning - w, cv2.BORDER_REPLICATE)
    # INTER_AREA at an integer factor is the exact block mean
    return cv2.resize(image, (W, H), interpolation=cv2.INTER_AREA)


def check_binning(binning: int) -> None:
    """SourceError unless `binning` is one the JPEG decoder can reduce by directly."""
    if binning not in REDUCED:
        raise SourceError(f"binning must be one of {sorted(REDUCED)}, got {binning}")
