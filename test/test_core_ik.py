"""The skeletal model and the weighted IK."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from vmocap_core.keypoints import INDEX, KEYPOINTS
from vmocap_core.method.ik import solve_ik
from vmocap_core.method.skeleton import BONES, Skeleton


def random_pose(sk: Skeleton, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.6, 0.6, 40)
    a[:3] = [0.2, -0.1, 1.0]
    for name, lo, hi in (("left_elbow", -2.0, -0.2), ("right_elbow", -2.0, -0.2), ("left_knee", 0.2, 2.0), ("right_knee", 0.2, 2.0)):
        a[sk.joint_names.index(name)] = rng.uniform(lo, hi)
    return sk.from_angles(a)


def test_model_has_40_dof_and_all_keypoints():
    sk = Skeleton()
    assert sk.nv == 40 and len(sk.joint_names) == 40
    assert sk.keypoint_positions(sk.neutral()).shape == (len(KEYPOINTS), 3)
    for name in KEYPOINTS:
        assert sk.model.existFrame(name)


def test_jacobians_match_finite_differences():
    sk = Skeleton()
    q = random_pose(sk, 0)
    p, J = sk.keypoint_jacobians(q)
    eps = 1e-6
    for i in range(40):
        dv = np.zeros(40)
        dv[i] = eps
        num = (sk.keypoint_positions(pin.integrate(sk.model, q, dv)) - p) / eps
        assert np.abs(num - J[:, :, i]).max() < 1e-4


def test_ik_recovers_a_known_pose_from_clean_markers():
    sk = Skeleton()
    q_true = random_pose(sk, 1)
    target = sk.keypoint_positions(q_true)
    q0 = random_pose(sk, 2)
    q0[:3] = q_true[:3] + [0.05, -0.05, 0.03]
    res = solve_ik(sk, q0, target, np.ones(len(KEYPOINTS)), max_iterations=100, line_search=True)
    err = np.linalg.norm(res.keypoints - target, axis=1)
    assert err.max() < 1e-3


def test_zero_weights_and_nan_targets_keep_ik_well_posed():
    sk = Skeleton()
    q_true = random_pose(sk, 3)
    target = sk.keypoint_positions(q_true)
    w = np.ones(len(KEYPOINTS))
    lost = [INDEX[n] for n in ("left_wrist", "left_elbow", "left_hand", "nose", "left_eye", "right_eye", "left_ear", "right_ear")]
    w[lost] = 0.0
    target[INDEX["left_wrist"]] = np.nan
    res = solve_ik(sk, q_true, target, w, max_iterations=10)
    assert np.isfinite(res.q).all()
    # The unobserved arm stays where the warm start had it.
    assert np.linalg.norm(res.keypoints[INDEX["left_wrist"]] - sk.keypoint_positions(q_true)[INDEX["left_wrist"]]) < 1e-6
    empty = solve_ik(sk, q_true, target, np.zeros(len(KEYPOINTS)))
    assert np.allclose(empty.q, q_true)


def test_bone_lengths_are_constant_by_construction():
    sk = Skeleton()
    kp = np.array([sk.keypoint_positions(random_pose(sk, s)) for s in range(20)])
    for bone, (a, b) in BONES.items():
        d = np.linalg.norm(kp[:, INDEX[a]] - kp[:, INDEX[b]], axis=1)
        assert d.std() < 1e-12, bone


def test_hinge_past_its_extension_limit_is_mirrored_not_clamped():
    sk = Skeleton()
    q = sk.neutral()
    i = sk.joint_names.index("left_elbow")
    dv = np.zeros(40)
    dv[i] = 0.6  # hyperextension
    free = sk.keypoint_positions(pin.integrate(sk.model, q, dv))
    q2 = sk.integrate(q, dv)
    assert q2[sk._rev_q[0]] < 0  # now a flexion
    assert np.allclose(sk.keypoint_positions(q2), free, atol=1e-9)  # same keypoints


def test_angles_roundtrip():
    sk = Skeleton()
    q = random_pose(sk, 4)
    assert np.allclose(sk.keypoint_positions(sk.from_angles(sk.to_angles(q))), sk.keypoint_positions(q), atol=1e-12)


def test_compiled_kinematics_equal_pinocchio():
    """The compiled forward kinematics / Jacobians (_ik_kernels) against Pinocchio's placements
    and the numpy assembly, on random poses of a non-default subject."""
    from vmocap_core.method import _ik_kernels
    from vmocap_core.method.skeleton import BodyDimensions

    assert _ik_kernels.AVAILABLE, "numba is pinned in requirements.lock"
    sk = Skeleton(BodyDimensions(thigh=0.47, shoulder_forward=0.03, shoulder_drop=-0.02, waist_ratio=0.35))
    for seed in range(5):
        q = random_pose(sk, seed)
        assert np.abs(sk.keypoint_positions(q) - sk.keypoint_positions_pinocchio(q)).max() < 1e-12
        p, J = sk.keypoint_jacobians(q)
        p_ref, J_ref = sk.keypoint_jacobians_numpy(q)
        assert np.abs(p - p_ref).max() < 1e-12 and np.abs(J - J_ref).max() < 1e-12


def test_compiled_lm_step_equals_the_normal_equations():
    from vmocap_core.method import _ik_kernels

    rng = np.random.default_rng(0)
    J = rng.normal(size=(25, 3, 40))
    r = rng.normal(size=(25, 3))
    w = rng.uniform(0, 1, 25)
    w[:5] = 0.0
    Jf = J.reshape(75, 40)
    H = Jf.T @ (Jf * np.repeat(w, 3)[:, None])
    g = Jf.T @ (np.repeat(w, 3) * r.reshape(-1))
    for reg in (1e-5, 0.0):
        ref = np.linalg.solve(H + 1e-3 * np.diag(np.diag(H)) + reg * np.eye(40), g)
        assert np.allclose(_ik_kernels.lm_step(J, r, w, 1e-3, reg, np.zeros(40), 0.0), ref, rtol=1e-8, atol=1e-10)


def test_ik_prior_pulls_towards_the_prior_pose():
    """The motion prior: weight 0 is plain IK, a large weight keeps the prior pose, and in
    between the solution lies between the two (closer to the markers for a small weight)."""
    sk = Skeleton()
    q_prior = random_pose(sk, 4)
    q_true = random_pose(sk, 5)
    q_true[:3] = q_prior[:3] + [0.03, 0.0, -0.02]
    target = sk.keypoint_positions(q_true)
    w = np.ones(len(KEYPOINTS))
    def fit(mu: float):
        return solve_ik(sk, q_prior, target, w, max_iterations=30, line_search=True, prior=q_prior, prior_weight=mu)
    d_true = [np.linalg.norm(fit(mu).keypoints - target, axis=1).mean() for mu in (0.0, 1e-4, 1e-2, 1e3)]
    d_prior = [np.linalg.norm(pin.difference(sk.model, q_prior, fit(mu).q)) for mu in (0.0, 1e-4, 1e-2, 1e3)]
    assert d_true[0] < 1e-3 and d_prior[-1] < 1e-3
    assert d_true[0] < d_true[1] < d_true[2] < d_true[3]
    assert d_prior[0] > d_prior[1] > d_prior[2] > d_prior[3]
