"""The per-frame check of the skeleton against the images (method/consistency.py) and what the
tracker does with it: uncertain (no joint_states), lost (start over), the keypoints and
cameras named, the per-keypoint confidence on NS/keypoints."""

from __future__ import annotations

import numpy as np

from vmocap_core.apps.bench.accuracy import default_motions, prepare
from vmocap_core.bag import messages as M
from vmocap_core.cameras.projection import Camera, Rig
from vmocap_core.graph_config import Topics
from vmocap_core.keypoints import INDEX
from vmocap_core.method.config import PipelineConfig
from vmocap_core.method.consistency import ViewCheck, check_views
from vmocap_core.method.markers import MarkerStage
from vmocap_core.method.pipeline import Pipeline
from vmocap_core.method.prediction import BodyPredictor
from vmocap_core.method.results import Markers, feedback_of, seed_of, skeleton_of
from vmocap_core.outputs.messages import markers_from_message, markers_message, result_messages
from vmocap_core.pcm.synthetic import NoiseModel, SyntheticPcmSource, benchmark_rig
from vmocap_core.pcm.views import PcmViews

CLEAN = NoiseModel(offset_px=0.0, p_missing=0.0, p_swap=0.0, p_false=0.0,
                   inverted_p_missing=0.0, inverted_p_swap=0.0)


def _motion():
    m = prepare(next(f for f in default_motions() if f.stem == "walk"))
    m.positions = m.positions[:200]
    return m


def _walk_maps(seed: int):
    """The walk, its rig and clean synthetic PCMs of it."""
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    return m, rig, SyntheticPcmSource(rig, m.positions, m.present, seed=seed, noise=CLEAN)


def test_check_agrees_with_consistent_maps_and_names_a_displaced_keypoint():
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    pcm = SyntheticPcmSource(rig, m.positions, m.present, seed=1, noise=CLEAN).render(40)
    body = m.positions[40]
    good = check_views(rig, pcm, body)
    seen = m.present
    assert np.all(good.confidence[seen] == 1.0) and good.agreement == 1.0
    assert not good.disagree.any() and good.describe(rig.names) == ""
    moved = body.copy()
    knee = INDEX["left_knee"]
    moved[knee] += [0.0, 0.0, 0.15]  # 15 cm off where every view sees the knee
    bad = check_views(rig, pcm, moved)
    assert bad.confidence[knee] == 0.0 and bad.disagree[knee] == (1 << len(rig)) - 1
    others = seen.copy()
    others[knee] = False
    assert np.all(bad.confidence[others] == 1.0)
    assert bad.describe(rig.names) == f"left_knee ({', '.join(rig.names)})"
    # the whole body 20 cm aside: nothing agrees
    assert check_views(rig, pcm, body + [0.2, 0.0, 0.0]).agreement == 0.0
    # the check survives the markers message (graph == offline)
    run = Pipeline(rig, PipelineConfig.of(fps=60.0))
    run.markers.feedback(body)
    run.markers._last = (pcm, None)
    run.markers.feedback(moved)
    mk = run.markers.step(pcm)
    back = markers_from_message(markers_message(mk))
    assert mk.check is not None and back.check is not None
    np.testing.assert_array_equal(back.check.confidence, mk.check.confidence)
    np.testing.assert_array_equal(back.check.disagree, mk.check.disagree)
    np.testing.assert_array_equal(back.check.agree, mk.check.agree)
    np.testing.assert_array_equal(back.cameras, mk.cameras)  # the cameras confirming each marker
    assert back.support == mk.support == 1.0
    # a recording made before the agreeing cameras were carried: read, the support unknown
    msg = markers_message(mk)
    pts = np.frombuffer(msg["data"], dtype=M.CHECKED_DTYPE)
    old = np.zeros(len(pts), M.CHECKED_V1_DTYPE)
    for name in M.CHECKED_V1_DTYPE.names:
        old[name] = pts[name]
    msg = {**msg, "fields": msg["fields"][:len(M.CHECKED_V1_DTYPE.names)], "point_step": M.CHECKED_V1_DTYPE.itemsize,
           "row_step": M.CHECKED_V1_DTYPE.itemsize * len(old), "data": old.tobytes()}
    legacy = markers_from_message(msg)
    assert legacy.check is not None and legacy.check.agree is None and legacy.check.support is None
    np.testing.assert_array_equal(legacy.check.confidence, mk.check.confidence)


