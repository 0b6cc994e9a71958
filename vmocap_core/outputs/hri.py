"""ROS4HRI (REP-155) outputs of the tracked subject, without ROS: the subject as a body with an id.

Per frame set (`HriOutputs.step`), beside the subject's own topics (streams.py):
- `/humans/bodies/tracked` (hri_msgs/IdsList), every frame set: `[id]` while the status is
  `tracking`, `[]` otherwise (a listener drops the body when its id leaves the list);
- `/humans/bodies/<id>/urdf` (std_msgs/String, transient local): the subject URDF with every
  link, joint and the robot name suffixed `_<id>`, when the id or the body dimensions change;
- `/humans/bodies/<id>/joint_states`: the URDF's joints suffixed `_<id>`, only while tracking;
- `/tf`: `world -> body_<id>` (origin at the mid-point of the hips, x forward, y to the left,
  z towards the head), `world -> pelvis_<id>` and the suffixed URDF's moving joints (the same
  transforms as the subject's /tf, renamed); `/tf_static`: the suffixed fixed joints, added
  to the static frames the subject publishes (every /tf_static message holds all of them).

Ids (`BodyIds`): a letter and four lowercase letters or digits, random (unique across runs,
seedable for tests). An id stays while the subject is tracked and through `GRACE_S` of frame
sets that are not (`uncertain`, a glitch of the maps); a subject the tracker lost, or one not
tracked for longer, comes back under a new id. The per-id topics of an ended id are closed
`RETIRE_S` later, so listeners opening them meanwhile still find the URDF.
"""

from __future__ import annotations

import random
import string
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..bag import messages as M
from ..errors import VmocapError
from ..graph_config import Topics
from ..keypoints import INDEX
from ..method.skeleton import BodyDimensions
from .streams import JOINTS, STRING, SubjectOutputs
from .tf import TF_TYPE, Transforms, UrdfKinematics, tf_message
from .urdf import BASE_LINK, JOINT_NAMES, SubjectModel, base_pose, joint_positions, matrix_to_quaternion

BODIES = "/humans/bodies"
TRACKED = f"{BODIES}/tracked"
IDS_LIST = "hri_msgs/msg/IdsList"
ID_LENGTH = 4  # characters after the leading letter
GRACE_S = 0.5  # capture time without tracking an id survives (uncertain spans of a few frame sets)
RETIRE_S = 5.0  # capture time after its end that an id's topics stay open


class HriError(VmocapError):
    """A robot description that cannot be turned into a body's (not URDF XML)."""


def body_topic(body_id: str, leaf: str) -> str:
    return f"{BODIES}/{body_id}/{leaf}"


def body_frame_id(body_id: str) -> str:
    return f"body_{body_id}"


def new_body_id(rng: random.Random, taken: set[str] | frozenset[str] = frozenset()) -> str:
    """A REP-155 id: short, starting with a letter; none of `taken`."""
    while True:
        body_id = rng.choice(string.ascii_lowercase) + "".join(rng.choices(string.ascii_lowercase + string.digits, k=ID_LENGTH))
        if body_id not in taken:
            return body_id


def suffixed_urdf(xml: str, suffix: str) -> str:
    """The URDF with the robot's, every link's and every joint's name (and the links and joints
    referring to them) suffixed: the description of one body among several."""
    try:
        root = ET.fromstring(xml)
    except ET.ParseError as exc:
        raise HriError(f"robot description is not XML: {exc}") from None
    if root.tag != "robot":
        raise HriError(f"robot description's root element is <{root.tag}>, not <robot>")
    root.set("name", root.get("name", "") + suffix)
    for el in root.iter():
        if el.tag in ("link", "joint") and el.get("name"):
            el.set("name", el.get("name", "") + suffix)
        elif el.tag in ("parent", "child") and el.get("link"):
            el.set("link", el.get("link", "") + suffix)
        elif el.tag == "mimic" and el.get("joint"):
            el.set("joint", el.get("joint", "") + suffix)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


