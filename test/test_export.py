"""`vmocap process --offline` then `vmocap export` on a synthetic bag with dropped frame sets;
every export read back by a parser we did not write (bvh, c3d, OpenSim, numpy's text reader,
csv) and compared with the processed bag. A recording of the live graph: test_export_live.py."""

from __future__ import annotations

import csv
import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import synthetic_bag, without_frames, write_config
from scipy.spatial.transform import Rotation

from vmocap_core.errors import VmocapError
from vmocap_core.export.markers import Z_TO_Y_UP
from vmocap_core.export.session import load_session
from vmocap_core.keypoints import INDEX, KEYPOINTS
from vmocap_core.method.skeleton import BONES

FPS = 30.0
GAP = range(70, 76)  # frame sets dropped from the recording


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vmocap_core.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def processed(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("export")
    rig, rig_path, kps = synthetic_bag(d / "full.mcap", frames=110, fps=FPS)
    without_frames(d / "full.mcap", d / "gap.mcap", GAP, FPS)
    cfg = write_config(d / "g.yaml", rig_path, kps, ["vmocap_markers"])
    out = d / "off.mcap"
    p = _cli("process", str(d / "gap.mcap"), "-o", str(out), "--config", str(cfg), "--offline", "--no-progress",
             "--plots", str(d / "plots"))
    assert p.returncode == 0, p.stdout + p.stderr
    files = {}
    for fmt in ("bvh", "c3d", "trc", "csv"):
        e = _cli("export", str(out), "--format", fmt, "-o", str(d / f"s.{fmt}"))
        assert e.returncode == 0, e.stdout + e.stderr
        files[fmt] = d / f"s.{fmt}"
    return {"dir": d, "bag": out, "session": load_session(out), "files": files}


def test_offline_session_has_the_gap_and_constant_links(processed) -> None:
    s = processed["session"]
    assert s.rate_hz == pytest.approx(FPS, rel=1e-6) and s.n_frames == 110
    assert not s.tracked[list(GAP)].any()  # nothing invented across the dropped frame sets
    segs = s.segments()
    assert GAP.start in [g.stop for g in segs] and GAP.stop in [g.start for g in segs]
    # the synthetic session plays the walk clip forth and back (38 frame sets each way): no
    # jump, so the dropped frame sets are the only gap
    others = [(a.stop, b.start) for a, b in zip(segs, segs[1:]) if (a.stop, b.start) != (GAP.start, GAP.stop)]
    assert not others, others
    assert s.tracked.sum() > 80
    tracked = s.keypoints[s.tracked]
    lengths = [np.linalg.norm(tracked[:, INDEX[a]] - tracked[:, INDEX[b]], axis=-1) for a, b in BONES.values()]
    assert max(float(np.std(v)) for v in lengths) < 1e-9
    assert all((processed["dir"] / "plots" / f).stat().st_size > 1000 for f in ("joint_angles.png", "keypoint_speeds.png"))


def test_trc_plain_parse_against_the_opensim_format(processed) -> None:
    s = processed["session"]
    rows = list(csv.reader(io.StringIO(processed["files"]["trc"].read_text()), delimiter="\t"))
    assert rows[0][:3] == ["PathFileType", "4", "(X/Y/Z)"]
    head = dict(zip(rows[1], rows[2]))
    assert float(head["DataRate"]) == pytest.approx(FPS) and int(head["NumFrames"]) == s.n_frames
    assert int(head["NumMarkers"]) == 25 and head["Units"] == "mm"
    assert [n for n in rows[3][2:] if n] == list(KEYPOINTS)
    assert rows[4][2:5] == ["X1", "Y1", "Z1"] and rows[5] == []
    data = rows[6:]
    assert len(data) == s.n_frames
    expect = (s.keypoints @ Z_TO_Y_UP.T * 1000.0).reshape(s.n_frames, -1)
    for i, row in enumerate(data):
        assert int(row[0]) == i + 1 and float(row[1]) == pytest.approx(i / FPS, abs=1e-6)
        vals = np.array([float(v) if v else np.nan for v in row[2:]])
        assert vals.shape == (75,)
        np.testing.assert_allclose(vals, expect[i], atol=5e-5, equal_nan=True)  # 4 decimals of mm
    assert all(v == "NaN" for i in GAP for v in data[i][2:])  # OpenSim reads NaN, not empty fields


def test_c3d_read_by_the_c3d_package(processed) -> None:
    import c3d

    s = processed["session"]
    with open(processed["files"]["c3d"], "rb") as f:
        r = c3d.Reader(f)
        assert r.point_rate == pytest.approx(FPS)
        assert [n.strip() for n in r.point_labels] == list(KEYPOINTS)
        assert r.get("POINT:UNITS").string_value.strip() == "mm"
        assert r.get("POINT:Y_SCREEN").string_value.strip() == "+Z"
        frames = [(p.copy()) for _, p, _ in r.read_frames(check_nan=False)]
    assert len(frames) == s.n_frames
    P = np.stack(frames)  # (N, 25, 5): x y z residual cameras
    valid = P[..., 3] >= 0
    assert np.array_equal(valid.all(axis=1), s.tracked)
    got = P[..., :3][valid]
    exp = (s.keypoints * 1000.0)[valid]
    np.testing.assert_allclose(got, exp, rtol=1e-6, atol=1e-3)  # float32 points


def test_csv_read_by_numpy(processed) -> None:
    s = processed["session"]
    text = processed["files"]["csv"].read_text()
    assert text.startswith("# vmocap session: rate 30.000000 Hz") and "Z up" in text.splitlines()[0]
    tab = np.genfromtxt(processed["files"]["csv"], delimiter=",", names=True, skip_header=1, filling_values=np.nan)
    assert len(tab) == s.n_frames
    np.testing.assert_allclose(tab["time_s"], s.times, atol=1e-6)
    np.testing.assert_allclose(tab["left_knee"], s.angles[:, s.joint_names.index("left_knee")], rtol=1e-8, atol=1e-9)
    for n in ("pelvis", "left_wrist", "right_toe"):
        got = np.stack([tab[f"{n}_{a}"] for a in "xyz"], axis=1)
        np.testing.assert_allclose(got, s.keypoints[:, KEYPOINTS.index(n)], rtol=1e-8, atol=1e-9, equal_nan=True)
    assert np.isnan(tab["root_x"][list(GAP)]).all()


def bvh_keypoints(path: Path):
    """(frame, (25, 3) keypoints) of a BVH file as the `bvh` package parses it, by forward
    kinematics of its hierarchy (R = Rz Rx Ry, degrees): first, middle and last frame."""
    from bvh import Bvh

    mocap = Bvh(Path(path).read_text())
    for k in (0, mocap.nframes // 2, mocap.nframes - 1):
        world: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for name in mocap.get_joints_names():
            off = np.array(mocap.joint_offset(name), float)
            rot = Rotation.from_euler("ZXY", mocap.frame_joint_channels(k, name, ["Zrotation", "Xrotation", "Yrotation"]),
                                      degrees=True).as_matrix()
            parent = mocap.joint_parent(name)
            if parent is None:
                pos = np.array(mocap.frame_joint_channels(k, name, ["Xposition", "Yposition", "Zposition"]), float) + off
                world[name] = (rot, pos)
            else:
                R, p = world[parent.name]
                world[name] = (R @ rot, p + R @ off)
        joint_of = {"pelvis": "root"}  # keypoints at joint centres are those joints
        yield k, np.array([world[joint_of.get(n, n)][1] for n in KEYPOINTS])


def test_bvh_forward_kinematics_reproduces_the_keypoints(processed) -> None:
    from bvh import Bvh

    s = processed["session"]
    files = sorted(processed["dir"].glob("s*.bvh"), key=lambda f: (len(f.name), f.name))
    assert [f.name for f in files] == ["s.bvh"] + [f"s_part{k}.bvh" for k in range(2, len(s.segments()) + 1)]  # split at gaps
    for seg, f in zip(s.segments(), files):
        mocap = Bvh(f.read_text())
        assert mocap.nframes == seg.stop - seg.start and mocap.frame_time == pytest.approx(1 / FPS, rel=1e-6)
        for k, got in bvh_keypoints(f):
            np.testing.assert_allclose(got, s.keypoints[seg.start + k] @ Z_TO_Y_UP.T, atol=1e-6)


def opensim_markers(path: Path) -> tuple[np.ndarray, list[str], str]:
    """(frames, markers, 3) of a TRC as OpenSim reads it, the marker names and the units."""
    saved = dict(os.environ)
    try:
        opensim = pytest.importorskip("opensim", reason="opensim not installed (pip install vmocap[opensim]; scripts/setup.sh)")
    finally:  # opensim 4.6's import sets LD_LIBRARY_PATH to PATH: later ROS node processes would not start
        os.environ.clear()
        os.environ.update(saved)
    table = opensim.TimeSeriesTableVec3(str(path))
    rows = [table.getRowAtIndex(i) for i in range(table.getNumRows())]
    P = np.array([[[r[k][a] for a in range(3)] for k in range(table.getNumColumns())] for r in rows])
    return P, list(table.getColumnLabels()), table.getTableMetaDataAsString("Units")


def test_trc_with_gaps_read_by_opensim(processed) -> None:
    """Untracked and dropped frames are NaN rows; every frame and marker is there."""
    s = processed["session"]
    P, labels, units = opensim_markers(processed["files"]["trc"])
    assert P.shape == (s.n_frames, len(KEYPOINTS), 3) and labels == list(KEYPOINTS) and units == "mm"
    assert np.isnan(P[list(GAP)]).all() and np.array_equal(np.isfinite(P).all(axis=(1, 2)), s.tracked)
    np.testing.assert_allclose(P, s.keypoints @ Z_TO_Y_UP.T * 1000.0, atol=5e-5)


def test_export_bad_input(processed, tmp_path: Path) -> None:
    raw = processed["dir"] / "gap.mcap"  # not processed: no keypoints topic
    e = _cli("export", str(raw), "--format", "csv", "-o", str(tmp_path / "x.csv"))
    assert e.returncode == 2 and "not a recording of the graph's outputs nor a processed bag" in e.stderr
    with pytest.raises(VmocapError):
        load_session(tmp_path / "missing.mcap")
