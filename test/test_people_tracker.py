"""Several people (issue 32, item 2): the multi-person tracker over the real CNN, its REP-155
outputs, and the scoring of everyone against exact truth."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from render_helpers import CLIP, half_size_rig, needs_rendering

from vmocap_core.keypoints import INDEX
from vmocap_core.pcm.detector import Detection

rendering = needs_rendering
pytestmark = pytest.mark.cnn_figures


@pytest.fixture(scope="module")
def rig():
    return half_size_rig()


FRAMES = 180  # 3 s at 60 Hz: the walker crosses the room in front of the subject


@pytest.fixture(scope="module")
def scene(rig, tmp_path_factory):
    """The two-person recording (the subject walking on the spot, a smaller body in other
    clothes crossing in front of it), its stamps and both truths (2, T, 25, 3)."""
    from vmocap_core.apps.bench import people
    from vmocap_core.apps.render.group import GroupSpec, Walker, render_group, truth_topic
    from vmocap_core.apps.render.recording import ClipSpec, read_truth

    walker = Walker(ClipSpec(CLIP, FRAMES, 60.0, 0, 1), people.walker_paths(2, FRAMES / 60.0)[0], 0.93)
    rec = render_group(GroupSpec(ClipSpec(CLIP, FRAMES, 60.0, 0), (walker,)), rig,
                       tmp_path_factory.mktemp("people") / "cache", progress=False)
    stamps, _ = read_truth(rec)
    return rec, stamps, np.stack([read_truth(rec, truth_topic(k))[1] for k in range(2)])


def _precision() -> str:
    from vmocap_core.pcm import selfcheck

    return "int8" if selfcheck.verdict("full").int8_correct else "float"


def _frame_sets(rec, rig):
    """(frame index, [image per rig camera]) of a rendered recording's raw images."""
    from vmocap_core.bag import BagReader
    from vmocap_core.bag import messages as M

    with BagReader(rec) as r:
        frame: list = []
        for k, m in enumerate(r.messages([f"/vmocap/{c.name}/image_raw" for c in rig])):
            frame.append(M.image_array(m.decode()))
            if len(frame) == len(rig):
                yield k // len(rig), frame
                frame = []


def _detection(rig, camera: int, pelvis: np.ndarray) -> Detection:
    uv, _ = rig.project(np.stack([pelvis, pelvis + [0.0, 0.0, 0.9], pelvis + [0.0, 0.0, 0.5]]))
    hip, head, shoulders = uv[camera]
    return Detection(0.9, np.r_[hip - 40, hip + 40], np.stack([hip, head, shoulders, head]))


def test_detections_of_tracked_people_are_theirs(rig):
    """A detection whose hip a tracked pelvis projects onto is that person's; one of someone
    standing 1.5 m away is left for a new person."""
    from vmocap_core.method.people_search import explained

    tracked, other = np.array([0.0, 0.0, 1.0]), np.array([1.5, 0.0, 1.0])
    found = [[_detection(rig, c, tracked), _detection(rig, c, other)] for c in range(len(rig))]
    left = explained(rig, found, tracked[None])
    assert [len(d) for d in left] == [1] * len(rig)
    assert all(np.allclose(d[0].keypoints[0], found[c][1].keypoints[0]) for c, d in enumerate(left))
    assert [len(d) for d in explained(rig, found, np.zeros((0, 3)))] == [2] * len(rig)


def test_tracked_bodies_are_hidden_from_the_detector(rig):
    """The search for others greys out each tracked body's silhouette and leaves the rest of
    the image, and the input images, as they were: a person standing 0.45 m beside it (in
    its box from most cameras) stays in view for the detector."""
    from vmocap_core.method.people_search import hidden

    images = [np.full((c.height, c.width, 3), 30, np.uint8) for c in rig]
    body = np.full((25, 3), np.nan)
    body[INDEX["pelvis"]], body[INDEX["neck"]] = [0.0, 0.0, 1.0], [0.0, 0.0, 1.5]
    body[INDEX["left_wrist"]], body[INDEX["right_wrist"]] = [0.0, 0.6, 1.4], [0.0, -0.6, 1.4]  # arms out: a wide box
    out = hidden(rig, images + [], body[None])
    uv, _ = rig.project(np.array([body[INDEX["pelvis"]], [0.0, 0.45, 1.0]]))
    for c, (im, o) in enumerate(zip(images, out)):
        assert (im == 30).all()  # the caller's images are not written to
        (u, v), (u2, v2) = np.round(uv[c]).astype(int)
        assert (o[v, u] == 127).all() and (o[v2, u2] == 30).all() and (o == 30).any()


def test_the_detector_glances_between_searches_for_newcomers(rig):
    """While a slot is free, the detector glances at the whole images every glance_every_s
    (0.2 s) between the full searches for newcomers (every detect_every_s, 0.5 s): someone
    walking in waits for the next glance, not for the next full search. A glance is the
    whole images only (no closer or turned look)."""
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_look import PeopleLook
    from vmocap_core.pcm.pipeline import BlazePosePcm

    pcm = BlazePosePcm(rig, rotation="all", threads=2, precision=_precision())
    looks: dict[int, tuple[bool, bool]] = {}
    detect, frame = pcm.detect_people, [0]

    def spy(images, turned=True, closer=True):
        looks.setdefault(frame[0], (turned, closer))
        return detect(images, turned, closer)

    pcm.detect_people = spy
    look = PeopleLook(rig, pcm, PeopleConfig(max_people=2))
    empty_room = [np.zeros((c.height, c.width, 3), np.uint8) for c in rig]
    for t in range(61):  # 1 s at 60 Hz
        frame[0] = t
        look.step(empty_room, t * 16_666_667)
    assert sorted(looks) == [0, 12, 24, 30, 42, 54, 60]
    assert all(looks[t] == (False, False) for t in (12, 24, 42, 54)) and looks[0] == (True, True)


