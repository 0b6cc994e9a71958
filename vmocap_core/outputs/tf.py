"""TF frames (tf2_msgs/TFMessage) of the subject and the cameras, without ROS.

- `/tf`: `world -> pelvis` (the floating base) and, like robot_state_publisher, one transform
  per moving URDF joint (parent link -> child link) at each tracked frame. Nothing while the
  subject is lost: a TF listener then fails with an extrapolation error instead of reading a
  stale pose as current.
- `/tf_static`: the URDF's fixed joints (the keypoint frames `kp_*`) and the cameras, each as
  `world -> CAM_link` (REP 103 body frame: x forward, y left, z up) and `CAM_link -> CAM` (REP
  103 optical frame: z forward, x right, y down), where CAM is the rig's camera name, the
  frame_id of its Image and CameraInfo messages.

`UrdfKinematics` is a small robot_state_publisher over our URDFs (revolute and fixed joints
with origin xyz/rpy and an axis); `TfTree` composes received transforms into world poses.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..bag import cdr
from ..bag.messages import WORLD_FRAME, header
from ..cameras.projection import Rig
from ..errors import VmocapError
from .urdf import BASE_LINK, matrix_to_quaternion

TF_TYPE = "tf2_msgs/msg/TFMessage"
# Body frame -> optical frame (REP 103): optical x = -body y, optical y = -body z, optical z = body x.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class TfError(VmocapError):
    """A URDF or a set of transforms that cannot be used."""


@dataclass
class Transforms:
    """N transforms parent -> child: translation (N, 3), rotation quaternion (N, 4) x y z w."""

    parents: list[str]
    children: list[str]
    t: np.ndarray
    q: np.ndarray

    def __len__(self) -> int:
        return len(self.children)

    @staticmethod
    def concat(parts: Sequence["Transforms"]) -> "Transforms":
        return Transforms(sum((p.parents for p in parts), []), sum((p.children for p in parts), []),
                          np.concatenate([p.t for p in parts]).reshape(-1, 3),
                          np.concatenate([p.q for p in parts]).reshape(-1, 4))


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) x y z w -> matrices (N, 3, 3)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a b of quaternions (N, 4) x y z w."""
    va, wa, vb, wb = a[:, :3], a[:, 3:], b[:, :3], b[:, 3:]
    return np.concatenate([wa * vb + wb * va + np.cross(va, vb), wa * wb - np.sum(va * vb, axis=1, keepdims=True)], axis=1)


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


