"""Image-level benchmark: a rendered body, the real CNN, the offline pipeline, 3D truth."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest
from render_helpers import CLIP, REPO, half_size_rig, needs_rendering

pytestmark = [needs_rendering, pytest.mark.cnn_figures]


@pytest.fixture(scope="module")
def rig():
    return half_size_rig()


def test_truth_reprojects_onto_the_rendered_body(rig):
    """Every truth keypoint projects inside the body's silhouette (image with the body minus
    the same scene without it), in every camera, through the lens distortion."""
    from vmocap_core.apps.render.body import load_body
    from vmocap_core.apps.render.pose import clip_joints, segment_transforms, skin
    from vmocap_core.apps.render.recording import ClipSpec, prepare_motion
    from vmocap_core.apps.render.scene import Appearance, SceneRenderer
    from vmocap_core.keypoints import KEYPOINTS

    spec = ClipSpec(CLIP, 20, 60.0, 0)
    m = prepare_motion(spec)
    body = load_body("slim")
    A, b = segment_transforms(body, clip_joints(m.positions, KEYPOINTS))
    scene = SceneRenderer(rig, body, Appearance.draw(np.random.default_rng(1)), 1)
    scene.fit_box([skin(body, A[k], b[k]) for k in (0, 19)])
    try:
        for k in (0, 19):
            with_body = scene.render(skin(body, A[k], b[k]))
            empty = [bg for bg in scene.empty_room()]
            uv, _ = rig.project(m.positions[k][m.present])
            for c in range(len(rig)):
                mask = np.abs(with_body[c].astype(int) - empty[c].astype(int)).sum(axis=2) > 0
                assert 200 < mask.sum() < mask.size // 4
                px = np.round(uv[c]).astype(int)
                near = [mask[v - 1:v + 2, u - 1:u + 2].any() for u, v in px]  # 1 px for the joint on an edge
                assert all(near), f"frame {k} camera {c}: keypoints off the body: {np.flatnonzero(~np.array(near))}"
    finally:
        scene.close()


def test_two_benches_rendering_one_clip_into_one_cache_at_once(rig, tmp_path):
    """Two processes render the same clip into the same cache at the same time (two benches
    started together): both succeed and the cached recording holds the same messages as a
    rendering alone (they shared one scratch file before: one process failed, and a mixture of
    the two, still a readable MCAP, stayed in the cache)."""
    import subprocess
    import sys

    from vmocap_core.apps.render.recording import ClipSpec, render_recording
    from vmocap_core.bag import BagReader
    from vmocap_core.cameras.rig_file import save_rig

    save_rig(rig, tmp_path / "rig.yaml")
    code = ("import sys; from pathlib import Path; from vmocap_core.cameras.rig_file import load_rig; "
            "from vmocap_core.apps.render.recording import ClipSpec, render_recording; "
            f"print(render_recording(ClipSpec(Path({str(CLIP)!r}), 30, 60.0, 3), load_rig({str(tmp_path / 'rig.yaml')!r}), "
            f"Path({str(tmp_path / 'shared')!r}), progress=False))")
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [e[-2000:] for _, e in outs]
    shared = {o.strip() for o, _ in outs}
    alone = render_recording(ClipSpec(CLIP, 30, 60.0, 3), rig, tmp_path / "alone", progress=False)

    def payloads(p):
        with BagReader(p) as r:
            return [(m.topic, bytes(m.data)) for m in r.messages(list(r.topics))]

    assert len(shared) == 1 and payloads(Path(shared.pop())) == payloads(alone)
    assert sorted(q.name for q in (tmp_path / "shared").iterdir()) == [alone.name]  # no scratch left


def test_same_seed_same_bytes(rig, tmp_path):
    from vmocap_core.apps.render.recording import ClipSpec, render_recording
    from vmocap_core.bag import BagReader

    spec = ClipSpec(CLIP, 3, 60.0, 7)
    a = render_recording(spec, rig, tmp_path / "a", progress=False)
    b = render_recording(spec, rig, tmp_path / "b", progress=False)
    assert a.name == b.name  # content-hash cache key
    assert render_recording(spec, rig, tmp_path / "a", progress=False) == a  # cache hit

    def payloads(p):
        with BagReader(p) as r:
            return [(m.topic, bytes(m.data)) for m in r.messages(list(r.topics))]

    pa, pb = payloads(a), payloads(b)
    assert len(pa) == 3 * (2 * len(rig) + 1)
    from mcap.reader import make_reader  # the reference reader sees the same channels and schemas

    with open(a, "rb") as fh:
        seen = {(ch.topic, sc.name) for sc, ch, _ in make_reader(fh).iter_messages()}
    assert ("/vmocap/truth/keypoints", "sensor_msgs/msg/PointCloud2") in seen
    assert {(f"/vmocap/{c.name}/image_raw", "sensor_msgs/msg/Image") for c in rig} <= seen
    assert {(f"/vmocap/{c.name}/camera_info", "sensor_msgs/msg/CameraInfo") for c in rig} <= seen
    assert pa == pb
    other = render_recording(ClipSpec(CLIP, 3, 60.0, 8), rig, tmp_path / "a", progress=False)
    assert payloads(other) != pa


@pytest.mark.graph_replay
def test_short_clip_offline_and_through_the_node_graph(rig, tmp_path):
    """Render, write the MCAP, run the real CNN + tracker on it offline (`vmocap process`
    path) and through the ROS 2 node graph (camera node playing the MCAP), score both."""
    from vmocap_core.apps.bench import images
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm import selfcheck

    # The graph plays the recording in lockstep (each frame set once the previous one's feedback
    # came back): every frame set is processed however fast this CPU's CNN is.
    check = selfcheck.verdict("full")
    precision = "int8" if check.int8_correct else "float"  # int8 is the default where it is right
    config = f"rot-{precision}"
    args = argparse.Namespace(frames=60, seed=0, cache=tmp_path / "cache", out=tmp_path / "out", json=True,
                              configs=[config], no_synthetic=True, graph="first", graph_rate=0.0, crop_prediction="rigid",
                              rig_file=tmp_path / "rig.yaml", tracker={"fps": 60.0})
    save_rig(rig, args.rig_file)
    args.out.mkdir()
    row = images.run_clip(CLIP, rig, args)
    for run in (config, f"graph:{config}"):
        r = row[run]
        assert r["mpjpe_mm"] is not None and np.isfinite(r["mpjpe_mm"]), (run, r)
        assert r["mpjpe_mm"] < 80.0, (run, r)
        assert r["tracked_pct"] > 90, (run, r)
        assert 0 < r["link_length_error_mm"] < 60, (run, r)
        assert 0 < r["accel_error_m_s2"] < 200, (run, r)
    # In lockstep (and with the probe matched before the first frame set) the graph runs the same
    # loop on the same frame sets as the offline run: it tracks from the same frame set, as well.
    g = row[f"graph:{config}"]
    assert g["init_frames"] == row[config]["init_frames"] and abs(g["mpjpe_mm"] - row[config]["mpjpe_mm"]) < 0.5, (row[config], g)
    assert (args.out / "walk.png").exists()
    # --offline: the same recording (cached), the whole-recording pass; the (live) graph is not run
    args.tracker = {"fps": 60.0, "offline": True}
    off = images.run_clip(CLIP, rig, args)
    assert f"graph:{config}" not in off and np.isfinite(off[config]["mpjpe_mm"]), off
    assert off[config]["accel_error_m_s2"] < row[config]["accel_error_m_s2"], (off[config], row[config])


def test_a_body_lying_face_down_is_found_again_after_every_view_lost_it(rig, tmp_path):
    """Issue 30, item 3 and its bad input "a person leaving all views and coming back lying
    down": the getup_facedown clip, tracked while the body lies face down, then every camera
    shows noise for 0.15 s (`--blackout`); the body comes back still lying, and the tracker
    outputs it as tracked again within 0.5 s, never more than 100 mm off."""
    from vmocap_core.apps.bench import images
    from vmocap_core.apps.render.recording import read_truth
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.keypoints import INDEX
    from vmocap_core.pcm import selfcheck

    precision = "int8" if selfcheck.verdict("full").int8_correct else "float"
    config = f"rot-{precision}"
    gone, back = 0.65, 0.8
    args = argparse.Namespace(frames=90, seed=0, cache=tmp_path / "cache", out=tmp_path / "out", json=True,
                              configs=[config], no_synthetic=True, graph="none", graph_rate=0.0, crop_prediction="rigid",
                              rig_file=tmp_path / "rig.yaml", tracker={"fps": 60.0}, blackout=(gone, back))
    save_rig(rig, args.rig_file)
    args.out.mkdir()
    row = images.run_clip(REPO / "vmocap_core" / "data" / "motions" / "development" / "getup_facedown.npz", rig, args)
    r = row[config]
    print({k: r.get(k) for k in ("mpjpe_mm", "tracked_pct", "false_tracking_pct", "reacquire_s", "init_frames")})
    stamps, truth = read_truth(row["recording"])
    t = (stamps - stamps[0]) * 1e-9
    assert truth[np.searchsorted(t, back), INDEX["pelvis"], 2] < 0.2  # still lying when seen again
    assert r["init_frames"] < gone * 60, r  # tracked before every view lost it
    assert r["reacquire_s"] is not None and r["reacquire_s"] <= 0.5, r
    assert r["false_tracking_pct"] == 0.0, r


def test_a_person_covered_in_one_view_is_tracked_on_and_the_view_named(rig, tmp_path):
    """Issue 30's bad input "a person covered in one view for a second": a grey panel stands
    between cam2 and the walking body for 1.2 s (`--cover`). Offline and through the node graph
    the others go on tracking it (no frame set held back, none over 100 mm off), and the graph's
    /diagnostics WARN names the covered camera."""
    from vmocap_core.apps.bench import images
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm import selfcheck

    precision = "int8" if selfcheck.verdict("full").int8_correct else "float"
    config = f"rot-{precision}"
    args = argparse.Namespace(frames=150, seed=0, cache=tmp_path / "cache", out=tmp_path / "out", json=True,
                              configs=[config], no_synthetic=True, graph="first", graph_rate=0.0, crop_prediction="rigid",
                              rig_file=tmp_path / "rig.yaml", tracker={"fps": 60.0}, cover=("cam2", "0.8", "2.0"))
    save_rig(rig, args.rig_file)
    args.out.mkdir()
    row = images.run_clip(CLIP, rig, args)
    for run in (config, f"graph:{config}"):
        r = row[run]
        print(run, {k: r.get(k) for k in ("mpjpe_mm", "tracked_pct", "false_tracking_pct", "init_frames", "covered")})
        assert r["init_frames"] < 0.8 * 60, (run, r)  # tracked before the panel came
        c = r["covered"]
        assert c["camera"] == "cam2" and c["frames"] == 72, (run, c)
        assert c["tracked_pct"] >= 95.0 and c["over_limit"] == 0, (run, c)
        assert c["mpjpe_mm"] < 1.5 * r["mpjpe_mm"], (run, r)
    said = [w for w in row[f"graph:{config}"]["warnings"] if "cam2" in w]
    assert said and all("cam0" not in w and "cam1" not in w and "cam3" not in w for w in said), \
        row[f"graph:{config}"]["warnings"]


def test_detector_finds_a_small_person_in_every_view(tmp_path):
    """punch at 1024x768: the person is ~45 px tall in the detector's 224 px letterbox, and the
    whole-image pass misses views (punch and run never initialized before the zoomed tiles).
    BlazePosePcm's detector crops must cover all 4 cameras and triangulate every core
    keypoint near the truth on the very first frame set."""
    from vmocap_core.apps.render.recording import ClipSpec, read_truth, render_recording
    from vmocap_core.bag import BagReader
    from vmocap_core.bag import messages as M
    from vmocap_core.cameras.rig_file import load_rig
    from vmocap_core.graph_config import Topics
    from vmocap_core.keypoints import INDEX
    from vmocap_core.method.config import MarkersConfig
    from vmocap_core.method.init import triangulated_markers
    from vmocap_core.method.init_report import CORE
    from vmocap_core.pcm.pipeline import BlazePosePcm

    full = load_rig(REPO / "config" / "benchmark_rig.yaml")
    rec = render_recording(ClipSpec(CLIP.with_name("punch.npz"), 4, 60.0, 0), full, tmp_path, progress=False)
    _, truth = read_truth(rec)
    want = {Topics().image(c.name): i for i, c in enumerate(full)}
    sets: list[list] = [[None] * len(full) for _ in truth]
    with BagReader(rec) as r:
        for k, m in enumerate(r.messages(list(want))):
            sets[k // len(full)][want[m.topic]] = M.image_array(m.decode()).copy()
    pcm = BlazePosePcm(full, rotation="all", precision="int8")
    counts = [sum(len(d) > 0 for d in pcm.detector.detect(images)) for images in sets]
    t = int(np.argmin(counts))  # the frame set where the whole-image pass finds the fewest views
    assert counts[t] <= 2, counts  # the case this test is about (rendering is deterministic)
    images, whole = sets[t], counts[t]
    pv = pcm.infer(images)
    print(f"whole-image detector finds the person in {whole}/4 views (frame set {t}); with tiles: {sorted(set(pv.camera.tolist()))}")
    assert sorted(set(pv.camera.tolist())) == [0, 1, 2, 3]
    mk = triangulated_markers(full, pv.sanitized(), MarkersConfig())
    core = [INDEX[n] for n in CORE]
    err = np.linalg.norm(mk.positions[core] - truth[t][core], axis=1)
    print(f"core keypoints triangulated from the detector crops: {np.isfinite(err).sum()}/{len(core)}, "
          f"median error {np.nanmedian(err) * 1000:.0f} mm")
    assert np.isfinite(err).all(), mk.residual_px[core]
    assert np.median(err) < 0.06


def test_leave_one_out_learns_each_clips_landmarks_from_the_others(rig, tmp_path):
    """`--leave-one-out`: each clip's landmark model comes from the other clips' lattice
    markers only, loads as a tracker's model, and is centimetres, not metres or nothing."""
    from vmocap_core.apps.bench import images
    from vmocap_core.method.landmarks import load_landmarks

    clips = [CLIP, CLIP.with_name("punch.npz")]
    args = argparse.Namespace(frames=60, seed=0, cache=tmp_path / "cache", out=tmp_path / "out", json=True,
                              tracker={"fps": 60.0})
    args.out.mkdir()
    models = images.leave_one_out_models(clips, rig, args)
    assert set(models) == {"walk", "punch"}
    for held, path in models.items():
        model = load_landmarks(str(path))
        assert model is not None and held not in model.note and ({"walk", "punch"} - {held}).pop() in model.note
        assert np.isfinite(model.offsets).all() and 0.005 < np.abs(model.offsets).max() < 0.1, model.offsets


