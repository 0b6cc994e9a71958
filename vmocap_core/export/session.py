"""A processed session read from a bag, on a regular time grid: what every exporter writes.

Frames are the keypoints messages (one per frame set, empty while not tracking) placed on the
grid of the recording's frame period; a frame set that never arrived (dropped) or was not
tracked is a gap: NaN keypoints and joint values, never interpolated.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..bag import BagReader
from ..bag import messages as M
from ..errors import BagError
from ..graph_config import Topics
from ..keypoints import KEYPOINTS
from ..method.skeleton import BodyDimensions, Skeleton
from ..method.smoothing import runs
from ..outputs.streams import pose_of
from ..outputs.urdf import JOINT_NAMES, model_angles

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
        """Runs of consecutive tracked frames."""
        return runs(self.tracked)

    def dims_at(self, frame: int) -> BodyDimensions:
        """The subject's dimensions identified last before this frame (else the first)."""
        if not self.subjects:
            raise BagError("the bag has no subject dimensions (/diagnostics status "
                           f"'{SUBJECT_STATUS}'): process it with `vmocap process` first")
        t = self.t0_ns + frame * 1e9 / self.rate_hz
        before = [d for s, d in self.subjects if s <= t + 1]
        return before[-1] if before else self.subjects[0][1]


def load_session(path: str | Path, namespace: str = "/vmocap", recover: bool = False) -> Session:
    """Read the keypoints, joint_states and subject diagnostics of a processed bag."""
    topics = Topics(namespace)
    kp: dict[int, np.ndarray | None] = {}
    js: dict[int, np.ndarray] = {}
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    names: list[str] = []
    subjects: list[tuple[int, BodyDimensions]] = []
    with BagReader(path, recover=recover) as reader:  # recover: a truncated bag, damaged chunks
        if topics.keypoints not in reader.topics:
            raise BagError(f"{path}: no {topics.keypoints} topic (not a processed bag: run `vmocap process`)")
        want = [topics.keypoints] + [t for t in (topics.joint_states, topics.root_pose, Topics.diagnostics)
                                     if t in reader.topics]
        for m in reader.messages(want):
            msg = m.decode()
            t = M.stamp_ns(msg)
            if m.topic == topics.keypoints:
                kp[t] = M.cloud_keypoints(msg)[0]
            elif m.topic == topics.joint_states:
                js[t] = np.asarray(msg["position"], dtype=np.float64)
                names = list(msg["name"])
            elif m.topic == topics.root_pose:
                poses[t] = pose_of(msg)
            else:
                for st in msg["status"]:
                    if st["name"] == SUBJECT_STATUS:
                        vals = {v["key"]: v["value"] for v in st["values"]}
                        d = json.loads(vals["dims"])
                        subjects.append((t, BodyDimensions(**{k: tuple(v) if isinstance(v, list) else v
                                                               for k, v in d.items()})))
    if not kp:
        raise BagError(f"{path}: the keypoints topic has no message")
    if names == list(JOINT_NAMES):  # the URDF's joints + the pelvis pose -> the model's 40 DOF
        js = {t: model_angles(q, poses[t]) for t, q in js.items() if t in poses}
        names = Skeleton().joint_names
    stamps = np.array(sorted(kp), dtype=np.int64)
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1e9 / 60.0
    if period <= 0:
        raise BagError(f"{path}: keypoint stamps do not increase")
    idx = np.round((stamps - stamps[0]) / period).astype(np.int64)
    N = int(idx[-1]) + 1
    K = np.full((N, len(KEYPOINTS), 3), np.nan)
    nq = len(names) or 40
    Q = np.full((N, nq), np.nan)
    for t, i in zip(stamps, idx):
        if kp[t] is not None and t in js:  # tracked: both the keypoints and the joint values
            K[i], Q[i] = kp[t], js[t]
    return Session(1e9 / period, int(stamps[0]), K, Q, names, sorted(subjects, key=lambda s: s[0]))
