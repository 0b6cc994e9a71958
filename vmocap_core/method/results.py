"""What the stages hand each other: virtual markers (marker stage -> skeleton stage) and the
skeleton of a frame (skeleton stage -> outputs, and back to the marker stage as feedback)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..keypoints import INDEX, KEYPOINTS
from .skeleton import BodyDimensions

if TYPE_CHECKING:
    from .consistency import ViewCheck

N_KP = len(KEYPOINTS)
PELVIS, NECK = INDEX["pelvis"], INDEX["neck"]
TRUNK = np.array([INDEX[n] for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip")])


@dataclass
class Markers:
    """Virtual markers of one frame set, in KEYPOINTS order."""

    stamp_ns: int
    positions: np.ndarray  # (25, 3), NaN where unknown
    weights: np.ndarray  # (25,), 0 where unknown
    kind: str  # "triangulated" | "lattice" | "none"
    score: float = 0.0  # mean weight per view over the observed keypoints (0..1)
    # triangulated markers: what a stalled initialization is diagnosed from (init_report.py)
    residual_px: np.ndarray | None = None  # (25,) triangulation residual, NaN: not triangulated
    # (25,) bit masks of the cameras whose peaks went in (triangulated), or whose maps agree
    # with the marker (lattice: consistency.check_views of the markers in their own frame set)
    cameras: np.ndarray | None = None
    presence: dict[str, float] | None = None  # CNN presence per camera (not in messages)
    # the previous frame set's skeleton checked against its PCMs (consistency.py; None: no skeleton was fed back)
    check: ViewCheck | None = None
    # people besides the subject the detector's census last saw (PcmViews.others; -1: not known)
    others: int = -1
    # lattice markers: (25,) bit masks of the cameras with a view in whose image the lattice
    # centre lies, i.e. the views that can weigh each marker (None: not known)
    inside: np.ndarray | None = None
    # several people (people_stages.py): the person these are the markers of (PcmViews.person); -1: the one subject
    person: int = -1
    # lattice markers: bit mask of the cameras whose maps were read with a limb group's sides swapped (mirror.py)
    mirrored: int = 0
    # several people (contested.py): (25,) True where another person's marker lies in the same place (weight set to 0)
    contested: np.ndarray | None = None

    @property
    def trunk_views(self) -> int | None:
        """Lattice markers: how many cameras' images hold the whole trunk (both hips and both
        shoulders, by `inside`); None: not known."""
        if self.inside is None:
            return None
        both = np.bitwise_and.reduce(np.asarray(self.inside, np.uint32)[TRUNK])
        return int(np.bitwise_count(both))

    @property
    def support(self) -> float | None:
        """Lattice markers: the share of the markers found (weight > 0) whose position two
        cameras' maps or more confirm (consistency.py), from this frame set alone; None for
        other markers."""
        if self.kind != "lattice" or self.cameras is None:
            return None
        from .consistency import two_camera_share

        return two_camera_share(self.cameras, self.weights > 0)


def nan_markers(stamp_ns: int, kind: str = "none") -> Markers:
    return Markers(stamp_ns, np.full((N_KP, 3), np.nan), np.zeros(N_KP), kind, 0.0)


# Statuses whose raw keypoints are fed back to the lattice search (the others re-initialize);
# only "tracking" results are output ("uncertain": the skeleton disagrees with the images,
# tracked on but not published, see skeleton_stage.py).
FEEDBACK_STATUSES = ("tracking", "identifying", "smoothing", "uncertain")


@dataclass
class TrackResult:
    stamp_ns: int
    status: str  # "initializing" | "identifying" | "smoothing" | "tracking" | "uncertain" | "lost"
    q: np.ndarray  # (40,) published DOF after the second IK (see Skeleton.to_angles)
    joint_names: list[str]
    keypoints: np.ndarray  # (25, 3) filtered output
    raw_keypoints: np.ndarray  # (25, 3) first IK at the CNN's landmarks (landmarks.py; fed back to the lattice search)
    scores: np.ndarray  # (25,) marker weights
    markers: np.ndarray  # (25, 3) virtual markers as joint centres (landmark offsets removed)
    link_lengths: dict[str, float] = field(default_factory=dict)
    dims: BodyDimensions | None = None  # the subject's skeleton (tracking results only)
    feedback_stamp_ns: int | None = None  # the frame set of raw_keypoints when not stamp_ns
    # (25,) per keypoint, the fraction of the views seeing it whose PCMs agree with the skeleton
    # (consistency.py; NaN: no view sees it or nothing was checked)
    confidence: np.ndarray = field(default_factory=lambda: np.full(N_KP, np.nan))
    # "lost" results: where the subject is expected (3,), for the detector to look there
    # (path_gate.py); None: where it was last tracked
    seed: np.ndarray | None = None

    @property
    def feedback_stamp(self) -> int:
        """The frame set whose first IK `raw_keypoints` is: stamp_ns, except in fixed-lag mode,
        where the output (stamp_ns) is `smoothing_lag_frames` frame sets older than the feedback
        that the next frame set's lattice search waits for."""
        return self.stamp_ns if self.feedback_stamp_ns is None else self.feedback_stamp_ns


def feedback_of(result: TrackResult) -> np.ndarray | None:
    """What the skeleton stage feeds back to the next frame's lattice search and crops: the
    first IK's keypoints; None: re-initialize; only the pelvis (the rest NaN): re-initialize,
    looking for the subject there (`seed_of`; one message type on the feedback topic)."""
    if result.status in FEEDBACK_STATUSES:
        return result.raw_keypoints
    if result.seed is None:
        return None
    seed = np.full((N_KP, 3), np.nan)
    seed[PELVIS] = result.seed
    return seed


def skeleton_of(feedback: np.ndarray | None) -> np.ndarray | None:
    """The fed-back skeleton (25, 3) to search and crop around; None for no feedback, a seed
    (`seed_of`) or a skeleton without its pelvis and neck."""
    if feedback is None or not np.isfinite(feedback[[PELVIS, NECK]]).all():
        return None
    return feedback


def seed_of(feedback: np.ndarray | None) -> np.ndarray | None:
    """The pelvis of a feedback that holds nothing else (feedback_of: where to look for the
    subject when re-initializing), else None."""
    if feedback is None or not np.isfinite(feedback[PELVIS]).all():
        return None
    rest = np.delete(feedback, PELVIS, axis=0)
    return None if np.isfinite(rest).any() else np.asarray(feedback[PELVIS], dtype=np.float64).copy()