class UrdfKinematics:
    """The joints of a URDF (revolute, continuous, prismatic, fixed) as arrays."""

    def __init__(self, xml: str) -> None:
        try:
            root = ET.fromstring(xml)
        except ET.ParseError as exc:
            raise TfError(f"robot_description is not XML: {exc}") from None
        self.name = root.get("name", "")
        movable, fixed = [], []
        for j in root.iter("joint"):
            kind = j.get("type")
            o = j.find("origin")
            xyz = np.fromstring(o.get("xyz", "0 0 0"), sep=" ") if o is not None else np.zeros(3)
            rpy = np.fromstring(o.get("rpy", "0 0 0"), sep=" ") if o is not None else np.zeros(3)
            ax = j.find("axis")
            axis = np.fromstring(ax.get("xyz", "1 0 0"), sep=" ") if ax is not None else np.array([1.0, 0, 0])
            parent, child = j.find("parent"), j.find("child")
            if parent is None or child is None or not j.get("name"):
                raise TfError(f"URDF joint {j.get('name')!r}: a joint needs a name, a parent and a child link")
            row = (str(j.get("name")), str(parent.get("link")), str(child.get("link")), xyz, _rpy_matrix(rpy),
                   axis / np.linalg.norm(axis), kind == "prismatic")
            if kind == "fixed":
                fixed.append(row)
            elif kind in ("revolute", "continuous", "prismatic"):
                movable.append(row)
            else:
                raise TfError(f"URDF joint {j.get('name')}: type {kind!r} is not supported")
        self.joint_names = [r[0] for r in movable]
        self._parents, self._children = [r[1] for r in movable], [r[2] for r in movable]
        self._index = {n: i for i, n in enumerate(self.joint_names)}
        self._mov = movable
        self._xyz = np.array([r[3] for r in movable]).reshape(-1, 3)
        self._rot = np.array([r[4] for r in movable]).reshape(-1, 3, 3)
        self._axis = np.array([r[5] for r in movable]).reshape(-1, 3)
        self._prismatic = np.array([r[6] for r in movable], dtype=bool)
        self._origin_q = matrix_to_quaternion(self._rot) if movable else np.zeros((0, 4))
        self._turned = ~np.all(np.abs(self._origin_q - [0, 0, 0, 1]) < 1e-15, axis=1)  # origin rpy != 0
        self._fixed = fixed
        self._all = np.arange(len(movable))

    def transforms(self, names: Sequence[str], positions: np.ndarray) -> Transforms:
        """The moving joints' transforms (parent -> child link) at a JointState."""
        try:
            idx = np.array([self._index[n] for n in names], dtype=np.intp)
        except KeyError as exc:
            raise TfError(f"joint state names a joint the URDF does not have: {exc}") from None
        if len(idx) != len(self.joint_names):
            missing = sorted(set(self.joint_names) - set(names))
            raise TfError(f"joint state lacks URDF joints {missing[:5]}")
        a = np.asarray(positions, dtype=np.float64).reshape(-1)
        if len(idx) == len(self._all) and np.array_equal(idx, self._all):
            idx = self._all  # a JointState in URDF order (ours): no reordering
            parents, children = self._parents, self._children
        else:
            parents, children = [self._mov[i][1] for i in idx], [self._mov[i][2] for i in idx]
        pri = self._prismatic[idx]
        half = np.where(pri, 0.0, a / 2)
        # origin rotation, then the rotation about the joint's axis
        q = np.concatenate([np.sin(half)[:, None] * self._axis[idx], np.cos(half)[:, None]], axis=1)
        if self._turned[idx].any():
            q = quaternion_multiply(self._origin_q[idx], q)
        t = self._xyz[idx]
        if pri.any():
            t = t + np.where(pri[:, None], np.einsum("nij,nj->ni", self._rot[idx], self._axis[idx] * a[:, None]), 0.0)
        return Transforms(parents, children, t, q)

    def static_transforms(self) -> Transforms:
        f = self._fixed
        return Transforms([r[1] for r in f], [r[2] for r in f], np.array([r[3] for r in f]).reshape(-1, 3),
                          matrix_to_quaternion(np.array([r[4] for r in f]).reshape(-1, 3, 3)))


def base_transform(translation: np.ndarray, quaternion: np.ndarray) -> Transforms:
    """world -> pelvis."""
    return Transforms([WORLD_FRAME], [BASE_LINK], np.asarray(translation, float).reshape(1, 3),
                      np.asarray(quaternion, float).reshape(1, 4))


def camera_transforms(rig: Rig) -> Transforms:
    """world -> CAM_link (REP 103 body) and CAM_link -> CAM (optical) for every camera."""
    R_wo = np.stack([c.R.T for c in rig])  # optical frame in world
    R_wb = R_wo @ R_BODY_OPTICAL.T
    n = len(rig)
    q_bo = matrix_to_quaternion(np.repeat(R_BODY_OPTICAL[None], n, axis=0))
    return Transforms([WORLD_FRAME] * n + [f"{c.name}_link" for c in rig],
                      [f"{c.name}_link" for c in rig] + [c.name for c in rig],
                      np.concatenate([np.stack([c.center for c in rig]), np.zeros((n, 3))]),
                      np.concatenate([matrix_to_quaternion(R_wb), q_bo]))


# In-process only (never encoded): (stamp, Transforms) a TFMessage dict was built from, for
# the fast encoder below (the generic one walks 35 nested structs per frame: ~7 ms).
TF_SOURCE = "_vmocap_tf"