def test_a_newly_tracked_person_makes_the_next_search_look_closer(rig):
    """The detector, a one-person model, draws the most prominent person of an image and can
    miss a small one beside them; once that person is tracked they are greyed out for the
    search. Someone's first skeleton brings a search for newcomers in the next frame set, not
    up to detect_every_s later, and it looks closer in every camera; the next ones, with nobody
    new, come every detect_every_s from there and do not (only every closer_every-th)."""
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_look import PeopleLook
    from vmocap_core.method.skeleton import Skeleton
    from vmocap_core.pcm.pipeline import BlazePosePcm

    pcm = BlazePosePcm(rig, rotation="all", threads=2, precision=_precision())
    looks: dict[int, bool] = {}
    detect, frame = pcm.detect_people, [0]

    def spy(images, turned=True, closer=True):
        looks.setdefault(frame[0], closer)
        return detect(images, turned, closer)

    pcm.detect_people = spy
    look = PeopleLook(rig, pcm, PeopleConfig(max_people=3, glance_every_s=10.0))
    sk = Skeleton()
    body = sk.keypoint_positions(sk.neutral())
    body = body - body[INDEX["pelvis"]] + [0.0, 0.0, 1.0]
    empty_room = [np.zeros((c.height, c.width, 3), np.uint8) for c in rig]
    period = 16_666_667
    for t in range(91):  # 1.5 s at 60 Hz: newcomer searches at 0, 10 (someone newly tracked), 40 and 70
        frame[0] = t
        if t == 10:  # someone found (as by the first search) and tracked from here on
            look.feedback(look._new_seat(body[INDEX["pelvis"]], t * period).number, t * period, body)
        elif t > 10:
            look.feedback(0, (t - 1) * period, body)
        look.step(empty_room, t * period)
    assert sorted(looks) == [0, 10, 40, 70]
    assert looks[0] and looks[10] and not looks[40] and not looks[70]


def test_people_outputs_give_each_body_its_own_id():
    """Two people: two different ids in /humans/bodies/tracked while both track, each with
    its urdf, joint_states and keypoints; a person the tracker ends leaves the list at once
    and their topics close RETIRE_S later."""
    from vmocap_core.method.skeleton import Skeleton
    from vmocap_core.outputs.hri import TRACKED
    from vmocap_core.outputs.people import PeopleOutputs, keypoints_topic

    sk = Skeleton()
    q = np.zeros(40)

    def person(number: int, status: str):
        result = SimpleNamespace(stamp_ns=0, status=status, q=q, keypoints=np.zeros((25, 3)),
                                 confidence=np.ones(25), dims=sk.dims)
        return SimpleNamespace(number=number, status=status, last=SimpleNamespace(skeleton=result))

    out = PeopleOutputs(seed=3, retire_s=1.0)
    ids_seen = []
    for k in range(3):
        t = int(k * 1e8)
        frame = SimpleNamespace(stamp_ns=t, people=[person(0, "tracking"), person(1, "tracking")], ended=[])
        for p in frame.people:
            p.last.skeleton.stamp_ns = t
        f = out.step(frame)
        ids = [m[2]["ids"] for m in f.messages if m[0] == TRACKED]
        assert len(ids) == 1 and len(ids[0]) == 2 and ids[0][0] != ids[0][1]
        ids_seen.append(ids[0])
        topics = {m[0] for m in f.messages}
        assert all(keypoints_topic("/vmocap", i) in topics and f"/humans/bodies/{i}/joint_states" in topics for i in ids[0])
        if k == 0:
            assert {c.topic for c in f.opened} >= {f"/humans/bodies/{i}/urdf" for i in ids[0]}
    assert ids_seen[0] == ids_seen[1] == ids_seen[2]
    gone = ids_seen[0][1]
    f = out.step(SimpleNamespace(stamp_ns=int(3e8), people=[person(0, "tracking")], ended=[1]))
    assert [m[2]["ids"] for m in f.messages if m[0] == TRACKED] == [[ids_seen[0][0]]]
    assert not f.closed
    f = out.step(SimpleNamespace(stamp_ns=int(1.5e9), people=[person(0, "tracking")], ended=[]))
    assert set(f.closed) == {f"/humans/bodies/{gone}/urdf", f"/humans/bodies/{gone}/joint_states",
                             keypoints_topic("/vmocap", gone)}


def test_time_from_each_entry_to_a_body():
    """The benchmark's re-entry figure: per entry into view (the first, and each after an
    absence of at least the gap), the seconds to the person's first body while present; a
    flicker shorter than the gap is no new entry; a stretch with no body is None."""
    from vmocap_core.apps.bench.people import RATE_HZ, entry_delays

    present = np.zeros(300, bool)
    present[10:100] = present[103:150] = present[200:260] = True  # out 3 frames (a flicker), then 50
    body = np.zeros(300, bool)
    body[40:150] = True  # a body 30 frames after the first entry, none after the re-entry
    assert entry_delays(present, body, 15) == [30 / RATE_HZ, None]
    body[230:260] = True
    assert entry_delays(present, body, 15) == [30 / RATE_HZ, 30 / RATE_HZ]
    assert entry_delays(present, body, 2) == [30 / RATE_HZ, 0.0, 30 / RATE_HZ]
    assert entry_delays(np.zeros(5, bool), body[:5], 2) == []


def test_the_wait_for_a_first_body_counts_as_time_without_one():
    """`missed_pct` counts from a person's first body on; `without_body_pct` over all their time
    in view, so a person found late is not scored as never missed."""
    from vmocap_core.apps.bench.people import people_figures

    T = 100
    truths = np.zeros((1, T, 25, 3))
    truths[0, :, :, 0] = np.linspace(0.0, 1.0, 25)  # a fixed body
    present = np.ones((1, T), bool)
    body = truths[0].copy()
    body[:40] = np.nan  # the first body at frame 40, then none at 90-99
    body[90:] = np.nan
    p = people_figures({"a": body}, truths, present)["persons"][0]
    assert p["missed_pct"] == 100 * 10 / 60 and p["without_body_pct"] == 100 * 50 / 100
    assert people_figures({}, truths, present)["persons"][0]["without_body_pct"] == 100.0


