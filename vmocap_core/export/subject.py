"""The subject of a recording, from whichever form the recording holds it in: its body
dimensions and its pelvis (root) pose per frame.

A `vmocap process` bag and a default `vmocap record` hold both directly: the dimensions on
/diagnostics ('vmocap: subject') and as the URDF on robot_description, the pelvis pose on
root_pose and /tf. A recorder given a topic list may hold only joint_states (the URDF's joints,
without the floating base) and keypoints. The keypoints are the skeleton's forward kinematics
at the joint states, and for a fixed pose that is linear in the body dimensions: so the
dimensions (least squares over a tracked run) and the pelvis pose (Kabsch per frame) are found
again from them, and the fit must reproduce the recorded keypoints or the export stops.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import BagError
from ..method.init import identify_dimensions
from ..method.skeleton import BodyDimensions, Skeleton
from ..outputs.tf import message_transforms, quaternion_to_matrix
from ..outputs.urdf import BASE_LINK, matrix_to_quaternion

# Keypoints are float64 forward kinematics: a fit further off than this means they are not the
# skeleton's at these joint states (another run's topics, a foreign URDF), not rounding.
FIT_TOLERANCE_M = 1e-5
SAMPLE_FRAMES = 60  # frames of a run the dimensions are fitted on (spread over it)
FIT_ROUNDS = 30  # Gauss-Newton steps when the pelvis pose is not recorded (converges in a few)

# The dimensions as a vector the keypoints are linear in: the waist height and the trunk above
# it in place of trunk and waist_ratio (their product is not linear).
_SCALARS = ("hip_width", "thigh", "shank", "waist", "upper_trunk", "shoulder_width", "shoulder_drop",
            "shoulder_forward", "upper_arm", "forearm", "hand")
_VECTORS = ("nose", "eye", "ear", "heel", "toe")
N_PARAMS = len(_SCALARS) + 3 * len(_VECTORS)
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])

Poses = tuple[np.ndarray, np.ndarray]  # pelvis translations (N, 3), quaternions (N, 4) x y z w


def dims_vector(d: BodyDimensions) -> np.ndarray:
    s = dict(d.to_dict(), waist=d.waist_ratio * d.trunk, upper_trunk=d.trunk * (1.0 - d.waist_ratio))
    return np.concatenate([np.array([s[k] for k in _SCALARS], float)] + [np.asarray(s[k], float) for k in _VECTORS])


def dims_of_vector(v: np.ndarray) -> BodyDimensions:
    n = len(_SCALARS)
    s = {k: float(x) for k, x in zip(_SCALARS, v[:n])}
    waist = s.pop("waist")
    trunk = waist + s.pop("upper_trunk")
    vec = {k: tuple(float(x) for x in v[n + 3 * i: n + 3 * i + 3]) for i, k in enumerate(_VECTORS)}
    return BodyDimensions(**s, trunk=trunk, waist_ratio=waist / trunk if trunk else 0.0, **vec)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ recorded forms
def dims_from_urdf(xml: str) -> BodyDimensions:
    """Inverse of `outputs.urdf.SubjectModel(dims).to_xml()`: the dimensions from the origins of
    its joints and keypoint frames. BagError when the URDF is not a vmocap subject's."""
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise BagError(f"robot_description is not XML: {exc}") from None
    o: dict[str, np.ndarray] = {}
    for j in root.iter("joint"):
        origin = j.find("origin")
        o[str(j.get("name"))] = np.fromstring(origin.get("xyz", "0 0 0") if origin is not None else "0 0 0", sep=" ")

    def at(name: str) -> np.ndarray:
        if name not in o or o[name].shape != (3,):
            raise BagError(f"robot_description is not a vmocap subject's URDF (no joint '{name}' with an origin)")
        return o[name]

    waist, upper = at("waist_rx")[2], at("neck_rx")[2]
    shoulder = at("left_shoulder_rx")
    kp = {k: tuple(float(x) for x in at(f"kp_{n}_joint")) for k, n in
          (("nose", "nose"), ("eye", "left_eye"), ("ear", "left_ear"), ("heel", "left_heel"), ("toe", "left_toe"))}
    return BodyDimensions(
        hip_width=2 * float(at("left_hip_rx")[1]), thigh=-float(at("left_knee")[2]), shank=-float(at("left_ankle_rx")[2]),
        trunk=float(waist + upper), waist_ratio=float(waist / (waist + upper)),
        shoulder_width=2 * float(shoulder[1]), shoulder_drop=float(upper - shoulder[2]), shoulder_forward=float(shoulder[0]),
        upper_arm=-float(at("left_elbow")[2]), forearm=-float(at("left_wrist_rx")[2]), hand=-float(at("kp_left_hand_joint")[2]),
        **kp)  # type: ignore[arg-type]


def tf_pelvis(msg: dict, world: str) -> tuple[int, np.ndarray, np.ndarray] | None:
    """(stamp, translation, quaternion) of the world -> pelvis transform in a TFMessage, if any."""
    tr = message_transforms(msg)
    for i, (parent, child) in enumerate(zip(tr.parents, tr.children)):
        if parent == world and child == BASE_LINK:
            s = msg["transforms"][i]["header"]["stamp"]
            return int(s["sec"]) * 1_000_000_000 + int(s["nanosec"]), tr.t[i].copy(), tr.q[i].copy()
    return None