_HIPS_NECK = np.array([INDEX["left_hip"], INDEX["right_hip"], INDEX["neck"]])


def body_pose(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """REP-155 body frame in the keypoints' frame: origin at the mid-point of the hips, z
    towards the neck, y towards the left hip (made orthogonal to z), x = y x z (forward).
    Translation (3,), quaternion (4,) x y z w; None when the hips or the neck are missing."""
    left, right, neck = np.asarray(keypoints, dtype=np.float64).reshape(-1, 3)[_HIPS_NECK]
    origin = (left + right) / 2
    z, y = neck - origin, left - right
    nz = np.linalg.norm(z)
    if not (np.isfinite(nz) and nz > 1e-6):
        return None
    z = z / nz
    y = y - (y @ z) * z
    ny = np.linalg.norm(y)
    if not (np.isfinite(ny) and ny > 1e-6):
        return None
    y = y / ny
    R = np.stack([np.cross(y, z), y, z], axis=1)
    return origin, matrix_to_quaternion(R[None])[0]


class BodyIds:
    """The tracked subject's body id over frame sets (module docstring): `update` gives the id
    of a frame set (None when it is not tracked), `retired` the ended ids whose topics may go."""

    def __init__(self, seed: int | None = None, grace_s: float = GRACE_S, retire_s: float = RETIRE_S,
                 used: set[str] | None = None) -> None:
        self._rng: random.Random = random.Random(seed) if seed is not None else random.SystemRandom()
        self.grace_ns, self.retire_ns = int(grace_s * 1e9), int(retire_s * 1e9)
        self.current: str | None = None
        self._untracked_since: int | None = None  # stamp of the first untracked frame set after the last tracked one
        self._used: set[str] = set() if used is None else used  # shared by the bodies of several people
        self._ended: dict[str, int] = {}  # id -> stamp of the frame set that ended it

    def update(self, stamp_ns: int, status: str) -> str | None:
        tracking = status == "tracking"
        if not tracking and self._untracked_since is None:
            self._untracked_since = stamp_ns
        if self.current is not None:
            # frame sets missing (a gap in the recording, dropped) end nothing; frame sets that are
            # there but untracked for longer than the grace do
            since = self._untracked_since
            gap = since is not None and not 0 <= stamp_ns - since <= self.grace_ns
            if status == "lost" or gap:  # lost: the tracker starts over, maybe on someone else
                self._end(stamp_ns)
        if not tracking:
            return None
        if self.current is None:
            self.current = new_body_id(self._rng, self._used)
            self._used.add(self.current)
        self._untracked_since = None
        return self.current

    def _end(self, stamp_ns: int) -> None:
        assert self.current is not None
        self._ended[self.current] = stamp_ns
        self.current = None

    def retired(self, stamp_ns: int) -> list[str]:
        """Ended ids whose topics close now (RETIRE_S after their end, or at once when the
        clock went back: another recording)."""
        gone = [i for i, end in self._ended.items() if not 0 <= stamp_ns - end <= self.retire_ns]
        for i in gone:
            del self._ended[i]
        return gone


@dataclass
class Channel:
    """A per-id output topic: a publisher to open (or, in `HriFrame.closed`, to close)."""

    topic: str
    type: str
    latched: bool


@dataclass
class HriFrame:
    """What one frame set asks of a publisher: open these topics, publish these messages (in
    this order), then close these topics."""

    opened: list[Channel] = field(default_factory=list)
    messages: list[tuple[str, str, dict]] = field(default_factory=list)
    closed: list[str] = field(default_factory=list)
    retired: list[str] = field(default_factory=list)  # the ids whose topics `closed` holds


def body_channels(body_id: str) -> list[Channel]:
    return [Channel(body_topic(body_id, "urdf"), STRING, True), Channel(body_topic(body_id, "joint_states"), JOINTS, False)]


class HriOutputs:
    """The REP-155 messages of the tracked subject, frame set by frame set (module docstring).
    `subject`: the SubjectOutputs publishing the same graph's /tf_static (the body's fixed
    frames join its static frames); `tf`: whether /tf and /tf_static are published at all."""

    def __init__(self, subject: SubjectOutputs | None = None, tf: bool = True, seed: int | None = None,
                 grace_s: float = GRACE_S, retire_s: float = RETIRE_S, used: set[str] | None = None) -> None:
        self.subject, self.tf = subject, tf
        self.ids = BodyIds(seed, grace_s, retire_s, used)
        self._described: tuple[str, BodyDimensions] | None = None
        self._kinematics: UrdfKinematics | None = None
        self._names: list[str] = []  # the suffixed JOINT_NAMES of the described body

    @property
    def body_id(self) -> str | None:
        return self.ids.current

    @property
    def fixed_frames(self) -> Transforms | None:
        """The described body's fixed frames (its suffixed keypoint frames; None before)."""
        return None if self._kinematics is None else self._kinematics.static_transforms()

    def step(self, result: Any, wanted: Callable[[str], bool] | None = None) -> HriFrame:
        """The frame set of a TrackResult (stamp_ns, status, q, keypoints, dims). A body's
        joint_states and /tf are not built where `wanted(topic)` is False (nobody listens)."""
        want = wanted or (lambda topic: True)
        t = result.stamp_ns
        body_id = self.ids.update(t, result.status)
        retired = self.ids.retired(t)
        frame = HriFrame(closed=[c.topic for i in retired for c in body_channels(i)], retired=retired)
        out = frame.messages
        if body_id is not None and result.dims is not None:
            if self._described is None or self._described[0] != body_id:
                frame.opened = body_channels(body_id)
            if self._described != (body_id, result.dims):
                out.extend(self._describe(t, body_id, result.dims))
            positions = joint_positions(result.q)
            js = body_topic(body_id, "joint_states")
            if want(js):
                out.append((js, JOINTS, M.joint_state_msg(t, self._names, positions)))
            if self.tf and want(Topics.tf):
                out.append((Topics.tf, TF_TYPE, tf_message(t, self._transforms(body_id, result, positions))))
        tracked = [body_id] if body_id is not None else []
        out.append((TRACKED, IDS_LIST, {"header": M.header(t), "ids": tracked}))
        return frame

    def _describe(self, stamp_ns: int, body_id: str, dims: BodyDimensions) -> list[tuple[str, str, dict]]:
        """The body's URDF and, with TF, /tf_static with its fixed frames."""
        sfx = f"_{body_id}"
        xml = suffixed_urdf(SubjectModel(dims).to_xml(), sfx)
        self._kinematics = UrdfKinematics(xml)
        self._names = [n + sfx for n in JOINT_NAMES]
        self._described = (body_id, dims)
        out = [(body_topic(body_id, "urdf"), STRING, {"data": xml})]
        if self.tf:
            static = self._kinematics.static_transforms()
            if self.subject is not None:
                self.subject.extra_static = static
                static = self.subject.static(stamp_ns)
            out.append((Topics.tf_static, TF_TYPE, tf_message(stamp_ns, static)))
        return out

    def _transforms(self, body_id: str, result: Any, positions: np.ndarray) -> Transforms:
        assert self._kinematics is not None  # described first
        t, q = base_pose(result.q)
        parts = [Transforms([M.WORLD_FRAME], [f"{BASE_LINK}_{body_id}"], t.reshape(1, 3), q.reshape(1, 4)),
                 self._kinematics.transforms(self._names, positions)]
        body = body_pose(result.keypoints)
        if body is not None:
            parts.insert(0, Transforms([M.WORLD_FRAME], [body_frame_id(body_id)], body[0].reshape(1, 3), body[1].reshape(1, 4)))
        return Transforms.concat(parts)