def test_support_counts_the_keypoints_two_cameras_hold():
    """Every view but camera 0's says nothing (its maps invalid): the views that see the body
    all agree (agreement 1), but one camera's rays do not fix a point: support 0."""
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    pcm = SyntheticPcmSource(rig, m.positions, m.present, seed=1, noise=CLEAN).render(40)
    body = m.positions[40]
    assert check_views(rig, pcm, body).support == 1.0
    valid = pcm.valid.copy()
    valid[pcm.camera != 0] = False
    alone = PcmViews(pcm.maps, pcm.image_to_map, pcm.camera, pcm.keypoints, valid, pcm.presence, pcm.stamp_ns)
    check = check_views(rig, alone, body)
    assert check.agreement == 1.0 and check.support == 0.0
    assert np.all(check.agree[m.present] == 1)


def _views_from(sources: list[SyntheticPcmSource], t: int) -> PcmViews:
    """View v of frame t from sources[v] (each view sees its own body)."""
    frames = [s.render(t) for s in sources]
    maps = np.stack([f.maps[v] for v, f in enumerate(frames)])
    return PcmViews(maps, frames[0].image_to_map, frames[0].camera, frames[0].keypoints, frames[0].valid,
                    frames[0].presence, frames[0].stamp_ns)


def test_tracker_stops_output_when_half_the_views_see_another_body():
    """From frame 100 two of the four cameras see the body 12 cm aside: the lattice search
    still finds strong markers (the other two views' peaks; the marker-weight rule would keep
    tracking), but the skeleton disagrees with half the views: uncertain within a few frame sets
    (no joint_states, empty NS/keypoints), then lost; before, tracking with full confidence."""
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    true = SyntheticPcmSource(rig, m.positions, m.present, seed=2, noise=CLEAN)
    aside = SyntheticPcmSource(rig, m.positions + np.array([0.0, 0.0, 0.12]), m.present, seed=2, noise=CLEAN)
    mixed = [true, true, aside, aside]
    tracker = Pipeline(rig, PipelineConfig.of(fps=60.0))
    topics = Topics()
    statuses, joint_states, scores = [], [], []
    for t in range(160):
        pcm = true.render(t) if t < 100 else _views_from(mixed, t)
        res = tracker.step(pcm)
        statuses.append(res.status)
        msgs = {topic: msg for topic, _, msg in result_messages(topics, res.skeleton)}
        joint_states.append(topics.joint_states in msgs)
        P, S, _ = M.cloud_keypoints(msgs[topics.keypoints])
        scores.append(S if P is not None else None)
        if t == 105:
            assert tracker.skeleton.disagreement is not None
            text = tracker.skeleton.disagreement.describe(rig.names)
            # keypoints named with the cameras that disagree (the skeleton lies between the two bodies)
            assert text.count("(") >= 3 and rig.names[3] in text, text
    assert statuses[60:100] == ["tracking"] * 40 and all(joint_states[60:100])
    assert all(np.all(s[m.present] == 1.0) for s in scores[60:100])  # confidence on NS/keypoints
    assert "tracking" not in statuses[100 + 4:]  # 3 frame sets of hysteresis, one of feedback
    assert not any(joint_states[104:]) and all(s is None for s in scores[104:])
    assert "uncertain" in statuses[100:] and "lost" in statuses[100:]
    first_lost = statuses.index("lost", 100)
    assert statuses[104:first_lost] == ["uncertain"] * (first_lost - 104)


def _blank(pcm: PcmViews, views: list[int]) -> PcmViews:
    """The PCMs with the given views' maps flat (zero): they cannot agree with anything."""
    maps = pcm.maps.copy()
    maps[views] = 0.0
    return PcmViews(maps, pcm.image_to_map, pcm.camera, pcm.keypoints, pcm.valid, pcm.presence, pcm.stamp_ns)


