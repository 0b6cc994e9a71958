"""Compiled per-iteration arithmetic of the IK (numba), with the numpy code as reference.

Pinocchio computes the world Jacobian of the joints in about a microsecond; what made an IK
iteration cost ~300 us was Python around it: reading 16 joint placements object by object
and some fifty small numpy operations. These kernels take plain arrays (q, the Jacobian)
and do the rest in one call each:

- `keypoints_fk`: forward kinematics of the keypoints from q for our fixed joint tree (joint
  placements are pure translations; spherical joints are unit quaternions x y z w, the
  revolute ones turn about their local Y axis), equal to Pinocchio's to round-off (tested);
- `point_jacobians`: the keypoints' translational Jacobians from Pinocchio's WORLD Jacobian;
- `lm_step`: one weighted Levenberg-Marquardt step (ik.py's equation).
"""

from __future__ import annotations

import numpy as np

try:
    from numba import njit

    AVAILABLE = True
except ImportError:  # numba is pinned; Skeleton falls back to Pinocchio + numpy without it
    AVAILABLE = False

    def njit(*args, **kwargs):  # type: ignore[no-redef]
        def wrap(f):
            return f

        return wrap

FREE, SPHERICAL, REVOLUTE_Y = 0, 1, 2


@njit(cache=True, inline="always")
def _quat_matrix(x: float, y: float, z: float, w: float, out: np.ndarray) -> None:
    out[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    out[0, 1] = 2.0 * (x * y - z * w)
    out[0, 2] = 2.0 * (x * z + y * w)
    out[1, 0] = 2.0 * (x * y + z * w)
    out[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    out[1, 2] = 2.0 * (y * z - x * w)
    out[2, 0] = 2.0 * (x * z - y * w)
    out[2, 1] = 2.0 * (y * z + x * w)
    out[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True, nogil=True)
def keypoints_fk(
    q: np.ndarray,  # (nq,)
    kind: np.ndarray,  # (nj,) FREE / SPHERICAL / REVOLUTE_Y; index 0 is the universe (unused)
    parent: np.ndarray,  # (nj,) parent joint id
    idx_q: np.ndarray,  # (nj,)
    placement: np.ndarray,  # (nj, 3) joint origin in the parent joint's frame
    kp_joint: np.ndarray,  # (K,) joint id of each keypoint
    kp_offset: np.ndarray,  # (K, 3) keypoint in its joint's frame
    out: np.ndarray,  # (K, 3) world keypoints
) -> None:
    nj = kind.shape[0]
    R = np.zeros((nj, 3, 3))
    o = np.zeros((nj, 3))
    R[0, 0, 0] = R[0, 1, 1] = R[0, 2, 2] = 1.0
    local = np.empty((3, 3))
    for j in range(1, nj):
        a = parent[j]
        i = idx_q[j]
        if kind[j] == FREE:
            o[j, 0], o[j, 1], o[j, 2] = q[i], q[i + 1], q[i + 2]
            _quat_matrix(q[i + 3], q[i + 4], q[i + 5], q[i + 6], local)
        else:
            for r in range(3):
                o[j, r] = o[a, r] + R[a, r, 0] * placement[j, 0] + R[a, r, 1] * placement[j, 1] + R[a, r, 2] * placement[j, 2]
            if kind[j] == SPHERICAL:
                _quat_matrix(q[i], q[i + 1], q[i + 2], q[i + 3], local)
            else:
                c, s = np.cos(q[i]), np.sin(q[i])
                local[:] = 0.0
                local[0, 0] = c
                local[0, 2] = s
                local[1, 1] = 1.0
                local[2, 0] = -s
                local[2, 2] = c
        if kind[j] == FREE:
            R[j] = local
        else:
            for r in range(3):
                for c2 in range(3):
                    R[j, r, c2] = R[a, r, 0] * local[0, c2] + R[a, r, 1] * local[1, c2] + R[a, r, 2] * local[2, c2]
    for k in range(kp_joint.shape[0]):
        j = kp_joint[k]
        for r in range(3):
            out[k, r] = o[j, r] + R[j, r, 0] * kp_offset[k, 0] + R[j, r, 1] * kp_offset[k, 1] + R[j, r, 2] * kp_offset[k, 2]


@njit(cache=True, nogil=True)
def point_jacobians(J6: np.ndarray, p: np.ndarray, support: np.ndarray, out: np.ndarray) -> None:
    """WORLD spatial Jacobian (6, nv) -> translational Jacobians (K, 3, nv) of the points p
    (K, 3): a point moves with v + w x p; DOF that do not move keypoint k (support) are 0."""
    K, nv = p.shape[0], J6.shape[1]
    for k in range(K):
        px, py, pz = p[k, 0], p[k, 1], p[k, 2]
        for i in range(nv):
            if support[k, i]:
                out[k, 0, i] = J6[0, i] + J6[4, i] * pz - J6[5, i] * py
                out[k, 1, i] = J6[1, i] + J6[5, i] * px - J6[3, i] * pz
                out[k, 2, i] = J6[2, i] + J6[3, i] * py - J6[4, i] * px
            else:
                out[k, 0, i] = out[k, 1, i] = out[k, 2, i] = 0.0


@njit(cache=True, nogil=True)
def lm_step(J: np.ndarray, r: np.ndarray, w: np.ndarray, lam: float, reg: float, prior: np.ndarray,
            prior_weight: float) -> np.ndarray:
    """dq = (J^T W J + lam diag(J^T W J) + (reg + mu) I)^-1 (J^T W r + mu d) for J (K, 3, nv),
    r (K, 3), w (K,), where d (nv,) is the tangent vector to a prior configuration and mu its
    weight (0: no prior).

    Plain loops instead of BLAS/LAPACK: as fast at this size (40 DOF), compiled in 2 s instead
    of 12 s, and a matrix that is not positive definite (reg = 0 with an unobserved DOF) gets
    more regularization instead of an exception."""
    K, nv = J.shape[0], J.shape[2]
    H = np.zeros((nv, nv))
    g = np.zeros(nv)
    for k in range(K):
        wk = w[k]
        if wk == 0.0:
            continue
        for c in range(3):
            rc = r[k, c]
            for a in range(nv):
                ja = J[k, c, a]
                if ja == 0.0:  # most DOF do not move a given keypoint
                    continue
                jw = ja * wk
                g[a] += jw * rc
                for b in range(nv):
                    H[a, b] += jw * J[k, c, b]
    if prior_weight > 0.0:
        for a in range(nv):
            g[a] += prior_weight * prior[a]
    # Cholesky factorization of H + lam diag(H) + reg I, then two triangular solves.
    L = np.zeros((nv, nv))
    extra = reg + prior_weight
    for _ in range(12):
        ok = True
        for i in range(nv):
            for j in range(i + 1):
                acc = H[i, j]
                if i == j:
                    acc += lam * H[i, i] + extra
                for m in range(j):
                    acc -= L[i, m] * L[j, m]
                if i == j:
                    if not (acc > 0.0):
                        ok = False
                        break
                    L[i, i] = np.sqrt(acc)
                else:
                    L[i, j] = acc / L[j, j]
            if not ok:
                break
        if ok:
            break
        extra = max(extra * 100.0, 1e-9)
    if not ok:  # non-finite input: no step
        return np.zeros(nv)
    y = np.empty(nv)
    for i in range(nv):
        acc = g[i]
        for m in range(i):
            acc -= L[i, m] * y[m]
        y[i] = acc / L[i, i]
    x = np.empty(nv)
    for i in range(nv - 1, -1, -1):
        acc = y[i]
        for m in range(i + 1, nv):
            acc -= L[m, i] * x[m]
        x[i] = acc / L[i, i]
    return x

