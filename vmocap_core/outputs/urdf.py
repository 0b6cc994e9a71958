"""The tracked subject as a URDF (ROS's robot description), built from its identified skeleton.

URDF has only 1-DOF joints, so each spherical joint of the 40-DOF model (skeleton.py) becomes
three revolute joints `NAME_rx`, `NAME_ry`, `NAME_rz` about the x, y, z axes of the joint frame,
in that order (R = Rx(rx) Ry(ry) Rz(rz), intrinsic XYZ Euler angles), with two massless links
between them. The hinges (elbows, knees) keep their names, axis (y) and limits. The free-flyer
root is not a joint: the base link `pelvis` hangs from `world` by a transform (TF), as ROS
tools expect of a floating base. So the URDF has the 34 DOF of `JOINT_NAMES`; a JointState with
these names (`joint_positions`) drives it, e.g. through robot_state_publisher.

Every keypoint is a fixed frame `kp_<keypoint>` on its segment, so TF (or any URDF forward
kinematics) gives the tracked keypoints. Segments are drawn as cylinders between their joints
(head: a sphere), with a nominal inertia of water-density solids for tools that need one.
"""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np

from ..calibration.geometry import rodrigues
from ..keypoints import KEYPOINTS
from ..method.skeleton import JOINTS, KEYPOINT_PARENTS, LIMITS, REVOLUTE, BodyDimensions, Skeleton

BASE_LINK = "pelvis"
# The body segment each joint of skeleton.JOINTS moves (the URDF link after the joint).
SEGMENT: dict[str, str] = {
    "root": BASE_LINK, "waist": "torso", "neck": "head",
    "left_shoulder": "left_upper_arm", "left_elbow": "left_forearm", "left_wrist": "left_hand",
    "right_shoulder": "right_upper_arm", "right_elbow": "right_forearm", "right_wrist": "right_hand",
    "left_hip": "left_thigh", "left_knee": "left_shank", "left_ankle": "left_foot",
    "right_hip": "right_thigh", "right_knee": "right_shank", "right_ankle": "right_foot",
}
SPHERICAL = tuple(j for j in JOINTS[1:] if j not in REVOLUTE)
AXES = ("x", "y", "z")


def _joint_table() -> tuple[list[str], np.ndarray, list[str], list[str]]:
    """URDF joint names, their axis index (0 x, 1 y, 2 z), parent and child links, in the
    order of the model's 40 DOF without the root."""
    names: list[str] = []
    axes: list[int] = []
    parents: list[str] = []
    children: list[str] = []
    parent_of = {j: _parent_joint(j) for j in JOINTS[1:]}
    for j in JOINTS[1:]:
        parent = SEGMENT[parent_of[j]]
        if j in REVOLUTE:
            names.append(j)
            axes.append(1)
            parents.append(parent)
            children.append(SEGMENT[j])
            continue
        links = [parent, f"{j}_rx_link", f"{j}_ry_link", SEGMENT[j]]
        for a in range(3):
            names.append(f"{j}_r{AXES[a]}")
            axes.append(a)
            parents.append(links[a])
            children.append(links[a + 1])
    return names, np.array(axes), parents, children


def _parent_joint(joint: str) -> str:
    if joint in ("waist", "left_hip", "right_hip"):
        return "root"
    if joint in ("neck", "left_shoulder", "right_shoulder"):
        return "waist"
    side, part = joint.split("_", 1)
    return f"{side}_" + {"elbow": "shoulder", "wrist": "elbow", "knee": "hip", "ankle": "knee"}[part]


JOINT_NAMES, JOINT_AXES, JOINT_PARENTS, JOINT_CHILDREN = _joint_table()
# Where each of the 34 URDF DOF sits in the model's published 40 (skeleton.Skeleton.to_angles).
_DOF40 = {name: 6 + i for i, name in enumerate(Skeleton().joint_names[6:])}
# First angle index (in the 40) of each spherical joint's rotation vector, and each hinge's.
_SPH_40 = np.array([_DOF40[f"{j}_rx"] for j in SPHERICAL])
_HINGES = [n for n in JOINT_NAMES if n in REVOLUTE]
_HINGE_40 = np.array([_DOF40[n] for n in _HINGES])
_SPH_OUT = np.array([JOINT_NAMES.index(f"{j}_rx") for j in SPHERICAL])
_HINGE_OUT = np.array([JOINT_NAMES.index(n) for n in _HINGES])