def test_one_bad_frame_set_does_not_flip_the_status():
    """Hysteresis: two frame sets where half the views' maps are flat (agreement 0.5, between
    check_fail_agreement and check_min_agreement), then consistent maps again: the verdict
    stays tracking throughout (the markers' own weight rule off). With it on, those two frame
    sets weigh half the track's and are not output, nor is the next one, whose markers carry
    the half-flat check of frame set 91, nor the one after: after a frame set held back, output
    resumes on the second frame set in a row that passes every rule (check_resume_frames; the
    hysteresis forgives a bad check only while the output flows). One frame set that
    every view contradicts: uncertain at once, tracking again after check_recover_frames."""
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    true = SyntheticPcmSource(rig, m.positions, m.present, seed=3, noise=CLEAN)
    aside = SyntheticPcmSource(rig, m.positions + np.array([0.0, 0.0, 0.4]), m.present, seed=3, noise=CLEAN)
    for ratio in (0.0, None):
        cfg = PipelineConfig.of(fps=60.0) if ratio is None else PipelineConfig.of(fps=60.0, check_min_weight_ratio=ratio)
        tracker = Pipeline(rig, cfg)
        agreement = []
        statuses = []
        for t in range(120):
            res = tracker.step(_blank(true.render(t), [2, 3]) if t in (90, 91) else true.render(t))
            statuses.append(res.status)
            agreement.append(res.markers.check.agreement if res.markers.check is not None else None)
        held = [] if ratio == 0.0 else [90, 91, 92, 93]
        assert [t for t in range(60, 120) if statuses[t] != "tracking"] == held, (ratio, statuses[85:])
        assert agreement[91] == agreement[92] == 0.5
    tracker = Pipeline(rig, PipelineConfig.of(fps=60.0))
    statuses = [tracker.step(aside.render(t) if t == 90 else true.render(t)).status for t in range(100)]
    # frame set 90's own markers find nothing two cameras hold (the body is 40 cm off the
    # lattice): not output; the check of its skeleton comes with frame set 91's markers
    assert statuses[60:90] == ["tracking"] * 30 and statuses[90:92] == ["uncertain"] * 2, statuses[85:]
    assert statuses[96:] == ["tracking"] * 4, statuses[85:]


def test_a_provisional_skeleton_flows_through_single_bad_checks_as_the_identified_one():
    """While a new subject's link lengths are identified its provisional skeleton is output
    (identify_output) with the same hysteresis as the identified one: the two half-flat frame
    sets of the test above are forgiven in either."""
    m = _motion()
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    true = SyntheticPcmSource(rig, m.positions, m.present, seed=3, noise=CLEAN)
    tracker = Pipeline(rig, PipelineConfig.of(fps=60.0, check_min_weight_ratio=0.0))
    statuses, provisional = [], []
    for t in range(120):
        statuses.append(tracker.step(_blank(true.render(t), [2, 3]) if t in (20, 21, 90, 91) else true.render(t)).status)
        provisional.append(tracker.skeleton.provisional)
    assert provisional[20] and provisional[22] and not any(provisional[40:])
    assert statuses[10:] == ["tracking"] * 110, statuses[:40]


def test_a_body_one_camera_holds_is_not_output():
    """From frame set 90 only camera 0's maps show the body (the other three flat): its lattice
    markers are held by one camera's rays, so that very frame set is not output (the check of
    the fed-back skeleton comes one frame set later), nor any after it, and the WARN says why."""
    _, rig, true = _walk_maps(4)
    tracker = Pipeline(rig, PipelineConfig.of(fps=60.0))
    statuses = []
    for t in range(100):
        statuses.append(tracker.step(_blank(true.render(t), [1, 2, 3]) if t >= 90 else true.render(t)).status)
        if t == 90:
            text = tracker.skeleton.warning("uncertain", rig.names)
            assert text is not None and "held by two cameras" in text, text
    assert statuses[60:90] == ["tracking"] * 30, statuses[55:]
    assert statuses[90] == "uncertain" and "tracking" not in statuses[90:], statuses[85:]


