"""Intrinsics (Zhang's method), pairwise rig initialization and the joint bundle adjustment.

Poses are (R, t) pairs mapping a source frame to a target frame: X_target = R @ X_source + t.
Camera extrinsics follow vmocap.camera: world -> camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from ..errors import CalibrationError
from .boards import Board, Detection

N_INTR = 9  # fx fy cx cy k1 k2 p1 p2 k3


# --------------------------------------------------------------------------- small maths


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) -> rotation matrices (N, 3, 3), vectorized."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(r, axis=1)
    small = th < 1e-12
    k = r / np.where(small, 1.0, th)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3) + s * Kx + (1.0 - c) * (Kx @ Kx)
    if small.any():  # first order near identity
        rs = r[small]
        Rs = np.tile(np.eye(3), (len(rs), 1, 1))
        Rs[:, 0, 1], Rs[:, 0, 2], Rs[:, 1, 2] = -rs[:, 2], rs[:, 1], -rs[:, 0]
        Rs[:, 1, 0], Rs[:, 2, 0], Rs[:, 2, 1] = rs[:, 2], -rs[:, 1], rs[:, 0]
        R[small] = Rs
    return R


def rotvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def compose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """a after b: X -> Ra (Rb X + tb) + ta."""
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def invert(a: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    return a[0].T, -a[0].T @ a[1]


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3): projection of their sum onto SO(3)."""
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def project(Xc: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Camera-frame points (M, 3) with per-point intrinsics (M, 9) -> pixels (M, 2) (OpenCV model)."""
    z = np.where(np.abs(Xc[:, 2]) > 1e-9, Xc[:, 2], 1e-9)
    x, y = Xc[:, 0] / z, Xc[:, 1] / z
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def intr_vector(K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    d = np.zeros(5)
    d[: min(5, len(dist))] = np.asarray(dist).ravel()[:5]
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *d])


def intr_matrices(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return K, np.asarray(v[4:9], dtype=np.float64).copy()


# --------------------------------------------------------------------------- intrinsics


@dataclass
class Intrinsics:
    K: np.ndarray
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    rms: float  # reprojection RMS (px) of the views kept
    views: int  # views used
    rejected: int = 0  # views dropped as outliers


def calibrate_intrinsics(name: str, views: dict[int, Detection], board: Board, size: tuple[int, int],
                         fix_k3: bool = True, max_views: int = 40) -> Intrinsics:
    """Zhang's method (cv2.calibrateCamera) on the board views of one camera, with one pass of
    per-view outlier rejection (views with an RMS above 3x the median and 1 px are dropped)."""
    keys = sorted(views)
    if len(keys) > max_views:  # evenly spread subset: the solver is cubic in the view count
        keys = [keys[i] for i in np.linspace(0, len(keys) - 1, max_views).round().astype(int)]
    if len(keys) < 3:
        raise CalibrationError(f"camera {name}: only {len(keys)} usable board views, Zhang's method needs at least 3")
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)

    def run(ks: list[int]):
        obj = [board.object_points[views[k].ids].astype(np.float32) for k in ks]
        img = [views[k].uv.astype(np.float32).reshape(-1, 1, 2) for k in ks]
        try:
            out = cv2.calibrateCameraExtended(obj, img, size, None, None, flags=flags, criteria=crit)
        except cv2.error as exc:
            raise CalibrationError(f"camera {name}: OpenCV calibration failed ({exc.err})") from None
        rms, K, dist, _r, _t, _si, _se, per_view = out
        return float(rms), K, dist.ravel(), per_view.ravel()

    rms, K, dist, per_view = run(keys)
    bad = per_view > max(3.0 * float(np.median(per_view)), 1.0)
    rejected = 0
    if bad.any() and (~bad).sum() >= 3:
        keys = [k for k, b in zip(keys, bad) if not b]
        rejected = int(bad.sum())
        rms, K, dist, per_view = run(keys)
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist[:5]
    return Intrinsics(K, d, rms, len(keys), rejected)


# --------------------------------------------------------------------------- extrinsics


@dataclass
class BoardPose:
    R: np.ndarray  # board -> camera
    t: np.ndarray
    rms: float
    n: int


def board_poses(views: dict[int, Detection], board: Board, K: np.ndarray, dist: np.ndarray,
                max_rms: float = 5.0) -> dict[int, BoardPose]:
    """Board -> camera pose of every view (planar PnP, IPPE, refined by Levenberg-Marquardt)."""
    out: dict[int, BoardPose] = {}
    for f, det in views.items():
        obj = board.object_points[det.ids]
        ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, det.uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok or len(rvecs) == 0:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj, det.uv, K, dist, rvecs[0].copy(), tvecs[0].copy())
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - det.uv) ** 2, axis=1))))
        if rms <= max_rms and tvec[2, 0] > 0:
            out[f] = BoardPose(cv2.Rodrigues(rvec)[0], tvec.ravel(), rms, len(det.ids))
    return out


def relative_pose(pa: dict[int, BoardPose], pb: dict[int, BoardPose],
                  flip: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Robust camera a -> camera b pose from the frames both saw the board in.

    With `flip` (a board numbered from either end), each frame offers two candidates; the
    rotation most frames agree with (within 5 degrees) picks one per frame."""
    shared = sorted(set(pa) & set(pb))
    if not shared:
        return None
    cands = []
    for f in shared:
        Ta = invert((pa[f].R, pa[f].t))
        opts = [compose((pb[f].R, pb[f].t), Ta)]
        if flip is not None:
            opts.append(compose(compose((pb[f].R, pb[f].t), flip), Ta))
        cands.append(opts)
    if flip is not None:
        allR = [o[0] for opts in cands for o in opts]
        support = [sum(min(rotation_angle_deg(R, o[0]) for o in opts) < 5.0 for opts in cands) for R in allR]
        best = allR[int(np.argmax(support))]
        chosen = [min(opts, key=lambda o: rotation_angle_deg(best, o[0])) for opts in cands]
    else:
        chosen = [opts[0] for opts in cands]
    Rs, ts = np.array([c[0] for c in chosen]), np.array([c[1] for c in chosen])
    R = mean_rotation(Rs)
    ang = np.array([rotation_angle_deg(R, r) for r in Rs])
    keep = ang <= max(3.0 * float(np.median(ang)), 2.0)  # single-view PnP flips are outliers
    R = mean_rotation(Rs[keep])
    return R, np.median(ts[keep], axis=0), int(keep.sum())


def initial_rig(poses: list[dict[int, BoardPose]], names: list[str], ref: int,
                flip: tuple[np.ndarray, np.ndarray] | None = None) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """World (= camera `ref`) -> camera poses along the spanning tree of most shared frames."""
    C = len(poses)
    rel: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]] = {}
    for a in range(C):
        for b in range(C):
            if a != b:
                r = relative_pose(poses[a], poses[b], flip)
                if r is not None:
                    rel[(a, b)] = r
    cams: list[tuple[np.ndarray, np.ndarray] | None] = [None] * C
    cams[ref] = (np.eye(3), np.zeros(3))
    while True:  # Prim's algorithm on the shared-frame counts
        best = None
        for (a, b), (_R, _t, n) in rel.items():
            if cams[a] is not None and cams[b] is None and (best is None or n > best[2]):
                best = (a, b, n)
        if best is None:
            break
        a, b, _ = best
        R, t, _n = rel[(a, b)]
        cams[b] = compose((R, t), cams[a])
    return cams