def test_a_new_id_after_a_re_entry_is_no_identity_switch():
    """REP-155: a person who left is ended and comes back under a new id; the benchmark counts
    that apart (`reentry_new_ids`), and an id change while they stay in view as a switch."""
    from vmocap_core.apps.bench.people import entries, identity_switches

    present = np.zeros(300, bool)
    present[10:100] = present[103:150] = present[200:260] = True  # a flicker, then out 50 frames
    starts = entries(present, 15)
    assert starts.tolist() == [10, 200]
    frames = np.r_[40:150, 230:260]
    ids = np.where(frames < 200, 0, 1)
    assert identity_switches(ids, frames, starts) == (0, 1)
    ids[frames >= 120] += 2  # another id in view (frame 120), then the new one after the re-entry
    assert identity_switches(ids, frames, starts) == (1, 1)
    assert identity_switches(np.zeros(0, int), np.zeros(0, int), starts) == (0, 0)


def test_the_walkers_paths_of_each_scene():
    """`--scene cross`: person 1 crosses the room at y = 0.9; `--scene beside`: it walks in
    and stops beside the subject's line, BESIDE_M away, until the end; `--scene facing`: it
    walks in along that line and stops on it facing the subject (`--scene hug`: nearer, at
    HUG_X); person 2 is the same in cross and beside; an unknown scene is an error."""
    from vmocap_core.apps.bench.people import BESIDE_M, FACING_X, HUG_X, walker_paths
    from vmocap_core.apps.render.group import TURN_RAD_S, Walker
    from vmocap_core.apps.render.recording import ClipSpec
    from vmocap_core.errors import VmocapError

    cross, beside = walker_paths(3, 8.0), walker_paths(3, 8.0, "beside")
    assert cross[0][0][1:] == (-4.2, 0.9) and cross[0][-1][1:] == (4.2, 0.9)
    assert beside[0][-1] == (8.0, 0.0, BESIDE_M) and beside[0][-2][1:] == (0.0, BESIDE_M)
    assert all(abs(y - BESIDE_M) < 1e-12 for _, _, y in beside[0]) and beside[1] == cross[1]
    # facing: along the subject's line (y = 0) from beyond the room to FACING_X, facing -x (the subject)
    facing = walker_paths(2, 4.0, "facing")[0]
    assert facing[0][1:] == (4.2, 0.0) and facing[-1] == (4.0, FACING_X, 0.0)
    assert walker_paths(2, 4.0, "hug")[0] == tuple((t, HUG_X if x == FACING_X else x, y) for t, x, y in facing)
    heading = Walker(ClipSpec(CLIP, 240, 60.0, 0, 1), facing)._heading(np.arange(240) / 60.0, np.array(facing))
    assert np.allclose(np.abs(heading), np.pi)
    with pytest.raises(VmocapError, match="scene"):
        walker_paths(2, 4.0, "waltz")
    # person 2 stops beside the subject and walks out the way it came: it turns on the spot at
    # TURN_RAD_S over 0.8 s within its stop, not in one frame; a walker that does not stop to
    # turn has the cache key it had
    t = np.arange(480) / 60.0
    back = Walker(ClipSpec(CLIP, 480, 60.0, 0, 2), cross[1])
    heading = back._heading(t, np.array(cross[1]))
    step = np.abs(np.angle(np.exp(1j * np.diff(heading))))
    assert step.max() <= TURN_RAD_S / 60.0 + 1e-9 and back.turns() and not Walker(ClipSpec(CLIP, 240, 60.0, 0, 1), facing).turns()
    turning = np.flatnonzero(step > 1e-9) / 60.0
    assert 2.0 <= turning.min() and turning[turning < 4.0].max() <= 3.2  # within the stop at (-1.2, -1.2), 2.0-3.2 s


@pytest.fixture(scope="module")
def offline(rig, scene, tmp_path_factory):
    """`vmocap process --max-people 2` of the two-person recording with the real CNN: (the
    output bag, its stats)."""
    from vmocap_core.apps.bench import images
    from vmocap_core.apps.process import process_bag

    out = tmp_path_factory.mktemp("people_offline") / "out.mcap"
    stats = process_bag(scene[0], out, rig, config={"fps": 60.0}, progress=False, overwrite=True, max_people=2,
                        provider=images._Provider(rig, "all", _precision()))
    return out, stats


@rendering
def test_two_people_each_tracked_with_their_own_id(rig, scene, offline):
    """Two people rendered with exact truth, `vmocap process --max-people 2` with the real CNN:
    each person gets a body of their own, matched to them with no identity switch and no
    ghost, within 40 mm of their truth; the subject topics follow the first one."""
    from vmocap_core.apps.bench import images, people

    rec, stamps, truths = scene
    out, stats = offline
    assert stats["people_max"] == 2, stats
    bodies = people.body_tracks(out, stamps)
    f = people.people_figures(bodies, truths, people.seen_by(rig, truths) >= 2)
    print(f)
    assert f["ghost_frames"] == 0 and len(bodies) == 2, f
    # the walker comes into two cameras' view as it crosses in front of the subject; where it is
    # found during the crossing (the search greys the subject's silhouette, not its box), it is
    # identified with half its views covered: 41 mm on the VNNI class's 8-bit kernels, 28 mm where
    # it is found just past the subject (AVX2-only, 7-bit); docs/people.md, not done
    for r, bound in zip(f["persons"], (40.0, 45.0)):
        assert r["mpjpe_mm"] is not None and r["mpjpe_mm"] < bound, f
        assert r["identity_switches"] == 0, f
    # the subject is never missed; the walker, once found, may go uncertain (not output, the same
    # id after it) while it passes in front of the subject: 16 frame sets (14 %) when it was found
    # before the crossing; the target is 2 % (docs/benchmarks.md)
    assert f["persons"][0]["missed_pct"] < 2.0 and f["persons"][1]["missed_pct"] < 20.0, f
    assert f["persons"][0]["ids"] != f["persons"][1]["ids"]
    subject = images.read_estimates(out, stamps)  # the subject topics: the first person found
    tracked = np.isfinite(subject).all(axis=(1, 2))
    assert np.nanmean(images.frame_mpjpe(subject, truths[0])[tracked]) < 40.0


