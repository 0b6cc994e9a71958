"""The ROS4HRI (REP-155) outputs of the subject without ROS (vmocap_core/outputs/hri.py): body
ids and their grace period, the suffixed URDF read by urdf_parser_py and Pinocchio, the body
frame, and the per-frame messages against the subject's own /tf and /tf_static."""

from __future__ import annotations

import dataclasses
import random
import re

import numpy as np
import pytest

from vmocap_core.bag import cdr
from vmocap_core.graph_config import Topics
from vmocap_core.keypoints import INDEX, KEYPOINTS
from vmocap_core.method.results import TrackResult
from vmocap_core.method.skeleton import LIMITS, BodyDimensions, Skeleton
from vmocap_core.outputs import hri as H
from vmocap_core.outputs.messages import result_messages
from vmocap_core.outputs.streams import SubjectOutputs
from vmocap_core.outputs.tf import TF_TYPE, TfTree, UrdfKinematics, message_transforms, quaternion_to_matrix
from vmocap_core.outputs.urdf import JOINT_NAMES, SubjectModel

PERIOD = 33_333_333  # 30 Hz
ID_RE = re.compile(r"^[a-z][a-z0-9]{4}$")


def _result(stamp: int, status: str = "tracking", dims: BodyDimensions | None = None, seed: int = 0) -> TrackResult:
    """A TrackResult of a random pose (joint limits kept) of a skeleton of `dims`."""
    rng = np.random.default_rng(seed)
    sk = Skeleton(dims or BodyDimensions())
    a = rng.uniform(-1.0, 1.0, 40)
    a[:3] = rng.uniform(-1, 1, 3)
    for name, (lo, hi) in LIMITS.items():
        a[sk.joint_names.index(name)] = rng.uniform(lo, hi)
    q = sk.from_angles(a)
    tracking = status == "tracking"
    kp = sk.keypoint_positions(q) if tracking else np.full((25, 3), np.nan)
    return TrackResult(stamp, status, sk.to_angles(q) if tracking else np.full(40, np.nan), sk.joint_names, kp, kp,
                       np.ones(25), kp, {}, (dims or BodyDimensions()) if tracking else None)


def test_body_ids_are_short_start_with_a_letter_and_differ_across_runs() -> None:
    ids = [H.new_body_id(random.Random(s)) for s in range(200)]
    assert all(ID_RE.match(i) for i in ids) and len(set(ids)) >= 199
    assert H.new_body_id(random.Random(7)) == H.new_body_id(random.Random(7))  # seedable
    taken = {H.new_body_id(random.Random(7))}
    assert H.new_body_id(random.Random(7), taken) not in taken
    # unseeded (the nodes): from the system's entropy, so two runs do not share ids
    a, b = H.BodyIds(), H.BodyIds()
    assert a.update(0, "tracking") != b.update(0, "tracking")


def _ids(statuses: list[tuple[int, str]], **kw) -> list[str | None]:
    ids = H.BodyIds(seed=1, **kw)
    return [ids.update(k * PERIOD, s) for k, s in statuses]


def test_id_survives_a_few_uncertain_frame_sets_and_dropped_frames_not_a_longer_loss() -> None:
    track = [(k, "tracking") for k in range(10)]
    # 5 uncertain frame sets (0.17 s) and back: the same id, absent from `tracked` meanwhile
    got = _ids(track + [(k, "uncertain") for k in range(10, 15)] + [(k, "tracking") for k in range(15, 20)])
    assert got[10:15] == [None] * 5 and set(got[:10]) == set(got[15:]) and ID_RE.match(got[0] or "")
    # 60 frame sets dropped (2 s) while tracking goes on: the same id
    got = _ids(track + [(70, "tracking")])
    assert got[-1] == got[0]
    # 20 uncertain frame sets (0.67 s > GRACE_S): a new id
    got = _ids(track + [(k, "uncertain") for k in range(10, 30)] + [(30, "tracking")])
    assert got[30] is not None and got[30] != got[0]
    # a few uncertain frame sets, then none for longer than the grace: a new id too
    got = _ids(track + [(10, "uncertain"), (40, "tracking")])
    assert got[-1] != got[0]
    # the tracker lost the subject: a new id even when it is tracked again at once
    got = _ids(track + [(10, "lost"), (11, "tracking")])
    assert got[-1] is not None and got[-1] != got[0]


