"""Calibration against known answers: the ChArUco rig of ../shared and the Pose2Sim demo."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vmocap_core.calibration.datasets import pose2sim_demo
from vmocap_core.cli import main

ROOT = Path(__file__).resolve().parents[1]
CHARUCO = ROOT.parent / "shared" / "data" / "calib_charuco"


def _run_json(argv, capsys) -> tuple[int, dict]:
    rc = main(argv)
    out = capsys.readouterr().out
    return rc, json.loads(out)


@pytest.mark.skipif(not (CHARUCO / "camera_array.toml").is_file(), reason="../shared/data/calib_charuco absent")
def test_charuco_rig_matches_reference(tmp_path, capsys):
    cams = [f"--camera={i}={CHARUCO / 'calibration/extrinsic' / f'cam_{i}.mp4'}" for i in range(4)]
    rc, out = _run_json(
        ["calibrate", f"--board={CHARUCO / 'charuco.toml'}", *cams, f"--intrinsics={CHARUCO / 'camera_array.toml'}",
         f"--reference={CHARUCO / 'camera_array.toml'}", "--every=3", "--check", "--json", "--no-progress",
         f"--out={tmp_path / 'rig.yaml'}", f"--camera-info-dir={tmp_path / 'info'}"], capsys)
    ext = out["reference"]["extrinsics"]
    assert ext["max_position_err_m"] < 0.02, ext
    assert ext["max_rotation_err_deg"] < 1.0, ext
    assert rc == 0
    # camera 1 sees the board from behind: only the mirrored decoding finds it
    cam1 = out["cameras"][1]
    assert cam1["mirrored_views"] >= 10 and cam1["rms"] < 2.0
    from vmocap_core.cameras.rig_file import load_rig

    rig = load_rig(tmp_path / "rig.yaml")
    assert rig.names == ["0", "1", "2", "3"]
    assert sorted(p.name for p in (tmp_path / "info").iterdir()) == ["0.yaml", "1.yaml", "2.yaml", "3.yaml"]


@pytest.mark.skipif(not (CHARUCO / "camera_array.toml").is_file(), reason="../shared/data/calib_charuco absent")
def test_intrinsics_of_wrong_size_are_refused(tmp_path, capsys):
    # a reference for 1280x720 given to images of another size: clear error naming the camera
    import cv2

    cap = cv2.VideoCapture(str(CHARUCO / "calibration/extrinsic/cam_0.mp4"))
    for i in range(4):
        ok, img = cap.read()
        cv2.imwrite(str(tmp_path / f"{i}.png"), cv2.resize(img, (640, 360)))
    rc = main(["calibrate", f"--board={CHARUCO / 'charuco.toml'}", f"--camera=0={tmp_path}", f"--camera=2={tmp_path}",
               f"--intrinsics={CHARUCO / 'camera_array.toml'}", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "camera 0" in err and "640x360" in err and "1280x720" in err


def test_pose2sim_checkerboard_focal_within_1_percent(capsys):
    demo = pose2sim_demo(fetch=False)
    if demo is None:
        pytest.skip("pose2sim==0.10.49 wheel not cached (vmocap calibrate's datasets.pose2sim_demo(fetch=True))")
    intr = demo / "calibration" / "intrinsics"
    cams = [f"--camera={d.name[4:9]}={d}" for d in sorted(intr.iterdir()) if d.is_dir()]
    rc, out = _run_json(["calibrate", "--board=checkerboard:4x7:0.06", *cams, "--intrinsics-only", "--min-views=5",
                         f"--reference={demo / 'calibration' / 'Calib.qca.txt'}", "--check", "--json", "--no-progress"], capsys)
    errs = {k: v["focal_err_pct"] for k, v in out["reference"]["intrinsics"].items()}
    assert len(errs) == 4 and max(errs.values()) < 1.0, errs
    assert rc == 0


@pytest.mark.skipif(not (CHARUCO / "camera_array.toml").is_file(), reason="../shared/data/calib_charuco absent")
def test_camera_that_never_sees_the_board_is_named(capsys):
    # camera 3 only sees the board from frame 24 on: with the first 12 frames it never does
    cams = [f"--camera={i}={CHARUCO / 'calibration/extrinsic' / f'cam_{i}.mp4'}" for i in (0, 3)]
    rc = main(["calibrate", f"--board={CHARUCO / 'charuco.toml'}", *cams, "--max-frames=12", "--every=2",
               f"--intrinsics={CHARUCO / 'camera_array.toml'}", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "camera 3: the board (charuco 4x5 squares" in err and "was never detected in 12 frames" in err
