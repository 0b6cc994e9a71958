"""`vmocap export` of a recording of the live graph (synthetic bag -> `vmocap launch` with a
recorder of the default topics -> `vmocap play`), and of that recording cut to the topic list
the demo gave its recorder before (keypoints, joint_states, markers, skeleton, diagnostics: no
robot_description, root_pose or /tf), where the subject's dimensions and pelvis pose come from
the keypoints. Both give the session `vmocap process` gives on the same bag; every format of the
cut one is read back by third-party readers (rosbags, ezc3d, OpenSim, Pose2Sim, bvh)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import domain_env, stop, synthetic_bag, vmocap, wait_for, wait_ready, write_config
from test_export import bvh_keypoints, opensim_markers

from vmocap_core.bag import BagReader, BagWriter
from vmocap_core.export.markers import Z_TO_Y_UP
from vmocap_core.export.session import load_session
from vmocap_core.export.subject import dims_vector
from vmocap_core.keypoints import KEYPOINTS

pytestmark = pytest.mark.graph_replay
N = 30
RECORDED = ["/vmocap/keypoints", "/vmocap/joint_states", "/vmocap/markers", "/vmocap/skeleton", "/diagnostics"]
FORMATS = ("bvh", "c3d", "trc", "csv")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vmocap_core.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> dict:
    from vmocap_core.apps.process import process_bag
    from vmocap_ros.bench.probe import Probe
    from vmocap_ros.common import init_rclpy

    d = tmp_path_factory.mktemp("export_live")
    env = domain_env(7)
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    bag = d / "in.mcap"
    rig, rig_path, kps = synthetic_bag(bag, N)
    offline = d / "offline.mcap"
    process_bag(bag, offline, rig, config={"fps": 30.0}, keypoints=kps, progress=False)

    out = d / "live.mcap"
    nodes = ["vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    cfg = write_config(d / "graph.yaml", rig_path, kps, nodes, output=out,
                       extra={"vmocap_markers": {"feedback_timeout_ms": 5000.0, "queue_depth": 100},
                              "vmocap_skeleton": {"queue_depth": 100}})
    rclpy = init_rclpy()
    probe = Probe(rclpy, [], input_topic=False)
    probe.recording = True

    def skeleton_subscribers(topic: str) -> int:
        probe.spin_for(0.1)
        last = probe.diag.get("vmocap_skeleton", [(0, {})])[-1][1]
        return int(last.get(f"subscribers:{topic}", 0))

    launch = vmocap(["launch", str(cfg)], env)
    try:
        assert wait_ready(launch, nodes, 90.0), stop(launch)
        # joint_states and keypoints are volatile: play once the recorder (and this probe) matched
        assert wait_for(lambda: skeleton_subscribers("/vmocap/joint_states") >= 2
                        and skeleton_subscribers("/vmocap/keypoints") >= 2, 90.0, 0.0), stop(launch)
        play = subprocess.run(
            [sys.executable, "-m", "vmocap_core.cli", "play", str(bag), "--rate", "2", "--wait-subscribers", "60",
             "--expect", *[f"/vmocap/pcm/{c}/{k}" for c in rig.names for k in ("heatmaps", "camera_info")]],
            env=env, capture_output=True, text=True, timeout=120)
        assert play.returncode == 0, play.stdout + play.stderr
        assert wait_for(lambda: (probe.spin_for(0.1), len(probe.samples["keypoints"]))[1] >= N, 30.0, 0.0), \
            f"only {len(probe.samples['keypoints'])} of {N} frame sets came out"
    finally:
        log = stop(launch)
        probe.close()
        rclpy.shutdown()
    assert launch.returncode == 0 and out.exists(), log
    with BagReader(out) as r:
        cut = _copy(out, d / "cut.mcap", set(r.topics) - set(RECORDED))
    files = {}
    for fmt in FORMATS:
        e = _cli("export", str(cut), "--format", fmt, "-o", str(d / f"live.{fmt}"))
        assert e.returncode == 0, e.stdout + e.stderr
        files[fmt] = d / f"live.{fmt}"
    return {"dir": d, "full": out, "bag": cut, "offline": offline, "session": load_session(cut), "files": files}


def test_recording_lacks_the_subject_topics_and_rosbags_reads_it(live) -> None:
    pytest.importorskip("rosbags")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([live["full"]], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        full = {c.topic for c in r.connections}
    assert {"/vmocap/robot_description", "/vmocap/root_pose", "/tf", "/tf_static"} <= full  # the recorder's defaults
    with AnyReader([live["bag"]], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        assert {c.topic for c in r.connections} == set(RECORDED)
        conns = [c for c in r.connections if c.topic == "/vmocap/joint_states"]
        js = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns)]
    assert len(js) == live["session"].tracked.sum() >= 10
    assert len(js[0].name) == 34  # the URDF's joints: no pelvis pose in joint_states


@pytest.mark.parametrize("which", ["full", "bag"])
def test_live_session_equals_the_processed_bag(live, which: str) -> None:
    """The full recording: dimensions from robot_description, pelvis from root_pose. The cut
    one: both recovered from the keypoints. Either gives the session of the bag `vmocap process`
    writes (robot_description, root_pose, /tf and the subject diagnostics)."""
    s, ref = (live["session"] if which == "bag" else load_session(live["full"])), load_session(live["offline"])
    assert s.n_frames == ref.n_frames == N and s.rate_hz == pytest.approx(30.0)
    assert np.array_equal(s.tracked, ref.tracked) and s.tracked.sum() >= 10
    assert s.joint_names == ref.joint_names
    np.testing.assert_allclose(s.angles[s.tracked], ref.angles[ref.tracked], atol=1e-6)
    np.testing.assert_allclose(s.keypoints[s.tracked], ref.keypoints[ref.tracked], atol=1e-6)
    # the provisional skeleton, then the identified one (identify_output), as the processed bag's
    assert len(s.subjects) == len(ref.subjects) == 2
    for (t, d), (t_ref, d_ref) in zip(s.subjects, ref.subjects):
        assert t == t_ref
        np.testing.assert_allclose(dims_vector(d), dims_vector(d_ref), atol=1e-6)


def test_live_c3d_read_by_ezc3d(live) -> None:
    ezc3d = pytest.importorskip("ezc3d", reason="ezc3d not installed (scripts/setup.sh installs it)")
    s = live["session"]
    c = ezc3d.c3d(str(live["files"]["c3d"]))
    P = c["data"]["points"]  # (4, markers, frames), mm; invalid points read as NaN
    assert P.shape == (4, len(KEYPOINTS), s.n_frames)
    assert c["parameters"]["POINT"]["LABELS"]["value"] == list(KEYPOINTS)
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(30.0)
    got = P[:3].transpose(2, 1, 0)  # (frames, markers, 3)
    assert np.array_equal(np.isfinite(got).all(axis=(1, 2)), s.tracked)
    np.testing.assert_allclose(got, s.keypoints * 1000.0, rtol=1e-6, atol=1e-3)


def test_live_trc_read_by_opensim(live) -> None:
    s = live["session"]
    P, labels, units = opensim_markers(live["files"]["trc"])
    assert labels == list(KEYPOINTS) and units == "mm" and P.shape == (s.n_frames, 25, 3)
    np.testing.assert_allclose(P, s.keypoints @ Z_TO_Y_UP.T * 1000.0, atol=5e-5)  # NaN where untracked
    assert np.array_equal(np.isfinite(P).all(axis=(1, 2)), s.tracked) and not s.tracked.all()


def test_live_recording_round_trips_through_opensim(live) -> None:
    """`vmocap opensim` on the live graph's recording (issue 31): a scaled model and joint angles
    OpenSim reads, untracked frame sets a gap in the .mot as in the TRC."""
    from vmocap_core.export.opensim import OpenSimError, import_opensim

    try:
        osim = import_opensim()
    except OpenSimError as exc:
        pytest.skip(str(exc))
    s, out = live["session"], live["dir"] / "osim"
    r = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "opensim", str(live["bag"]), "-o", str(out), "--name", "live"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    osim.Model(str(out / "live_scaled.osim")).initSystem()
    mot = osim.TimeSeriesTable(str(out / "live_ik.mot"))
    assert mot.getNumRows() == s.n_frames
    knee = mot.getDependentColumn("knee_angle_r").to_numpy()
    assert np.array_equal(np.isfinite(knee), s.tracked)


def test_live_trc_read_by_pose2sim(live) -> None:
    common = pytest.importorskip("Pose2Sim.common", reason="Pose2Sim not installed")
    s = live["session"]
    data, frames, _, markers, _ = common.read_trc(str(live["files"]["trc"]))
    assert markers == list(KEYPOINTS) and len(frames) == s.n_frames
    np.testing.assert_allclose(data.to_numpy(float).reshape(-1, 25, 3), s.keypoints @ Z_TO_Y_UP.T * 1000.0, atol=5e-5)


def test_live_csv_and_bvh(live) -> None:
    s = live["session"]
    tab = np.genfromtxt(live["files"]["csv"], delimiter=",", names=True, skip_header=1, filling_values=np.nan)
    assert len(tab) == s.n_frames
    np.testing.assert_allclose(tab["root_z"], s.angles[:, s.joint_names.index("root_z")], atol=1e-8, equal_nan=True)
    # one file per skeleton: the provisional one's frames, then the identified one's
    files = [live["files"]["bvh"], live["files"]["bvh"].with_name("live_part2.bvh")]
    assert sorted(live["dir"].glob("live*.bvh")) == sorted(files) and len(s.segments()) == 2
    for path, seg in zip(files, s.segments()):
        for k, got in bvh_keypoints(path):
            np.testing.assert_allclose(got, s.keypoints[seg.start + k] @ Z_TO_Y_UP.T, atol=1e-6)


def _copy(src: Path, dst: Path, drop: set[str], keypoints=None) -> Path:
    with BagReader(src) as r, BagWriter(dst) as w:
        for m in r.messages():
            if m.topic in drop:
                continue
            if m.topic == "/vmocap/keypoints" and keypoints is not None:
                w.write(m.topic, m.type, keypoints(m.decode()), m.log_time_ns)
            else:
                w.write(m.topic, m.type, m.data, m.log_time_ns)
    return dst


def test_export_names_what_is_missing(live, tmp_path: Path) -> None:
    """One line naming the missing topic; 'no tracked frame' only when none was tracked."""
    from vmocap_core.bag import messages as M

    bag = _copy(live["bag"], tmp_path / "no_joints.mcap", {"/vmocap/joint_states"})
    e = _cli("export", str(bag), "--format", "trc", "-o", str(tmp_path / "x.trc"))
    assert e.returncode == 2 and "no /vmocap/joint_states message" in e.stderr and len(e.stderr.strip().splitlines()) == 1

    def stretched(msg: dict) -> dict:  # keypoints that are not the skeleton's at the joint states
        P = M.cloud_keypoints(msg)[0]
        return msg if P is None else M.keypoint_cloud(M.stamp_ns(msg), P * [1.0, 1.0, 1.05])

    bag = _copy(live["bag"], tmp_path / "foreign.mcap", set(), keypoints=stretched)
    e = _cli("export", str(bag), "--format", "bvh", "-o", str(tmp_path / "x.bvh"))
    assert e.returncode == 2 and len(e.stderr.strip().splitlines()) == 1, e.stderr
    assert "/vmocap/robot_description and no /vmocap/root_pose" in e.stderr

    def untracked(msg: dict) -> dict:
        return M.keypoint_cloud(M.stamp_ns(msg), None)

    bag = _copy(live["bag"], tmp_path / "untracked.mcap", {"/vmocap/joint_states"}, keypoints=untracked)
    e = _cli("export", str(bag), "--format", "csv", "-o", str(tmp_path / "x.csv"))
    assert e.returncode == 2 and "no tracked frame" in e.stderr