@dataclass
class SceneObservations:
    """Scene points with known world coordinates and their pixels in some cameras."""

    points: np.ndarray  # (P, 3) metres
    uv: dict[str, np.ndarray]  # camera -> (P, 2), NaN where not seen


@dataclass
class BundleResult:
    cameras: list[tuple[np.ndarray, np.ndarray]]  # world -> camera
    intr: np.ndarray  # (C, 9)
    rms: np.ndarray  # (C,) board + scene reprojection RMS per camera (px)
    n_obs: np.ndarray  # (C,) observations (points) per camera
    frames: int
    cost_before: float
    cost_after: float


@dataclass
class Problem:
    cam: np.ndarray  # (M,) camera index of each observation
    frame: np.ndarray  # (M,) frame slot, -1 for a scene point (fixed world coordinates)
    X: np.ndarray  # (M, 3) board coordinates (frame >= 0) or world coordinates
    uv: np.ndarray  # (M, 2)
    frame_keys: list[int] = field(default_factory=list)


def build_problem(views: list[dict[int, Detection]], board: Board, frame_keys: list[int],
                  scene: SceneObservations | None, names: list[str]) -> Problem:
    slot = {f: i for i, f in enumerate(frame_keys)}
    cam, frame, X, uv = [], [], [], []
    for c, v in enumerate(views):
        for f, det in v.items():
            if f in slot:
                n = len(det.ids)
                cam.append(np.full(n, c))
                frame.append(np.full(n, slot[f]))
                X.append(board.object_points[det.ids])
                uv.append(det.uv)
    if scene is not None:
        for c, name in enumerate(names):
            if name in scene.uv:
                seen = np.all(np.isfinite(scene.uv[name]), axis=1)
                cam.append(np.full(seen.sum(), c))
                frame.append(np.full(seen.sum(), -1))
                X.append(scene.points[seen])
                uv.append(scene.uv[name][seen])
    cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
    return Problem(cat(cam, (0,)).astype(int), cat(frame, (0,)).astype(int), cat(X, (0, 3)), cat(uv, (0, 2)), list(frame_keys))