def test_shader_programs_are_compiled_once(rig):
    """Rendering frame after frame compiles no new shader program: pyrender's own cache missed
    on every render under OSMesa and kept ~13 MB per frame set, so a clip's length was bounded
    by RAM."""
    from vmocap_core.apps.render.body import load_body
    from vmocap_core.apps.render.pose import clip_joints, segment_transforms, skin
    from vmocap_core.apps.render.recording import ClipSpec, prepare_motion
    from vmocap_core.apps.render.scene import Appearance, SceneRenderer
    from vmocap_core.keypoints import KEYPOINTS

    m = prepare_motion(ClipSpec(CLIP, 4, 60.0, 0))
    body = load_body("average")
    A, b = segment_transforms(body, clip_joints(m.positions, KEYPOINTS))
    scene = SceneRenderer(rig, body, Appearance.draw(np.random.default_rng(2)), 2)
    scene.fit_box(skin(body, A[k], b[k]) for k in range(4))  # a generator: one posed body at a time
    try:
        scene.render(skin(body, A[0], b[0]))
        compiled = scene._renderer()._renderer._program_cache.inner._program_cache
        first = len(compiled)
        for k in range(1, 4):
            scene.render(skin(body, A[k], b[k]))
        assert first > 0 and len(compiled) == first, (first, len(compiled))
    finally:
        scene.close()


