"""Frames through shared memory (vmocap_core/cameras/shm.py): another process reads what the
camera process wrote, a frame overwritten or whose ring is gone is lost (None, counted), a
reference from another machine or PID namespace is refused (the caller goes back to DDS)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from vmocap_core.cameras import shm
from vmocap_core.cameras.shm import FrameReader, FrameRing, ShmUnavailable

READ_IN_CHILD = """
import sys
import numpy as np
from vmocap_core.cameras.shm import FrameReader
r = FrameReader()
for ref in sys.argv[1:]:
    a = r.read("cam0", bytes.fromhex(ref))
    print(-1 if a is None else int(np.frombuffer(a, np.uint8).astype(np.int64).sum()), a is not None and a.nbytes)
"""


def _image(seed: int, shape=(48, 64, 3)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, shape, dtype=np.uint8)


def test_another_process_reads_the_frames_a_ring_holds() -> None:
    ring = FrameRing(48 * 64 * 3, slots=3)
    try:
        imgs = [_image(k) for k in range(4)]
        refs = [ring.write(memoryview(i).cast("B")) for i in imgs]  # the 4th overwrites the 1st's slot
        out = subprocess.run([sys.executable, "-c", READ_IN_CHILD, *(r.hex() for r in refs)],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        got = [line.split() for line in out.stdout.splitlines()]
        assert got[0] == ["-1", "False"]  # its slot was written again: lost, not another frame
        for (total, n), img in zip(got[1:], imgs[1:]):
            assert int(total) == int(img.astype(np.int64).sum()) and int(n) == img.nbytes
    finally:
        ring.close()


def test_read_copies_the_pixels_and_counts_what_is_lost() -> None:
    ring = FrameRing(48 * 64 * 3, slots=2)
    reader = FrameReader()
    img = _image(1)
    ref = ring.write(img.tobytes())
    a = reader.read("cam0", ref)
    assert a is not None and np.array_equal(np.frombuffer(a, np.uint8).reshape(img.shape), img)
    ring.write(_image(2).tobytes())
    ring.write(_image(3).tobytes())  # the first slot again
    assert np.array_equal(np.frombuffer(a, np.uint8).reshape(img.shape), img)  # a copy, not a view of the slot
    assert reader.read("cam0", ref) is None and reader.overwritten == 1
    with pytest.raises(ValueError):
        ring.write(b"x" * (48 * 64 * 3 + 1))
    last = ring.write(b"last")
    ring.close()
    other = FrameRing(16)  # a restarted camera (its descriptor number may be the old one's)
    late = FrameReader()  # a reader that had not mapped the old ring: its references are lost
    try:
        assert late.read("cam0", last) is None and late.gone == 1
        assert bytes(reader.read("cam0", last)) == b"last"  # mapped before: the memory lives while mapped
        ref2 = other.write(b"0123456789abcdef")
        for r in (reader, late):
            assert bytes(r.read("cam0", ref2)) == b"0123456789abcdef"
    finally:
        other.close()
        reader.close()
        late.close()


def test_references_this_process_cannot_follow_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    ring = FrameRing(8)
    try:
        ref = ring.write(b"12345678")
        with pytest.raises(ShmUnavailable, match="not a frame reference"):
            FrameReader().read("cam0", b"\x00" * 8)
        with pytest.raises(ShmUnavailable, match="not a frame reference"):
            FrameReader().read("cam0", b"X" * len(ref))
        monkeypatch.setattr(shm, "boot_id", lambda: b"\x01" * 16)
        with pytest.raises(ShmUnavailable, match="another machine"):
            FrameReader().read("cam0", ref)
        monkeypatch.undo()
        monkeypatch.setattr(shm, "pid_namespace", lambda: 1)
        with pytest.raises(ShmUnavailable, match="PID namespace"):
            FrameReader().read("cam0", ref)
    finally:
        ring.close()
