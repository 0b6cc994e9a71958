"""Camera frames (and heatmaps) between processes of one machine through shared memory.

When the camera and PCM nodes run in separate processes, each image (2.4 MB at 1024x768) crosses
DDS: encoded, serialized, cut into fragments by the transport, reassembled and taken again, a
copy at each step, on the cores the CNN needs (the heatmaps to the markers node likewise). A `FrameRing` keeps a camera's last frames in an
anonymous memory file (memfd) owned by the camera process; a small reference (`Ref`) names the
slot, and the reader copies the pixels out once (`FrameReader`). The reader opens the file
through /proc/PID/fd/FD, so nothing is left in /dev/shm when a process dies: the memory goes
with the last process that has it open. A reference from another machine (boot id) or another
PID namespace cannot be opened: `ShmUnavailable`, and the caller goes back to DDS. A ring that is
gone (the camera process restarted, a larger frame made a new ring) loses the frames referring
to it, nothing more.

Each slot starts with a sequence number, odd while the slot is written (a seqlock): a reader
that finds another number than its reference's before or after its copy has a frame that was
overwritten (the reader fell a whole ring behind) and drops it.
"""

from __future__ import annotations

import mmap
import os
import struct
import uuid

import numpy as np

from ..errors import VmocapError

MAGIC = b"VMOCAPSH"
_FILE_HEADER = struct.Struct("<8s16sQQ")  # magic, ring id, slots, slot size (bytes, header included)
_SLOT_HEADER = struct.Struct("<Q")  # sequence number
_REF = struct.Struct("<8s16sQ16sIIQQQ")  # magic, boot id, PID namespace, ring id, pid, fd, slot, seq, nbytes
DATA_OFFSET = 64  # a slot's pixels start at this offset in the slot (cache-line aligned)


class ShmUnavailable(VmocapError):
    """A reference this process cannot follow (another machine, another PID namespace, a ring
    that is gone): the frames must come over DDS."""


def pid_namespace() -> int:
    """The inode of this process's PID namespace: a pid in a reference means the same process only within it."""
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return 0


def boot_id() -> bytes:
    """This machine's boot id (16 bytes): references are only followed on the machine that made them."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return uuid.UUID(f.read().strip()).bytes
    except (OSError, ValueError):
        return b"\0" * 16


class FrameRing:
    """A camera's last `slots` frames in shared memory (writer side, one thread at a time)."""

    def __init__(self, slot_bytes: int, slots: int = 6, name: str = "vmocap-frames") -> None:
        if slots < 2 or slot_bytes < 1:
            raise ValueError("a frame ring needs at least 2 slots of at least 1 byte")
        self.slots, self.capacity = int(slots), int(slot_bytes)
        self.slot_size = DATA_OFFSET + -(-self.capacity // 64) * 64
        self.size = DATA_OFFSET + self.slots * self.slot_size
        self.ring_id = uuid.uuid4().bytes
        self.boot, self.pidns = boot_id(), pid_namespace()
        self.fd = os.memfd_create(name, os.MFD_CLOEXEC)
        os.ftruncate(self.fd, self.size)
        self.map = mmap.mmap(self.fd, self.size)
        _FILE_HEADER.pack_into(self.map, 0, MAGIC, self.ring_id, self.slots, self.slot_size)
        self._next = 0
        self._seq = 0

    def write(self, data: memoryview | bytes) -> bytes:
        """Copy one frame's bytes into the next slot; the reference (`Ref` bytes) to send."""
        n = memoryview(data).nbytes
        if n > self.capacity:
            raise ValueError(f"a frame of {n} bytes does not fit a ring of {self.capacity}-byte slots")
        slot, self._next = self._next, (self._next + 1) % self.slots
        self._seq += 2
        base = DATA_OFFSET + slot * self.slot_size
        _SLOT_HEADER.pack_into(self.map, base, self._seq - 1)  # odd: being written
        self.map[base + DATA_OFFSET: base + DATA_OFFSET + n] = data
        _SLOT_HEADER.pack_into(self.map, base, self._seq)
        return _REF.pack(MAGIC, self.boot, self.pidns, self.ring_id, os.getpid(), self.fd, slot, self._seq, n)

    def close(self) -> None:
        if self.fd >= 0:
            self.map.close()
            os.close(self.fd)
            self.fd = -1


class FrameReader:
    """Follows references to FrameRings of other processes; keeps the last ring of each source
    (a restarted camera process makes a new one) mapped."""

    def __init__(self) -> None:
        self.boot, self.pidns = boot_id(), pid_namespace()
        self._maps: dict[str, tuple[bytes, mmap.mmap, int]] = {}  # source -> (ring id, map, slot size)
        self.overwritten = 0  # frames dropped: their slot was written again before the copy ended
        self.gone = 0  # frames dropped: their ring no longer exists

    def read(self, source: str, ref: bytes) -> np.ndarray | None:
        """The frame's bytes (a copy), or None when it is lost (its slot written again meanwhile,
        its ring gone). ShmUnavailable: this process cannot follow such references at all."""
        try:
            magic, boot, pidns, ring_id, pid, fd, slot, seq, n = _REF.unpack(bytes(ref))
        except struct.error:
            raise ShmUnavailable(f"{source}: not a frame reference ({len(ref)} bytes)") from None
        if magic != MAGIC:
            raise ShmUnavailable(f"{source}: not a frame reference")
        if boot != self.boot:
            raise ShmUnavailable(f"{source}: the frames are in another machine's memory")
        if pidns != self.pidns:
            raise ShmUnavailable(f"{source}: the camera process is in another PID namespace")
        held = self._maps.get(source)
        if held is None or held[0] != ring_id:
            held = self._open(source, pid, fd, ring_id)
            if held is None:
                self.gone += 1
                return None
        _, m, slot_size = held
        base = DATA_OFFSET + slot * slot_size
        if base + DATA_OFFSET + n > len(m):
            raise ShmUnavailable(f"{source}: a reference beyond its ring")
        if _SLOT_HEADER.unpack_from(m, base)[0] != seq:
            self.overwritten += 1
            return None
        out = np.frombuffer(m, np.uint8, n, base + DATA_OFFSET).copy()
        if _SLOT_HEADER.unpack_from(m, base)[0] != seq:
            self.overwritten += 1
            return None
        return out

    def _open(self, source: str, pid: int, fd: int, ring_id: bytes) -> tuple[bytes, mmap.mmap, int] | None:
        """The ring mapped, None when it is gone (its process ended, its descriptor closed or reused)."""
        try:
            f = os.open(f"/proc/{pid}/fd/{fd}", os.O_RDONLY | os.O_CLOEXEC)
        except FileNotFoundError:
            return None
        except OSError as exc:  # no permission (another user)
            raise ShmUnavailable(f"{source}: the camera process's frame memory cannot be opened ({exc.strerror})") from None
        try:
            size = os.fstat(f).st_size
            if size < _FILE_HEADER.size:
                return None
            m = mmap.mmap(f, size, prot=mmap.PROT_READ)
        finally:
            os.close(f)
        magic, rid, slots, slot_size = _FILE_HEADER.unpack_from(m, 0)
        if magic != MAGIC or rid != ring_id or DATA_OFFSET + slots * slot_size > size:
            m.close()
            return None
        old = self._maps.pop(source, None)
        if old is not None:
            old[1].close()
        self._maps[source] = (ring_id, m, slot_size)
        return self._maps[source]

    def close(self) -> None:
        for _, m, _ in self._maps.values():
            m.close()
        self._maps.clear()