def test_body_variants_and_motion_groups():
    """Variant 0 is the clip's own shape and name; variant 1 another shape, look and cache
    entry. Groups come from the keypoints: upright, upside down, low to the ground."""
    from vmocap_core.apps.bench import images
    from vmocap_core.apps.bench.motion_groups import motion_group
    from vmocap_core.apps.render.recording import ClipSpec, cache_key
    from vmocap_core.cameras.rig_file import load_rig
    from vmocap_core.motion import load_motion

    a, b = ClipSpec(CLIP, 3, 60.0, 0), ClipSpec(CLIP, 3, 60.0, 0, variant=1)
    assert a.label() == "walk" and b.label() == f"walk-{b.shape()}" and a.shape() != b.shape()
    assert a.rng_seed() != b.rng_seed()
    full = load_rig(REPO / "config" / "benchmark_rig.yaml")
    assert cache_key(a, full) != cache_key(b, full)
    files = {p.stem: p for p in images.clip_files([Path("all")])}
    assert len(files) == 15 and {"backflip", "roll", "walk", "getup_faceup"} <= set(files)
    want = {"walk": "regular", "spin": "regular", "cartwheel": "inverted", "backflip": "inverted",
            "crawl": "floor", "roll": "floor", "getup_faceup": "floor"}
    assert {n: motion_group(load_motion(files[n]).positions) for n in want} == want


