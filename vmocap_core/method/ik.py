"""Weighted inverse kinematics of the skeletal model (paper II-E, eq. 3-4).

    min_q  sum_k W_k || p_k(q) - m_k ||^2

solved by Levenberg-Marquardt steps dq = (J^T W J + lambda diag(J^T W J) + mu I)^-1 J^T W r on
the model's tangent space. The mu I term is a Tikhonov regularizer: a keypoint with weight 0
(not seen by two cameras) leaves its DOF at the warm-start value instead of making the normal
equations singular.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from . import _ik_kernels
from .skeleton import Skeleton

_NO_PRIOR = np.zeros(40)


@dataclass
class IkResult:
    q: np.ndarray  # (nq,) solution
    keypoints: np.ndarray  # (25, 3) forward kinematics of q
    cost: float  # weighted mean squared residual (m^2)
    iterations: int


def solve_ik(
    skeleton: Skeleton,
    q0: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    max_iterations: int = 10,
    tolerance: float = 1e-6,
    damping: float = 1e-3,
    regularization: float = 1e-6,
    line_search: bool = False,
    prior: np.ndarray | None = None,
    prior_weight: float = 0.0,
) -> IkResult:
    """Fit the skeleton to weighted 3D targets (25, 3) starting from q0.

    Targets with weight 0 or non-finite coordinates are ignored. `line_search` accepts a step
    only if it lowers the cost (and raises the damping otherwise): use it far from the solution,
    e.g. at initialization; warm-started tracking converges in a few plain steps.
    `prior` (a configuration, e.g. the pose predicted from the previous frames) adds
    prior_weight * ||q - prior||^2 to the cost (tangent-space distance; the weighted residual
    is in m^2 with weights normalized to sum 1): a motion prior that keeps per-frame marker
    noise out of the pose.
    """
    w = np.asarray(weights, dtype=np.float64).copy()
    x = np.asarray(targets, dtype=np.float64)
    finite = np.isfinite(x).all(axis=1)
    w[~finite | ~np.isfinite(w)] = 0.0
    w = np.clip(w, 0.0, None)
    x = np.where(finite[:, None], x, 0.0)  # type: ignore[index]  # numpy stub: all(axis=1) is an array
    wsum = w.sum()
    if wsum <= 0.0:
        p = skeleton.keypoint_positions(q0)
        return IkResult(q0.copy(), p, float("nan"), 0)
    w = w / wsum  # scale-free damping
    mu = float(prior_weight) if prior is not None and prior_weight > 0.0 else 0.0
    q = np.asarray(q0, dtype=np.float64).copy()
    lam = damping

    def objective(q_: np.ndarray, r_: np.ndarray) -> tuple[float, float, np.ndarray]:
        """(weighted mean squared residual, that + the prior term, tangent vector to the prior)."""
        data = float(w @ (r_ * r_).sum(axis=1))
        if not mu:
            return data, data, _NO_PRIOR
        d_ = pin.difference(skeleton.model, q_, prior)
        return data, data + mu * float(d_ @ d_), d_

    p, J = skeleton.keypoint_jacobians(q)
    r = x - p
    cost, total, d = objective(q, r)
    it = 0
    for it in range(1, max_iterations + 1):
        if _ik_kernels.AVAILABLE:
            dq = _ik_kernels.lm_step(J, r, w, lam, regularization, d, mu)
        else:
            Jf = J.reshape(-1, J.shape[2])  # (3K, nv)
            Jw = Jf * np.repeat(w, 3)[:, None]
            H = Jw.T @ Jf
            g = Jw.T @ r.reshape(-1) + mu * d
            dq = np.linalg.solve(H + lam * np.diag(np.diag(H)) + (regularization + mu) * np.eye(len(g)), g)
        q_new = skeleton.integrate(q, dq)
        last = it == max_iterations and not line_search
        # The last plain step needs positions only (a Jacobian there would go unused).
        p_new, J_new = (skeleton.keypoint_positions(q_new), J) if last else skeleton.keypoint_jacobians(q_new)
        r_new = x - p_new
        cost_new, total_new, d_new = objective(q_new, r_new)
        if line_search and total_new > total:
            lam *= 10.0
            if lam > 1e6:
                break
            continue
        if line_search:
            lam = max(lam / 3.0, 1e-9)
        converged = total - total_new < tolerance * max(total, 1e-12) or float(np.abs(dq).max()) < 1e-7
        q, p, J, r, cost, total, d = q_new, p_new, J_new, r_new, cost_new, total_new, d_new
        if converged:
            break
    return IkResult(q, p, cost, it)


_warm = False


def warm_up() -> None:
    """Compile (or load from numba's cache) the IK kernels now, with the argument types of
    real calls, instead of on the first tracked frame (a fresh compile takes seconds)."""
    global _warm
    if not _warm:
        sk = Skeleton()
        q = sk.neutral()
        p = sk.keypoint_positions(q)
        solve_ik(sk, q, p, np.ones(len(p)), max_iterations=2)
        _warm = True