@rendering
def test_two_people_offline_each_from_their_own_whole_recording(rig, scene, tmp_path):
    """`vmocap process --max-people 2 --offline`: each person's live results go through the
    whole-recording pass on their own (identified over all their frames, smoothed without
    lag). Both bodies keep their own ids, with no ghost, and each is nearer its truth than live
    on the frame sets both give them (offline also gives the frame sets live held back while the
    track was being confirmed: a person walking in, harder to see); the subject topics hold the
    first person's offline results."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.process import process_bag

    rec, stamps, truths = scene
    seen = people.seen_by(rig, truths) >= 2
    figures = {}
    errors = {}  # mode -> (P, T): each person's MPJPE against the nearest body (NaN: none within the bound)
    for mode in ("live", "offline"):
        out = tmp_path / f"{mode}.mcap"
        stats = process_bag(rec, out, rig, config={"fps": 60.0, "offline": mode == "offline"}, progress=False,
                            max_people=2, provider=images._Provider(rig, "all", _precision()))
        bodies = people.body_tracks(out, stamps)
        figures[mode] = people.people_figures(bodies, truths, seen)
        e = np.stack([[images.frame_mpjpe(b, truth) for b in bodies.values()] for truth in truths])  # (P, B, T)
        e = np.where(e <= images.FALSE_TRACKING_MM, e, np.inf).min(axis=1)
        errors[mode] = np.where(np.isfinite(e), e, np.nan)
    both = np.isfinite(errors["live"]) & np.isfinite(errors["offline"])
    common = {mode: [float(np.mean(e[k][both[k]])) for k in range(len(truths))] for mode, e in errors.items()}
    print(figures, "on the frame sets both give:", common)
    assert stats["people_offline"] == {"reconstructed": 2, "never_tracked": 0}, stats
    live, offline = figures["live"], figures["offline"]
    assert offline["ghost_frames"] == 0 and len(offline["persons"]) == 2, offline
    for k, (a, b) in enumerate(zip(live["persons"], offline["persons"])):
        assert b["identity_switches"] == 0 and b["missed_pct"] <= a["missed_pct"] + 1.0, figures
        assert both[k].sum() > 0.5 * np.isfinite(errors["live"][k]).sum(), both[k].sum()
        assert common["offline"][k] < common["live"][k] and b["mpjpe_mm"] < 40.0, (common, figures)
    subject = images.read_estimates(tmp_path / "offline.mcap", stamps)
    tracked = np.isfinite(subject).all(axis=(1, 2))
    assert tracked.sum() > 0.8 * len(stamps)
    assert np.nanmean(images.frame_mpjpe(subject, truths[0])[tracked]) < live["persons"][0]["mpjpe_mm"]


@rendering
@pytest.mark.graph_replay
def test_two_people_through_the_node_graph_as_ros4hri_bodies(rig, scene, offline, tmp_path):
    """vmocap_camera plays the two-person recording in lockstep into the graph with max_people 2
    (vmocap_pcm crops both, vmocap_markers and vmocap_skeleton run a stage per person on their
    slots' topics). A client that behaves like libhri's HRIListener (default QoS on
    /humans/bodies/tracked, a body's urdf, joint_states and keypoints opened when its id
    appears) sees two bodies at once with different ids, each URDF's movable joints equal to
    its JointState names suffixed with its id, each body's TF frame at its hips' mid-point (the
    last /tf_static holding both bodies' fixed frames), and each body's keypoints on a different
    person's truth: the same keypoints as `vmocap process --max-people 2` gives that body."""
    pytest.importorskip("hri_msgs.msg", reason="hri_msgs not built (bash scripts/build_ros_msgs.sh)")
    pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs not built (bash scripts/build_ros_msgs.sh)")
    import os

    from graph_helpers import domain_env, stop, vmocap, wait_for, wait_ready
    from sensor_msgs.msg import PointCloud2
    from test_graph_hri import HriListener, _stamp

    from vmocap_core.apps.bench import images, people
    from vmocap_core.bag.messages import CLOUD_DTYPE
    from vmocap_core.cameras.rig_file import save_rig
    from vmocap_core.outputs.people import keypoints_topic
    from vmocap_core.outputs.tf import UrdfKinematics
    from vmocap_core.outputs.urdf import JOINT_NAMES
    from vmocap_core.pcm import selfcheck
    from vmocap_ros.bench.images_graph import graph_config
    from vmocap_ros.common import init_rclpy, qos
    from vmocap_ros.run_node import make_executor

    rec, stamps, truths = scene
    save_rig(rig, tmp_path / "rig.yaml")
    cfg = graph_config(tmp_path, rec, tmp_path / "rig.yaml", "all", {"fps": 60.0}, 0.0, max_people=2)
    env = domain_env(23)
    env["VMOCAP_PCM_PRECISION"] = "int8" if selfcheck.verdict("full").int8_correct else "float"
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    rclpy = init_rclpy()
    clouds: dict[str, dict[int, np.ndarray]] = {}

    def on_cloud(body: str):
        def take(msg) -> None:
            if msg.width:
                pts = np.frombuffer(bytes(msg.data), dtype=CLOUD_DTYPE)
                clouds[body][_stamp(msg.header)] = np.stack([pts["x"], pts["y"], pts["z"]], axis=1)[np.argsort(pts["id"])]
        return take

    class Listener(HriListener):
        def _on_tracked(self, msg) -> None:  # HRIListener's bookkeeping, and each new body's keypoints
            for body in msg.ids:
                if body not in clouds:
                    clouds[body] = {}
                    self.node.create_subscription(PointCloud2, keypoints_topic("/vmocap", body), on_cloud(body), qos(200))
            super()._on_tracked(msg)

    hri = Listener(rclpy)
    executor = make_executor()
    executor.add_node(hri.node)
    launch = vmocap(["launch", str(cfg)], env)
    try:
        assert wait_ready(launch, ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton"], 120.0), stop(launch)
        assert wait_for(lambda: (executor.spin_once(timeout_sec=0.1), hri.tracked and hri.tracked[-1][0])[1]
                        == int(stamps[-1]), 600.0, 0.0), f"the last frame set never came out ({len(hri.tracked)} did)"
    finally:
        log = stop(launch)
        hri.close(executor, rclpy)
    assert launch.returncode == 0, log
    both = [ids for _, ids in hri.tracked if len(ids) == 2]
    assert both and all(a != b for a, b in both), hri.tracked[-3:]
    for _, body in hri.appeared:
        urdf = UrdfKinematics(hri.urdf[body])
        js = hri.joint_states.get(body, [])
        assert js and urdf.joint_names == list(js[-1].name) == [f"{n}_{body}" for n in JOINT_NAMES]
    # TF: each body's frame at its hips' mid-point; the last /tf_static holds both bodies' fixed frames
    for body, got in clouds.items():
        at = [(st, t) for st, tr in hri.tf for child, t in zip(tr.children, tr.t) if child == f"body_{body}"]
        assert at, f"no TF body_{body}"
        kp = [(got[st], t) for st, t in at if st in got]
        assert kp and all(np.allclose(t, (k[INDEX["left_hip"]] + k[INDEX["right_hip"]]) / 2, atol=1e-6) for k, t in kp)
        assert any(c.endswith(f"_{body}") for c in hri.tf_static[-1].children), f"{body} not in the last /tf_static"
    row = {int(s): i for i, s in enumerate(stamps)}
    bodies = {}
    for body, got in clouds.items():
        est = np.full((len(stamps), 25, 3), np.nan)
        for s, P in got.items():
            est[row[s]] = P
        bodies[body] = est
    f = people.people_figures(bodies, truths, people.seen_by(rig, truths) >= 2)
    print(f)
    assert f["ghost_frames"] == 0, f
    # the walker's bound as in test_two_people_each_tracked_with_their_own_id (40.9 mm on the VNNI class)
    for r, bound in zip(f["persons"], (40.0, 45.0)):
        assert r["mpjpe_mm"] is not None and r["mpjpe_mm"] < bound and r["identity_switches"] == 0, f
    assert set(f["persons"][0]["ids"]).isdisjoint(f["persons"][1]["ids"])
    assert images.frame_mpjpe(bodies[f["persons"][0]["ids"][0]], truths[0]).size == len(stamps)
    # /diagnostics: each person tracked at the last report, with what their link lengths are
    lengths = dict(e.split(": ") for e in hri.diag["link_lengths"].split(", ")) if hri.diag["link_lengths"] != "-" else {}
    assert lengths and set(lengths.values()) <= {"provisional", "identified"} and set(lengths) <= set(clouds), hri.diag
    # the graph's bodies are the offline ones (their ids are drawn anew each run; two people found
    # in one frame set have no order): every keypoint the client got is the offline one of that
    # frame set
    off = people.body_tracks(offline[0], stamps)
    tracked = {i: np.isfinite(v).all(axis=(1, 2)) for i, v in (bodies | off).items()}

    def apart(g: str, o: str) -> float:
        both = tracked[g] & tracked[o]
        return float(np.abs(bodies[g][both] - off[o][both]).max()) if both.any() else np.inf

    pairs = [(g, min(off, key=lambda o: apart(g, o))) for g in bodies]
    assert len(pairs) == len({o for _, o in pairs}) == len(off) == 2, (list(bodies), list(off))
    for g, o in pairs:
        # the client opens a body's keypoints when its id appears: it may miss the first few
        assert tracked[g].sum() >= tracked[o].sum() - 5 and not (tracked[g] & ~tracked[o]).any(), (g, o)
        assert np.abs(bodies[g][tracked[g]] - off[o][tracked[g]]).max() <= 1e-6, (g, o)


@rendering
def test_a_camera_stops_while_two_are_tracked(rig, scene):
    """Bad input: cam2 gives no more images from frame set 140 on, while both people are
    tracked. The subject stays tracked on the other three cameras. The walker, near the room's
    edge by then, is in view of cam1 and cam2 only: with cam2 gone one camera sees it, so it has
    no body (not a ghost, not a guess), and nobody else appears."""
    from vmocap_core.apps.bench import images
    from vmocap_core.method.config import PipelineConfig
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_tracker import PeopleTracker

    rec, stamps, truths = scene
    stop_at = 140
    pts = truths[1][:, [INDEX["pelvis"], INDEX["neck"]]]
    uv, front = rig.project(pts)
    size = np.array([[c.width, c.height] for c in rig])[:, None, None]
    seen = (front & (uv >= 0).all(-1) & (uv < size).all(-1)).all(-1)  # (C, T) the walker in view
    assert seen[[1, 2], stop_at:].all() and not seen[[0, 3], stop_at:].any()  # the premise
    tracker = PeopleTracker(rig, images._Provider(rig, "all", _precision()).pcm, PipelineConfig.from_dict({"fps": 60.0}),
                            PeopleConfig(max_people=2))
    est = np.full((2, len(stamps), 25, 3), np.nan)  # per person number 0, 1 (no one else may appear)
    for f, frame in _frame_sets(rec, rig):
        if f >= stop_at:
            frame[2] = None
        for p in tracker.step(frame, int(stamps[f])).people:
            assert p.number < 2, "a third person appeared"
            if p.status == "tracking":
                est[p.number, f] = p.last.skeleton.keypoints
    both = np.isfinite(est[:, :stop_at, 0, 0]).all(axis=0)
    assert both.any(), "both people were never tracked before the camera stopped"
    t0 = np.flatnonzero(both)[0]
    d = np.nanmean(np.linalg.norm(est[:, t0, None] - truths[None, :, t0], axis=-1), axis=-1)  # (number, person)
    subject, walker = int(np.argmin(d[:, 0])), int(np.argmin(d[:, 1]))
    assert subject != walker, d
    after = np.arange(stop_at + 5, len(stamps))
    e = images.frame_mpjpe(est[subject, after], truths[0, after])
    print(f"subject tracked {np.isfinite(e).mean():.0%} after the stop, MPJPE {np.nanmean(e):.1f} mm")
    assert np.isfinite(e).mean() > 0.8 and np.nanmean(e) < 50.0
    w = images.frame_mpjpe(est[walker, stop_at:], truths[1, stop_at:])
    print(f"walker: {np.isfinite(w).sum()} frame sets with a body after the stop")
    assert np.isfinite(w).sum() <= 3 and not (w > 100.0).any(), w


@rendering
def test_a_person_lying_on_the_floor_beside_the_subject(rig, tmp_path_factory, tmp_path):
    """Bad input: a second person lies on the floor 1 m beside the subject's path and gets up
    (the getup_faceup clip) while the subject walks. With max_people 2 the subject keeps one
    body on them throughout (never on the person on the floor), no body is nobody's (a ghost),
    and the person on the floor is either not tracked (the detector's search for newcomers has
    no turned look: they are found when they get up) or tracked within the false-tracking
    bound."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.process import process_bag
    from vmocap_core.apps.render.group import GroupSpec, Walker, render_group, truth_topic
    from vmocap_core.apps.render.recording import ClipSpec, read_truth
    from vmocap_core.paths import DATA

    floor = Walker(ClipSpec(DATA / "motions" / "getup_faceup.npz", FRAMES, 60.0, 0, 1), ((0.0, 0.0, 1.0),), 0.93)
    rec = render_group(GroupSpec(ClipSpec(CLIP, FRAMES, 60.0, 0), (floor,)), rig,
                       tmp_path_factory.mktemp("floor") / "cache", progress=False)
    stamps, _ = read_truth(rec)
    truths = np.stack([read_truth(rec, truth_topic(k))[1] for k in range(2)])
    lying = truths[1][:, INDEX["neck"], 2] < 0.5  # the premise: on the floor for a while
    assert lying[:30].all(), truths[1][:30, INDEX["neck"], 2]
    out = tmp_path / "out.mcap"
    process_bag(rec, out, rig, config={"fps": 60.0}, progress=False, overwrite=True, max_people=2,
                provider=images._Provider(rig, "all", _precision()))
    f = people.people_figures(people.body_tracks(out, stamps), truths, people.seen_by(rig, truths) >= 2)
    subject = images.read_estimates(out, stamps)
    e = images.frame_mpjpe(subject, truths[0])
    print(f"{f}; subject topics tracked {np.isfinite(e).mean():.0%}, MPJPE {np.nanmean(e):.1f}, max {np.nanmax(e):.0f} mm; "
          f"on the floor for {lying.sum()} frame sets")
    assert f["ghost_frames"] == 0, f
    assert f["persons"][0]["identity_switches"] == 0 and f["persons"][0]["mpjpe_mm"] < 40.0, f
    assert np.isfinite(e).mean() > 0.7 and np.nanmean(e) < 40.0 and np.nanmax(e) < images.FALSE_TRACKING_MM, e


def _standing_in_the_way(rig, folder, x: float, frames: int = 240):
    """A smaller person standing on the subject's line at `x`, facing the subject as it walks up
    and back: (recording, stamps, both truths (2, T, 25, 3), their hips' distance (T,))."""
    from vmocap_core.apps.render.group import GroupSpec, Walker, render_group, truth_topic
    from vmocap_core.apps.render.recording import ClipSpec, read_truth

    # a step towards the subject first: a person standing all along would face +x, away from it
    other = Walker(ClipSpec(CLIP, frames, 60.0, 0, 1), ((0.0, x + 0.1, 0.0), (0.2, x, 0.0)), 0.93)
    rec = render_group(GroupSpec(ClipSpec(CLIP, frames, 60.0, 0), (other,)), rig, folder / "cache", progress=False)
    stamps, _ = read_truth(rec)
    truths = np.stack([read_truth(rec, truth_topic(k))[1] for k in range(2)])
    apart = np.linalg.norm(truths[0, :, INDEX["pelvis"], :2] - truths[1, :, INDEX["pelvis"], :2], axis=1)
    return rec, stamps, truths, apart


@rendering
def test_two_people_face_to_face(rig, tmp_path_factory, tmp_path):
    """Bad input: two people face to face at handshake distance (hips 0.44-0.55 m apart: the
    subject walks up to the other person, who stands in its way, twice). In every view one body
    is in front of the other and the detector sees them as one. With max_people 2 each keeps
    their own body and id: no identity switch, no body that is nobody's, the subject is never
    missed; the standing person may go uncertain (no output) while the subject is closest.
    Without the others greyed in each person's crops (occlusion.others_greyed) the standing
    person's track slid onto the subject, ended, and came back under a new id."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.bench.people import FACING_X
    from vmocap_core.apps.process import process_bag

    rec, stamps, truths, apart = _standing_in_the_way(rig, tmp_path_factory.mktemp("facing"), FACING_X)
    assert apart.min() < 0.56 and (apart < 0.6).sum() >= 20, apart.min()  # the premise: close, for a while
    out = tmp_path / "out.mcap"
    process_bag(rec, out, rig, config={"fps": 60.0}, progress=False, overwrite=True, max_people=2,
                provider=images._Provider(rig, "all", _precision()))
    bodies = people.body_tracks(out, stamps)
    f = people.people_figures(bodies, truths, people.seen_by(rig, truths) >= 2)
    close = apart < 0.6
    print(f"{f}; {close.sum()} frame sets closer than 0.6 m")
    for r in f["persons"]:
        assert r["identity_switches"] == 0 and r["mpjpe_mm"] is not None and r["mpjpe_mm"] < 40.0, f
    assert f["persons"][0]["missed_pct"] < 2.0 and f["persons"][1]["missed_pct"] < 25.0, f
    assert f["ghost_frames"] == 0 and f["bodies"] == 2, f


@rendering
def test_people_in_view_from_the_start_are_found_at_the_first_look(rig, tmp_path_factory):
    """Two people in view from the first frame set, the other standing 1.1 m from the subject,
    smaller: the detector, a one-person model, draws the nearer and more prominent person in every
    camera at the first look (twice: a whole body and a part of it). With those just found
    greyed it looks once more, and both are found in the first frame set, each with crops in
    two cameras or more, not only after the first one's skeleton (five frame sets later)."""
    from vmocap_core.apps.bench.people import FACING_X
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_look import PeopleLook
    from vmocap_core.pcm.pipeline import BlazePosePcm

    rec, stamps, truths, apart = _standing_in_the_way(rig, tmp_path_factory.mktemp("first_look"), FACING_X, frames=10)
    assert apart[0] > 1.0, apart[0]  # the premise: two bodies apart, each seen whole
    look = PeopleLook(rig, BlazePosePcm(rig, rotation="all", threads=2, precision=_precision()), PeopleConfig(max_people=2))
    _, images = next(iter(_frame_sets(rec, rig)))
    found = look.step(images, int(stamps[0]))
    seeds = np.array([s.seed for s in look.seats])
    print(seeds, truths[:, 0, INDEX["pelvis"]])
    assert len(seeds) == 2 and all(len(v.camera) >= 2 for v in found.views.values()), found.views
    d = np.linalg.norm(seeds[:, None, :2] - truths[None, :, 0, INDEX["pelvis"], :2], axis=-1)  # (seat, person)
    assert sorted(d.argmin(axis=1)) == [0, 1] and d.min(axis=1).max() < 0.3, d


@rendering
def test_searches_beside_the_frame_sets_find_both_where_they_are_now(rig, tmp_path_factory, monkeypatch):
    """A free-running graph's look (`beside`): the detector's searches run in a thread of their
    own, on copies of the images of the frame set they were due at, and the frame sets never
    run one. The first frame set is looked at before its search ended (nobody seated yet). Its
    finds are given out half a second later, when the subject has walked on: found again there
    (one zoomed look around each), not where they were; then the second look's (the person the
    first look found greyed). Both people are seated, each with crops in two cameras or more,
    each seed within 0.3 m of a different person where they are now."""
    from vmocap_core.apps.bench.people import FACING_X
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_look import PeopleLook
    from vmocap_core.pcm.pipeline import BlazePosePcm

    later = 30  # frame sets (0.5 s at 60 Hz)
    rec, stamps, truths, _ = _standing_in_the_way(rig, tmp_path_factory.mktemp("beside"), FACING_X, frames=later + 2)
    pelvis = truths[:, :, INDEX["pelvis"]]
    assert np.linalg.norm(pelvis[0, later] - pelvis[0, 0]) > 0.4  # the premise: the subject walked on meanwhile
    pcm = BlazePosePcm(rig, rotation="all", threads=2, precision=_precision())

    def in_the_frame_set(*args, **kwargs):
        raise AssertionError("a frame set ran a search")

    monkeypatch.setattr(pcm, "detect_people", in_the_frame_set)
    look = PeopleLook(rig, pcm, PeopleConfig(max_people=2), beside=True)
    try:
        frames = dict(_frame_sets(rec, rig))
        assert look.step(frames[0], int(stamps[0])).views == {}  # the search runs beside: nobody yet
        for k in (later, later + 1):  # the first look's finds, then the second's
            assert look.wait_search(120), "the search did not end"
            found = look.step(frames[k], int(stamps[k]))
        assert look.search_error == ""
    finally:
        look.close()
    seeds = np.array([s.seed for s in look.seats])
    print(seeds, pelvis[:, later])
    assert len(seeds) == 2 and all(len(v.camera) >= 2 for v in found.views.values()), found.views
    d = np.linalg.norm(seeds[:, None, :2] - pelvis[None, :, later, :2], axis=-1)  # (seat, person)
    assert sorted(d.argmin(axis=1)) == [0, 1] and d.min(axis=1).max() < 0.3, d


@pytest.fixture(scope="module")
def hug(rig, tmp_path_factory):
    """The other person standing 0.25 m from where the subject turns (_standing_in_the_way)."""
    from vmocap_core.apps.bench.people import HUG_X

    return _standing_in_the_way(rig, tmp_path_factory.mktemp("hug"), HUG_X)


@rendering
def test_one_subject_at_hug_distance_stays_the_subject(rig, hug, tmp_path):
    """Bad input: the other person stands 0.25 m from where the subject turns (hips 0.2-0.3 m
    apart: a hug, their arms passing through each other), and the detector sees one body. With
    the default one subject the output stays on the subject: never on the other person, never
    a body that is nobody's, never more than FALSE_TRACKING_MM off while output."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.process import process_bag

    rec, stamps, truths, apart = hug
    assert apart.min() < 0.3 and (apart < 0.4).sum() >= 20, apart.min()  # the premise: all but touching, for a while
    out = tmp_path / "out.mcap"
    process_bag(rec, out, rig, config={"fps": 60.0}, progress=False, overwrite=True,
                provider=images._Provider(rig, "all", _precision()))
    est = images.read_estimates(out, stamps)
    f = people.identity_figures(est, truths, people.seen_by(rig, truths)[0] >= 2)
    e = images.frame_mpjpe(est, truths[0])
    print(f"{f}; tracked {np.isfinite(e).mean():.0%}, MPJPE {np.nanmean(e):.1f}, max {np.nanmax(e):.0f} mm; "
          f"{(apart < 0.4).sum()} frame sets closer than 0.4 m")
    assert f["swap_frames"] == 0 and f["ghost_frames"] == 0, f
    assert np.isfinite(e).mean() > 0.7 and np.nanmax(e) < images.FALSE_TRACKING_MM, e


@rendering
def test_the_subject_at_hug_distance_with_two_tracked(rig, hug, tmp_path):
    """The same scene with max_people 2: the subject's topics stay on the subject and never
    more than FALSE_TRACKING_MM off while output. The standing person's track slides onto the
    subject at the hug and is ended; with nobody else tracked the subject's limbs must not stay
    on the untracked body beside them (MarkerSlot re-acquires while the person is tracked alone;
    on this half-size rig the old code passed too: the full-size scene's failure is traced in
    docs/benchmarks.md, session 54)."""
    from vmocap_core.apps.bench import images, people
    from vmocap_core.apps.process import process_bag

    rec, stamps, truths, _ = hug
    out = tmp_path / "out.mcap"
    process_bag(rec, out, rig, config={"fps": 60.0}, progress=False, overwrite=True, max_people=2,
                provider=images._Provider(rig, "all", _precision()))
    est = images.read_estimates(out, stamps)
    f = people.identity_figures(est, truths, people.seen_by(rig, truths)[0] >= 2)
    e = images.frame_mpjpe(est, truths[0])
    print(f"{f}; tracked {np.isfinite(e).mean():.0%}, MPJPE {np.nanmean(e):.1f}, max {np.nanmax(e):.0f} mm")
    assert f["swap_frames"] == 0, f
    assert np.isfinite(e).mean() > 0.7 and np.nanmax(e) < images.FALSE_TRACKING_MM, e


def _clear_of(rig, person: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(T,) how many cameras have `person`'s pelvis and neck ((T, 25, 3) truth) inside its
    image and outside `other`'s projected box grown by 15 % (clear of the box: clear of the
    silhouette the detector's greying draws, whatever the pose)."""
    grow_share = 0.15
    uv, front = rig.project(person[:, [INDEX["pelvis"], INDEX["neck"]]])  # (C, T, 2, 2)
    box, _ = rig.project(other)  # (C, T, 25, 2)
    lo, hi = np.nanmin(box, axis=2), np.nanmax(box, axis=2)  # (C, T, 2)
    grow = grow_share * (hi - lo).max(axis=-1, keepdims=True)
    size = np.array([[c.width, c.height] for c in rig], float)[:, None, None]
    inside = front & (uv >= 0).all(-1) & (uv < size).all(-1)
    covered = ((uv >= (lo - grow)[:, :, None]) & (uv <= (hi + grow)[:, :, None])).all(-1)
    return (inside & ~covered).all(-1).sum(axis=0)


@rendering
def test_more_people_than_max_people_are_counted_not_tracked(rig, scene):
    """Bad input: two people in view with max_people 1. The subject (found first) is tracked;
    the walker gets no body, and the detector's looks while the one slot is taken count them
    as a person left out (what /diagnostics reports: seen by two cameras, as a newcomer is) in
    most looks while three cameras see them clear of the subject (whose body is greyed out for
    the detector; near the room's edge, small in two views, the detector misses them)."""
    from vmocap_core.apps.bench import images
    from vmocap_core.method.config import PipelineConfig
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_tracker import PeopleTracker

    rec, stamps, truths = scene
    tracker = PeopleTracker(rig, images._Provider(rig, "all", _precision()).pcm, PipelineConfig.from_dict({"fps": 60.0}),
                            PeopleConfig(max_people=1, count_every_s=0.25))
    seen = _clear_of(rig, truths[1], truths[0])  # (T,) cameras that see the walker clear of the subject
    est = np.full((len(stamps), 25, 3), np.nan)
    counted, looks = [], 0
    for f, frame in _frame_sets(rec, rig):
        out = tracker.step(frame, int(stamps[f]))
        assert len(out.people) <= 1 and all(p.number == 0 for p in out.people), [p.number for p in out.people]
        if out.people and out.people[0].status == "tracking":
            est[f] = out.people[0].last.skeleton.keypoints
            if tracker.look._last_detection_ns == int(stamps[f]):  # a look while the slot is taken
                looks += 1
                counted.append((int(seen[f]), f, out.left_out))
    e = images.frame_mpjpe(est, truths[0])
    print(f"subject tracked {np.isfinite(e).mean():.0%}, MPJPE {np.nanmean(e):.1f} mm; looks (cameras clear, frame, counted) "
          f"{counted}")
    assert np.isfinite(e).mean() > 0.6 and np.nanmax(e) < 100.0
    walker_looks = [n for cams, _, n in counted if cams >= 3]
    assert looks >= 5 and len(walker_looks) >= 3, counted
    assert sum(n >= 1 for n in walker_looks) >= 0.6 * len(walker_looks), counted


@rendering
def test_two_people_from_binned_images(rig, scene):
    """Binning (REP 104): the scene's 512x384 images are the 1024x768 rig's images binned 2
    times. The tracker is given the full rig and the CNN the rig as the images show it: the
    detections, the greyed bodies and the crops are read in binned pixels, the pipelines keep
    the full rig, and both people are tracked as from images of that size (the subject within
    40 mm, the walker 45)."""
    from vmocap_core.apps.bench import images
    from vmocap_core.cameras.projection import Camera, Rig, binning_affine
    from vmocap_core.method.config import PipelineConfig
    from vmocap_core.method.people_config import PeopleConfig
    from vmocap_core.method.people_tracker import PeopleTracker

    rec, stamps, truths = scene
    unbin = np.linalg.inv(binning_affine(2))
    full = Rig([Camera(c.name, unbin @ c.K, c.dist, c.R, c.t, 2 * c.width, 2 * c.height) for c in rig])
    for a, b in zip(full.binned(2), rig):
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
        assert (a.width, a.height) == (b.width, b.height)
    tracker = PeopleTracker(full, images._Provider(rig, "all", _precision()).pcm, PipelineConfig.from_dict({"fps": 60.0}),
                            PeopleConfig(max_people=2), binning=2)
    assert not tracker.people and tracker.seen[0].width == rig[0].width
    est = np.full((2, len(stamps), 25, 3), np.nan)
    for f, frame in _frame_sets(rec, rig):
        for p in tracker.step(frame, int(stamps[f])).people:
            assert p.number < 2, "a third person appeared"
            if p.status == "tracking":
                est[p.number, f] = p.last.skeleton.keypoints
                assert tracker.slots[tracker.look.seats[0].slot].rig is full  # the stages keep the full rig
    e = np.array([[np.nanmean(images.frame_mpjpe(est[n], truths[k])) for k in range(2)] for n in range(2)])
    print(f"MPJPE (number x person): {e.round(1).tolist()}")
    assert np.isfinite(e).all()
    assert sorted(np.argmin(e, axis=1)) == [0, 1], e
    # each person's bound as in test_two_people_each_tracked_with_their_own_id (the same scene):
    # the walker, identified half covered while crossing, 40.4 mm with the 7-bit kernels on the
    # Zen 4 class (flags avx2 avx512f avx512_vnni)
    mine = e[np.argmin(e, axis=0), np.arange(2)]  # per person, the body that is theirs
    assert (mine < np.array([40.0, 45.0])).all(), e
