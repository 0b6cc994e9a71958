"""Writing rosbag2-compatible MCAP files: profile "ros2", schemas "ros2msg" (full definition
text), messages "cdr". Readable by ros2 bag, `rosbags`, Foxglove and mcap_io.BagReader.

The writer never leaves a half-written file under the final name: it writes `NAME.partial`
and renames it to NAME only after the MCAP footer and summary are written (on close, and on
SIGINT/SIGTERM in the recorder, which closes it); an exception inside `with` removes the
partial file and leaves an existing NAME as it was. It refuses (OutputPathError) to write
onto one of its `inputs`, or to replace an existing NAME or NAME.partial without `overwrite`
(vmocap_core.files). A process killed with SIGKILL leaves only `NAME.partial`, which
`BagReader(..., recover=True)` reads.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterable

from mcap.writer import CompressionType, Writer

from ..errors import BagError, OutputPathError
from ..files import check_output
from . import cdr

PARTIAL_SUFFIX = ".partial"
# What rosbag2 records as the publisher QoS (reliable, volatile, keep last): players use it.
_QOS_YAML = (
    "- history: 1\n  depth: {depth}\n  reliability: 1\n  durability: {durability}\n"
    "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  avoid_ros_namespace_conventions: false\n"
)
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}


class BagWriter:
    """Write messages (dicts or CDR bytes) into a rosbag2-compatible MCAP file."""

    def __init__(self, path: str | os.PathLike, compression: str = "none", chunk_size: int = 4 << 20, *,
                 overwrite: bool = False, inputs: Iterable[str | os.PathLike] = ()) -> None:
        self.path = Path(path)
        if compression not in _COMPRESSION:
            raise BagError(f"{self.path}: unknown compression {compression!r} (none, zstd, lz4)")
        self.overwrite = overwrite
        self.inputs = list(inputs)
        self.tmp_path = self.path.with_name(self.path.name + PARTIAL_SUFFIX)
        self._final = self.path
        self._compression = _COMPRESSION[compression]
        self._chunk_size = chunk_size
        self._file: Any = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._seq: dict[int, int] = {}
        self.count = 0

    def open(self) -> "BagWriter":
        if self._writer is not None:
            return self
        final = check_output(self.path, self.inputs, self.overwrite)
        self.tmp_path = final.with_name(final.name + PARTIAL_SUFFIX)
        check_output(self.tmp_path, self.inputs, overwrite=True)
        final.parent.mkdir(parents=True, exist_ok=True)
        try:
            # exclusive unless told to overwrite: a partial file is a recording not closed properly
            self._file = open(self.tmp_path, "wb" if self.overwrite else "xb")
        except FileExistsError:
            raise OutputPathError(f"{self.tmp_path}: exists (a recording that was not closed properly, or another "
                                  "writer): refusing to replace it; read it with --recover, move it away or pass "
                                  "--overwrite") from None
        except OSError as exc:
            raise BagError(f"{self.path}: cannot create ({exc})") from None
        self._final = final
        self._writer = Writer(self._file, chunk_size=self._chunk_size, compression=self._compression)
        self._writer.start(profile="ros2", library="vmocap")
        return self

    def add_topic(self, topic: str, type_name: str, qos_depth: int = 10, latched: bool = False) -> int:
        """Register `topic` with message type `type_name` ("pkg/msg/Type"); idempotent.
        latched: recorded as transient local (robot_description, /tf_static), which players
        offer again to late subscribers."""
        if self._writer is None:
            self.open()
        assert self._writer is not None
        if topic in self._channels:
            cid, known = self._channels[topic]
            if known != type_name:
                raise BagError(f"{self.path}: topic {topic} already has type {known}, not {type_name}")
            return cid
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                name=type_name, encoding="ros2msg", data=cdr.schema_text(type_name).encode()
            )
        cid = self._writer.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=self._schemas[type_name],
            metadata={"offered_qos_profiles": _QOS_YAML.format(depth=1 if latched else qos_depth, durability=1 if latched else 2)},
        )
        self._channels[topic] = (cid, type_name)
        self._seq[cid] = 0
        return cid

    def write(self, topic: str, type_name: str, msg: dict | bytes, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        cid = self.add_topic(topic, type_name)
        data = msg if isinstance(msg, (bytes, bytearray, memoryview)) else cdr.encode(type_name, msg)
        self._seq[cid] += 1
        assert self._writer is not None
        self._writer.add_message(
            channel_id=cid,
            log_time=int(log_time_ns),
            data=bytes(data),
            publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
            sequence=self._seq[cid],
        )
        self.count += 1

    def close(self) -> None:
        """Write the footer and summary, flush to disk and move the file to its final name."""
        if self._writer is None:
            return
        writer, f = self._writer, self._file
        self._writer = None
        try:
            writer.finish()
            f.flush()
            os.fsync(f.fileno())
        finally:
            f.close()
        if not self.overwrite and os.path.lexists(self._final):  # appeared while we wrote: keep both
            raise OutputPathError(f"{self.path}: appeared while writing; refusing to replace it (the recording "
                                  f"is complete in {self.tmp_path})")
        os.replace(self.tmp_path, self._final)

    def abort(self) -> None:
        """Drop what was written: the partial file goes, an existing NAME stays as it was."""
        if self._writer is None:
            return
        self._writer = None
        self._file.close()
        self.tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:  # a failed run leaves no output that looks complete
            self.abort()
