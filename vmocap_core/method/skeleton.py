"""The 40-DOF human skeletal model (paper II-B) on Pinocchio.

Joint table (velocity-space DOF; the model's q uses unit quaternions for the 3-DOF joints):

| joint          | type        | DOF | parent  | placement in parent frame            |
|----------------|-------------|-----|---------|--------------------------------------|
| root           | free flyer  | 6   | world   | pelvis keypoint = origin             |
| waist          | spherical   | 3   | root    | (0, 0, waist_height)                 |
| neck           | spherical   | 3   | waist   | (0, 0, trunk - waist_height)         |
| left_shoulder  | spherical   | 3   | waist   | (fwd, +shoulder_width/2, neck - drop)|
| left_elbow     | revolute Y  | 1   | l_sh    | (0, 0, -upper_arm)                   |
| left_wrist     | spherical   | 3   | l_elbow | (0, 0, -forearm)                     |
| right_*        | (mirror)    | 7   |         |                                      |
| left_hip       | spherical   | 3   | root    | (0, +hip_width/2, 0)                 |
| left_knee      | revolute Y  | 1   | l_hip   | (0, 0, -thigh)                       |
| left_ankle     | spherical   | 3   | l_knee  | (0, 0, -shank)                       |
| right_*        | (mirror)    | 7   |         |                                      |
| total          |             | 40  |         |                                      |

Neutral pose (q = neutral): standing upright, Z up, facing +X, left is +Y, arms hanging.
Elbow flexion is a negative rotation about the upper arm's Y axis, knee flexion a positive one
about the thigh's Y axis (the 1-DOF joints carry anatomical limits). Keypoints are frames fixed
to the joints (keypoint table `KEYPOINT_PARENTS`); link lengths are parameters of the subject
(`BodyDimensions`), so every pose has the same bone lengths by construction.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import pinocchio as pin

from ..keypoints import KEYPOINTS
from . import _ik_kernels

JOINTS: tuple[str, ...] = (
    "root",
    "waist",
    "neck",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_hip",
    "right_knee",
    "right_ankle",
)
REVOLUTE = ("left_elbow", "right_elbow", "left_knee", "right_knee")
# Anatomical limits of the 1-DOF joints (radians).
LIMITS = {
    "left_elbow": (-2.7, 0.05),
    "right_elbow": (-2.7, 0.05),
    "left_knee": (-0.05, 2.7),
    "right_knee": (-0.05, 2.7),
}

# The joint each keypoint is fixed to.
KEYPOINT_PARENTS: dict[str, str] = {
    "pelvis": "root",
    "left_hip": "left_hip",
    "right_hip": "right_hip",
    "left_knee": "left_knee",
    "right_knee": "right_knee",
    "left_ankle": "left_ankle",
    "right_ankle": "right_ankle",
    "left_heel": "left_ankle",
    "right_heel": "right_ankle",
    "left_toe": "left_ankle",
    "right_toe": "right_ankle",
    "neck": "neck",
    "nose": "neck",
    "left_eye": "neck",
    "right_eye": "neck",
    "left_ear": "neck",
    "right_ear": "neck",
    "left_shoulder": "left_shoulder",
    "right_shoulder": "right_shoulder",
    "left_elbow": "left_elbow",
    "right_elbow": "right_elbow",
    "left_wrist": "left_wrist",
    "right_wrist": "right_wrist",
    "left_hand": "left_wrist",
    "right_hand": "right_wrist",
}


@dataclass
class BodyDimensions:
    """Link lengths of one subject (metres). Defaults: an adult of about 1.75 m."""

    hip_width: float = 0.17
    thigh: float = 0.42
    shank: float = 0.41
    trunk: float = 0.46  # pelvis to neck, upright
    waist_ratio: float = 0.5  # waist joint height as a fraction of the trunk
    shoulder_width: float = 0.36
    shoulder_drop: float = 0.05  # shoulders below the neck keypoint (negative: above)
    shoulder_forward: float = 0.0  # shoulders in front of the neck keypoint (negative: behind)
    upper_arm: float = 0.28
    forearm: float = 0.26
    hand: float = 0.08  # wrist to hand keypoint
    # Offsets of the face keypoints from the neck joint (x forward, z up), left side; the right
    # side mirrors y.
    nose: tuple[float, float, float] = (0.10, 0.0, 0.17)
    eye: tuple[float, float, float] = (0.08, 0.035, 0.20)
    ear: tuple[float, float, float] = (0.0, 0.075, 0.17)
    heel: tuple[float, float, float] = (-0.05, 0.0, -0.07)
    toe: tuple[float, float, float] = (0.17, 0.0, -0.07)

    def to_dict(self) -> dict[str, object]:
        return asdict(self)

    def bone_lengths(self) -> dict[str, float]:
        """The distances between joint keypoints the model holds constant."""
        return {
            "hip_width": self.hip_width,
            "thigh": self.thigh,
            "shank": self.shank,
            "upper_arm": self.upper_arm,
            "forearm": self.forearm,
            "shoulder_width": self.shoulder_width,
        }


# Rotation by pi about the local z axis (the long axis of upper arms and thighs).
_TWIST_PI = pin.Quaternion(0.0, 0.0, 0.0, 1.0)


def _quat_to_rotvec(quats: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) as x y z w -> rotation vectors (N, 3) with angle in [0, pi]."""
    q = quats * np.where(quats[:, 3:] < 0, -1.0, 1.0)  # w >= 0: the short way round
    v = q[:, :3]
    s = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(s, q[:, 3])
    scale = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)
    return v * scale[:, None]