def test_false_tracking_counts_tracked_frames_over_100_mm():
    """false_tracking_pct: of the frames reported `tracking` (keypoints out), the share whose
    MPJPE is over 100 mm; frames identifying, uncertain or lost carry no keypoints and do not count."""
    from vmocap_core.apps.bench import images

    status = ["identifying", "tracking", "tracking", "uncertain", "tracking", "lost", "tracking", "tracking"]
    error_mm = np.array([500.0, 40.0, 150.0, 300.0, 99.0, 800.0, 101.0, 20.0])
    tracked = np.array([s == "tracking" for s in status])
    assert images.false_tracking(tracked, error_mm) == {"tracked_frames": 5, "false_tracked_frames": 2,
                                                        "false_tracking_pct": 40.0}
    # the same series through score(): truth keypoints, estimates off by error_mm along x, none when not tracking
    rng = np.random.default_rng(0)
    truth = np.full((len(status), 25, 3), np.nan)
    truth[:, :14] = rng.normal(0.0, 0.5, (len(status), 14, 3))
    est = truth + np.array([1.0, 0.0, 0.0]) * error_mm[:, None, None] / 1000
    est[~tracked] = np.nan
    r = images.score(est, truth)
    assert (r["tracked_frames"], r["false_tracked_frames"]) == (5, 2) and r["false_tracking_pct"] == pytest.approx(40.0)
    # tracked_pct from the first tracked frame (5 of 7), output_pct of all frames (5 of 8)
    assert r["tracked_pct"] == pytest.approx(100 * 5 / 7) and r["output_pct"] == pytest.approx(100 * 5 / 8)
    none = images.score(np.full_like(est, np.nan), truth)
    assert none["false_tracking_pct"] is None and none["tracked_frames"] == 0
    rows = [{"c": r}, {"c": {**none, "n": 0}}]
    assert images._pool_false_tracking(rows, "c") == pytest.approx(40.0)


