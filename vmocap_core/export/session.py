"""A tracked session read from a bag, on a regular time grid: what every exporter writes.

The bag is a recording of the graph's outputs (the recorder node, `vmocap record`) or a
`vmocap process` bag. Frames are the keypoints messages (one per frame set, empty while not
tracking) placed on the grid of the recording's frame period; a frame set that never arrived
(dropped) or was not tracked is a gap: NaN keypoints and joint values, never interpolated.
The subject's dimensions and pelvis pose come from where the recording holds them
(export/subject.py).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bag import BagReader
from ..bag import messages as M
from ..errors import BagError
from ..graph_config import Topics
from ..keypoints import INDEX, KEYPOINTS
from ..method.skeleton import BONES, BodyDimensions, Skeleton
from ..method.smoothing import runs
from ..outputs.streams import pose_of
from ..outputs.urdf import JOINT_NAMES, model_angles, quaternion_to_rotvec, rotvec_to_quaternion
from .subject import Poses, SubjectFit, dims_from_urdf, fit_run, tf_pelvis

SUBJECT_STATUS = "vmocap: subject"  # the /diagnostics status `vmocap process` writes


@dataclass
class Session:
    rate_hz: float
    t0_ns: int  # stamp of frame 0
    keypoints: np.ndarray  # (N, 25, 3) metres, world frame (Z up), NaN in gaps
    angles: np.ndarray  # (N, 40) JointState positions (m, rad), NaN in gaps
    joint_names: list[str]
    subjects: list[tuple[int, BodyDimensions]]  # (stamp, dims) identifications, by stamp

    @property
    def n_frames(self) -> int:
        return len(self.keypoints)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.rate_hz

    @property
    def tracked(self) -> np.ndarray:
        return np.isfinite(self.keypoints).all(axis=(1, 2)) & np.isfinite(self.angles).all(axis=1)

    def segments(self) -> list[slice]:
        """Runs of consecutive tracked frames, split where the subject's dimensions change (a
        BVH file holds one skeleton)."""
        starts = {int(round((t - self.t0_ns) * self.rate_hz / 1e9)) for t, _ in self.subjects}
        out = []
        for seg in runs(self.tracked):
            cuts = [seg.start] + sorted(i for i in starts if seg.start < i < seg.stop) + [seg.stop]
            out += [slice(a, b) for a, b in zip(cuts, cuts[1:])]
        return out

    def dims_at(self, frame: int) -> BodyDimensions:
        """The subject's dimensions identified last before this frame (else the first)."""
        dims = _dims_at(self.subjects, self.t0_ns + (frame + 0.5) * 1e9 / self.rate_hz)  # the frame's stamp, rounded
        if dims is None:
            raise BagError("the bag has no subject dimensions (/diagnostics status "
                           f"'{SUBJECT_STATUS}', robot_description, or keypoints with joint_states)")
        return dims


def _dims_at(subjects: list[tuple[int, BodyDimensions]], t: float) -> BodyDimensions | None:
    """The dimensions identified last before stamp t (else the first; None without any)."""
    before = [d for s, d in subjects if s <= t + 1]
    return before[-1] if before else subjects[0][1] if subjects else None


