"""Where the CNN's keypoints sit on the body: landmark offsets from the joint centres.

The skeletal model's keypoints are joint centres (skeleton.py). A CNN's landmarks are not:
BlazePose puts its hips in front of the hip joints and its shoulders on the body's surface
above the shoulder joints. A `LandmarkModel` holds, for each such keypoint, the landmark's
offset from the joint centre in the frame of one body segment (pelvis, thorax, upper arm,
forearm, thigh, shank), as markers in optical motion capture are placed on segments. The
skeleton stage subtracts the offset, turned by the segment's current orientation, from the
virtual markers before the IK (so identification, IK, filter and output all work on joint
centres), and adds it to the skeleton it feeds back, so the lattice search looks for the
landmark where the CNN puts it.

Offsets are learnt (`learn_offsets`) from recordings with exact joint centres, i.e. the image
benchmark's renders; `scripts/learn_landmarks.py` writes them to
`vmocap_core/data/landmarks/<name>.yaml`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml

from ..errors import VmocapError
from ..keypoints import INDEX, KEYPOINTS
from .skeleton import Skeleton

DATA = Path(__file__).resolve().parent.parent / "data" / "landmarks"
CNN_LANDMARKS = "blazepose"  # the shipped model of the CNN's keypoints (pcm/blazepose.py, both variants)

# The frame that carries each keypoint's landmark offset (left side; right mirrors): the
# segment the landmark lies on. Limb landmarks ride on their joint's frame: elbows on the upper
# arm, wrists on the forearm, knees on the thigh, ankles on the shank. Hips and shoulders ride on
# TRUNK frames built from keypoints (the pelvis-to-neck line with the hip or shoulder line): the
# root's and the waist's own orientations are not seen by any keypoint, since a trunk shorter
# than its identified length is fitted by bending the waist forwards or backwards alike, and the
# two bends turn those frames apart. Face, hand and foot keypoints are offsets of their own
# already (skeleton.py).
TRUNK = {"left_hip": ("left_hip", "right_hip"), "left_shoulder": ("left_shoulder", "right_shoulder")}
TRUNK |= {k.replace("left_", "right_"): v for k, v in TRUNK.items()}
SEGMENT: dict[str, str] = {
    "left_hip": "trunk",
    "left_shoulder": "trunk",
    "left_elbow": "left_shoulder",
    "left_wrist": "left_elbow",
    "left_knee": "left_hip",
    "left_ankle": "left_knee",
}
SEGMENT |= {k.replace("left_", "right_"): v.replace("left_", "right_") for k, v in SEGMENT.items()}
_MIRROR = np.array([1.0, -1.0, 1.0])


class LandmarkError(VmocapError, ValueError):
    """A landmark model that cannot be loaded."""


@dataclass(frozen=True)
class LandmarkModel:
    """Landmark offsets (25, 3) in metres, each in the frame of its keypoint's SEGMENT joint
    (zero for the keypoints not in SEGMENT)."""

    name: str
    offsets: np.ndarray
    note: str = ""  # where the offsets come from
    learnt_on: tuple[str, ...] = ()  # the clips (recordings) they were learnt on

    def correction(self, skeleton: Skeleton, q: np.ndarray) -> np.ndarray:
        """(25, 3) world vectors from each joint centre to its landmark, in pose q."""
        return np.einsum("kij,kj->ki", segment_rotations(skeleton, q), self.offsets)

    def neck_dimensions(self) -> dict[str, float]:
        """The shoulders' place relative to the neck keypoint (BodyDimensions fields) that keeps
        the neck where a CNN without a neck landmark puts it, at its shoulder landmarks'
        midpoint: the shoulder joint centres lie the shoulder offset's x and z away from it."""
        x, _, z = self.offsets[INDEX["left_shoulder"]]
        return {"shoulder_forward": float(-x), "shoulder_drop": float(z)}