def test_verdict_reads_the_support_of_the_fed_back_skeleton():
    """Agreement 1 throughout: support below check_min_support (0.6) turns the status after
    check_uncertain_frames (3) in a row, below check_fail_support (0.35) at once; a check
    recorded without the agreeing cameras is judged by its agreement alone."""
    from vmocap_core.method.config import SkeletonConfig
    from vmocap_core.method.consistency import Verdict, ViewCheck

    cfg = SkeletonConfig()

    def verdict() -> Verdict:
        return Verdict(cfg.check_min_agreement, cfg.check_uncertain_frames, cfg.check_recover_frames,
                       cfg.check_lost_frames, cfg.check_fail_agreement, cfg.check_fail_frames,
                       cfg.check_min_support, cfg.check_fail_support)

    def check(two: int, one: int = 0) -> ViewCheck:
        """Every keypoint seen and agreed on: `two` of them by cameras 0 and 1, `one` by camera 0."""
        agree = np.zeros(25, np.uint32)
        agree[:two] = 0b11
        agree[two:two + one] = 0b01
        confidence = np.full(25, np.nan)
        confidence[:two + one] = 1.0
        return ViewCheck(confidence, np.zeros(25, np.uint32), agree)

    half = check(10, 10)
    assert half.agreement == 1.0 and half.support == 0.5
    v = verdict()
    assert [v.update(half) for _ in range(3)] == ["ok", "ok", "uncertain"]
    v = verdict()
    assert v.update(check(4, 16)) == "uncertain"  # support 0.2
    legacy = ViewCheck(half.confidence, half.disagree)
    v = verdict()
    assert legacy.support is None and [v.update(legacy) for _ in range(3)] == ["ok"] * 3


def _faded(pcm: PcmViews, factor: float) -> PcmViews:
    """The PCMs with every view's maps scaled down: the body still where it is, its maps fading."""
    return PcmViews(pcm.maps * factor, pcm.image_to_map, pcm.camera, pcm.keypoints, pcm.valid, pcm.presence, pcm.stamp_ns)


def test_fading_maps_are_not_output_and_a_stopped_camera_is_not_fading():
    """From frame set 90 to 92 every view's maps hold 0.4 of their height (a body turning over,
    the CNN losing it everywhere at once): the markers weigh ~0.4 of the track's recent median,
    below check_min_weight_ratio (0.55), so those frame sets are not output and the WARN says
    why; the first frame set after them passes and is held too (check_resume_frames: the
    second in a row is output). From 100 on camera 3's maps are flat (a
    covered camera): a quarter of the weight, tracking goes on."""
    from vmocap_core.method.consistency import WeightTrend

    _, rig, true = _walk_maps(5)
    tracker = Pipeline(rig, PipelineConfig.of(fps=60.0))
    statuses = []
    for t in range(130):
        pcm = true.render(t)
        pcm = _faded(pcm, 0.4) if 90 <= t < 93 else _blank(pcm, [3]) if t >= 100 else pcm
        statuses.append(tracker.step(pcm).status)
        if t == 90:
            text = tracker.skeleton.warning("uncertain", rig.names)
            assert text is not None and "fading" in text, text
    assert statuses[60:90] == ["tracking"] * 30, statuses[55:]
    assert statuses[90:94] == ["uncertain"] * 4 and statuses[94:] == ["tracking"] * 36, statuses[85:]
    off = Pipeline(rig, PipelineConfig.of(fps=60.0, check_min_weight_ratio=0.0))
    assert [off.step(_faded(true.render(t), 0.4) if 90 <= t < 93 else true.render(t)).status
            for t in range(95)][90:93] == ["tracking"] * 3
    trend = WeightTrend(30)
    assert trend.ratio(np.ones(25), None) is None  # no check: not judged