# ------------------------------------------------------------------------------ rotations
def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Matrices (N, 3, 3) -> unit quaternions (N, 4) as x y z w, w >= 0."""
    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    d01, s01 = R[:, 1, 0] - R[:, 0, 1], R[:, 1, 0] + R[:, 0, 1]
    d02, s02 = R[:, 0, 2] - R[:, 2, 0], R[:, 0, 2] + R[:, 2, 0]
    d12, s12 = R[:, 2, 1] - R[:, 1, 2], R[:, 2, 1] + R[:, 1, 2]
    # Shepperd's method: four candidates (x y z w, each scaled by 4 times one component),
    # take the one of the largest component for a stable division.
    cand = np.stack([
        np.stack([d12, d02, d01, 1 + tr], axis=1),
        np.stack([1 + 2 * R[:, 0, 0] - tr, s01, s02, d12], axis=1),
        np.stack([s01, 1 + 2 * R[:, 1, 1] - tr, s12, d02], axis=1),
        np.stack([s02, s12, 1 + 2 * R[:, 2, 2] - tr, d01], axis=1),
    ], axis=1)  # (N, 4 candidates, 4)
    diag = np.stack([1 + tr, 1 + 2 * R[:, 0, 0] - tr, 1 + 2 * R[:, 1, 1] - tr, 1 + 2 * R[:, 2, 2] - tr], axis=1)
    q = cand[np.arange(len(R)), np.argmax(diag, axis=1)]
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ------------------------------------------------------------------------------ joint states
def rotvec_to_quaternion(v: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) -> unit quaternions (N, 4) x y z w."""
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    theta = np.sqrt(np.einsum("ij,ij->i", v, v))
    # sin(theta/2)/theta, with its limit 1/2 at 0
    s = np.where(theta > 1e-12, np.sin(theta / 2) / np.where(theta > 1e-12, theta, 1.0), 0.5)
    return np.concatenate([v * s[:, None], np.cos(theta / 2)[:, None]], axis=1)


def joint_positions(angles: np.ndarray) -> np.ndarray:
    """The model's 40 published DOF (Skeleton.to_angles) -> the 34 URDF joint positions."""
    a = np.asarray(angles, dtype=np.float64).reshape(40)
    x, y, z, w = rotvec_to_quaternion(a[_SPH_40[:, None] + np.arange(3)]).T
    # the entries of R (from the quaternion) that R = Rx(a) Ry(b) Rz(c) is solved with
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    r10, r11 = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z)
    r12, r22 = 2 * (y * z - x * w), 1 - 2 * (x * x + y * y)
    cb = np.hypot(r12, r22)
    lock = cb < 1e-9  # gimbal lock (b = +-pi/2): only a +- c is defined; put it all into a
    euler = np.stack([np.where(lock, np.arctan2(np.sign(r02) * r10, r11), np.arctan2(-r12, r22)),
                      np.arctan2(r02, cb), np.where(lock, 0.0, np.arctan2(-r01, r00))], axis=1)
    out = np.empty(len(JOINT_NAMES))
    out[_SPH_OUT[:, None] + np.arange(3)] = euler
    out[_HINGE_OUT] = a[_HINGE_40]
    return out


def base_pose(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """world -> pelvis of the 40 DOF: translation (3,), quaternion (4,) x y z w, w >= 0."""
    a = np.asarray(angles, dtype=np.float64).reshape(40)
    q = rotvec_to_quaternion(a[3:6])[0]
    return a[:3].copy(), q if q[3] >= 0 else -q


def quaternion_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) x y z w -> rotation vectors (N, 3), angle in [0, pi]."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    q = q * np.where(q[:, 3:] < 0, -1.0, 1.0)
    s = np.linalg.norm(q[:, :3], axis=1)
    angle = 2.0 * np.arctan2(s, q[:, 3])
    return q[:, :3] * np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0)[:, None]


