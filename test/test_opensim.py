"""The OpenSim round trip (`vmocap opensim`, export/opensim.py) on a short processed session with a
gap: every file read back by OpenSim itself; bad input (no upright stretch, 0.5 s, a limb without
markers, OpenSim not installed). Skips without OpenSim (pip install vmocap[opensim])."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from graph_helpers import synthetic_bag, without_frames, write_config

from vmocap_core.export.markers import Z_TO_Y_UP
from vmocap_core.export.opensim import LUMBAR, MARKERS, OpenSimError, import_opensim, round_trip, session_markers
from vmocap_core.export.session import load_session
from vmocap_core.keypoints import INDEX

FPS = 30.0
GAP = range(60, 66)  # frame sets dropped from the recording


def _opensim():
    try:
        return import_opensim()
    except OpenSimError as exc:
        pytest.skip(str(exc))


def _cli(*args: str, pre: str = "") -> subprocess.CompletedProcess:
    code = f"import sys; {pre}; from vmocap_core.cli import main; sys.argv = ['vmocap', 'opensim'] + sys.argv[1:]; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def trip(tmp_path_factory) -> dict:
    _opensim()
    d = tmp_path_factory.mktemp("opensim")
    rig, rig_path, kps = synthetic_bag(d / "full.mcap", frames=100, fps=FPS)
    without_frames(d / "full.mcap", d / "gap.mcap", GAP, FPS)
    cfg = write_config(d / "g.yaml", rig_path, kps, ["vmocap_markers"])
    bag = d / "off.mcap"
    p = subprocess.run([sys.executable, "-m", "vmocap_core.cli", "process", str(d / "gap.mcap"), "-o", str(bag), "--config",
                        str(cfg), "--offline", "--no-progress"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    e = _cli(str(bag), "-o", str(d / "osim"), "--name", "s", pre="pass")
    assert e.returncode == 0, e.stdout + e.stderr
    return {"dir": d, "bag": bag, "out": d / "osim", "session": load_session(bag), "stdout": e.stdout}


def test_round_trip_files_read_by_opensim(trip) -> None:
    osim = _opensim()
    s, out = trip["session"], trip["out"]
    table = osim.TimeSeriesTableVec3(str(out / "s.trc"))
    assert list(table.getColumnLabels()) == list(MARKERS) and table.getNumRows() == s.n_frames
    P = np.array([[[table.getRowAtIndex(i)[k][a] for a in range(3)] for k in range(len(MARKERS))] for i in range(s.n_frames)])
    assert np.isnan(P[list(GAP)]).all()  # gaps stay gaps
    np.testing.assert_allclose(P[s.tracked], (session_markers(s.keypoints) @ Z_TO_Y_UP.T * 1000.0)[s.tracked], atol=5e-5)
    model = osim.Model(str(out / "s_scaled.osim"))
    model.initSystem()
    mot = osim.TimeSeriesTable(str(out / "s_ik.mot"))
    labels = list(mot.getColumnLabels())
    assert "knee_angle_r" in labels and mot.getNumRows() == s.n_frames
    knee = mot.getDependentColumn("knee_angle_r").to_numpy()
    assert np.isnan(knee[list(GAP)]).all() and np.isfinite(knee[s.tracked]).all()
    assert knee[s.tracked].max() - knee[s.tracked].min() > 5.0  # the walk bends the knee (degrees)
    err = osim.TimeSeriesTable(str(out / "s_ik_marker_errors.sto")).getDependentColumn("marker_error_RMS").to_numpy()
    assert np.nanmedian(err[s.tracked]) < 0.02  # metres: OpenSim's own report
    assert (out / "s_joint_angles.png").stat().st_size > 5000
    assert "IK marker RMS error median" in trip["stdout"]


def test_thigh_scaled_to_the_identified_length(trip) -> None:
    """The scaled model's hip-to-knee distance is the session's thigh (joint centres on joints)."""
    osim = _opensim()
    model = osim.Model(str(trip["out"] / "s_scaled.osim"))
    state = model.initSystem()
    ms = model.getMarkerSet()
    d = np.linalg.norm(ms.get("RHip").getLocationInGround(state).to_numpy() - ms.get("RKnee").getLocationInGround(state).to_numpy())
    K = trip["session"].keypoints[trip["session"].tracked]
    thigh = np.linalg.norm(K[:, INDEX["right_hip"]] - K[:, INDEX["right_knee"]], axis=1).mean()
    assert d == pytest.approx(thigh, abs=0.01)


def test_no_upright_stretch_and_short_session(trip, tmp_path: Path) -> None:
    s = trip["session"]
    turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # lying on the back
    lying = dataclasses.replace(s, keypoints=s.keypoints @ turn.T)
    info = round_trip(lying, tmp_path, "lying", progress=False)
    assert "link_lengths" in info["scaled_on"] and any("no 0.5 s upright stretch" in w for w in info["warnings"])
    assert (tmp_path / "lying_static_from_link_lengths.trc").is_file() and info["marker_rms_mm"]["median"] < 20.0
    short = dataclasses.replace(s, keypoints=s.keypoints[:15], angles=s.angles[:15])  # 0.5 s
    info = round_trip(short, tmp_path, "short", progress=False)
    ok = s.tracked[:15]
    assert info["tracked"] == ok.sum() > 5 and np.isfinite(info["ik"].values[ok]).all() and np.isnan(info["ik"].values[~ok]).all()


def test_limb_without_markers(trip, tmp_path: Path) -> None:
    """A left arm missing in every frame: said so, scaled from the link lengths, its
    coordinates not reported, the rest solved."""
    s = trip["session"]
    K = s.keypoints.copy()
    K[:, [INDEX[k] for k in ("left_elbow", "left_wrist", "left_hand")]] = np.nan
    info = round_trip(dataclasses.replace(s, keypoints=K), tmp_path, "arm", progress=False)
    assert info["missing_markers"] == ["LElbow", "LWrist", "LIndex"]
    assert "elbow_flex_l" not in info["ik"].names and "knee_angle_l" in info["ik"].names
    assert any("LElbow" in w for w in info["warnings"]) and info["tracked"] == s.tracked.sum()


def test_opensim_not_installed(trip, tmp_path: Path) -> None:
    e = _cli(str(trip["bag"]), "-o", str(tmp_path / "x"), pre="sys.modules['opensim'] = None")
    assert e.returncode != 0 and "pip install 'vmocap[opensim]'" in e.stderr
    assert len(e.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


def test_the_pelvis_does_not_turn_against_the_trunk(trip) -> None:
    """Markers on the hip and shoulder centres hold the lumbar joint's rotations loosely: IK pulls
    all three towards neutral (export/opensim.py, LUMBAR), so the pelvis and the hips carry the
    walk, not a lumbar twist (without the pull: 20 degrees of bending, 40 of axial turn)."""
    osim = _opensim()
    s = trip["session"]
    mot = osim.TimeSeriesTable(str(trip["out"] / "s_ik.mot"))
    for name in LUMBAR:
        q = mot.getDependentColumn(name).to_numpy()[s.tracked]
        assert np.abs(q).max() < 5.0, name  # degrees
