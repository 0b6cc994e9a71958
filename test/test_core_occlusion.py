"""Several people: the keypoints one tracked body hides from a camera (method/occlusion.py)."""

from __future__ import annotations

import numpy as np

from vmocap_core.keypoints import INDEX
from vmocap_core.method.occlusion import GREY, hidden_keypoints, others_greyed, outside_images, without_hidden
from vmocap_core.method.skeleton import Skeleton
from vmocap_core.pcm.synthetic import benchmark_rig
from vmocap_core.pcm.views import PcmViews


def _standing(at: np.ndarray) -> np.ndarray:
    sk = Skeleton()
    q = sk.neutral()
    kp = sk.keypoint_positions(q)
    return kp - kp[INDEX["pelvis"]] + np.array([at[0], at[1], 1.0])


def test_a_body_between_a_camera_and_another_hides_it_from_that_camera_only():
    rig = benchmark_rig()
    cam0 = -rig[0].R.T @ rig[0].t  # camera 0's centre
    towards = np.array([cam0[0], cam0[1], 0.0]) / np.linalg.norm(cam0[:2])
    back, front = _standing(np.zeros(3)), _standing(1.2 * towards)  # front stands between cam0 and back
    hidden = hidden_keypoints(rig, np.stack([back, front]))
    assert hidden.shape == (2, len(rig), 25)
    # the back body's hips and knees are behind the other from cam0 (which looks down from 2.5 m:
    # its head and shoulders show above the other's)
    lower = [INDEX[n] for n in ("pelvis", "left_hip", "right_hip", "left_knee", "right_knee")]
    assert hidden[0, 0, lower].all()
    assert not hidden[1, 0].any()  # nothing covers the body in front
    opposite = int(np.argmax([np.linalg.norm((-c.R.T @ c.t)[:2] - cam0[:2]) for c in rig]))
    # from the opposite camera the roles turn
    assert not hidden[0, opposite].any() and hidden[1, opposite, lower].all()
    # side by side as cam0 sees them (1 m apart across its view): neither hides the other there
    side = np.array([-towards[1], towards[0], 0.0])
    assert not hidden_keypoints(rig, np.stack([back, _standing(1.0 * side)]))[:, 0].any()
    # unknown keypoints neither hide nor are hidden; one body hides nothing
    unknown = front.copy()
    unknown[:] = np.nan
    assert not hidden_keypoints(rig, np.stack([back, unknown])).any()
    assert not hidden_keypoints(rig, back[None]).any()


def test_hidden_keypoints_are_invalid_in_that_cameras_views_only():
    V, J = 3, 25
    pcm = PcmViews(np.zeros((V, J, 4, 4)), np.tile(np.eye(2, 3), (V, 1, 1)), np.array([0, 1, 1]), np.arange(J),
                   np.ones((V, J), bool), np.ones(V))
    hidden = np.zeros((4, 25), bool)
    hidden[1, [INDEX["pelvis"], INDEX["neck"]]] = True
    out = without_hidden(pcm, hidden)
    assert out.valid[0].all() and pcm.valid.all()
    assert not out.valid[1:, [INDEX["pelvis"], INDEX["neck"]]].any() and out.valid[1:].sum() == 2 * (J - 2)


def test_keypoints_outside_an_image_are_unseen_there():
    """A body in the middle of the room is inside every image; one walked out past a camera's
    side is outside that camera's image, or behind it."""
    rig = benchmark_rig()
    inside = _standing(np.zeros(3))
    assert not outside_images(rig, inside[None]).any()
    cam0 = -rig[0].R.T @ rig[0].t
    gone = _standing(1.3 * np.array([cam0[0], cam0[1], 0.0]))  # beyond cam0, behind it
    out = outside_images(rig, np.stack([inside, gone]))
    assert out.shape == (2, len(rig), 25) and out[1, 0].all() and not out[0].any()


def test_each_person_sees_the_others_greyed_outside_their_own_outline():
    """Two bodies, one partly behind the other as cam0 sees them: in each body's copy of cam0's
    image the other's keypoints clear of the body's own outline are grey and the body's own
    keypoints are not (its own outline is kept, where the other covers it too). The input
    images are left alone; a camera where the two do not overlap has no copy; a person without
    a skeleton (None) gets every body greyed; one body alone needs no copy."""
    rig = benchmark_rig()
    cam0 = -rig[0].R.T @ rig[0].t
    towards = np.array([cam0[0], cam0[1], 0.0]) / np.linalg.norm(cam0[:2])
    side = np.array([-towards[1], towards[0], 0.0])
    bodies = np.stack([_standing(np.zeros(3)), _standing(1.2 * towards + 0.1 * side)])  # 1 in front, a bit aside
    images = [np.full((c.height, c.width, 3), 255, np.uint8) for c in rig]
    out = others_greyed(rig, images, bodies, [0, 1, None])
    assert all((im == 255).all() for im in images)
    uv = np.round(rig.project(bodies)[0][0]).astype(int)  # (2, 25, 2) in cam0
    lo, hi = uv.min(axis=1), uv.max(axis=1)
    for me, other in ((0, 1), (1, 0)):
        mine = out[(me, 0)][uv[me, :, 1], uv[me, :, 0], 0]
        assert (mine == 255).all(), mine  # the body's own keypoints
        clear = ((uv[other] < lo[me] - 15) | (uv[other] > hi[me] + 15)).any(axis=1)  # off its own box
        assert clear.any()
        assert (out[(me, 0)][uv[other, clear, 1], uv[other, clear, 0], 0] == GREY).all()
        assert (out[(2, 0)][uv[other, :, 1], uv[other, :, 0], 0] == GREY).all()
    apart = others_greyed(rig, images, np.stack([_standing(-1.2 * side), _standing(1.2 * side)]), [0, 1])
    assert (0, 0) not in apart and (1, 0) not in apart
    assert others_greyed(rig, images, bodies[:1], [0]) == {}