@pytest.mark.graph_replay
def test_second_person_walks_through_the_subject_stays_the_subject(rig, tmp_path):
    """Issue 32, item 1, with the default single-subject tracker: a second person (another body,
    smaller, other clothes) enters, crosses in front of the subject from cam1 and leaves. The
    output keeps following the subject (no frame nearer the other person, no ghost, no gap),
    offline and through the node graph, and its MPJPE stays within 10 % of the same clip
    rendered alone; the detector counts the other person in view, at initialization and while
    tracking, and vmocap_pcm's /diagnostics says so."""
    import json

    from vmocap_core.apps.bench import people
    from vmocap_core.apps.render.recording import ClipSpec, read_truth, render_recording
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm import selfcheck
    from vmocap_core.pcm.pipeline import BlazePosePcm

    precision = "int8" if selfcheck.verdict("full").int8_correct else "float"
    config = f"rot-{precision}"
    args = argparse.Namespace(people=2, clips=None, frames=150, seed=0, cache=tmp_path / "cache", out=tmp_path / "out",
                              json=True, configs=[config], graph="first", graph_rate=0.0, rig_file=tmp_path / "rig.yaml",
                              tracker={"fps": 60.0})
    args.out.mkdir()
    save_rig(rig, args.rig_file)
    assert people.run(args, rig) == 0
    result = json.loads((args.out / "people.json").read_text())
    row = result["runs"][config]
    print(json.dumps({k: row[k] for k in ("alone", "group", "mpjpe_ratio")}, indent=None)[:1500])
    rec = Path(result["recording"])
    truths = np.stack([read_truth(rec, people_topic)[1] for people_topic in ("/vmocap/truth/keypoints",
                                                                             "/vmocap/truth/person1/keypoints")])
    # the walker passes in front of the subject in cam1 (nearer the camera, pelvises in one image column)
    pel = truths[:, :, 0]
    uv, _ = rig.project(pel)
    depth = np.linalg.norm(pel - rig[1].center, axis=-1)
    crossing = (np.abs(uv[1, 0, :, 0] - uv[1, 1, :, 0]) < 10) & (depth[1] < depth[0])
    assert crossing.any() and np.flatnonzero(crossing)[0] > row["group"]["init_frames"]
    assert result["persons"][1]["present_pct"] > 80
    g, a = row["group"], row["alone"]
    assert a["mpjpe_mm"] is not None and g["mpjpe_mm"] is not None, row
    assert g["swap_frames"] == 0 and g["identity_switches"] == 0 and g["ghost_frames"] == 0, g
    assert g["missed_pct"] < 2.0 and g["tracked_pct"] > 95, g
    assert row["mpjpe_ratio"] <= people.RATIO_TARGET, row
    gr = row["graph"]  # its first frame sets may come out before this test's subscriber matched: not init_frames
    assert gr["swap_frames"] == 0 and gr["identity_switches"] == 0 and gr["ghost_frames"] == 0, gr
    assert gr["missed_pct"] < 2.0 and gr["mpjpe_mm"] <= people.RATIO_TARGET * a["mpjpe_mm"], gr
    assert gr["others_in_view_max"] >= 1, gr
    # others in view (what vmocap_pcm reports): none beside the subject alone; around the crossing the
    # detector's initialization run and, while tracking, its census (one camera per frame set) find the walker
    first = int(np.flatnonzero(crossing)[0])
    pcm = BlazePosePcm(rig, rotation="all", precision=precision, census_every=1)
    pcm.infer(_frame_images(render_recording(ClipSpec(CLIP, 150, 60.0, 0), rig, args.cache), rig, first))
    assert pcm.others_in_view.tolist() == [0] * len(rig)
    at_init, census = 0, 0
    for frame in (first - 10, first, first + 10):
        images = _frame_images(rec, rig, frame)
        pcm.infer(images)
        at_init += int(pcm.others_in_view.sum())
        pcm.others_in_view[:] = 0
        for _ in range(len(rig)):
            pcm.infer(images, keypoints=truths[0, frame])
        census += int(pcm.others_in_view.sum())
    assert at_init >= 2 and census >= 2, (at_init, census)