def test_ended_ids_retire_after_retire_s() -> None:
    ids = H.BodyIds(seed=3, retire_s=1.0)
    first = ids.update(0, "tracking")
    ids.update(PERIOD, "lost")
    assert ids.retired(PERIOD) == [] and ids.retired(PERIOD + 10**9) == []
    assert ids.retired(2 * PERIOD + 10**9) == [first] and ids.retired(10**10) == []
    second = ids.update(10**10, "tracking")
    ids.update(10**10 + PERIOD, "lost")
    assert ids.retired(5) == [second]  # the clock went back: another recording


def test_suffixed_urdf_read_by_urdf_parser_py_and_pinocchio() -> None:
    urdf = pytest.importorskip("urdf_parser_py.urdf")
    import pinocchio as pin

    xml = SubjectModel(dataclasses.replace(BodyDimensions(), thigh=0.47)).to_xml()
    sx = H.suffixed_urdf(xml, "_ab12c")
    robot, orig = urdf.URDF.from_xml_string(sx), urdf.URDF.from_xml_string(xml)
    assert robot.name == "vmocap_subject_ab12c" and robot.get_root() == "pelvis_ab12c"
    assert [j.name for j in robot.joints] == [j.name + "_ab12c" for j in orig.joints]
    assert [lk.name for lk in robot.links] == [lk.name + "_ab12c" for lk in orig.links]
    assert all(j.parent.endswith("_ab12c") and j.child.endswith("_ab12c") for j in robot.joints)
    movable = [j.name for j in robot.joints if j.type != "fixed"]
    assert movable == [n + "_ab12c" for n in JOINT_NAMES]
    model = pin.buildModelFromXML(sx)
    assert model.getFrameId("kp_left_wrist_ab12c") < model.nframes
    with pytest.raises(H.HriError, match="not XML"):
        H.suffixed_urdf("<robot", "_x")
    with pytest.raises(H.HriError, match="<html>"):
        H.suffixed_urdf("<html/>", "_x")


def test_body_frame_at_the_hips_mid_point_facing_forward() -> None:
    sk = Skeleton()
    kp = sk.keypoint_positions(sk.from_angles(np.zeros(40)))  # upright, facing +x
    t, q = H.body_pose(kp)
    np.testing.assert_allclose(t, (kp[INDEX["left_hip"]] + kp[INDEX["right_hip"]]) / 2, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(q)[0], np.eye(3), atol=1e-12)
    r = _result(0, seed=4)
    t, q = H.body_pose(r.keypoints)
    R = quaternion_to_matrix(q)[0]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    up = r.keypoints[INDEX["neck"]] - t
    np.testing.assert_allclose(R[:, 2], up / np.linalg.norm(up), atol=1e-12)
    assert R[:, 1] @ (r.keypoints[INDEX["left_hip"]] - r.keypoints[INDEX["right_hip"]]) > 0
    assert H.body_pose(np.full((25, 3), np.nan)) is None