def _mirror(v: tuple[float, float, float], side: str) -> np.ndarray:
    x, y, z = v
    return np.array([x, y if side == "left" else -y, z])


@dataclass
class Skeleton:
    """A Pinocchio model of the 40-DOF body with keypoint frames, for one subject."""

    dims: BodyDimensions = field(default_factory=BodyDimensions)

    def __post_init__(self) -> None:
        self.model = self._build()
        self.data = self.model.createData()
        self.nq, self.nv = self.model.nq, self.model.nv
        assert self.nv == 40, self.nv
        self.joint_ids = np.array([self.model.getJointId(n) for n in JOINTS])
        # Keypoint k hangs at offset[k] in the frame of joint parent[k].
        self._parent = np.array([self.model.getJointId(KEYPOINT_PARENTS[n]) for n in KEYPOINTS])
        self._offset = np.array([self._keypoint_offset(n) for n in KEYPOINTS])
        # support[k, j] is True when DOF j moves keypoint k (its joint or an ancestor).
        self._support = np.zeros((len(KEYPOINTS), self.nv), dtype=bool)
        for k, jid in enumerate(self._parent):
            for anc in self.model.supports[int(jid)]:
                if anc == 0:
                    continue
                jm = self.model.joints[anc]
                self._support[k, jm.idx_v : jm.idx_v + jm.nv] = True
        self._rev_q = np.array([self.model.joints[self.model.getJointId(n)].idx_q for n in REVOLUTE])
        self._rev_lo = np.array([LIMITS[n][0] for n in REVOLUTE])
        self._rev_hi = np.array([LIMITS[n][1] for n in REVOLUTE])
        # Extension side of each hinge (elbows extend towards +, knees towards -) and the
        # configuration index of the spherical joint above it.
        self._rev_ext_hi = np.array([abs(LIMITS[n][1]) < abs(LIMITS[n][0]) for n in REVOLUTE])
        self._rev_parent_q = np.array(
            [self.model.joints[self.model.parents[self.model.getJointId(n)]].idx_q for n in REVOLUTE]
        )
        self.joint_names = self._dof_names()
        # Index maps between q (quaternions) and the published 40 DOF (rotation vectors).
        quat_q, rotvec_v, hinge_v = [], [], []
        for jid in self.joint_ids:
            j = self.model.joints[int(jid)]
            if j.nq == 7:
                quat_q.append(np.arange(3, 7))
                rotvec_v.append(np.arange(3, 6))
            elif j.nq == 4:
                quat_q.append(np.arange(j.idx_q, j.idx_q + 4))
                rotvec_v.append(np.arange(j.idx_v, j.idx_v + 3))
            else:
                hinge_v.append(j.idx_v)
        self._quat_q = np.array(quat_q)
        self._rotvec_v = np.concatenate(rotvec_v)
        self._hinge_v = np.array(hinge_v)
        # The joint tree as plain arrays for the compiled forward kinematics (_ik_kernels).
        kinds = {"JointModelFreeFlyer": _ik_kernels.FREE, "JointModelSpherical": _ik_kernels.SPHERICAL,
                 "JointModelRY": _ik_kernels.REVOLUTE_Y}
        nj = self.model.njoints
        self._fk_tree = (
            np.array([kinds.get(self.model.joints[j].shortname(), -1) for j in range(nj)], dtype=np.int64),
            np.array(self.model.parents, dtype=np.int64),
            np.array([max(self.model.joints[j].idx_q, 0) for j in range(nj)], dtype=np.int64),
            np.array([self.model.jointPlacements[j].translation for j in range(nj)]),
            self._parent.astype(np.int64),
            np.ascontiguousarray(self._offset, dtype=np.float64),
        )

    # ---- model construction -------------------------------------------------------------
    def _build(self) -> pin.Model:
        d = self.dims
        m = pin.Model()
        m.name = "vmocap_human40"
        ids: dict[str, int] = {}

        def add(name: str, parent: str | None, joint: pin.JointModel, offset: np.ndarray) -> None:
            pid = 0 if parent is None else ids[parent]
            ids[name] = m.addJoint(pid, joint, pin.SE3(np.eye(3), np.asarray(offset, float)), name)
            # A nominal inertia keeps Pinocchio's algorithms well defined; IK does not use it.
            m.appendBodyToJoint(ids[name], pin.Inertia.FromSphere(1.0, 0.05), pin.SE3.Identity())

        add("root", None, pin.JointModelFreeFlyer(), np.zeros(3))
        wz = d.waist_ratio * d.trunk
        add("waist", "root", pin.JointModelSpherical(), [0, 0, wz])
        add("neck", "waist", pin.JointModelSpherical(), [0, 0, d.trunk - wz])
        for side, s in (("left", 1.0), ("right", -1.0)):
            add(f"{side}_shoulder", "waist", pin.JointModelSpherical(), [d.shoulder_forward, s * d.shoulder_width / 2, d.trunk - wz - d.shoulder_drop])
            add(f"{side}_elbow", f"{side}_shoulder", pin.JointModelRY(), [0, 0, -d.upper_arm])
            add(f"{side}_wrist", f"{side}_elbow", pin.JointModelSpherical(), [0, 0, -d.forearm])
        for side, s in (("left", 1.0), ("right", -1.0)):
            add(f"{side}_hip", "root", pin.JointModelSpherical(), [0, s * d.hip_width / 2, 0])
            add(f"{side}_knee", f"{side}_hip", pin.JointModelRY(), [0, 0, -d.thigh])
            add(f"{side}_ankle", f"{side}_knee", pin.JointModelSpherical(), [0, 0, -d.shank])
        for name in REVOLUTE:
            j = m.joints[ids[name]]
            m.lowerPositionLimit[j.idx_q] = LIMITS[name][0]
            m.upperPositionLimit[j.idx_q] = LIMITS[name][1]
        # Keypoints as operational frames, so Pinocchio tools (and users) see them.
        for name in KEYPOINTS:
            jid = ids[KEYPOINT_PARENTS[name]]
            m.addFrame(pin.Frame(name, jid, pin.SE3(np.eye(3), self._keypoint_offset(name)), pin.FrameType.OP_FRAME))
        return m

    def _keypoint_offset(self, name: str) -> np.ndarray:
        d = self.dims
        side = "left" if name.startswith("left_") else "right"
        base = name.split("_", 1)[-1]
        if base in ("eye", "ear", "heel", "toe"):
            return _mirror(getattr(d, base), side)
        if name == "nose":
            return np.array(d.nose, float)
        if base == "hand":
            return np.array([0.0, 0.0, -d.hand])
        return np.zeros(3)  # joint-centre keypoints

    def _dof_names(self) -> list[str]:
        names = [f"root_{a}" for a in ("x", "y", "z", "rx", "ry", "rz")]
        for n in JOINTS[1:]:
            names += [n] if n in REVOLUTE else [f"{n}_{a}" for a in ("rx", "ry", "rz")]
        return names

    # ---- configurations -----------------------------------------------------------------
    def neutral(self) -> np.ndarray:
        return pin.neutral(self.model)

    def integrate(self, q: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """q (+) dv, keeping the 1-DOF joints within their limits.

        A hinge pushed past its extension limit is mirrored instead of clamped: bending by -a
        with the parent segment twisted by pi about its long axis puts the distal keypoint where
        bending by +a would. Clamping would leave a straight limb with the wrong twist, a local
        minimum the IK cannot leave (the twist does not move a keypoint on the twist axis).
        """
        q = pin.integrate(self.model, q, dv)
        a = q[self._rev_q]
        over = np.where(self._rev_ext_hi, a > self._rev_hi, a < self._rev_lo)
        for i in np.flatnonzero(over):
            qi, pq = self._rev_q[i], self._rev_parent_q[i]
            q[qi] = -q[qi]
            quat = pin.Quaternion(q[pq + 3], q[pq], q[pq + 1], q[pq + 2]) * _TWIST_PI
            q[pq : pq + 4] = quat.coeffs()
        q[self._rev_q] = np.clip(q[self._rev_q], self._rev_lo, self._rev_hi)
        return q

    def to_angles(self, q: np.ndarray) -> np.ndarray:
        """q (nq) -> the 40 published DOF: root position, rotation vectors, hinge angles."""
        out = np.empty(40)
        out[:3] = q[:3]
        quats = q[self._quat_q]  # (11, 4) x y z w: the root and the spherical joints
        rotvec = _quat_to_rotvec(quats)
        out[self._rotvec_v] = rotvec.reshape(-1)
        out[self._hinge_v] = q[self._rev_q]
        return out

    def from_angles(self, angles: np.ndarray) -> np.ndarray:
        """Inverse of to_angles."""
        q = self.neutral()
        i = 0
        for jid in self.joint_ids:
            j = self.model.joints[int(jid)]
            if j.nq == 7:
                q[0:3] = angles[0:3]
                q[3:7] = pin.Quaternion(pin.exp3(angles[3:6])).coeffs()
                i = 6
            elif j.nq == 4:
                q[j.idx_q : j.idx_q + 4] = pin.Quaternion(pin.exp3(angles[i : i + 3])).coeffs()
                i += 3
            else:
                q[j.idx_q] = angles[i]
                i += 1
        return q

    # ---- kinematics ---------------------------------------------------------------------
    def _placements(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (nj, 3, 3) and translations (nj, 3) of the joints of self.data."""
        H = np.array([M.homogeneous for M in self.data.oMi])
        return H[:, :3, :3], H[:, :3, 3]

    def keypoint_positions(self, q: np.ndarray) -> np.ndarray:
        """Forward kinematics: (25, 3) keypoints in KEYPOINTS order."""
        if not _ik_kernels.AVAILABLE:
            return self.keypoint_positions_pinocchio(q)
        out = np.empty((len(KEYPOINTS), 3))
        _ik_kernels.keypoints_fk(np.asarray(q, dtype=np.float64), *self._fk_tree, out)
        return out

    def keypoint_positions_pinocchio(self, q: np.ndarray) -> np.ndarray:
        """keypoint_positions from Pinocchio's joint placements (the reference)."""
        pin.forwardKinematics(self.model, self.data, q)
        return self._keypoints_of_data()

    def _keypoints_of_data(self) -> np.ndarray:
        """Keypoints (25, 3) from the joint placements in self.data (after Pinocchio's FK)."""
        R, t = self._placements()
        return np.einsum("kij,kj->ki", R[self._parent], self._offset) + t[self._parent]

    def keypoint_jacobians(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints (25, 3) and their translational Jacobians (25, 3, 40) in the world frame."""
        if not _ik_kernels.AVAILABLE:
            return self.keypoint_jacobians_numpy(q)
        J6 = pin.computeJointJacobians(self.model, self.data, q)  # (6, 40), WORLD convention
        p = self.keypoint_positions(q)
        Jp = np.empty((p.shape[0], 3, self.nv))
        _ik_kernels.point_jacobians(J6, p, self._support, Jp)
        return p, Jp

    def keypoint_jacobians_numpy(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """keypoint_jacobians with Pinocchio's placements and numpy (the reference)."""
        J6 = pin.computeJointJacobians(self.model, self.data, q)  # also updates the placements
        p = self._keypoints_of_data()
        # WORLD spatial Jacobian: a point p moves with v + w x p (cross product written out).
        v, w = J6[:3], J6[3:]  # (3, 40)
        px, py, pz = p[:, 0, None], p[:, 1, None], p[:, 2, None]
        Jp = np.empty((p.shape[0], 3, self.nv))
        Jp[:, 0] = v[0] + w[1] * pz - w[2] * py
        Jp[:, 1] = v[1] + w[2] * px - w[0] * pz
        Jp[:, 2] = v[2] + w[0] * py - w[1] * px
        Jp *= self._support[:, None, :]
        return p, Jp


# Keypoint pairs whose distance the model keeps constant (used for the bone-length metric).
BONES: dict[str, tuple[str, str]] = {
    "left_upper_arm": ("left_shoulder", "left_elbow"),
    "right_upper_arm": ("right_shoulder", "right_elbow"),
    "left_forearm": ("left_elbow", "left_wrist"),
    "right_forearm": ("right_elbow", "right_wrist"),
    "left_thigh": ("left_hip", "left_knee"),
    "right_thigh": ("right_hip", "right_knee"),
    "left_shank": ("left_knee", "left_ankle"),
    "right_shank": ("right_knee", "right_ankle"),
    "hips": ("left_hip", "right_hip"),
    "shoulders": ("left_shoulder", "right_shoulder"),
    "neck_left_shoulder": ("neck", "left_shoulder"),
}
