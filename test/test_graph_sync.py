"""The approximate-time synchronizer: matching, drops, duplicates, disorder, silent cameras."""

import numpy as np
import pytest

from vmocap_core.cameras.sync import ApproximateSync

MS = 1_000_000
CAMS = ["c0", "c1", "c2", "c3"]


def feed(sync, events):
    out = []
    for name, stamp in events:
        out += sync.add(name, stamp, (name, stamp))
    return out


def test_complete_sets_with_jitter_any_arrival_order():
    rng = np.random.default_rng(0)
    events = []
    for k in range(50):
        base = 1_000 * MS + k * 33 * MS
        order = rng.permutation(4)
        events += [(CAMS[i], base + int(rng.integers(-3, 4)) * MS) for i in order]
    sync = ApproximateSync(CAMS, tolerance_ns=8 * MS)
    sets = feed(sync, events)
    assert len(sets) == 50
    assert all(s.complete for s in sets)
    stamps = [s.stamp_ns for s in sets]
    assert stamps == sorted(stamps)
    for k, s in enumerate(sets):
        assert all(abs(st - (1_000 + k * 33) * MS) <= 3 * MS for st in s.stamps.values())
        assert s.stamp_ns == min(s.stamps.values())
    st = sync.stats()
    assert st.complete == 50 and st.partial == 0 and sum(st.dropped_frames.values()) == 0


def test_lost_frame_gives_partial_set_when_camera_moves_on():
    sync = ApproximateSync(CAMS, tolerance_ns=5 * MS)
    ev = [(c, 0) for c in CAMS[:3]]  # c3 misses frame 0
    assert feed(sync, ev) == []  # still waiting for c3
    out = feed(sync, [("c3", 33 * MS)])  # c3 has moved past: set 0 goes without it
    assert len(out) == 1 and out[0].missing == ("c3",) and len(out[0].items) == 3
    out = feed(sync, [(c, 33 * MS) for c in CAMS[:3]])
    assert len(out) == 1 and out[0].complete
    st = sync.stats()
    assert st.partial == 1 and st.complete == 1 and st.missing["c3"] == 1


def test_duplicates_and_late_frames_are_dropped_and_counted():
    sync = ApproximateSync(CAMS, tolerance_ns=5 * MS)
    out = feed(sync, [(c, 0) for c in CAMS])
    assert len(out) == 1
    assert feed(sync, [("c0", 0)]) == []  # its set is gone: late
    feed(sync, [("c1", 33 * MS), ("c1", 33 * MS)])  # duplicate
    out = feed(sync, [(c, 33 * MS) for c in ("c0", "c2", "c3")])
    assert len(out) == 1 and out[0].complete
    st = sync.stats()
    assert st.late["c0"] == 1 and st.duplicates["c1"] == 1


def test_out_of_order_within_a_camera_is_reordered():
    sync = ApproximateSync(["a", "b"], tolerance_ns=2 * MS, min_cameras=2)
    out = feed(sync, [("a", 66 * MS), ("a", 33 * MS), ("b", 33 * MS), ("b", 66 * MS)])
    assert [s.stamp_ns for s in out] == [33 * MS, 66 * MS]
    assert all(s.complete for s in out)


def test_silent_camera_graph_continues_on_the_others_and_reports_it():
    sync = ApproximateSync(CAMS, tolerance_ns=5 * MS, min_cameras=2, silent_after_ns=200 * MS)
    sets = []
    for k in range(30):
        cams = CAMS if k < 10 else CAMS[:3]  # c3 goes silent after frame 9
        sets += feed(sync, [(c, k * 33 * MS) for c in cams])
    # every frame set is emitted, at most a few late ones wait for the silence timeout
    assert len(sets) >= 28
    assert all(len(s.items) >= 3 for s in sets)
    assert "c3" in sync.stats().silent
    assert sets[-1].missing == ("c3",)
    # once silent, sets are emitted immediately (no waiting for c3)
    sets2 = feed(sync, [(c, 30 * 33 * MS) for c in CAMS[:3]])
    assert len(sets2) == 1 and sets2[0].stamp_ns == 30 * 33 * MS
    # it comes back (its first frame arrives before the others' of the same set)
    sets3 = feed(sync, [(c, 31 * 33 * MS) for c in CAMS[::-1]])
    assert len(sets3) == 1 and sets3[0].complete and "c3" not in sync.stats().silent