def test_a_body_walking_out_of_two_images_is_not_fading():
    """The weights sum the views (eq. 3): a body leaving cameras 2 and 3's images halves them
    while the maps of cameras 0 and 1 are as strong as before. Judged per view that can see
    each keypoint (Markers.inside), that is no fading; the same weights with every camera still
    looking are (0.5 of the track's, below check_min_weight_ratio), as are maps fading in the
    views left."""
    from vmocap_core.method.config import SkeletonConfig
    from vmocap_core.method.consistency import WeightTrend

    check = ViewCheck(np.ones(25), np.zeros(25, np.uint32), np.full(25, 0b1111, np.uint32))
    every, two = np.full(25, 0b1111, np.uint32), np.full(25, 0b0011, np.uint32)
    ratios = {}
    for name, inside, weights in (("left", two, 1.6), ("fading", every, 1.6), ("left, fading", two, 0.6),
                                  ("legacy", None, 1.6)):
        trend = WeightTrend(30)
        for _ in range(20):
            assert trend.ratio(np.full(25, 3.2), check, None if inside is None else every) in (None, 1.0)
        ratios[name] = trend.ratio(np.full(25, weights), check, inside)
    limit = SkeletonConfig().check_min_weight_ratio
    assert np.isclose(ratios["left"], 1.0) and np.isclose(ratios["fading"], 0.5) and np.isclose(ratios["legacy"], 0.5), ratios
    assert ratios["left, fading"] < limit < ratios["left"], ratios
    outside = np.zeros(25, np.uint32)  # no view can see a keypoint: not judged by it
    trend = WeightTrend(30)
    assert trend.ratio(np.zeros(25), check, outside) is None
    # markers another person found in the same place (contested.py) were set to 0, not faded
    trend = WeightTrend(30)
    for _ in range(20):
        trend.ratio(np.full(25, 3.2), check, every)
    weights, contested = np.full(25, 3.2), np.zeros(25, bool)
    weights[:13], contested[:13] = 0.0, True
    assert np.isclose(trend.ratio(weights, check, every, contested), 1.0)
    assert trend.ratio(weights, check, every) < limit


def test_a_view_says_nothing_of_keypoints_predicted_outside_its_image():
    """Camera 0's image is cut at the middle of the body: the keypoints right of the cut are
    outside it, and its maps place them 15 cm aside (the landmark model's guess from the rest of
    the body). The marker stage takes those keypoints from the other three views, and neither
    the markers' confirming cameras nor the check of the skeleton fed back count camera 0 for
    them; with the whole image, camera 0 disagrees there."""
    m, rig, true = _walk_maps(seed=1)
    aside = SyntheticPcmSource(rig, m.positions + [0.15, 0.0, 0.0], m.present, seed=1, noise=CLEAN)
    pcm = _views_from([aside, true, true, true], 40)
    body = m.positions[40]
    uv, _ = rig.project(body)
    cut = int(np.nanmedian(uv[0, m.present, 0]))
    cam0 = rig[0]
    narrowed = Rig([Camera(cam0.name, cam0.K, cam0.dist, cam0.R, cam0.t, cut, cam0.height), *list(rig)[1:]])
    outside = m.present & (uv[0, :, 0] > cut - 1)
    assert 3 <= outside.sum() < m.present.sum() - 3

    def run(r: Rig):
        stage = MarkerStage(r, PipelineConfig.of(fps=60.0).markers)
        stage.feedback(body)
        mk = stage.step(pcm)
        stage.feedback(body)
        return mk, stage.step(pcm).check

    mk, check = run(narrowed)
    assert check is not None and mk.cameras is not None and mk.inside is not None
    assert not (mk.inside[outside] & 1).any() and (mk.inside[m.present & ~outside] == 0b1111).all()
    assert not (mk.cameras[outside] & 1).any() and not (check.disagree[outside] & 1).any()
    assert np.all(np.linalg.norm(mk.positions[outside] - body[outside], axis=1) < 0.02)
    assert (check.disagree[m.present & ~outside] & 1).all()  # inside its image camera 0 still counts
    _, whole = run(rig)
    assert whole is not None and (whole.disagree[outside] & 1).all()


def _slid(run: Pipeline, t: int, positions: np.ndarray, agree: bool) -> Markers:
    """Lattice markers at `positions` with a check of the fed-back skeleton that every view
    agrees with (or none)."""
    seen = np.isfinite(positions).all(axis=1)
    conf = np.where(seen, 1.0 if agree else 0.0, np.nan)
    everyone = np.uint32((1 << len(run.rig)) - 1)
    check = ViewCheck(conf, np.where(agree, 0, everyone).astype(np.uint32) * np.ones(len(conf), np.uint32),
                      (everyone if agree else np.uint32(0)) * np.ones(len(conf), np.uint32))
    return Markers(int(t * 1e9 / 60), positions.copy(), seen.astype(float), "lattice", 1.0, check=check)


