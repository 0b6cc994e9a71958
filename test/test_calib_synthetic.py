"""Rig calibration on synthetic detections with a known answer, and board detection on
rendered images (including a board seen from behind)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vmocap_core.calibration import CharucoBoard, SceneObservations, calibrate_rig, compare_extrinsics
from vmocap_core.calibration.boards import Detection
from vmocap_core.calibration.geometry import rodrigues
from vmocap_core.calibration.observe import CameraViews
from vmocap_core.cameras.projection import Camera, Rig, look_at
from vmocap_core.errors import CalibrationError

W, H = 960, 720


def true_rig() -> Rig:
    K = np.array([[800.0, 0, 470], [0, 805.0, 365], [0, 0, 1]])
    dist = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
    cams = []
    for i, eye in enumerate([(2.0, 0.3, 1.2), (0.2, 2.1, 1.0), (-1.8, 0.8, 1.4)]):
        R, t = look_at(np.array(eye), np.array([0.0, 0.0, 1.0]))
        cams.append(Camera(f"c{i}", K, dist, R, t, W, H))
    return Rig(cams)


def synthetic_views(rig: Rig, board: CharucoBoard, n_frames: int, seed: int = 0, blind: str | None = None):
    rng = np.random.default_rng(seed)
    views = [CameraViews(c.name, (W, H), frames_read=n_frames) for c in rig]
    centre = board.object_points.mean(0)
    for f in range(n_frames):
        R = rodrigues(rng.normal(0, 0.5, 3))[0]
        t = np.array([0, 0, 1.0]) + rng.normal(0, 0.15, 3) - R @ centre
        Xw = board.object_points @ R.T + t
        uv, front = rig.project(Xw)
        for c, cam in enumerate(rig):
            normal_cam = cam.R @ R[:, 2]
            inside = front[c] & (uv[c, :, 0] > 5) & (uv[c, :, 0] < W - 5) & (uv[c, :, 1] > 5) & (uv[c, :, 1] < H - 5)
            # a board seen too obliquely is not detected
            depth_dir = (cam.R @ Xw.mean(0) + cam.t)
            cosang = abs(normal_cam @ depth_dir) / np.linalg.norm(depth_dir)
            if cam.name == blind or inside.sum() < 8 or cosang < 0.3:
                continue
            ids = np.flatnonzero(inside)
            views[c].views[f] = Detection(ids, uv[c, ids] + rng.normal(0, 0.2, (len(ids), 2)))
    for v in views:
        v.max_corners = max([len(d.ids) for d in v.views.values()], default=0)
    return views


@pytest.fixture(scope="module")
def board():
    return CharucoBoard(5, 7, 0.06, 0.045, "DICT_4X4_50")


def test_rig_from_given_intrinsics(board):
    rig = true_rig()
    views = synthetic_views(rig, board, 40)
    res = calibrate_rig(views, board, intrinsics={c.name: c for c in rig})
    cmp = compare_extrinsics(res.rig, rig)
    assert cmp["max_position_err_m"] < 0.003, cmp
    assert cmp["max_rotation_err_deg"] < 0.1, cmp
    assert all(r.rms < 0.5 for r in res.cameras)
    # world frame = the first camera
    assert np.allclose(res.rig[0].R, np.eye(3)) and np.allclose(res.rig[0].t, 0)


def test_rig_with_zhang_intrinsics():
    # a large board filling the views: the lens is observable from 40 frames
    board = CharucoBoard(7, 9, 0.1, 0.075, "DICT_4X4_50")
    rig = true_rig()
    views = synthetic_views(rig, board, 40, seed=1)
    res = calibrate_rig(views, board, refine_intrinsics=True)
    for est, ref in zip(res.rig, rig):
        assert abs(est.K[0, 0] - ref.K[0, 0]) / ref.K[0, 0] < 0.005
    cmp = compare_extrinsics(res.rig, rig)
    assert cmp["max_position_err_m"] < 0.012 and cmp["max_rotation_err_deg"] < 0.3, cmp


def test_scene_points_define_the_world(board):
    rig = true_rig()
    views = synthetic_views(rig, board, 30, seed=2)
    pts = np.array([[0.5, 0.5, 0.0], [-0.5, 0.5, 0.0], [-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.0, 0.8], [0.3, -0.2, 1.5]])
    uv, _ = rig.project(pts)
    scene = SceneObservations(pts, {c.name: uv[i] + 0.1 for i, c in enumerate(rig)})
    res = calibrate_rig(views, board, intrinsics={c.name: c for c in rig}, scene=scene)
    for est, ref in zip(res.rig, rig):
        assert np.linalg.norm(est.center - ref.center) < 0.01
        assert np.degrees(np.arccos(np.clip((np.trace(est.R.T @ ref.R) - 1) / 2, -1, 1))) < 0.3


def test_blind_camera_is_named(board):
    rig = true_rig()
    views = synthetic_views(rig, board, 12, blind="c2")
    with pytest.raises(CalibrationError, match=r"camera c2: the board .* was never detected in 12 frames"):
        calibrate_rig(views, board, intrinsics={c.name: c for c in rig})


def test_few_views_warns(board):
    rig = true_rig()
    views = synthetic_views(rig, board, 40, seed=3)
    views[1].views = dict(list(views[1].views.items())[:4])
    res = calibrate_rig(views, board, intrinsics={c.name: c for c in rig})
    assert any("camera c1: only 4 board views" in w for w in res.warnings)


def test_detect_rendered_board_front_and_back(board):
    img = board._board.generateImage((500, 700), marginSize=40)
    canvas = np.full((720, 960), 200, np.uint8)
    src = np.float32([[0, 0], [500, 0], [500, 700], [0, 700]])
    dst = np.float32([[300, 80], [690, 120], [660, 650], [280, 610]])
    M = cv2.getPerspectiveTransform(src, dst)
    warped = cv2.warpPerspective(img, M, (960, 720), dst=canvas, borderMode=cv2.BORDER_TRANSPARENT)
    front = board.detect(warped)
    assert front is not None and len(front.ids) == len(board.object_points) and not front.mirrored
    back = board.detect(np.ascontiguousarray(warped[:, ::-1]))  # the pattern seen through the paper
    assert back.mirrored and len(back.ids) == len(front.ids)
    # same physical corner ids; pixels are those of the flipped image
    order_f, order_b = np.argsort(front.ids), np.argsort(back.ids)
    expect = front.uv[order_f].copy()
    expect[:, 0] = 959 - expect[:, 0]
    assert np.abs(back.uv[order_b] - expect).max() < 0.5


def test_chessboard_numbered_from_either_end():
    # a chessboard has no marked origin: detectors number it from either end per view
    from vmocap_core.calibration import CheckerBoard

    board = CheckerBoard(7, 5, 0.08)
    rig = true_rig()
    views = synthetic_views(rig, board, 30, seed=4)
    rng = np.random.default_rng(5)
    flipped = 0
    for v in views:
        for f, det in v.views.items():
            if len(det.ids) < len(board.object_points):
                continue
            if rng.random() < 0.4:
                v.views[f] = Detection(board.flip_ids(det.ids), det.uv)
                flipped += 1
    assert flipped > 10
    res = calibrate_rig(views, board, intrinsics={c.name: c for c in rig})
    cmp = compare_extrinsics(res.rig, rig)
    assert cmp["max_position_err_m"] < 0.005 and cmp["max_rotation_err_deg"] < 0.2, cmp
    assert all(r.rms < 0.6 for r in res.cameras)


def test_scene_points_file(tmp_path):
    from vmocap_core.calibration.cli import load_scene
    from vmocap_core.errors import RigFileError

    f = tmp_path / "scene.yaml"
    f.write_text("points: [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\npixels:\n  c0: [[10, 20], null, [30, 40]]\n")
    sc = load_scene(str(f), ["c0", "c1"])
    assert sc.points.shape == (3, 3) and np.isnan(sc.uv["c0"][1]).all() and sc.uv["c0"][2].tolist() == [30, 40]
    with pytest.raises(RigFileError, match="cameras \\['c0'\\] are not calibrated here"):
        load_scene(str(f), ["c5"])
    f.write_text("points: [[0, 0, 0], [1, 0, 0]]\npixels:\n  c0: [[10, 20]]\n")
    with pytest.raises(RigFileError, match="pixels.c0.*1 entries for 2 points"):
        load_scene(str(f), ["c0"])


def test_scene_points_only(board):
    # no board at all (Pose2Sim's 'scene' method): every camera placed from known points
    rig = true_rig()
    views = [CameraViews(c.name, (W, H), frames_read=1) for c in rig]
    rng = np.random.default_rng(6)
    pts = rng.uniform([-0.8, -0.8, 0.0], [0.8, 0.8, 1.8], (10, 3))
    uv, _ = rig.project(pts)
    scene = SceneObservations(pts, {c.name: uv[i] + rng.normal(0, 0.3, uv[i].shape) for i, c in enumerate(rig)})
    res = calibrate_rig(views, board, intrinsics={c.name: c for c in rig}, scene=scene)
    for est, ref in zip(res.rig, rig):
        assert np.linalg.norm(est.center - ref.center) < 0.02
    assert res.frames == 0 and all(r.rms < 1.0 for r in res.cameras)