class _TfTemplate:
    """CDR bytes of TFMessages with one list of frame names: everything but the stamps and
    the numbers is fixed, so a message is a copy of the template with two numpy scatters."""

    def __init__(self, parents: Sequence[str], children: Sequence[str]) -> None:
        body, stamps, numbers = bytearray(), [], []

        def align(n: int) -> None:
            body.extend(b"\x00" * ((-len(body)) % n))

        def string(s: str) -> None:
            align(4)
            b = s.encode() + b"\x00"
            body.extend(len(b).to_bytes(4, "little") + b)

        body.extend(len(children).to_bytes(4, "little"))
        for p, c in zip(parents, children):
            align(4)
            stamps.append(len(body))
            body.extend(bytes(8))
            string(p)
            string(c)
            align(8)
            numbers.append(len(body))
            body.extend(bytes(56))  # translation x y z, rotation x y z w (float64)
        align(8)
        self.body = np.frombuffer(bytes(body), dtype=np.uint8)
        self.sec = np.array(stamps) // 4
        self.num = (np.array(numbers)[:, None] // 8 + np.arange(7)).ravel()

    def encode(self, stamp_ns: int, tr: Transforms) -> bytes:
        # offsets count from the end of the 4-byte encapsulation header (CDR alignment origin)
        body = self.body.copy()
        u32 = body.view("<u4")
        u32[self.sec] = stamp_ns // 1_000_000_000
        u32[self.sec + 1] = stamp_ns % 1_000_000_000
        body.view("<f8")[self.num] = np.hstack([tr.t, tr.q]).ravel()
        return cdr.CDR_HEADER + body.tobytes()


_TEMPLATES: dict[tuple, _TfTemplate] = {}


def _encode_tf(msg: dict) -> bytes | None:
    src = msg.get(TF_SOURCE)
    if src is None or not len(src[1]):
        return None
    stamp_ns, tr = src
    key = (tuple(tr.parents), tuple(tr.children))
    tpl = _TEMPLATES.get(key)
    if tpl is None:
        if len(_TEMPLATES) > 64:  # frame sets change only with a new rig or URDF
            _TEMPLATES.clear()
        tpl = _TEMPLATES[key] = _TfTemplate(*key)
    return tpl.encode(int(stamp_ns), tr)


cdr.FAST_ENCODERS[TF_TYPE] = _encode_tf


class _TransformList(Sequence):
    """TransformStamped dicts made when read (the fast encoder reads the arrays instead)."""

    def __init__(self, stamp_ns: int, tr: Transforms) -> None:
        self.stamp_ns, self.tr = stamp_ns, tr

    def __len__(self) -> int:
        return len(self.tr)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        tr = self.tr
        return {"header": header(self.stamp_ns, tr.parents[i]), "child_frame_id": tr.children[i],
                "transform": {"translation": dict(zip("xyz", map(float, tr.t[i]))),
                              "rotation": dict(zip("xyzw", map(float, tr.q[i])))}}


def tf_message(stamp_ns: int, tr: Transforms) -> dict:
    """TFMessage dict (see bag.cdr) of the transforms, all with one stamp."""
    return {TF_SOURCE: (stamp_ns, tr), "transforms": _TransformList(stamp_ns, tr)}


def message_transforms(msg: dict) -> Transforms:
    """Inverse of `tf_message` (also for any TFMessage decoded by bag.cdr)."""
    if TF_SOURCE in msg:
        return msg[TF_SOURCE][1]
    ts = msg["transforms"]
    return Transforms([m["header"]["frame_id"] for m in ts], [m["child_frame_id"] for m in ts],
                      np.array([[m["transform"]["translation"][k] for k in "xyz"] for m in ts]).reshape(-1, 3),
                      np.array([[m["transform"]["rotation"][k] for k in "xyzw"] for m in ts]).reshape(-1, 4))


class TfTree:
    """The latest transform of each child frame; poses of frames in the world frame."""

    def __init__(self) -> None:
        self._parent: dict[str, str] = {}
        self._R: dict[str, np.ndarray] = {}
        self._t: dict[str, np.ndarray] = {}

    def add(self, tr: Transforms) -> None:
        R = quaternion_to_matrix(tr.q) if len(tr) else np.zeros((0, 3, 3))
        for p, c, Ri, ti in zip(tr.parents, tr.children, R, tr.t):
            self._parent[c], self._R[c], self._t[c] = p, Ri, np.asarray(ti, float)

    def world_pose(self, frame: str, root: str = WORLD_FRAME) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of `frame` in `root` (TfError when the chain is broken)."""
        R, t = np.eye(3), np.zeros(3)
        f, seen = frame, 0
        while f != root:
            if f not in self._parent or seen > 256:
                raise TfError(f"no TF chain from {root} to {frame} (stops at {f})")
            R, t = self._R[f] @ R, self._R[f] @ t + self._t[f]
            f, seen = self._parent[f], seen + 1
        return R, t

    def positions(self, frames: Iterable[str], root: str = WORLD_FRAME) -> np.ndarray:
        """Origins (N, 3) of frames in `root`."""
        return np.array([self.world_pose(f, root)[1] for f in frames]).reshape(-1, 3)