def test_frame_messages_rename_the_subjects_tf_and_join_its_static_frames() -> None:
    topics = Topics("/vmocap")
    subject = SubjectOutputs()
    hri = H.HriOutputs(subject, seed=2)
    a, b = BodyDimensions(), dataclasses.replace(BodyDimensions(), thigh=0.5)
    seq = [_result(0, dims=a, seed=1), _result(PERIOD, dims=a, seed=2), _result(2 * PERIOD, "uncertain"),
           _result(3 * PERIOD, dims=b, seed=3), _result(4 * PERIOD, "lost"), _result(5 * PERIOD, dims=b, seed=5)]
    frames, ours = [], []
    for r in seq:
        ours.append({topic: m for topic, _, m in result_messages(topics, r, subject=subject)})
        frames.append(hri.step(r))
    body = frames[0].messages[-1][2]["ids"][0]
    sfx = f"_{body}"
    # tracked: every frame set, last; [id] only while tracking; encodes as hri_msgs/IdsList
    tracked = [f.messages[-1] for f in frames]
    assert [t[0] for t in tracked] == [H.TRACKED] * 6
    assert [m["ids"] for _, _, m in tracked][:4] == [[body], [body], [], [body]]
    assert tracked[4][2]["ids"] == [] and tracked[5][2]["ids"][0] not in ("", body)
    assert cdr.decode(H.IDS_LIST, cdr.encode(H.IDS_LIST, tracked[0][2]))["ids"] == [body]
    # per-id topics opened when the id appears, described again with new dimensions
    assert [c.topic for c in frames[0].opened] == [f"/humans/bodies/{body}/urdf", f"/humans/bodies/{body}/joint_states"]
    assert frames[1].opened == [] and frames[3].opened == []
    topics_of = [[t for t, _, _ in f.messages] for f in frames]
    assert topics_of[0] == [f"/humans/bodies/{body}/urdf", "/tf_static", f"/humans/bodies/{body}/joint_states", "/tf",
                            H.TRACKED]
    assert topics_of[1] == [f"/humans/bodies/{body}/joint_states", "/tf", H.TRACKED]
    assert topics_of[2] == [H.TRACKED] and topics_of[3][0] == f"/humans/bodies/{body}/urdf"
    xml = frames[3].messages[0][2]["data"]
    assert UrdfKinematics(xml).joint_names == [n + sfx for n in JOINT_NAMES]
    assert UrdfKinematics(xml).transforms([n + sfx for n in JOINT_NAMES], np.zeros(34)).t[JOINT_NAMES.index("left_knee")] \
        == pytest.approx([0, 0, -0.5])
    js = frames[1].messages[0][2]
    assert js["name"] == [n + sfx for n in JOINT_NAMES]
    np.testing.assert_array_equal(js["position"], ours[1][topics.joint_states]["position"])
    # /tf: the subject's transforms renamed, plus body_<id>; /tf_static: the subject's and the body's fixed frames
    for k in (0, 1, 3):
        mine = message_transforms(dict((t, m) for t, _, m in frames[k].messages)["/tf"])
        theirs = message_transforms(ours[k][topics.tf])
        assert mine.children[0] == f"body_{body}" and mine.parents[0] == "world"
        assert mine.parents[1:] == [p if p == "world" else p + sfx for p in theirs.parents]
        assert mine.children[1:] == [c + sfx for c in theirs.children]
        np.testing.assert_array_equal(mine.t[1:], theirs.t)
        np.testing.assert_array_equal(mine.q[1:], theirs.q)
        t, q = H.body_pose(seq[k].keypoints)
        np.testing.assert_array_equal(mine.t[0], t)
        # the plain encoder and the fast one agree on the body's frames too
        msg = dict((t, m) for t, _, m in frames[k].messages)["/tf"]
        assert cdr.encode(TF_TYPE, {"transforms": list(msg["transforms"])}) == cdr.encode(TF_TYPE, msg)
    static = message_transforms(frames[3].messages[1][2])
    assert {f"kp_{k}" for k in KEYPOINTS} <= set(static.children)  # the subject's
    assert {f"kp_{k}{sfx}" for k in KEYPOINTS} <= set(static.children)  # the body's
    # what a TF listener makes of it: the body's kp frames at the subject's keypoints
    tree = TfTree()
    tree.add(static)
    tree.add(message_transforms(dict((t, m) for t, _, m in frames[3].messages)["/tf"]))
    np.testing.assert_allclose(tree.positions([f"kp_{k}{sfx}" for k in KEYPOINTS]), seq[3].keypoints, atol=1e-9)
    # after the loss: a new id described and opened; the old one's topics close RETIRE_S later
    new = tracked[5][2]["ids"][0]
    assert [c.topic for c in frames[5].opened][0] == f"/humans/bodies/{new}/urdf"
    later = hri.step(_result(4 * PERIOD + int(H.RETIRE_S * 1e9) + 1, "initializing"))
    assert later.closed == [f"/humans/bodies/{body}/urdf", f"/humans/bodies/{body}/joint_states"]


def test_without_tf_no_tf_messages_and_the_subject_static_untouched() -> None:
    subject = SubjectOutputs()
    hri = H.HriOutputs(subject, tf=False, seed=1)
    f = hri.step(_result(0))
    assert [t for t, _, _ in f.messages if t.startswith("/tf")] == [] and subject.extra_static is None


def test_nobody_listening_skips_joint_states_and_tf_but_not_the_description() -> None:
    hri = H.HriOutputs(SubjectOutputs(), seed=1)
    listened = {H.TRACKED}
    f = hri.step(_result(0), wanted=lambda topic: topic in listened)
    body = hri.body_id
    assert [t for t, _, _ in f.messages] == [f"/humans/bodies/{body}/urdf", "/tf_static", H.TRACKED]
    listened.add("/tf")
    f = hri.step(_result(PERIOD, seed=1), wanted=lambda topic: topic in listened)
    assert [t for t, _, _ in f.messages] == ["/tf", H.TRACKED]