def _frame_images(rec, rig, frame):
    """The cameras' images of one frame set of a rendered recording."""
    from vmocap_core.bag import BagReader
    from vmocap_core.bag import messages as M

    with BagReader(rec) as r:
        return [M.image_array(m.decode()) for k, m in enumerate(r.messages([f"/vmocap/{c.name}/image_raw" for c in rig]))
                if frame * len(rig) <= k < (frame + 1) * len(rig)]


def test_the_subject_passing_shoulder_to_shoulder_stays_the_subject(rig, tmp_path):
    """Issue 32, item 1, "stands beside them": a second person (0.93x, other clothes) walks in
    and stops 0.4 m from the line the subject walks along (`--scene beside`), so the subject
    passes them shoulder to shoulder. The subject's crops hold both bodies and the landmark
    model's maps slide onto the other one; the check says uncertain, and a track that comes
    back from doubt (or is lost) off the subject's path looks for the subject where it was
    heading (method/path_gate.py). Before, the output followed the other person for 44 of
    240 frame sets (36 % false tracking); with the AVX2-only class's 7-bit kernels for 46,
    until the path points confirmed just before the doubt were dropped (they lean on the
    other body) and only the horizontal place counted."""
    import json

    from vmocap_core.apps.bench import people
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.pcm import selfcheck

    precision = "int8" if selfcheck.verdict("full").int8_correct else "float"
    config = f"rot-{precision}"
    args = argparse.Namespace(people=2, clips=None, frames=240, seed=0, cache=tmp_path / "cache", out=tmp_path / "out",
                              json=True, configs=[config], graph="none", graph_rate=0.0, rig_file=tmp_path / "rig.yaml",
                              tracker={"fps": 60.0}, scene="beside")
    args.out.mkdir()
    save_rig(rig, args.rig_file)
    people.run(args, rig)
    result = json.loads((args.out / "people.json").read_text())
    g = result["runs"][config]["group"]
    print(json.dumps(g)[:800])
    assert g["swap_frames"] == 0 and g["identity_switches"] == 0, g
    assert g["false_tracking_pct"] < 5.0 and g["tracked_pct"] > 70, g
    # vmocap_pcm's census of others in view, in its low-priority thread as in the graph: the person
    # standing there (from 1.2 s on) is counted while the subject walks past them (it was 0 with
    # one look every 120 frame sets in the frame set's own thread)
    from vmocap_core.apps.render.recording import read_truth
    from vmocap_core.keypoints import INDEX
    from vmocap_core.pcm.pipeline import BlazePosePcm

    rec = Path(result["recording"])
    subject = read_truth(rec, "/vmocap/truth/keypoints")[1][:, INDEX["pelvis"]]
    pcm = BlazePosePcm(rig, rotation="all", precision=precision, census_every=1, census_background=True)
    counted = []
    try:
        for frame in range(90, 240, 20):
            images = _frame_images(rec, rig, frame)
            for _ in range(len(rig)):
                pcm.census.offer(images, subject[frame])
                assert pcm.census.wait(60), "the census look did not finish"
                counted.append(int(pcm.others_in_view.max()))  # as the diagnostics say it
    finally:
        pcm.close()
    print(f"others in view after each look: {counted}")
    assert pcm.census.error == "" and pcm.census.looks == len(counted), (pcm.census.error, pcm.census.looks)
    assert max(counted) >= 1 and np.mean(np.array(counted) > 0) > 0.3, counted


