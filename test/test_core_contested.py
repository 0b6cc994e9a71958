"""Several people: a marker two people found in one place is used by neither (contested.py)."""

from __future__ import annotations

import numpy as np

from vmocap_core.keypoints import INDEX
from vmocap_core.method import people_stages
from vmocap_core.method.contested import contested
from vmocap_core.method.people_config import PeopleConfig
from vmocap_core.method.people_stages import PeopleSkeletons
from vmocap_core.method.results import N_KP, Markers


def _markers(x: float, kind: str = "lattice", stamp_ns: int = 0) -> Markers:
    """A body's markers spread along y at x (0.15 m apart), weight 1."""
    p = np.zeros((N_KP, 3))
    p[:, 0], p[:, 1], p[:, 2] = x, np.arange(N_KP) * 0.15, 1.0
    return Markers(stamp_ns, p, np.ones(N_KP), kind, 1.0)


def _beside() -> dict[int, Markers]:
    """Two bodies 0.5 m apart; person 0's left ankle hung on person 1's right ankle (3 cm off)."""
    a, b = _markers(0.0), _markers(0.5)
    a.positions[INDEX["left_ankle"]] = b.positions[INDEX["right_ankle"]] + [0.0, 0.0, 0.03]
    return {0: a, 1: b}


def test_two_peoples_markers_in_one_place_are_contested_for_both():
    both = contested(_beside(), radius=0.1)
    assert np.flatnonzero(both[0]).tolist() == [INDEX["left_ankle"]]
    assert np.flatnonzero(both[1]).tolist() == [INDEX["right_ankle"]]
    # 0.1 m is a limb's thickness: bodies 0.5 m apart have nothing in common
    far = contested({0: _markers(0.0), 1: _markers(0.5)}, radius=0.1)
    assert not far[0].any() and not far[1].any()


def test_markers_not_found_or_triangulated_take_no_part():
    m = _beside()
    m[1].weights[INDEX["right_ankle"]] = 0.0  # not found this frame set: nothing to contest
    assert not any(v.any() for v in contested(m, 0.1).values())
    m = _beside()
    m[1].kind = "triangulated"  # initializing: its markers are the CNN's centroids, no body yet
    assert not any(v.any() for v in contested(m, 0.1).values())


def test_neither_skeleton_stage_weighs_a_contested_marker(monkeypatch):
    seen: dict[int, np.ndarray] = {}
    step = people_stages.SkeletonStage.step

    def spy(stage, markers):
        seen[markers.person] = markers.weights.copy()
        return step(stage, markers)

    monkeypatch.setattr(people_stages.SkeletonStage, "step", spy)
    markers = _beside_numbered()
    PeopleSkeletons(people=PeopleConfig(max_people=2)).step(0, markers)
    assert seen[0][INDEX["left_ankle"]] == 0.0 and seen[1][INDEX["right_ankle"]] == 0.0
    assert (np.delete(seen[0], INDEX["left_ankle"]) == 1.0).all()
    assert markers[0].weights[INDEX["left_ankle"]] == 1.0  # the caller's markers are left as they came
    # off (contested_m 0): every marker counts
    seen.clear()
    PeopleSkeletons(people=PeopleConfig(max_people=2, contested_m=0.0)).step(0, _beside_numbered())
    assert (seen[0] == 1.0).all() and (seen[1] == 1.0).all()


def _beside_numbered() -> dict[int, Markers]:
    markers = _beside()
    for n, m in markers.items():
        m.person = n
    return markers