def model_angles(positions: np.ndarray, base: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Inverse of `joint_positions` + `base_pose`: the 34 URDF joint positions and the pelvis
    pose -> the model's 40 DOF (Skeleton.to_angles order; rotation vectors of angle <= pi)."""
    pos = np.asarray(positions, dtype=np.float64).reshape(len(JOINT_NAMES))
    a, b, c = pos[_SPH_OUT[:, None] + np.arange(3)].T
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    one, zero = np.ones_like(a), np.zeros_like(a)
    Rx = np.stack([one, zero, zero, zero, ca, -sa, zero, sa, ca], 1).reshape(-1, 3, 3)
    Ry = np.stack([cb, zero, sb, zero, one, zero, -sb, zero, cb], 1).reshape(-1, 3, 3)
    Rz = np.stack([cc, -sc, zero, sc, cc, zero, zero, zero, one], 1).reshape(-1, 3, 3)
    out = np.empty(40)
    out[_SPH_40[:, None] + np.arange(3)] = quaternion_to_rotvec(matrix_to_quaternion(Rx @ Ry @ Rz))
    out[_HINGE_40] = pos[_HINGE_OUT]
    t, q = base
    out[:3] = np.asarray(t, dtype=np.float64)
    out[3:6] = quaternion_to_rotvec(np.asarray(q, dtype=np.float64))[0]
    return out


# ------------------------------------------------------------------------------ the URDF
@dataclass
class SubjectModel:
    """The URDF of one identified subject: joint origins and keypoint frames from its skeleton."""

    dims: BodyDimensions

    def __post_init__(self) -> None:
        sk = Skeleton(self.dims)
        m = sk.model
        # Origin of each URDF joint in its parent link: the skeleton's joint placement for the
        # first axis of a joint, zero for the next two (they turn about the same point).
        place = {m.names[i]: np.array(m.jointPlacements[i].translation) for i in range(1, m.njoints)}
        self.origins = np.zeros((len(JOINT_NAMES), 3))
        for i, name in enumerate(JOINT_NAMES):
            base = name[:-3] if name.endswith(("_rx", "_ry", "_rz")) else name
            if name in REVOLUTE or name.endswith("_rx"):
                self.origins[i] = place[base]
        self.keypoint_links = [SEGMENT[KEYPOINT_PARENTS[k]] for k in KEYPOINTS]
        self.keypoint_offsets = np.array([sk._keypoint_offset(k) for k in KEYPOINTS])
        self._place = place

    # ---- geometry ---------------------------------------------------------------------
    def _segments(self) -> dict[str, list[tuple[np.ndarray, np.ndarray, float]]]:
        """Cylinders (from, to, radius) of each segment link, in the link's frame."""
        p = self._place
        kp = dict(zip(KEYPOINTS, self.keypoint_offsets))
        o = np.zeros(3)
        segs: dict[str, list] = {BASE_LINK: [(p["left_hip"], p["right_hip"], 0.06), (o, p["waist"], 0.06)],
                                 "torso": [(o, p["neck"], 0.07), (p["left_shoulder"], p["right_shoulder"], 0.05)]}
        for side in ("left", "right"):
            segs[f"{side}_upper_arm"] = [(o, p[f"{side}_elbow"], 0.04)]
            segs[f"{side}_forearm"] = [(o, p[f"{side}_wrist"], 0.033)]
            segs[f"{side}_hand"] = [(o, kp[f"{side}_hand"], 0.03)]
            segs[f"{side}_thigh"] = [(o, p[f"{side}_knee"], 0.06)]
            segs[f"{side}_shank"] = [(o, p[f"{side}_ankle"], 0.045)]
            segs[f"{side}_foot"] = [(kp[f"{side}_heel"], kp[f"{side}_toe"], 0.035), (o, kp[f"{side}_heel"], 0.035)]
        return segs

    def head_center(self) -> tuple[np.ndarray, float]:
        face = self.keypoint_offsets[[KEYPOINTS.index(k) for k in ("nose", "left_ear", "right_ear")]]
        c = face.mean(axis=0)
        return c, float(max(0.08, np.linalg.norm(face - c, axis=1).max()))

    def to_xml(self, name: str = "vmocap_subject") -> str:
        """The URDF document."""
        lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr(name)}>",
                 '  <material name="body"><color rgba="0.85 0.65 0.5 1"/></material>']
        segs = self._segments()
        for link in [BASE_LINK] + [SEGMENT[j] for j in JOINTS[1:]]:
            lines += [f'  <link name="{link}">']
            if link == "head":
                c, r = self.head_center()
                lines += _sphere(c, r)
                lines += _inertial(c, 1000.0 * 4.0 / 3.0 * np.pi * r**3, r, 2 * r)
            else:
                mass, com = 0.0, np.zeros(3)
                for a, b, r in segs[link]:
                    lines += _cylinder(a, b, r)
                    mm = 1000.0 * np.pi * r * r * max(float(np.linalg.norm(b - a)), 1e-3)
                    mass, com = mass + mm, com + mm * (a + b) / 2
                length = max(float(np.linalg.norm(b - a)) for a, b, _ in segs[link])
                lines += _inertial(com / mass, mass, max(r for *_, r in segs[link]), length)
            lines += ["  </link>"]
        for j in SPHERICAL:
            lines += [f'  <link name="{j}_rx_link"/>', f'  <link name="{j}_ry_link"/>']
        for i, name in enumerate(JOINT_NAMES):
            axis = np.eye(3)[JOINT_AXES[i]]
            lo, hi = LIMITS.get(name, (-np.pi / 2, np.pi / 2) if name.endswith("_ry") else (-np.pi, np.pi))
            lines += [f'  <joint name="{name}" type="revolute">',
                      f'    <parent link="{JOINT_PARENTS[i]}"/><child link="{JOINT_CHILDREN[i]}"/>',
                      f'    <origin xyz="{_v(self.origins[i])}" rpy="0 0 0"/><axis xyz="{_v(axis)}"/>',
                      f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="1000" velocity="20"/>',
                      "  </joint>"]
        for k, link, off in zip(KEYPOINTS, self.keypoint_links, self.keypoint_offsets):
            lines += [f'  <link name="kp_{k}"/>',
                      f'  <joint name="kp_{k}_joint" type="fixed"><parent link="{link}"/><child link="kp_{k}"/>'
                      f'<origin xyz="{_v(off)}" rpy="0 0 0"/></joint>']
        lines += ["</robot>", ""]
        return "\n".join(lines)


