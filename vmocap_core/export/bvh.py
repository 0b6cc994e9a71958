"""BVH export: the subject's skeleton as the hierarchy, the joint states as rotations.

Hierarchy: the 15 joints of skeleton.py (root = pelvis) with offsets from the identified body
dimensions; every keypoint that is not a joint centre (face, hands, heels, toes) is a child
joint with a fixed offset and zero rotations, so the file's forward kinematics gives all 25
keypoints. Units metres, Y up (Blender's importer default: up Y, forward -Z): vmocap's Z-up
world is rotated by -90 deg about X ((x, y, z) -> (x, z, -y)), offsets and rotations alike,
so the rest pose stands upright. Rotation channels Zrotation Xrotation Yrotation (R = Rz Rx Ry,
degrees, relative to the parent).

BVH has no way to mark a missing frame: each tracked segment goes to its own file (split;
nothing is held or interpolated across a gap).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import VmocapError
from ..keypoints import KEYPOINTS
from ..method.skeleton import JOINTS, REVOLUTE, Skeleton
from .markers import Z_TO_Y_UP
from .session import Session

ROT_CHANNELS = "Zrotation Xrotation Yrotation"


def _hierarchy(sk: Skeleton) -> tuple[list[tuple[str, str | None, np.ndarray]], list[str]]:
    """(name, parent, offset in the parent's frame, Z up) of every BVH joint, parents first;
    and the BVH joint that each keypoint is (KEYPOINTS order)."""
    model = sk.model
    nodes: list[tuple[str, str | None, np.ndarray]] = []
    for name in JOINTS:
        jid = model.getJointId(name)
        parent = model.names[model.parents[jid]] if name != "root" else None
        nodes.append((name, parent, np.array(model.jointPlacements[jid].translation)))
    of_keypoint = []
    for k, kp in enumerate(KEYPOINTS):
        joint = model.names[int(sk._parent[k])]
        off = np.asarray(sk._offset[k], dtype=np.float64)
        if np.abs(off).max() < 1e-12:
            of_keypoint.append(joint)
        else:
            nodes.append((kp, joint, off))
            of_keypoint.append(kp)
    return nodes, of_keypoint


def _local_rotations(session: Session, frames: slice) -> dict[str, np.ndarray]:
    """Per skeleton joint, its rotation relative to the parent (T, 3, 3), Z up."""
    col = {n: i for i, n in enumerate(session.joint_names)}
    A = session.angles[frames]
    out: dict[str, np.ndarray] = {}
    try:
        for name in JOINTS:
            if name in REVOLUTE:
                out[name] = Rotation.from_rotvec(A[:, [col[name]]] * np.array([[0.0, 1.0, 0.0]])).as_matrix()
            else:
                axes = [col[f"{name}_{a}"] for a in ("rx", "ry", "rz")]
                out[name] = Rotation.from_rotvec(A[:, axes]).as_matrix()
    except KeyError as exc:
        raise VmocapError(f"joint_states lack the joint {exc} of the vmocap skeleton") from None
    return out


def bvh_text(session: Session, frames: slice) -> str:
    """One tracked segment as a BVH file."""
    sk = Skeleton(session.dims_at(frames.start))
    nodes, _ = _hierarchy(sk)
    children: dict[str | None, list[int]] = {}
    for i, (_, parent, _) in enumerate(nodes):
        children.setdefault(parent, []).append(i)
    lines = ["HIERARCHY"]
    order: list[int] = []  # depth-first: the order of the channels in each MOTION line

    def emit(i: int, depth: int) -> None:
        order.append(i)
        name, parent, off = nodes[i]
        ind = "\t" * depth
        o = Z_TO_Y_UP @ off
        lines.append(f"{ind}{'ROOT' if parent is None else 'JOINT'} {name}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}\tOFFSET {o[0]:.9f} {o[1]:.9f} {o[2]:.9f}")
        pos = "Xposition Yposition Zposition " if parent is None else ""
        lines.append(f"{ind}\tCHANNELS {6 if parent is None else 3} {pos}{ROT_CHANNELS}")
        kids = children.get(name, [])
        for c in kids:
            emit(c, depth + 1)
        if not kids:
            lines.extend([f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET 0.0 0.0 0.0", f"{ind}\t}}"])
        lines.append(f"{ind}}}")

    emit(children[None][0], 0)
    T = frames.stop - frames.start
    rot = _local_rotations(session, frames)
    cols = []
    root_pos = session.angles[frames][:, [session.joint_names.index(f"root_{a}") for a in "xyz"]]
    cols.append(root_pos @ Z_TO_Y_UP.T)
    for name, _, _ in (nodes[i] for i in order):
        # R' = A R A^T: the same rotation seen in the Y-up frame; fixed keypoint joints: none.
        R = np.einsum("ij,tjk,lk->til", Z_TO_Y_UP, rot[name], Z_TO_Y_UP) if name in rot else np.tile(np.eye(3), (T, 1, 1))
        cols.append(Rotation.from_matrix(R).as_euler("ZXY", degrees=True))
    motion = np.concatenate(cols, axis=1)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / session.rate_hz:.9f}"]
    lines += [" ".join(f"{v:.9g}" for v in row) for row in motion]
    return "\n".join(lines) + "\n"


def write_bvh(session: Session, path: str | Path) -> list[Path]:
    """Write each tracked segment (split at gaps): `path` for the first, `STEM_partK.bvh`
    for the K-th (K >= 2). Returns the files written."""
    path = Path(path)
    segs = session.segments()
    if not segs:
        raise VmocapError("the session has no tracked frame: nothing to export")
    out = []
    for k, seg in enumerate(segs, start=1):
        p = path if k == 1 else path.with_name(f"{path.stem}_part{k}{path.suffix}")
        p.write_text(bvh_text(session, seg))
        out.append(p)
    return out