def test_a_track_back_from_doubt_on_another_body_is_lost_and_looks_where_the_subject_went():
    """The walk tracked from synthetic maps; then the markers slide over 12 frame sets onto a
    body 0.45 m aside (the subject walking past someone standing: the crops and the lattice
    search follow the other body's peaks) while the views disagree (uncertain), and the views
    agree with that body again. Without the path gate the track would resume "tracking" on it;
    with it the status is "lost", the diagnostics say why, and the feedback is a seed where the
    subject was heading (within 0.1 m of the walk), which crosses the feedback topic as it is:
    the detector looks there (not where the track went), and the lattice search starts over.
    The same slide onto a body where the subject was heading resumes tracking."""
    m, rig, source = _walk_maps(seed=4)
    aside = np.array([0.0, 0.45, 0.0])
    for offset, gate in ((aside, True), (aside, False), (np.zeros(3), True)):
        run = Pipeline(rig, PipelineConfig.of(fps=60.0, check_resume_max_m=0.3 if gate else 0.0))
        statuses = [run.step(source.render(t)).status for t in range(100)]
        assert statuses[-20:] == ["tracking"] * 20
        for t in range(100, 130):
            slide = offset * min((t - 99) / 12, 1.0)
            res = run.skeleton.step(_slid(run, t, m.positions[t] + slide, agree=t >= 112))
            statuses.append(res.status)
            if res.status != "tracking" and res.status != "uncertain":
                break
        if offset.any() and gate:
            assert statuses[100:112] == ["uncertain"] * 12 and statuses[-1] == "lost", statuses[100:]
            assert "m from where the subject was heading" in run.skeleton.warning("lost", rig.names)
            fb = feedback_of(res)
            seed = seed_of(fb)
            assert skeleton_of(fb) is None and seed is not None
            assert np.linalg.norm(seed - m.positions[len(statuses) - 1, INDEX["pelvis"]]) < 0.1, seed
            P, _, _ = M.cloud_keypoints(M.keypoint_cloud(res.stamp_ns, fb))
            assert np.array_equal(seed_of(P), seed)
            predictor = BodyPredictor()
            predictor.update(res.stamp_ns, P)
            assert np.array_equal(seed_of(predictor.predict(res.stamp_ns + 16_000_000)), seed)
            run.markers.feedback(P)
            assert run.markers.centres is None  # the lattice search starts over
        else:  # tracking again on the body the markers slid to
            assert statuses[100:112] == ["uncertain"] * 12 and statuses[-1] == "tracking", statuses[100:]
            assert "lost" not in statuses


def test_a_body_off_its_path_is_the_subject_when_nobody_else_is_in_view():
    """The path gate (path_gate.py) ends a track that comes back from doubt far from where the
    subject was heading: it has slid onto someone else. From frame set 100 half the views' maps
    are flat (uncertain) while the body darts 0.5 m sideways in 0.2 s (a flip, a dive); the
    views agree again at 112. When the detector's census counted nobody else in view
    (`PcmViews.others` 0) the body is the subject and the track goes on; someone else in view
    (1) or no count (-1, e.g. census off): lost, looked for where the subject was heading."""
    m = _motion()
    dart = np.clip((np.arange(len(m.positions)) - 100) / 12.0, 0.0, 1.0)  # 0 -> 1 over frame sets 100-112
    walk = np.nanmean(np.diff(m.positions[:100, INDEX["pelvis"], :2], axis=0), axis=0)
    side = np.array([-walk[1], walk[0], 0.0]) / np.linalg.norm(walk)
    positions = m.positions + 0.5 * dart[:, None, None] * side
    rig = benchmark_rig(np.nanmean(m.positions[:, 0], axis=0))
    source = SyntheticPcmSource(rig, positions, m.present, seed=4, noise=CLEAN)
    for others in (0, 1, -1):
        tracker = Pipeline(rig, PipelineConfig.of(fps=60.0))
        statuses = []
        for t in range(150):
            pcm = source.render(t)
            pcm = _blank(pcm, [2, 3]) if 100 <= t < 112 else pcm
            pcm.others = others
            statuses.append(tracker.step(pcm).status)
        assert statuses[60:100] == ["tracking"] * 40 and "uncertain" in statuses[100:112], (others, statuses[95:])
        if others == 0:
            assert "lost" not in statuses[100:] and statuses[125:] == ["tracking"] * 25, statuses[95:]
        else:
            assert "lost" in statuses[112:125], (others, statuses[95:])
