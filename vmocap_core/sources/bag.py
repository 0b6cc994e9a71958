"""A camera source reading one camera's images from a rosbag2 MCAP file."""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

from ..bag import BagReader
from ..bag import messages as M
from ..errors import BagError, SourceError
from .base import Frame, FrameSource


class BagFrameSource(FrameSource):
    """Frames of `camera` from the Image topic `topic` (default /vmocap/CAMERA/image_raw).

    Recorded: `read` returns frames as fast as asked (pacing is the caller's: see
    vmocap_ros' camera node); `exhausted` turns True at the end unless `loop`.
    """

    def __init__(self, path: str | Path, camera: str, topic: str | None = None, start_offset_s: float = 0.0,
                 loop: bool = False, recover: bool = False) -> None:
        self.path = Path(path)
        self.name = camera
        self.topic = topic or f"/vmocap/{camera}/image_raw"
        self.start_offset_ns = int(start_offset_s * 1e9)
        self.loop = loop
        self.recover = recover
        self._reader: BagReader | None = None
        self._it: Iterator | None = None
        self._done = False
        self._seq = 0

    def open(self) -> None:
        try:
            self._reader = BagReader(self.path, recover=self.recover).open()
        except BagError as exc:
            raise SourceError(f"camera {self.name}: {exc}") from None
        if self.topic not in self._reader.topics:
            topics = sorted(self._reader.topics)
            self.close()
            raise SourceError(f"camera {self.name}: {self.path} has no topic {self.topic} (topics: {topics})")
        self._restart()

    def _restart(self) -> None:
        assert self._reader is not None
        start = self._reader.start_ns + self.start_offset_ns if self.start_offset_ns else None
        self._it = iter(self._reader.messages([self.topic], start_ns=start))

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
        for _ in range(2):
            try:
                m = next(self._it)
            except StopIteration:
                if not self.loop:
                    self._done = True
                    return None
                self._restart()
                continue
            except BagError as exc:
                raise SourceError(f"camera {self.name}: {exc}") from None
            msg = m.decode()
            self._seq += 1
            return Frame(self.name, M.stamp_ns(msg), M.image_array(msg), self._seq)
        self._done = True
        return None
