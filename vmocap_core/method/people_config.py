"""The settings of several people (our extension; the paper tracks one person), read from
`max_people` (under `/**`) and the PCM node's people parameters; and the rule that ends a
person, which the PCM side (people_look.py: whom it crops) and the skeleton side
(people_stages.py: whose body is output) both apply to what they were fed back, so that
neither has to tell the other."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..errors import VmocapError


class PeopleError(VmocapError):
    """A setting the multi-person tracker cannot work with."""


@dataclass
class PeopleConfig:
    max_people: int = 2  # people tracked at once; more in view are counted, not tracked
    detect_every_s: float = 0.5  # while fewer are tracked: the detector looks for newcomers this often
    # ... and glances at the whole images this often in between (no closer look): someone walking
    # in waits for a body this long plus their initialization, not detect_every_s plus it
    glance_every_s: float = 0.2
    count_every_s: float = 2.0  # while max_people are tracked: it counts the people left out this often (0: never)
    end_after_s: float = 1.0  # a person without a skeleton for this long is ended
    reacquire_m: float = 1.0  # a lost person is found again within this of their last hip centre
    same_body_m: float = 0.15  # two skeletons whose keypoints lie this close (median): one body
    contested_m: float = 0.1  # two people's markers this close: one body part, neither IK uses it (contested.py; 0: off)
    hold_s: float = 0.25  # before their skeleton: a camera that lost a person's detection keeps its last crop this long
    wait_search_s: float = 0.1  # while someone waits for crops (found, lost): the detector runs this often
    closer_every: int = 4  # every this many searches for newcomers look closer in every camera (people_look.py)
    remember_s: float = 60.0  # an ended person's skeleton is kept this long: if they come back, no new identification
    # a person's track (identified, or found again) is output once this many frame sets agreed
    # with its skeleton (SkeletonConfig.check_confirm_frames, the larger of the two): with other
    # bodies about, a first fit may lean on one of them or on a body half up off the floor
    confirm_frames: int = 3

    def __post_init__(self) -> None:
        if int(self.max_people) < 1:
            raise PeopleError(f"max_people must be at least 1, got {self.max_people}")
        if min(self.detect_every_s, self.glance_every_s, self.count_every_s) < 0:
            raise PeopleError("detect_every_s, glance_every_s and count_every_s must be >= 0")
        if self.contested_m < 0:
            raise PeopleError(f"contested_m must be >= 0 (0: off), got {self.contested_m}")
        if int(self.confirm_frames) < 0:
            raise PeopleError(f"confirm_frames must be >= 0, got {self.confirm_frames}")


def ended_people(stamp_ns: int, seen_ns: Mapping[int, int], bodies: Mapping[int, np.ndarray | None],
                 config: PeopleConfig) -> tuple[set[int], set[int]]:
    """The people (numbers) who end at this frame set: (those without a skeleton for
    end_after_s, with their last one at `seen_ns`: left the room, or lost and not found again),
    (the younger of two whose fed-back skeletons `bodies` lie on one body: a track that jumped
    to its neighbour)."""
    gone = {n for n, t in seen_ns.items() if not 0 <= stamp_ns - t <= config.end_after_s * 1e9}
    merged: set[int] = set()
    fed = [(n, kp) for n, kp in bodies.items() if n not in gone and kp is not None]
    for i, (na, a) in enumerate(fed):
        for nb, b in fed[i + 1:]:
            d = np.linalg.norm(a - b, axis=1)
            if np.isfinite(d).any() and float(np.nanmedian(d)) < config.same_body_m:
                merged.add(max(na, nb))
    return gone, merged
