"""The subject's URDF and TF, checked with third-party parts: urdf_parser_py and Pinocchio's
URDF loader read the description; Pinocchio's FK at the recorded joint states, and the TF
chain rosbags reads back from the MCAP, give the recorded keypoints; the camera frames
reproject them to the rig's pixels (cv2.projectPoints)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import synthetic_bag
from outputs_helpers import cloud as _cloud
from outputs_helpers import rosbags_messages as _rosbags_messages
from outputs_helpers import tf_keypoint_errors

from vmocap_core.keypoints import KEYPOINTS
from vmocap_core.method.skeleton import LIMITS, BodyDimensions, Skeleton
from vmocap_core.outputs import urdf as U

NS = "/vmocap"


@pytest.fixture(scope="module")
def processed(tmp_path_factory) -> tuple[Path, object]:
    from vmocap_core.apps.process import process_bag
    d = tmp_path_factory.mktemp("urdf")
    rig, _, kps = synthetic_bag(d / "in.mcap", frames=40)
    stats = process_bag(d / "in.mcap", d / "out.mcap", rig, keypoints=kps, progress=False)
    assert stats["tracking"] >= 5, stats
    return d / "out.mcap", rig


def _random_angles(sk: Skeleton, rng: np.random.Generator) -> np.ndarray:
    a = rng.uniform(-2.0, 2.0, 40)
    a[:3] = rng.uniform(-1, 1, 3)
    for name, (lo, hi) in LIMITS.items():
        a[sk.joint_names.index(name)] = rng.uniform(lo, hi)
    return a


def _pin_keypoints(pin, model, names, positions, t, quat) -> np.ndarray:
    q = np.zeros(model.nq)
    for n, v in zip(names, positions):
        q[model.joints[model.getJointId(n)].idx_q] = v
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    R = pin.Quaternion(quat[3], quat[0], quat[1], quat[2]).toRotationMatrix()
    return np.array([R @ data.oMf[model.getFrameId(f"kp_{k}")].translation + t for k in KEYPOINTS])


def test_urdf_parses_with_urdf_parser_py_and_pinocchio() -> None:
    urdf = pytest.importorskip("urdf_parser_py.urdf")
    import pinocchio as pin

    dims = dataclasses.replace(BodyDimensions(), thigh=0.47, upper_arm=0.31)
    xml = U.SubjectModel(dims).to_xml()
    robot = urdf.URDF.from_xml_string(xml)
    assert robot.get_root() == "pelvis"
    moving = [j for j in robot.joints if j.type != "fixed"]
    assert [j.name for j in moving] == U.JOINT_NAMES and len(U.JOINT_NAMES) == 34
    knee = robot.joint_map["left_knee"]
    assert (knee.limit.lower, knee.limit.upper) == LIMITS["left_knee"] and list(knee.axis) == [0, 1, 0]
    assert robot.joint_map["left_knee"].origin.xyz == pytest.approx([0, 0, -0.47])
    assert {f"kp_{k}" for k in KEYPOINTS} <= set(robot.link_map)
    assert all(robot.link_map[seg].visual is not None for seg in U.SEGMENT.values())
    model = pin.buildModelFromXML(xml)
    assert model.nq == model.nv == 34
    assert sorted(model.names[1:]) == sorted(U.JOINT_NAMES)


def test_pinocchio_fk_of_the_urdf_equals_the_skeleton_at_random_poses() -> None:
    import pinocchio as pin

    rng = np.random.default_rng(3)
    sk = Skeleton(dataclasses.replace(BodyDimensions(), shank=0.38, shoulder_width=0.4))
    model = pin.buildModelFromXML(U.SubjectModel(sk.dims).to_xml())
    worst = 0.0
    for _ in range(20):
        q = sk.from_angles(_random_angles(sk, rng))
        angles = sk.to_angles(q)
        got = _pin_keypoints(pin, model, U.JOINT_NAMES, U.joint_positions(angles), *U.base_pose(angles))
        worst = max(worst, float(np.abs(got - sk.keypoint_positions(q)).max()))
    assert worst < 1e-9, worst


def test_joint_positions_at_gimbal_lock() -> None:
    import pinocchio as pin

    sk = Skeleton()
    model = pin.buildModelFromXML(U.SubjectModel(sk.dims).to_xml())
    R = lambda axis, a: pin.exp3(a * np.eye(3)[axis])  # noqa: E731
    for b in (np.pi / 2, -np.pi / 2):
        angles = sk.to_angles(sk.neutral())
        i = sk.joint_names.index("left_shoulder_rx")
        angles[i:i + 3] = pin.log3(R(0, 0.3) @ R(1, b) @ R(2, 0.5))  # ry at the lock
        q = sk.from_angles(angles)
        got = _pin_keypoints(pin, model, U.JOINT_NAMES, U.joint_positions(angles), *U.base_pose(angles))
        assert np.abs(got - sk.keypoint_positions(q)).max() < 1e-9


def test_recorded_joint_states_and_root_pose_reproduce_the_keypoints(processed) -> None:
    import pinocchio as pin

    out, _ = processed
    msgs = _rosbags_messages(out)
    # the description in effect at each joint state: the last one written before it
    models = [(t, pin.buildModelFromXML(m.data)) for t, m in msgs[f"{NS}/robot_description"]]
    kp = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m for _, m in msgs[f"{NS}/keypoints"]}
    poses = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m.pose for _, m in msgs[f"{NS}/root_pose"]}
    states = msgs[f"{NS}/joint_states"]
    assert len(states) >= 5 and len(poses) == len(states)
    worst = 0.0
    for logged, js in states:
        model = [m for t, m in models if t <= logged][-1]
        stamp = js.header.stamp.sec * 10**9 + js.header.stamp.nanosec
        p = poses[stamp]
        t = np.array([p.position.x, p.position.y, p.position.z])
        quat = np.array([p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w])
        got = _pin_keypoints(pin, model, list(js.name), js.position, t, quat)
        worst = max(worst, float(np.abs(got - _cloud(kp[stamp])).max()))
    assert worst < 1e-6, worst


def test_tf_read_by_rosbags_gives_the_keypoints_and_nothing_while_not_tracking(processed) -> None:
    out, _ = processed
    msgs = _rosbags_messages(out)
    worst, tf_stamps, tracked = tf_keypoint_errors(msgs, NS)
    assert worst < 1e-6, worst
    # TF exactly at the tracked frames: none while initializing/identifying (no stale pose)
    assert sorted(tf_stamps) == sorted(tracked) and len(tf_stamps) >= 5
    # the description came before the first joint state that needs it
    assert msgs[f"{NS}/robot_description"][0][0] <= msgs[f"{NS}/joint_states"][0][0]


def test_camera_frames_reproject_the_keypoints_like_the_rig(processed) -> None:
    import cv2

    from vmocap_core.bag import BagReader
    from vmocap_core.bag.messages import cloud_keypoints
    from vmocap_core.outputs.tf import TfTree, message_transforms

    out, rig = processed
    tree = TfTree()
    with BagReader(out) as r:
        for m in r.messages(["/tf_static"]):
            tree.add(message_transforms(m.decode()))
        pts = [cloud_keypoints(m.decode())[0] for m in r.messages([f"{NS}/keypoints"])]
    X = next(p for p in pts if p is not None)
    ref, _ = rig.project(X)
    for c, cam in enumerate(rig):
        R, t = tree.world_pose(cam.name)  # optical frame in world
        link_R, _ = tree.world_pose(f"{cam.name}_link")
        # REP 103: the body frame looks along its x axis, the optical frame along z
        np.testing.assert_allclose(link_R[:, 0], R[:, 2], atol=1e-12)
        Xc = (X - t) @ R  # world -> optical frame
        uv, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        np.testing.assert_allclose(uv.reshape(-1, 2), ref[c], atol=1e-6)


def test_reidentified_subject_gets_a_new_description_before_its_joint_state() -> None:
    from vmocap_core.bag import cdr
    from vmocap_core.graph_config import Topics
    from vmocap_core.method.results import TrackResult
    from vmocap_core.outputs.messages import result_messages
    from vmocap_core.outputs.streams import SubjectOutputs, TfFromStates
    from vmocap_core.outputs.tf import TF_TYPE, UrdfKinematics

    topics = Topics(NS)
    subject = SubjectOutputs()
    rng = np.random.default_rng(5)
    nan = np.full((25, 3), np.nan)

    def result(stamp: int, dims: BodyDimensions | None, status: str = "tracking") -> TrackResult:
        sk = Skeleton(dims or BodyDimensions())
        q = sk.from_angles(_random_angles(sk, rng))
        kp = sk.keypoint_positions(q) if status == "tracking" else nan
        return TrackResult(stamp, status, sk.to_angles(q) if status == "tracking" else np.full(40, np.nan),
                           sk.joint_names, kp, kp, np.ones(25), kp, {}, dims if status == "tracking" else None)

    a, b = BodyDimensions(), dataclasses.replace(BodyDimensions(), thigh=0.5, forearm=0.3)
    seq = [result(1, a), result(2, a), result(3, None, "lost"), result(4, b), result(5, b)]
    order = [(r.stamp_ns, topic) for r in seq for topic, _, _ in result_messages(topics, r, subject=subject)]
    descriptions = [s for s, topic in order if topic == topics.robot_description]
    assert descriptions == [1, 4] and subject.descriptions == 2
    for s in descriptions:
        topics_at = [topic for st, topic in order if st == s]
        assert topics_at.index(topics.robot_description) < topics_at.index(topics.joint_states)
    assert not any(topic == topics.tf for s, topic in order if s == 3)
    # the new description has the new thigh, and a recorder's TF (TfFromStates) equals ours
    msgs = list(result_messages(topics, seq[4], subject=subject))
    xml = subject.model.to_xml()
    zero = UrdfKinematics(xml).transforms(U.JOINT_NAMES, np.zeros(34))
    assert zero.t[U.JOINT_NAMES.index("left_knee")] == pytest.approx([0, 0, -0.5])
    rec = TfFromStates(topics)
    rec.add(topics.robot_description, {"data": xml})
    got = [x for topic, _, m in msgs for x in rec.add(topic, m)]
    ours = next(m for topic, _, m in msgs if topic == topics.tf)
    assert len(got) == 1 and got[0][0] == topics.tf
    assert cdr.encode(TF_TYPE, got[0][2]) == cdr.encode(TF_TYPE, ours)
    # the fast TFMessage encoder gives the generic encoder's bytes
    plain = {"transforms": list(ours["transforms"])}
    assert cdr.encode(TF_TYPE, plain) == cdr.encode(TF_TYPE, ours) and len(plain["transforms"]) == 35


def test_vmocap_urdf_cli(processed, tmp_path: Path) -> None:
    from vmocap_core.cli import main
    from vmocap_core.outputs.tf import UrdfKinematics

    out, _ = processed
    assert main(["urdf", "--bag", str(out), "-o", str(tmp_path / "a.urdf")]) == 0
    assert UrdfKinematics((tmp_path / "a.urdf").read_text()).joint_names == U.JOINT_NAMES
    assert main(["urdf", "--keypoints", str(out), "-o", str(tmp_path / "b.urdf")]) == 0
    assert "kp_left_toe" in (tmp_path / "b.urdf").read_text()
    assert main(["urdf", "--bag", str(tmp_path / "a.urdf"), "-o", str(tmp_path / "c.urdf")]) == 2  # not a bag
    assert not (tmp_path / "c.urdf").exists()


def test_viewer_configs_name_our_topics_and_joints() -> None:
    import json

    import yaml

    from vmocap_core.graph_config import Topics

    config = Path(__file__).resolve().parents[1] / "config"
    t = Topics(NS)
    rviz = yaml.safe_load((config / "vmocap.rviz").read_text())
    displays = {d["Class"]: d for d in rviz["Visualization Manager"]["Displays"]}
    assert rviz["Visualization Manager"]["Global Options"]["Fixed Frame"] == "world"
    model = displays["rviz_default_plugins/RobotModel"]["Description Topic"]
    assert model["Value"] == t.robot_description and model["Durability Policy"] == "Transient Local"
    assert displays["rviz_default_plugins/MarkerArray"]["Topic"]["Value"] == t.skeleton
    assert displays["rviz_default_plugins/PointCloud2"]["Topic"]["Value"] == t.keypoints
    fox = json.loads((config / "vmocap_foxglove.json").read_text())["configById"]
    assert fox["3D!vmocap"]["layers"]["subject"]["topic"] == t.robot_description
    for p in fox["Plot!joints"]["paths"]:  # joint_states.position[i] is the labelled joint
        assert p["value"] == f"{t.joint_states}.position[{U.JOINT_NAMES.index(p['label'])}]"
