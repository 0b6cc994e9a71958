"""Several people, the stages after the CNN: markers two people found in one place (contested.py),
and who the subject topics carry (PeopleSkeletons.subject)."""

from __future__ import annotations

import numpy as np

from vmocap_core.keypoints import INDEX
from vmocap_core.method import people_stages
from vmocap_core.method.contested import contested
from vmocap_core.method.people_config import PeopleConfig
from vmocap_core.method.people_stages import PeopleSkeletons
from vmocap_core.method.results import N_KP, Markers, nan_markers


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
    flagged: dict[int, np.ndarray | None] = {}
    step = people_stages.SkeletonStage.step

    def spy(stage, markers):
        seen[markers.person] = markers.weights.copy()
        flagged[markers.person] = markers.contested
        return step(stage, markers)

    monkeypatch.setattr(people_stages.SkeletonStage, "step", spy)
    markers = _beside_numbered()
    PeopleSkeletons(people=PeopleConfig(max_people=2)).step(0, markers)
    assert seen[0][INDEX["left_ankle"]] == 0.0 and seen[1][INDEX["right_ankle"]] == 0.0
    assert (np.delete(seen[0], INDEX["left_ankle"]) == 1.0).all()
    # flagged, so that the weight set to 0 is not read as the maps fading (consistency.WeightTrend)
    assert np.flatnonzero(flagged[0]).tolist() == [INDEX["left_ankle"]]
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


def test_the_subject_topics_wait_for_the_subject_rather_than_take_another_body():
    """The first person found is the subject; once their lengths are identified, a track of theirs
    that ends is waited for (their skeleton recognized in a newcomer), not handed to the other."""
    people = PeopleSkeletons(people=PeopleConfig(max_people=3))

    def step(t: int, numbers: list[int], gone: tuple[int, ...] = ()) -> None:
        people.step(t * 16_666_667, {n: nan_markers(t * 16_666_667) for n in numbers}, gone)

    step(0, [0, 1])
    assert people.subject == 0
    bodies = [object(), object()]  # identified skeletons are compared by identity
    people.stages[0].identified, people.stages[1].identified = bodies
    step(1, [0, 1])
    step(2, [1], gone=(0,))  # the subject's track ended
    assert people.subject is None  # not person 1
    step(3, [1, 2])
    assert people.subject is None  # a newcomer, not recognized (yet)
    people.stages[2].identified = bodies[0]  # recognized: the subject's remembered skeleton
    step(4, [1, 2])
    assert people.subject == 2
    # a subject who ended before being identified: the first found of the others carries on
    fresh = PeopleSkeletons(people=PeopleConfig(max_people=3))
    fresh.step(0, {0: nan_markers(0), 1: nan_markers(0)})
    fresh.step(1, {1: nan_markers(1)}, gone=(0,))
    assert fresh.subject == 1
