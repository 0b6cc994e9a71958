"""Synchronized video files and the multi-camera rig (lock-step, software trigger, sizes)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vmocap_core.calibration.datasets import pose2sim_demo
from vmocap_core.cameras.projection import Camera, Rig
from vmocap_core.cameras.rig_source import SourceRig
from vmocap_core.cameras.video import VideoFrameSource, open_videos
from vmocap_core.errors import SourceError

FPS = 25.0


def write_video(path: Path, n: int, first: int = 0, size=(64, 48)) -> Path:
    """Frame k shows the number first + k as its grey level (x8) so content can be checked."""
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, size)
    assert w.isOpened()
    for k in range(n):
        w.write(np.full((size[1], size[0], 3), 8 * (first + k), np.uint8))
    w.release()
    return path


def level(img: np.ndarray) -> int:
    return int(round(float(img.mean()) / 8))


def test_offsets_align_content_and_stamps(tmp_path):
    # b's file started 3 frames earlier than a's, c's 2 frames later
    a = write_video(tmp_path / "a.avi", 20, first=5)
    b = write_video(tmp_path / "b.avi", 20, first=2)
    c = write_video(tmp_path / "c.avi", 20, first=7)
    srcs = open_videos([a, b, c], offsets={"b": 3, "c": -2})
    with SourceRig(srcs, period_ns=int(1e9 / FPS)) as rig:
        sets = []
        while (fs := rig.read_set()) is not None:
            sets.append(fs)
        report = rig.report()
    # common logical frames: c starts at 2, b (17 frames after its offset) ends at 16
    assert len(sets) == 15
    for fs in sets:
        assert fs.spread_ns == 0
        content = {n: level(f.image) - f.seq for n, f in fs.frames.items()}
        assert len(set(content.values())) == 1, content  # same instant in every file
    assert sets[0].frames["c"].seq == 2 and sets[0].frames["a"].seq == 2
    assert sets[1].stamp_ns - sets[0].stamp_ns == int(1e9 / FPS)
    assert report["sets"] == 15 and report["spread_ms_max"] == 0.0
    for cam in report["cameras"].values():
        assert cam["rate_hz"] == pytest.approx(FPS, rel=1e-6) and cam["gaps"] == 0


def test_software_trigger_fires_all_at_once(tmp_path):
    paths = [write_video(tmp_path / f"{n}.avi", 6) for n in ("x", "y")]
    srcs = open_videos(paths, trigger_mode=True)
    with SourceRig(srcs, trigger_mode=True) as rig:
        assert srcs[0].read(timeout=0.01) is None  # nothing without a trigger
        fs = rig.read_set()
        assert set(fs.frames) == {"x", "y"} and fs.frames["x"].seq == 0
        fs = rig.read_set()
        assert fs.frames["y"].seq == 1
    with pytest.raises(SourceError, match=r"cameras \['y'\] have no software trigger"):
        SourceRig([VideoFrameSource(paths[0], trigger_mode=True), VideoFrameSource(paths[1])], trigger_mode=True)


def test_size_mismatch_with_calibration_is_clear(tmp_path):
    p = write_video(tmp_path / "cam0.avi", 3, size=(64, 48))
    calib = Rig([Camera("cam0", np.diag([50.0, 50.0, 1.0]), np.zeros(5), np.eye(3), np.zeros(3), 80, 60)])
    with pytest.raises(SourceError, match="camera cam0: image is 64x48 but the rig was calibrated at 80x60"):
        SourceRig([VideoFrameSource(p)], calibration=calib).start()


def test_missing_file_and_mono(tmp_path):
    with pytest.raises(SourceError, match="camera nope: video file .* does not exist"):
        VideoFrameSource(tmp_path / "nope.avi").open()
    p = write_video(tmp_path / "m.avi", 2)
    with VideoFrameSource(p, mono=True, flip="h") as s:
        f = s.read()
        assert f.image.shape == (48, 64) and f.encoding == "mono8"
        assert s.read() is not None and s.read() is None and s.exhausted


def test_pose2sim_demo_videos_against_their_calibration():
    demo = pose2sim_demo(fetch=False)
    if demo is None:
        pytest.skip("pose2sim==0.10.49 wheel not cached")
    from vmocap_core.calibration.reference import load_qualisys_intrinsics

    vids = sorted((demo / "videos").glob("cam*.mp4"))
    srcs = open_videos(vids)
    with SourceRig(srcs, period_ns=int(1e9 / 60)) as rig:
        for _ in range(3):
            fs = rig.read_set()
            assert len(fs.frames) == 4 and fs.spread_ns == 0
        assert all(c["rate_hz"] == pytest.approx(60.0) for c in rig.report()["cameras"].values())
    # the demo's cam01/cam02 videos are 1080 wide, the Qualisys calibration 1088: refused
    calib = load_qualisys_intrinsics(demo / "calibration" / "Calib.qca.txt")
    with pytest.raises(SourceError, match="camera cam01: image is 1080x1920 but the rig was calibrated at 1088x1920"):
        SourceRig(open_videos(vids), calibration=calib).start()


def test_loop_and_realtime_pacing(tmp_path):
    import time

    p = write_video(tmp_path / "l.avi", 4)
    with VideoFrameSource(p, loop=True, realtime=True, offset_frames=1) as s:
        t0 = time.monotonic()
        frames = [s.read() for _ in range(7)]  # 3 frames per pass after the offset
        elapsed = time.monotonic() - t0
    assert [f.seq for f in frames] == list(range(7))
    assert [level(f.image) for f in frames] == [1, 2, 3, 1, 2, 3, 1]
    assert frames[6].stamp_ns - frames[0].stamp_ns == int(round(6e9 / FPS))
    assert elapsed >= 6 / FPS - 0.01  # paced like a live camera


def test_make_source_from_uri(tmp_path):
    from vmocap_core.cameras import make_source
    from vmocap_core.cameras.v4l2 import V4L2FrameSource

    write_video(tmp_path / "cam0.avi", 5, first=0)
    write_video(tmp_path / "cam1.avi", 5, first=0)
    s0 = make_source("video", f"{tmp_path}?fps=10&offset.cam1=2&mono=true", "cam0")
    s1 = make_source("video", f"{tmp_path}/{{camera}}.avi?fps=10&offset.cam1=2", "cam1")
    with s0, s1:
        f0, f1 = s0.read(), s1.read()
    assert f0.image.ndim == 2 and s0.fps == 10 and f0.seq == 0 and level(f0.image) == 0
    assert f1.seq == 0 and level(f1.image) == 2  # cam1's offset
    v = make_source("v4l2", "cam0=/dev/video4,cam1=/dev/video6?width=1280&height=720&fourcc=MJPG", "cam1")
    assert isinstance(v, V4L2FrameSource) and v.device == "/dev/video6" and v.req["width"] == 1280
    with pytest.raises(SourceError, match="camera cam2: source uri .* names no target"):
        make_source("v4l2", "cam0=/dev/video4", "cam2")
    with pytest.raises(SourceError, match="bad video source option"):
        make_source("video", f"{tmp_path}?colour=red", "cam0")
    with pytest.raises(SourceError, match="unknown source kind 'ndi'"):
        make_source("ndi", "x", "cam0")