@cache
def _segment_ids() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each keypoint's SEGMENT joint id (every Skeleton builds the same joint tree; 0, the
    universe, for the unlisted and the TRUNK ones), and the TRUNK keypoints with their
    (left, right) keypoint pairs."""
    model = Skeleton().model
    ids = np.zeros(len(KEYPOINTS), dtype=np.intp)
    for k, joint in SEGMENT.items():
        if k not in TRUNK:
            ids[INDEX[k]] = model.getJointId(joint)
    rows = np.array([INDEX[k] for k in TRUNK])
    pairs = np.array([[INDEX[a], INDEX[b]] for a, b in TRUNK.values()])
    return ids, rows, pairs


def trunk_axes(left: np.ndarray, right: np.ndarray, pelvis: np.ndarray, top: np.ndarray) -> tuple[np.ndarray, ...]:
    """Axes x, y, z (..., 3) of trunk frames: y from `right` to `left` (a hip or shoulder
    pair), z from `pelvis` towards `top` orthogonal to y, x = y x z (forward); broadcasting."""
    y = left - right
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    z = top - pelvis
    z = z - y * np.sum(z * y, axis=-1, keepdims=True)
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    return np.cross(y, z), y, z


def segment_rotations(skeleton: Skeleton, q: np.ndarray) -> np.ndarray:
    """(25, 3, 3) world rotations of each keypoint's SEGMENT frame in pose q."""
    ids, rows, pairs = _segment_ids()
    pin.forwardKinematics(skeleton.model, skeleton.data, q)
    R, _ = skeleton._placements()
    out = R[ids]
    kp = skeleton._keypoints_of_data()
    out[rows] = np.stack(trunk_axes(kp[pairs[:, 0]], kp[pairs[:, 1]], kp[INDEX["pelvis"]], kp[INDEX["neck"]]), axis=2)
    return out


def from_left(name: str, left_mm: dict[str, list[float]], note: str = "", learnt_on: tuple[str, ...] = ()) -> LandmarkModel:
    """A model from the left side's offsets in mm (the right side mirrors y)."""
    offsets = np.zeros((len(KEYPOINTS), 3))
    for k, v in left_mm.items():
        if k not in SEGMENT or not k.startswith("left_"):
            raise LandmarkError(f"landmark offsets are given for left_* keypoints of {sorted(SEGMENT)}, not {k!r}")
        offsets[INDEX[k]] = np.asarray(v, dtype=np.float64) * 1e-3
        offsets[INDEX[k.replace("left_", "right_")]] = offsets[INDEX[k]] * _MIRROR
    return LandmarkModel(name, offsets, note, learnt_on)


def resolve(spec: str, pcm_landmarks: str) -> str:
    """A config's `landmarks` with "auto" replaced by the PCM source's own (`pcm_landmarks`)."""
    return pcm_landmarks if spec == "auto" else spec


def load_landmarks(spec: str) -> LandmarkModel | None:
    """'none' (joint centres: a PCM model whose keypoints are joint centres, e.g. the
    synthetic one), a shipped model's name ('blazepose') or a YAML file's path. 'auto' that
    nothing resolved (no PCM source known, e.g. markers from elsewhere) is 'none'."""
    if spec in ("", "none", "auto"):
        return None
    path = DATA / f"{spec}.yaml" if "/" not in spec and not spec.endswith(".yaml") else Path(spec)
    if not path.exists():
        shipped = sorted(p.stem for p in DATA.glob("*.yaml"))
        raise LandmarkError(f"landmarks {spec!r}: no such file {path} (shipped: none, {', '.join(shipped)})")
    d = yaml.safe_load(path.read_text())
    if not isinstance(d, dict) or not isinstance(d.get("offsets_mm"), dict):
        raise LandmarkError(f"{path}: expected a mapping with 'offsets_mm' (left keypoint -> [x, y, z] mm)")
    return from_left(str(d.get("name", path.stem)), d["offsets_mm"], str(d.get("note", "")),
                     tuple(str(c) for c in d.get("learnt_on", ())))


def learn_offsets(skeleton: Skeleton, poses: np.ndarray, markers: np.ndarray, truth: np.ndarray) -> dict[str, np.ndarray]:
    """Landmark samples in the segment frames: for frames with poses q (N, nq) of the skeleton
    fitted to the true joint centres truth (N, 25, 3), each measured landmark markers (N, 25, 3)
    minus its true joint centre, turned into its segment's frame; right-side samples mirrored
    onto the left. Returns left keypoint -> (n, 3) samples in metres (NaN rows dropped)."""
    local = np.empty_like(markers)
    for f, q in enumerate(poses):
        local[f] = np.einsum("kji,kj->ki", segment_rotations(skeleton, q), markers[f] - truth[f])
    out = {}
    for k in SEGMENT:
        if k.startswith("left_"):
            s = np.concatenate([local[:, INDEX[k]], local[:, INDEX[k.replace("left_", "right_")]] * _MIRROR])
            out[k] = s[np.isfinite(s).all(axis=1)]
    return out