def test_below_min_cameras_the_set_is_dropped():
    sync = ApproximateSync(CAMS, tolerance_ns=5 * MS, min_cameras=2, silent_after_ns=10**12)
    feed(sync, [("c0", 0)])
    out = feed(sync, [(c, 33 * MS) for c in CAMS])
    assert len(out) == 1 and out[0].stamp_ns == 33 * MS and out[0].complete
    st = sync.stats()
    assert st.dropped_sets == 1 and st.dropped_frames["c0"] == 1


def test_flush_and_bad_arguments():
    sync = ApproximateSync(["a", "b"], tolerance_ns=0)
    feed(sync, [("a", 5), ("b", 5), ("a", 9)])
    assert [s.stamp_ns for s in sync.flush()] == []  # 'a' alone at 9 is below min_cameras
    with pytest.raises(KeyError):
        sync.add("zz", 1, None)
    with pytest.raises(ValueError):
        ApproximateSync(["a", "a"], 0)


def test_camera_back_from_silence_is_matched_again_even_if_its_first_frame_is_late():
    # views arrive cam0 first; cameras 1-3 pause for longer than the silence timeout
    sync = ApproximateSync(CAMS, tolerance_ns=MS, min_cameras=2, silent_after_ns=100 * MS)
    out = []
    for k in range(5):
        out += feed(sync, [(c, k * 33 * MS) for c in CAMS])
    for k in range(5, 12):  # only cam0 delivers: its lone frames are dropped (below min_cameras)
        out += feed(sync, [("c0", k * 33 * MS)])
    assert set(sync.stats().silent) == {"c1", "c2", "c3"}
    for k in range(12, 20):  # all back, cam0 always first
        out += feed(sync, [(c, k * 33 * MS) for c in CAMS])
    assert not sync.stats().silent
    late_sets = [s for s in out if s.stamp_ns >= 13 * 33 * MS]
    # after the first set back (whose cam0 frame went alone), every set is complete again
    assert len(late_sets) == 7 and all(s.complete for s in late_sets)


def test_the_first_frame_set_after_a_gap_in_every_stream_is_matched():
    """A recording with a gap (or cameras restarted together): the first camera back must not make
    the others silent, which dropped the first frame set after the gap as below min_cameras."""
    sync = ApproximateSync(CAMS, tolerance_ns=5 * MS, min_cameras=2, silent_after_ns=500 * MS)
    out = []
    for k in list(range(10)) + list(range(180, 185)):  # 5.6 s without any frame
        out += feed(sync, [(c, k * 33 * MS) for c in CAMS])
    assert [s.stamp_ns // (33 * MS) for s in out] == list(range(10)) + list(range(180, 185))
    assert all(s.complete for s in out) and sync.stats().dropped_sets == 0


def test_a_camera_whose_stamps_lag_is_reported_not_silently_ignored():
    """cam1's stamps trail the others by 1 s (a clock offset, or its source started early):
    every frame of it arrives after its set went out; `lagging` names it (the nodes WARN)."""
    from vmocap_core.cameras.sync import lagging

    sync = ApproximateSync(["cam0", "cam1", "cam2"], 8_000_000, min_cameras=2, silent_after_ns=300_000_000)
    period = 33_333_333
    before = dict(sync.stats().late)
    sets = []
    for k in range(60):
        t = 10**12 + k * period
        sets += sync.add("cam0", t, k)
        sets += sync.add("cam2", t, k)
        if k >= 30:
            sets += sync.add("cam1", t - 10**9, k)  # one second behind
    late = dict(sync.stats().late)
    assert all("cam1" not in fs.items for fs in sets[30:])
    assert set(lagging(before, late)) == {"cam1"} and lagging(late, late) == {}


def test_frames_missing_counts_skipped_periods_only():
    from vmocap_core.cameras.sync import frames_missing

    period = int(1e9 / 30)
    assert frames_missing(None, 5 * period, 30.0) == 0  # the first frame set
    assert frames_missing(0, period, 30.0) == 0
    assert frames_missing(0, 4 * period, 30.0) == 3
    assert frames_missing(0, int(1.4 * period), 30.0) == 0  # jitter, or cameras a little slower than fps
    assert frames_missing(4 * period, period, 30.0) == 0  # a looped recording starts again
