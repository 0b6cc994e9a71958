"""When a recorded source starts playing (cameras/start.py), without ROS."""

from vmocap_core.cameras.start import PARTIAL_MATCH_S, SETTLE_S, StartGate


def test_starts_once_every_image_topic_has_a_reader() -> None:
    g = StartGate(0.0, 60.0)
    assert g.update(0.0, [True, False], True) is None
    assert g.update(0.5, [True, True], True) is None  # settling
    assert g.update(0.5 + SETTLE_S, [True, True], True) == ""


def test_a_reader_of_some_cameras_waits_longer_and_is_named() -> None:
    g = StartGate(0.0, 60.0)
    assert g.update(1.0, [True, False, False], True) is None
    assert g.update(1.0 + PARTIAL_MATCH_S - 0.1, [True, False, False], True) is None
    assert g.update(1.0 + PARTIAL_MATCH_S, [True, False, False], True) == " (subscribers on 1 of 3 image topics)"


def test_waited_topics_hold_it_until_the_deadline() -> None:
    g = StartGate(0.0, 3.0)
    assert g.update(2.9, [True, True], False) is None
    assert g.update(3.0, [True, True], False) == " (no subscriber yet)"