def _subject_dims(msg: dict) -> BodyDimensions | None:
    for st in msg["status"]:
        if st["name"] == SUBJECT_STATUS:
            d = json.loads({v["key"]: v["value"] for v in st["values"]}["dims"])
            return BodyDimensions(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
    return None


@dataclass
class _Recorded:
    """What a recording holds of the tracked subject, by stamp."""

    keypoints: dict[int, np.ndarray | None] = field(default_factory=dict)
    joints: dict[int, np.ndarray] = field(default_factory=dict)
    names: list[str] = field(default_factory=list)
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # root_pose, else /tf
    subjects: list[tuple[int, BodyDimensions]] = field(default_factory=list)  # /diagnostics
    described: list[tuple[int, BodyDimensions]] = field(default_factory=list)  # robot_description


def _read(path: str | Path, topics: Topics, recover: bool = False) -> _Recorded:
    rec = _Recorded()
    with BagReader(path, recover=recover) as reader:
        if topics.keypoints not in reader.topics:
            raise BagError(f"{path}: no {topics.keypoints} topic: not a recording of the graph's outputs nor a processed "
                           "bag (record the graph, or run `vmocap process`)")
        pose_topic = topics.root_pose if topics.root_pose in reader.topics else Topics.tf
        want = [topics.keypoints] + [t for t in (topics.joint_states, pose_topic, Topics.diagnostics, topics.robot_description)
                                     if t in reader.topics]
        urdf: BodyDimensions | None = None  # a description waits for the joint state it came before
        for m in reader.messages(want):
            msg = m.decode()
            if m.topic == topics.keypoints:
                rec.keypoints[M.stamp_ns(msg)] = M.cloud_keypoints(msg)[0]
            elif m.topic == topics.joint_states:
                t = M.stamp_ns(msg)
                rec.joints[t] = np.asarray(msg["position"], dtype=np.float64)
                rec.names = list(msg["name"])
                if urdf is not None:
                    rec.described.append((t, urdf))
                    urdf = None
            elif m.topic == topics.root_pose:
                rec.poses[M.stamp_ns(msg)] = pose_of(msg)
            elif m.topic == Topics.tf:
                if (found := tf_pelvis(msg, M.WORLD_FRAME)) is not None:
                    rec.poses[found[0]] = found[1:]
            elif m.topic == topics.robot_description:
                urdf = dims_from_urdf(msg["data"])
            elif (dims := _subject_dims(msg)) is not None:
                rec.subjects.append((M.stamp_ns(msg), dims))
    if urdf is not None:  # described, never followed by a joint state
        rec.described.append((max(rec.keypoints, default=0), urdf))
    if not rec.keypoints:
        raise BagError(f"{path}: the keypoints topic has no message")
    return rec


_BONES = np.array([(INDEX[a], INDEX[b]) for a, b in BONES.values()])


def _same_lengths(ts: list[int], keypoints: dict[int, np.ndarray]) -> list[list[int]]:
    """A tracked run's stamps split where its bones change length: a new skeleton without a
    gap (the identified one replacing the provisional one, SkeletonConfig.identify_output)."""
    K = np.array([keypoints[t] for t in ts])
    lengths = np.linalg.norm(K[:, _BONES[:, 0]] - K[:, _BONES[:, 1]], axis=-1)
    change = np.flatnonzero(np.nan_to_num(np.abs(np.diff(lengths, axis=0)), nan=0.0).max(axis=1, initial=0.0) > 1e-6) + 1
    return [[int(t) for t in part] for part in np.split(np.asarray(ts), change)]


def _model_dofs(path: str | Path, rec: _Recorded, topics: Topics, stamps: np.ndarray, idx: np.ndarray,
                tracked: np.ndarray) -> tuple[dict[int, np.ndarray], list[tuple[int, BodyDimensions]]]:
    """The model's 40 DOF of every tracked stamp, and the subjects' dimensions by stamp: as
    recorded, or fitted per tracked run (export/subject.py) where the recording lacks them."""
    urdf = rec.names == list(JOINT_NAMES)
    rest = np.array([0.0, 0.0, 0.0, 1.0])
    local: dict[int, np.ndarray] = {}
    for t in stamps[tracked]:
        q = rec.joints[t]
        local[t] = model_angles(q, (np.zeros(3), rest)) if urdf else np.concatenate([np.zeros(6), q[6:]])
        if not urdf:  # the 40 DOF carry the pelvis pose themselves
            rec.poses[t] = (q[:3], rotvec_to_quaternion(q[3:6])[0])
    known = rec.subjects or rec.described
    subjects = list(known)
    fit: SubjectFit | None = None
    out: dict[int, np.ndarray] = {}
    grid = np.zeros(int(idx[-1]) + 1, dtype=bool)
    grid[idx[tracked]] = True
    at = dict(zip(idx.tolist(), stamps.tolist()))
    for ts in (part for seg in runs(grid) for part in _same_lengths([at[i] for i in range(seg.start, seg.stop)], rec.keypoints)):
        dims = _dims_at(known, ts[0])
        poses: Poses | None = None
        if all(t in rec.poses for t in ts):
            poses = (np.array([rec.poses[t][0] for t in ts]), np.array([rec.poses[t][1] for t in ts]))
        if dims is None or poses is None:
            fit = fit or SubjectFit()
            sk = Skeleton()
            configs = np.array([sk.from_angles(local[t]) for t in ts])
            W = np.array([rec.keypoints[t] for t in ts])
            try:
                fitted, poses = fit_run(W, configs, dims, poses, fit)
            except BagError as exc:
                missing = ([topics.robot_description] if dims is None else []) + ([topics.root_pose] if poses is None else [])
                raise BagError(f"{path}: {exc}; the recording has no {' and no '.join(missing)} to use instead") from None
            if dims is None:
                subjects.append((ts[0], fitted))
        for t, tr, q in zip(ts, *poses):
            out[t] = np.concatenate([tr, quaternion_to_rotvec(q)[0], local[t][6:]])
    return out, sorted(subjects, key=lambda s: s[0])


def load_session(path: str | Path, namespace: str = "/vmocap", recover: bool = False) -> Session:
    """Read the keypoints, joint_states and the subject (dimensions, pelvis pose) of a recording
    of the graph's outputs or a `vmocap process` bag."""
    topics = Topics(namespace)
    rec = _read(path, topics, recover)  # recover: BagReader's (a truncated bag, damaged chunks)
    stamps = np.array(sorted(rec.keypoints), dtype=np.int64)
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1e9 / 60.0
    if period <= 0:
        raise BagError(f"{path}: keypoint stamps do not increase")
    idx = np.round((stamps - stamps[0]) / period).astype(np.int64)
    shown = np.array([rec.keypoints[t] is not None for t in stamps], dtype=bool)
    if shown.any() and not rec.joints:
        raise BagError(f"{path}: {shown.sum()} tracked keypoint frames but no {topics.joint_states} message: "
                       f"the joint values are missing (record {topics.joint_states})")
    tracked = shown & np.array([t in rec.joints for t in stamps], dtype=bool)
    js, names, subjects = rec.joints, rec.names, rec.subjects or rec.described
    if tracked.any() and rec.names in (list(JOINT_NAMES), Skeleton().joint_names):
        js, subjects = _model_dofs(path, rec, topics, stamps, idx, tracked)
        names = Skeleton().joint_names
    N = int(idx[-1]) + 1
    K = np.full((N, len(KEYPOINTS), 3), np.nan)
    Q = np.full((N, len(names) or 40), np.nan)
    for t, i, ok in zip(stamps, idx, tracked):
        if ok and t in js:  # tracked: both the keypoints and the joint values
            K[i], Q[i] = rec.keypoints[t], js[t]
    return Session(1e9 / period, int(stamps[0]), K, Q, names, sorted(subjects, key=lambda s: s[0]))