def _f(x: float) -> str:
    return repr(float(x))


def _v(x: np.ndarray) -> str:
    return " ".join(repr(float(c)) for c in x)


def _rpy_z_to(d: np.ndarray) -> np.ndarray:
    """URDF rpy (R = Rz(yaw) Ry(pitch) Rx(roll)) of a rotation taking +z onto direction d."""
    z = np.array([0.0, 0.0, 1.0])
    d = d / np.linalg.norm(d)
    axis = np.cross(z, d)
    s, c = np.linalg.norm(axis), float(d[2])
    v = axis / s * np.arctan2(s, c) if s > 1e-12 else (np.array([np.pi, 0, 0]) if c < 0 else np.zeros(3))
    R = rodrigues(v)[0]
    return np.array([np.arctan2(R[2, 1], R[2, 2]), np.arctan2(-R[2, 0], np.hypot(R[2, 1], R[2, 2])),
                     np.arctan2(R[1, 0], R[0, 0])])


def _cylinder(a: np.ndarray, b: np.ndarray, r: float) -> list[str]:
    length = float(np.linalg.norm(b - a))
    if length < 1e-6:
        return []
    return ["    <visual>", f'      <origin xyz="{_v((a + b) / 2)}" rpy="{_v(_rpy_z_to(b - a))}"/>',
            f'      <geometry><cylinder radius="{_f(r)}" length="{_f(length)}"/></geometry>',
            '      <material name="body"/>', "    </visual>"]


def _sphere(c: np.ndarray, r: float) -> list[str]:
    return ["    <visual>", f'      <origin xyz="{_v(c)}" rpy="0 0 0"/>',
            f'      <geometry><sphere radius="{_f(r)}"/></geometry>', '      <material name="body"/>', "    </visual>"]


def _inertial(com: np.ndarray, mass: float, r: float, length: float) -> list[str]:
    # Nominal: a solid cylinder's inertia about its centre, the same about every axis.
    i = mass * (3 * r * r + length * length) / 12.0
    return ["    <inertial>", f'      <origin xyz="{_v(com)}" rpy="0 0 0"/><mass value="{_f(mass)}"/>',
            f'      <inertia ixx="{_f(i)}" ixy="0" ixz="0" iyy="{_f(i)}" iyz="0" izz="{_f(i)}"/>', "    </inertial>"]