def test_a_person_standing_beside_from_the_start(rig, tmp_path):
    """A second person (larger, other clothes) stands beside the subject from the first frame,
    behind it from cam0: the tracker initializes as soon as with the subject alone (the
    detector crops of every camera on one person, pcm.choice) and stays on that person."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.process import process_bag
    from vmocap_core.apps.render.group import GroupSpec, Walker, render_group, truth_topic
    from vmocap_core.apps.render.recording import ClipSpec, read_truth
    from vmocap_core.pcm import selfcheck

    precision = "int8" if selfcheck.verdict("full").int8_correct else "float"
    frames = 100
    spec = GroupSpec(ClipSpec(CLIP, frames, 60.0, 0), (Walker(ClipSpec(CLIP, frames, 60.0, 0, 1), ((0.0, -1.2, -1.2),), 1.06),))
    rec = render_group(spec, rig, tmp_path / "cache", progress=False)
    stamps, _ = read_truth(rec)
    truths = np.stack([read_truth(rec, truth_topic(k))[1] for k in range(2)])
    assert np.allclose(truths[1, :, 0, :2], [-1.2, -1.2])  # standing there (walking in place)
    out = tmp_path / "out.mcap"
    process_bag(rec, out, rig, config={"fps": 60.0}, progress=False, provider=images._Provider(rig, "all", precision),
                overwrite=True)
    est = images.read_estimates(out, stamps)
    d = np.stack([images.frame_mpjpe(est, g) for g in truths])
    tracked = np.flatnonzero(np.isfinite(d[0]))
    assert tracked.size and tracked[0] <= 40, tracked[:3]  # 33 alone
    followed = int(np.argmin(d[:, tracked[0]]))
    f = people.identity_figures(est, truths[[followed, 1 - followed]], np.ones(len(stamps), bool))
    assert f["swap_frames"] == 0 and f["identity_switches"] == 0 and f["ghost_frames"] == 0, f
    assert f["missed_pct"] < 2.0, f
    assert np.nanmean(d[followed]) < 60.0, np.nanmean(d[followed])


def test_reversed_and_mirrored_motions(tmp_path):
    """`--transform`: a clip played backwards, and reflected with left and right swapped, as
    motions of their own (STEM_reversed.npz, STEM_mirrored.npz); a file that is no clip is refused."""
    from vmocap_core.apps.bench.motion_groups import motion_group
    from vmocap_core.errors import MotionFileError
    from vmocap_core.keypoints import INDEX
    from vmocap_core.motion import load_motion, transformed

    clip = REPO / "vmocap_core" / "data" / "motions" / "cartwheel.npz"
    m = load_motion(clip)
    back = load_motion(transformed(clip, "reversed", tmp_path))
    assert back.name == "cartwheel_reversed" and back.fps == m.fps
    np.testing.assert_array_equal(back.positions, m.positions[::-1])
    mirror = load_motion(transformed(clip, "mirrored", tmp_path))
    left, right = INDEX["left_wrist"], INDEX["right_wrist"]
    np.testing.assert_allclose(mirror.positions[:, left], m.positions[:, right] * [1, -1, 1])
    np.testing.assert_allclose(mirror.positions[:, INDEX["pelvis"]], m.positions[:, INDEX["pelvis"]] * [1, -1, 1])
    assert motion_group(mirror.positions) == motion_group(back.positions) == motion_group(m.positions) == "inverted"
    (tmp_path / "bad.npz").write_bytes(b"no clip")
    with pytest.raises(MotionFileError):
        transformed(tmp_path / "bad.npz", "mirrored", tmp_path)