# ------------------------------------------------------------------------------ the fit
class SubjectFit:
    """Forward kinematics of the keypoints as a linear map of the dimensions, at the joint
    configurations of some frames (root at the origin): keypoints (N, 25, 3) = A (N, 25, 3, P) @ v."""

    def __init__(self) -> None:
        self._unit = [Skeleton(dims_of_vector(e)) for e in np.eye(N_PARAMS)]

    def basis(self, configs: np.ndarray) -> np.ndarray:
        """A at configurations (N, nq) whose root is the origin."""
        return np.stack([np.stack([sk.keypoint_positions(q) for sk in self._unit], axis=-1) for q in configs])


def kabsch(B: np.ndarray, W: np.ndarray) -> Poses:
    """Per frame, the rigid motion (t, quaternion) that best takes points B (N, K, 3) onto W."""
    cb, cw = B.mean(axis=1), W.mean(axis=1)
    H = np.einsum("nki,nkj->nij", B - cb[:, None], W - cw[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("nji,nkj->nik", Vt, U)))  # det(V U^T): no reflection
    D = np.zeros((len(B), 3, 3))
    D[:, 0, 0], D[:, 1, 1], D[:, 2, 2] = 1.0, 1.0, d
    R = np.einsum("nji,njk,nlk->nil", Vt, D, U)  # V D U^T
    return cw - np.einsum("nij,nj->ni", R, cb), matrix_to_quaternion(R)


def _to_root(W: np.ndarray, poses: Poses) -> np.ndarray:
    t, q = poses
    return np.einsum("nji,nkj->nki", quaternion_to_matrix(q), W - t[:, None])  # R^T (W - t)


def _fit_dims_and_poses(A: np.ndarray, W: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dimensions v with per-frame poses (R, t) such that R (A v) + t = W: Gauss-Newton on v,
    a rotation increment and a translation per frame, the frames' 6x6 blocks eliminated from the
    normal equations (Schur complement, as in bundle adjustment). Alternating the two linear
    problems instead converges linearly (~150 rounds on a walk); this takes ~4 steps."""
    S, K = W.shape[:2]
    t, q = kabsch(A @ v, W)
    R = quaternion_to_matrix(q)
    for _ in range(FIT_ROUNDS):
        P = np.einsum("nij,nkj->nki", R, A @ v)  # (S, K, 3) turned, not yet moved
        r = (P + t[:, None] - W).reshape(S, 3 * K)
        Jv = np.einsum("nij,nkjp->nkip", R, A).reshape(S, 3 * K, N_PARAMS)
        blocks = np.zeros((S, K, 3, 6))
        blocks[..., 0, 1], blocks[..., 0, 2], blocks[..., 1, 2] = P[..., 2], -P[..., 1], P[..., 0]  # d(exp(w) P)/dw = -[P]x
        blocks[..., 1, 0], blocks[..., 2, 0], blocks[..., 2, 1] = -P[..., 2], P[..., 1], -P[..., 0]
        blocks[..., 3:] = np.eye(3)
        Jp = blocks.reshape(S, 3 * K, 6)
        Hpp_inv = np.linalg.inv(np.einsum("nki,nkj->nij", Jp, Jp))
        Hvp = np.einsum("nkp,nkj->npj", Jv, Jp)
        gp = np.einsum("nkj,nk->nj", Jp, r)
        HvpHi = np.einsum("npj,nji->npi", Hvp, Hpp_inv)
        reduced = np.einsum("nkp,nkq->pq", Jv, Jv) - np.einsum("npi,nqi->pq", HvpHi, Hvp)
        dv = np.linalg.lstsq(reduced, np.einsum("npi,ni->p", HvpHi, gp) - np.einsum("nkp,nk->p", Jv, r), rcond=None)[0]
        dp = -np.einsum("nij,nj->ni", Hpp_inv, gp + np.einsum("npj,p->nj", Hvp, dv))
        v = v + dv
        R = np.einsum("nij,njk->nik", Rotation.from_rotvec(dp[:, :3]).as_matrix(), R)
        t = t + dp[:, 3:]
        if max(np.abs(dv).max(), np.abs(dp).max()) < 1e-12:
            break
    return v


def fit_run(W: np.ndarray, configs: np.ndarray, dims: BodyDimensions | None, poses: Poses | None,
            fit: SubjectFit, sample: int = SAMPLE_FRAMES) -> tuple[BodyDimensions, Poses]:
    """The dimensions (unless given) and pelvis poses (unless given) of one tracked run: its
    keypoints W (N, 25, 3) and joint configurations (N, nq) with the root at the origin.
    BagError when they do not reproduce the keypoints within FIT_TOLERANCE_M."""
    if dims is None:
        pick = np.unique(np.linspace(0, len(W) - 1, min(sample, len(W))).round().astype(np.intp))
        A, Ws = fit.basis(configs[pick]), W[pick]
        flat = A.reshape(-1, N_PARAMS)
        if poses is not None:
            v = np.linalg.lstsq(flat, _to_root(Ws, (poses[0][pick], poses[1][pick])).reshape(-1), rcond=None)[0]
        else:
            v = _fit_dims_and_poses(A, Ws, dims_vector(identify_dimensions(Ws)))
        dims = dims_of_vector(v)
    sk = Skeleton(dims)
    B = np.stack([sk.keypoint_positions(q) for q in configs])
    if poses is None:
        poses = kabsch(B, W)
    err = np.linalg.norm(np.einsum("nij,nkj->nki", quaternion_to_matrix(poses[1]), B) + poses[0][:, None] - W, axis=2)
    if not err.max() <= FIT_TOLERANCE_M:
        raise BagError(f"the keypoints are not the skeleton's at the joint states ({err.max() * 1e3:.3f} mm off): "
                       "they do not belong to one run of the skeleton node")
    return dims, poses
