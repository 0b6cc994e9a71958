"""MCAP I/O without ROS: CDR against rclpy's own serializer, rosbags reads our files,
truncated/corrupt bags give a clear BagError, recovery reads what precedes the damage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vmocap_core.bag import BagReader, BagWriter, cdr
from vmocap_core.bag import heatmaps as H
from vmocap_core.bag import messages as M
from vmocap_core.errors import BagError
from vmocap_core.keypoints import KEYPOINTS


def _image(k: int) -> dict:
    img = np.full((6, 8, 3), k % 256, dtype=np.uint8)
    return M.image_msg(img, 1_000_000_000 + k * 33_333_333, "cam0")


def _write(path: Path, n: int = 40, compression: str = "zstd") -> None:
    with BagWriter(path, compression=compression, chunk_size=4096) as w:
        for k in range(n):
            t = 1_000_000_000 + k * 33_333_333
            w.write("/vmocap/cam0/image_raw", "sensor_msgs/msg/Image", _image(k), t)
            w.write("/vmocap/joint_states", "sensor_msgs/msg/JointState", M.joint_state_msg(t, ["a", "b"], [k, -k]), t)


SAMPLES = {
    "sensor_msgs/msg/Image": lambda: _image(3),
    "sensor_msgs/msg/CameraInfo": lambda: {"header": M.header(5, "c"), "width": 4, "height": 3, "distortion_model": "plumb_bob",
                                           "d": [0.1, -0.2, 0, 0, 0.01], "k": np.arange(9.0), "r": np.eye(3).ravel(), "p": np.arange(12.0)},
    "sensor_msgs/msg/PointCloud2": lambda: M.keypoint_cloud(7, np.random.default_rng(0).normal(size=(25, 3)), np.ones(25), "lattice"),
    "sensor_msgs/msg/JointState": lambda: M.joint_state_msg(9, ["x", "yy", "zzz"], [1.0, 2.0, 3.0]),
    "visualization_msgs/msg/MarkerArray": lambda: M.skeleton_markers(11, np.random.default_rng(1).normal(size=(25, 3))),
    "diagnostic_msgs/msg/DiagnosticArray": lambda: M.diagnostics_msg(13, [(1, "n", "m", {"k": "v"})]),
    "rosgraph_msgs/msg/Clock": lambda: M.clock_msg(15),
}


@pytest.mark.parametrize("type_name", sorted(SAMPLES))
def test_cdr_matches_rclpy_serialization(type_name: str) -> None:
    pytest.importorskip("rclpy")
    from rclpy.serialization import deserialize_message, serialize_message

    from vmocap_ros.common import msg_class

    cls = msg_class(type_name)
    ours = cdr.encode(type_name, SAMPLES[type_name]())
    ros_msg = deserialize_message(ours, cls)  # rclpy reads our bytes ...
    theirs = serialize_message(ros_msg)
    # (rclpy's buffer may carry a few trailing slack bytes: only the content is compared)
    assert len(theirs) >= len(ours)
    # ... and we read rclpy's bytes back to the same message (padding bytes may differ)
    again = cdr.encode(type_name, cdr.decode(type_name, theirs))
    assert deserialize_message(again, cls) == ros_msg


def test_empty_numpy_point_array_encodes() -> None:
    """One keypoint left (no complete bone): the LINE_LIST gets a (0, 3) array of points, which
    encodes as an empty sequence that rclpy reads."""
    pytest.importorskip("rclpy")
    from rclpy.serialization import deserialize_message

    from vmocap_ros.common import msg_class

    kp = np.full((25, 3), np.nan)
    kp[3] = [0.1, 0.2, 1.0]
    msg = M.skeleton_markers(11, kp)
    assert msg["markers"][0]["points"].shape == (0, 3)
    ros_msg = deserialize_message(cdr.encode("visualization_msgs/msg/MarkerArray", msg),
                                  msg_class("visualization_msgs/msg/MarkerArray"))
    assert len(ros_msg.markers[0].points) == 0 and len(ros_msg.markers[1].points) == 1


def test_rosbags_reads_our_bag(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = tmp_path / "b.mcap"
    _write(bag)
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        msgs = [(c.topic, t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages()]
    assert types == {"/vmocap/cam0/image_raw": "sensor_msgs/msg/Image", "/vmocap/joint_states": "sensor_msgs/msg/JointState"}
    assert len(msgs) == 80
    img = [m for topic, _, m in msgs if topic.endswith("image_raw")][5]
    assert (img.width, img.height, img.encoding) == (8, 6, "bgr8") and int(img.data[0]) == 5
    js = [m for topic, _, m in msgs if topic.endswith("joint_states")][7]
    assert list(js.name) == ["a", "b"] and list(js.position) == [7.0, -7.0]


def test_schema_is_full_ros2msg_definition(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    text = cdr.schema_text("visualization_msgs/msg/MarkerArray")
    for dep in ("MSG: visualization_msgs/Marker", "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time",
                "MSG: geometry_msgs/Pose", "MSG: sensor_msgs/CompressedImage", "MSG: visualization_msgs/MeshFile"):
        assert dep in text
    bag = tmp_path / "m.mcap"
    with BagWriter(bag) as w:
        w.write("/s", "visualization_msgs/msg/MarkerArray", M.skeleton_markers(1, np.zeros((25, 3))), 1)
    with open(bag, "rb") as f:
        r = make_reader(f)
        assert r.get_header().profile == "ros2"
        (schema,) = r.get_summary().schemas.values()
        (channel,) = r.get_summary().channels.values()
    assert schema.encoding == "ros2msg" and schema.name == "visualization_msgs/msg/MarkerArray"
    assert schema.data.decode() == text and channel.message_encoding == "cdr"


def test_reader_time_range_and_topics(tmp_path: Path) -> None:
    bag = tmp_path / "b.mcap"
    _write(bag)
    with BagReader(bag) as r:
        assert r.message_counts == {"/vmocap/cam0/image_raw": 40, "/vmocap/joint_states": 40}
        start = r.start_ns + 10 * 33_333_333
        got = list(r.messages(["/vmocap/joint_states"], start_ns=start))
        assert len(got) == 30 and got[0].decode()["position"][0] == 10.0
        with pytest.raises(BagError, match="no topic"):
            list(r.messages(["/nope"]))


def test_truncated_bag_clear_error_and_recovery(tmp_path: Path) -> None:
    bag = tmp_path / "full.mcap"
    _write(bag, n=200, compression="none")
    data = bag.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(BagError) as err:
        BagReader(cut).open()
    assert str(cut) in str(err.value) and "truncated" in str(err.value)
    r = BagReader(cut, recover=True).open()
    got = list(r.messages(["/vmocap/joint_states"]))
    assert 50 < len(got) < 200
    # what was recovered is intact and in order
    pos = [m.decode()["position"][0] for m in got]
    assert pos == [float(k) for k in range(len(pos))]
    r.close()


def test_not_an_mcap_and_missing_file(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not a bag at all")
    with pytest.raises(BagError, match="not an MCAP"):
        BagReader(junk).open()
    with pytest.raises(BagError, match="no such bag"):
        BagReader(tmp_path / "missing.mcap").open()


def test_writer_is_atomic(tmp_path: Path) -> None:
    out = tmp_path / "o.mcap"
    w = BagWriter(out).open()
    w.write("/vmocap/joint_states", "sensor_msgs/msg/JointState", M.joint_state_msg(1, ["a"], [1.0]), 1)
    assert not out.exists() and w.tmp_path.exists()  # nothing under the final name yet
    w.close()
    assert out.exists() and not w.tmp_path.exists()
    # an exception inside `with` leaves the existing file as it was and no partial file
    with pytest.raises(RuntimeError):
        with BagWriter(out, overwrite=True) as w2:
            w2.write("/x", "sensor_msgs/msg/JointState", M.joint_state_msg(1, ["a"], [1.0]), 1)
            raise RuntimeError("boom")
    assert BagReader(out).open().message_counts == {"/vmocap/joint_states": 1}
    assert not w2.tmp_path.exists()


def test_pcm_message_roundtrip_exact() -> None:
    from vmocap_core.pcm.synthetic import benchmark_rig
    from vmocap_core.pcm.views import PcmViews, stride_affine

    rig = benchmark_rig()
    rng = np.random.default_rng(2)
    A = np.stack([stride_affine(16), stride_affine(8)])
    A[1, :, 2] += [3.0, -2.0]
    rot = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    A[1, :, :2] = rot @ A[1, :, :2]  # a rotated crop
    views = PcmViews(maps=rng.random((2, 3, 12, 16)), image_to_map=A, camera=[2, 0], keypoints=[0, 1, 7],
                     valid=[[True, False, True], [True, True, True]], presence=[0.5, 1.0], stamp_ns=42)
    pairs = [(cdr.decode("sensor_msgs/msg/Image", cdr.encode("sensor_msgs/msg/Image", i)),
              cdr.decode("sensor_msgs/msg/CameraInfo", cdr.encode("sensor_msgs/msg/CameraInfo", c)))
             for i, c in H.pcm_msgs(views, rig)]
    assert pairs[0][0]["encoding"] == "32FC4"  # no visibility: the maps as they were, presence last
    back = H.pcm_views(pairs, rig, np.array([0, 1, 7]))
    assert np.array_equal(back.visibility, np.ones((2, 3)))
    assert np.allclose(back.image_to_map, A, atol=1e-12)
    assert np.array_equal(back.camera, [2, 0]) and np.array_equal(back.valid, views.valid)
    assert np.array_equal(back.maps[views.valid], views.maps[views.valid])
    assert np.allclose(back.presence, [0.5, 1.0]) and back.stamp_ns == 42
    # the CameraInfo K is the heatmap's own projection: a world point lands on its map cell
    X = np.array([[0.3, -0.2, 1.1]])
    uv, _ = rig.project(X)
    K = np.asarray(pairs[1][1]["k"]).reshape(3, 3)
    cam = rig[0]
    xc = cam.R @ X[0] + cam.t
    from vmocap_core.pcm.views import apply_affine

    expect = apply_affine(A[1], uv[0, 0])
    # distorted normalized coordinates = K_cam^-1 uv; then the heatmap K maps them to the map
    d = np.linalg.solve(cam.K, np.array([*uv[0, 0], 1.0]))
    assert np.allclose((K @ d)[:2], expect, atol=1e-9) and xc[2] > 0


def test_pcm_messages_without_data_decode_like_the_data() -> None:
    """In one process vmocap_pcm hands its PcmViews to vmocap_markers inside data-less Image
    dicts: the decoded frame set equals, bit for bit, the one decoded from the data, but for
    the affine, which is the sender's own (the data's comes back through K = A K_cam)."""
    from vmocap_core.pcm.synthetic import benchmark_rig
    from vmocap_core.pcm.views import PcmViews, stride_affine

    rig = benchmark_rig()
    rng = np.random.default_rng(3)
    maps = rng.random((3, 4, 12, 16))
    maps[2, 3] = np.nan  # a channel said valid but all NaN: invalid after decoding
    maps[0, 0, 5, 7] = np.nan  # one NaN cell stays
    views = PcmViews(maps=maps, image_to_map=np.stack([stride_affine(16)] * 3), camera=[2, 0, 1], keypoints=[0, 1, 7, 9],
                     valid=[[True, False, True, True], [True, True, True, True], [False, True, True, True]],
                     presence=[0.1, 1.0, 1 / 3], stamp_ns=7, visibility=rng.random((3, 4)))
    kp = np.array([0, 1, 7, 9])
    with_data = H.pcm_views(H.pcm_msgs(views, rig), rig, kp)
    pairs = H.pcm_msgs(views, rig, data=False)
    assert all("data" not in img and H.PCM_VIEW in img for img, _ in pairs)
    without = H.pcm_views(pairs, rig, kp)
    assert np.allclose(with_data.visibility, views.visibility, atol=1e-7)  # float32 on the wire
    for field in ("maps", "camera", "keypoints", "valid", "presence", "visibility"):
        a, b = getattr(with_data, field), getattr(without, field)
        assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), field
    assert np.array_equal(without.image_to_map, views.image_to_map)
    assert np.allclose(with_data.image_to_map, views.image_to_map, rtol=1e-12, atol=1e-12)
    assert not without.valid[2, 3] and without.stamp_ns == 7
    # a mixed frame set (one view decoded from bytes) is the same too
    full = H.pcm_msgs(views, rig)
    mixed = H.pcm_views([full[0], pairs[1], pairs[2]], rig, kp)
    assert np.array_equal(mixed.maps, with_data.maps, equal_nan=True) and np.array_equal(mixed.presence, with_data.presence)
    assert np.array_equal(mixed.visibility, with_data.visibility)


def test_the_others_in_view_travel_with_the_pcm_and_the_markers() -> None:
    """The census's count (PcmViews.others) reaches vmocap_skeleton: in the PCM messages'
    extra channel (with or without data) and in the checked markers' cloud; messages from
    before it (no extra channel, the older cloud layout) read as not known (-1)."""
    from vmocap_core.method.consistency import ViewCheck
    from vmocap_core.method.results import Markers
    from vmocap_core.outputs.messages import markers_from_message, markers_message
    from vmocap_core.pcm.synthetic import benchmark_rig
    from vmocap_core.pcm.views import PcmViews, stride_affine

    rig = benchmark_rig()
    kp = np.array([0, 1, 7])
    views = PcmViews(maps=np.random.default_rng(4).random((2, 3, 12, 16)), image_to_map=np.stack([stride_affine(16)] * 2),
                     camera=[0, 1], keypoints=kp, valid=np.ones((2, 3), bool), presence=[1.0, 1.0], stamp_ns=5)
    assert H.pcm_msgs(views, rig)[0][0]["encoding"] == "32FC4" and H.pcm_views(H.pcm_msgs(views, rig), rig, kp).others == -1
    for others in (0, 3):
        views.others = others
        wire = [(cdr.decode("sensor_msgs/msg/Image", cdr.encode("sensor_msgs/msg/Image", i)), c)
                for i, c in H.pcm_msgs(views, rig)]
        back = H.pcm_views(wire, rig, kp)
        assert back.others == others and np.array_equal(back.visibility, np.ones((2, 3)))
        assert H.pcm_views(H.pcm_msgs(views, rig, data=False), rig, kp).others == others
    n = len(KEYPOINTS)
    check = ViewCheck(np.ones(n), np.zeros(n, np.uint32), np.ones(n, np.uint32))
    inside = np.full(n, 0b0111, np.uint32)
    markers = Markers(5, np.zeros((n, 3)), np.ones(n), "lattice", check=check, others=2, inside=inside)
    msg = markers_message(markers)
    assert markers_from_message(msg).others == 2 and np.array_equal(markers_from_message(msg).inside, inside)
    markers.others = -1
    assert markers_from_message(markers_message(markers)).others == -1
    # the layouts before the fields: the same points without `others` and `inside`, or `inside`
    def older(dtype: np.dtype) -> dict:
        pts = np.frombuffer(msg["data"], dtype=M.CHECKED_DTYPE)
        old = np.zeros(len(pts), dtype=dtype)
        for name in dtype.names:
            old[name] = pts[name]
        return dict(msg, fields=msg["fields"][:len(dtype.names)], point_step=dtype.itemsize,
                    row_step=dtype.itemsize * len(old), data=old.tobytes())

    back = markers_from_message(older(M.CHECKED_V2_DTYPE))
    assert back.others == -1 and back.check is not None and np.array_equal(back.check.agree, check.agree)
    assert back.inside is None
    back = markers_from_message(older(M.CHECKED_V3_DTYPE))
    assert back.check is not None
    assert back.others == 2 and back.inside is None and np.array_equal(back.check.agree, check.agree)


def test_the_person_and_their_company_travel_with_the_pcm() -> None:
    """Several people: whose maps they are (PcmViews.person) and how many others have a skeleton
    beside them (PcmViews.company, which decides the marker stage's re-acquisition) reach
    vmocap_markers through the wire and in-process; a sender from before `company` (the extra
    channel's cell J + 2 zero) reads as not known (-1)."""
    import dataclasses

    from vmocap_core.pcm.synthetic import benchmark_rig
    from vmocap_core.pcm.views import PcmViews, stride_affine

    rig = benchmark_rig()
    kp = np.array([0, 1, 7])
    views = PcmViews(maps=np.random.default_rng(5).random((2, 3, 12, 16)), image_to_map=np.stack([stride_affine(16)] * 2),
                     camera=[0, 1], keypoints=kp, valid=np.ones((2, 3), bool), presence=[1.0, 1.0], stamp_ns=5)
    for person, company in ((0, 0), (2, 1), (1, -1), (-1, 3)):
        sent = dataclasses.replace(views, person=person, company=company)
        wire = [(cdr.decode("sensor_msgs/msg/Image", cdr.encode("sensor_msgs/msg/Image", i)), c)
                for i, c in H.pcm_msgs(sent, rig)]
        for back in (H.pcm_views(wire, rig, kp), H.pcm_views(H.pcm_msgs(sent, rig, data=False), rig, kp)):
            assert (back.person, back.company) == (person, company)
            np.testing.assert_array_equal(back.maps, sent.maps.astype(np.float32))
    older = H.pcm_msgs(dataclasses.replace(views, person=1, company=2), rig)
    J = len(kp)
    for img, _ in older:
        arr = M.image_array(img).copy()  # (H, W, J + 2): keypoints, presence, the extra channel
        extra = arr[..., J + 1].reshape(-1)
        extra[J + 2] = 0.0  # what a sender without the field wrote there
        arr[..., J + 1] = extra.reshape(arr.shape[:2])
        img["data"] = type(img["data"])(arr.tobytes())
    assert (H.pcm_views(older, rig, kp).person, H.pcm_views(older, rig, kp).company) == (1, -1)


def test_camera_info_mismatch_is_reported() -> None:
    from vmocap_core.pcm.synthetic import benchmark_rig

    cam = benchmark_rig()[0]
    good = M.camera_info_msg(cam, 0)
    assert M.camera_info_mismatch(good, cam) is None
    bad = dict(good, k=np.asarray(good["k"]) * 1.01)
    assert "K differs" in M.camera_info_mismatch(bad, cam)
    assert "1024x768" in M.camera_info_mismatch(dict(good, width=640), cam)


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_indexed_reader_equals_the_mcap_library(tmp_path: Path, compression: str) -> None:
    """Uncompressed chunks are read in place (message indexes + memory map), compressed ones
    by the mcap library: both give the library's messages, order and time range."""
    from mcap.reader import SeekingReader

    path = tmp_path / "b.mcap"
    with BagWriter(path, compression=compression, chunk_size=4096) as w:
        for k in range(40):  # two topics with equal stamps (file order decides ties)
            t = 1_000_000_000 + (k // 2) * 33_333_333
            w.write("/vmocap/cam0/image_raw", "sensor_msgs/msg/Image", _image(k), t)
            w.write("/vmocap/joint_states", "sensor_msgs/msg/JointState", M.joint_state_msg(t, ["a"], [k]), t)
    lo, hi = 1_000_000_000 + 3 * 33_333_333, 1_000_000_000 + 11 * 33_333_333
    with open(path, "rb") as f:
        ref = [(ch.topic, rec.log_time, rec.data) for _, ch, rec in SeekingReader(f).iter_messages(log_time_order=True)]
    with BagReader(path) as r:
        got = [(m.topic, m.log_time_ns, m.data) for m in r.messages()]
        part = [(m.topic, m.log_time_ns, bytes(m.data)) for m in r.messages(["/vmocap/cam0/image_raw"], lo, hi)]
        views = list(r.messages(["/vmocap/cam0/image_raw"], zero_copy=True))
        assert all(isinstance(m.data, bytes) for m in r.messages())
        assert all(isinstance(m.data, memoryview if compression == "none" else bytes) for m in views)
        first = M.image_array(cdr.decode(views[0].type, views[0].data, copy=False))
        assert np.array_equal(first, M.image_array(_image(0)))
    assert got == ref
    assert part == [x for x in ref if x[0] == "/vmocap/cam0/image_raw" and lo <= x[1] < hi] and len(part) == 16


def test_indexed_reader_reports_a_corrupt_message_offset(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    _write(path, compression="none")
    data = bytearray(path.read_bytes())
    with BagReader(path) as r:
        pos = r._indexed({"/vmocap/cam0/image_raw"}, None, None)[5][1]
    data[pos] = 0x42  # not a message record any more: the chunk's CRC catches it first
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with BagReader(bad) as r, pytest.raises(BagError, match=r"chunk \d+ of \d+ \(byte offset \d+.*is damaged"):
        list(r.messages(["/vmocap/cam0/image_raw"]))