def bundle_adjust(problem: Problem, cameras: list[tuple[np.ndarray, np.ndarray]],
                  frames: list[tuple[np.ndarray, np.ndarray]], intr: np.ndarray, fixed_cam: int | None,
                  refine_intrinsics: bool = False, fix_k3: bool = True, loss_scale: float = 2.0) -> BundleResult:
    """Joint least squares over camera poses, board poses (and optionally intrinsics) of the
    reprojection error of every board corner and scene point, with a sparse Jacobian."""
    C, F, M = len(cameras), len(frames), len(problem.cam)
    free_cams = [c for c in range(C) if c != fixed_cam]
    cam_col = {c: 6 * i for i, c in enumerate(free_cams)}
    f0 = 6 * len(free_cams)
    i0 = f0 + 6 * F
    intr_free = np.array([0, 1, 2, 3, 4, 5, 6, 7] + ([] if fix_k3 else [8])) if refine_intrinsics else np.zeros(0, int)
    n_if = len(intr_free)
    n = i0 + n_if * C

    x0 = np.zeros(n)
    for c in free_cams:
        x0[cam_col[c]: cam_col[c] + 3] = rotvec(cameras[c][0])
        x0[cam_col[c] + 3: cam_col[c] + 6] = cameras[c][1]
    for i, (R, t) in enumerate(frames):
        x0[f0 + 6 * i: f0 + 6 * i + 3] = rotvec(R)
        x0[f0 + 6 * i + 3: f0 + 6 * i + 6] = t
    if n_if:
        x0[i0:] = intr[:, intr_free].ravel()

    is_board = problem.frame >= 0
    fslot = np.where(is_board, problem.frame, 0)

    def unpack(x: np.ndarray):
        rc = np.zeros((C, 3))
        tc = np.zeros((C, 3))
        for c in range(C):
            if c in cam_col:
                rc[c], tc[c] = x[cam_col[c]: cam_col[c] + 3], x[cam_col[c] + 3: cam_col[c] + 6]
            else:
                rc[c], tc[c] = rotvec(cameras[c][0]), cameras[c][1]
        fp = x[f0:i0].reshape(F, 6)
        it = intr.copy()
        if n_if:
            it[:, intr_free] = x[i0:].reshape(C, n_if)
        return rodrigues(rc), tc, rodrigues(fp[:, :3]) if F else np.zeros((0, 3, 3)), fp[:, 3:], it

    def residuals(x: np.ndarray) -> np.ndarray:
        Rc, tc, Rf, tf, it = unpack(x)
        Xw = problem.X.copy()
        if F:
            Xb = np.einsum("mij,mj->mi", Rf[fslot], problem.X) + tf[fslot]
            Xw = np.where(is_board[:, None], Xb, problem.X)
        Xc = np.einsum("mij,mj->mi", Rc[problem.cam], Xw) + tc[problem.cam]
        return (project(Xc, it[problem.cam]) - problem.uv).ravel()

    sp = lil_matrix((2 * M, n), dtype=np.int8)
    rows = np.arange(M)
    for c in free_cams:
        r = rows[problem.cam == c]
        for k in range(6):
            sp[2 * r, cam_col[c] + k] = 1
            sp[2 * r + 1, cam_col[c] + k] = 1
    for k in range(6):
        r = rows[is_board]
        sp[2 * r, f0 + 6 * problem.frame[r] + k] = 1
        sp[2 * r + 1, f0 + 6 * problem.frame[r] + k] = 1
    for k in range(n_if):
        sp[2 * rows, i0 + n_if * problem.cam + k] = 1
        sp[2 * rows + 1, i0 + n_if * problem.cam + k] = 1

    r0 = residuals(x0)
    sol = least_squares(residuals, x0, jac_sparsity=sp.tocsr(), method="trf", loss="soft_l1",
                        f_scale=loss_scale, x_scale="jac", max_nfev=200)
    Rc, tc, _Rf, _tf, it = unpack(sol.x)
    res = sol.fun.reshape(M, 2)
    err2 = np.sum(res ** 2, axis=1)
    rms = np.array([np.sqrt(err2[problem.cam == c].mean()) if np.any(problem.cam == c) else np.nan for c in range(C)])
    n_obs = np.bincount(problem.cam, minlength=C)
    return BundleResult([(Rc[c], tc[c]) for c in range(C)], it, rms, n_obs, F,
                        float(np.sqrt(np.mean(r0 ** 2))) if M else 0.0,
                        float(np.sqrt(np.mean(sol.fun ** 2))) if M else 0.0)


def rigid_align(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation (no scale) with dst ~ R src + t (Kabsch)."""
    ms, md = src.mean(0), dst.mean(0)
    H = (src - ms).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, md - R @ ms
