"""OpenSim round trip of a session: markers named as the BlazePose marker set of Pose2Sim's
OpenSim setup expects, the model scaled to the subject, OpenSim's inverse kinematics.

The model, marker set and IK weights come from the `pose2sim==0.10.49` wheel (BSD-3), read out
of the zip with our own code. Where our keypoints are joint centres (the landmark model moved the
CNN's hips, shoulders, elbows, wrists, knees and ankles onto them: method/landmarks.py) the
marker is put on the model's joint centre; where they are the CNN's landmarks (nose, eyes,
index fingertip, heel, big toe) the marker keeps Pose2Sim's place. Thumb and pinky have no
keypoint of ours and are left out of the marker set and the IK.

`import opensim` (4.6) sets LD_LIBRARY_PATH to PATH in the process, which keeps ROS node
processes started later from this process from loading: the environment is restored after
the import. Nodes never import this module.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration import datasets
from ..errors import VmocapError
from ..keypoints import INDEX
from ..method.rotation import trunk_lean
from ..method.skeleton import BodyDimensions, Skeleton
from .markers import Z_TO_Y_UP, write_marker_trc
from .opensim_ik import IKResult, inverse_kinematics  # noqa: F401 (inverse_kinematics re-exported)
from .session import Session

SETUP = "Pose2Sim/OpenSim_Setup"
MODEL, MARKER_SET = "Model_Pose2Sim_simple.osim", "Markers_BlazePose.xml"
CLAMPED = ("arm_rot_r", "arm_rot_l")  # coordinates whose range IK must keep (adapted_model)
SCALE_SETUP, IK_SETUP = "Scaling_Setup_Pose2Sim_Blazepose.xml", "IK_Setup_Pose2Sim_Blazepose.xml"
LUMBAR = ("L5_S1_Flex_Ext", "L5_S1_Lat_Bending", "L5_S1_axial_rotation")  # IK pulls all three towards neutral (opensim_setup)
LUMBAR_PULL = 0.1  # IK weight of a lumbar rotation the setup leaves free (per rad^2; the markers' are per m^2, 1-2)
INSTALL = "pip install 'vmocap[opensim]' (opensim==4.6; scripts/setup.sh installs it)"

# Marker -> (our keypoint, the model joint whose centre it is). Left side; right mirrors.
JOINT_CENTRES: dict[str, tuple[str, str]] = {
    "LShoulder": ("left_shoulder", "acromial_l"),
    "LElbow": ("left_elbow", "elbow_l"),
    "LWrist": ("left_wrist", "radius_hand_l"),
    "LHip": ("left_hip", "hip_l"),
    "LKnee": ("left_knee", "walker_knee_l"),
    "LAnkle": ("left_ankle", "ankle_l"),
}
# Marker -> our keypoint that is the CNN's landmark (BlazePose's own point) where Pose2Sim puts it.
LANDMARKS: dict[str, str] = {"LEye": "left_eye", "LIndex": "left_hand", "LBigToe": "left_toe", "LHeel": "left_heel"}
JOINT_CENTRES |= {"R" + m[1:]: (k.replace("left_", "right_"), j[:-1] + "r") for m, (k, j) in JOINT_CENTRES.items()}
LANDMARKS |= {"R" + m[1:]: k.replace("left_", "right_") for m, k in LANDMARKS.items()} | {"Nose": "nose"}
MARKERS: dict[str, str] = {m: k for m, (k, _) in JOINT_CENTRES.items()} | LANDMARKS
UNMAPPED = ("LThumb", "LPinky", "RThumb", "RPinky")
# Markers OpenSim's marker placer moves to where the subject has them in the scaling stretch:
# the landmarks, and the shoulders (our shoulder joints hang off the neck, the model's off the
# torso); the other joint centres stay on the model's joints.
PLACED = set(LANDMARKS) | {"LShoulder", "RShoulder"}

# The joint angles the plot shows and the benchmark scores (each with _r and _l).
MAIN_ANGLES = ("hip_flexion", "hip_adduction", "knee_angle", "ankle_angle", "arm_flex", "arm_add", "elbow_flex")

UPRIGHT_SECONDS = 0.5  # the stretch the model is scaled on
UPRIGHT_TRUNK_DEG = 20.0  # pelvis->neck from vertical


class OpenSimError(VmocapError):
    """OpenSim missing, or a session OpenSim cannot be run on (says which and why)."""


def import_opensim() -> Any:
    """The `opensim` module, with the process environment as it was before the import."""
    saved = dict(os.environ)
    try:
        import opensim
    except ImportError as exc:
        raise OpenSimError(f"OpenSim is not installed ({exc}): {INSTALL}") from None
    finally:
        os.environ.clear()
        os.environ.update(saved)
    opensim.Logger.removeFileSink()  # its default opensim.log in the working directory: round_trip logs next to its files
    return opensim


@dataclass
class OpenSimSetup:
    folder: Path  # the unpacked OpenSim_Setup (model, marker set, setups, Geometry)
    marker_weights: dict[str, float]  # IK marker tasks of the mapped markers
    coordinate_weights: dict[str, float]  # IK coordinate tasks (held at their default value)

    @property
    def model(self) -> Path:
        return self.folder / MODEL


def opensim_setup(fetch: bool = True) -> OpenSimSetup:
    """Pose2Sim's OpenSim setup, unpacked from the cached wheel (fetched from PyPI once)."""
    if datasets.pose2sim_demo(fetch=fetch) is None:
        raise OpenSimError(f"the {datasets.POSE2SIM} wheel is not cached (make demo, or run again with network)")
    for d in datasets.cache_dirs():
        if (d / datasets.WHEEL).is_file():
            folder = d / SETUP
            if not (folder / IK_SETUP).is_file():
                with zipfile.ZipFile(d / datasets.WHEEL) as z:
                    wanted = [n for n in z.namelist() if n.startswith(SETUP + "/") and not n.endswith(".stl")]
                    z.extractall(d, wanted)
            break
    else:
        raise OpenSimError(f"the {datasets.POSE2SIM} wheel is not in {', '.join(map(str, datasets.cache_dirs()))}")
    tasks = ET.parse(folder / IK_SETUP).getroot().iter()
    markers: dict[str, float] = {}
    coords: dict[str, float] = {}
    for e in tasks:
        if e.tag in ("IKMarkerTask", "IKCoordinateTask") and (e.findtext("apply") or "").strip() == "true":
            (markers if e.tag == "IKMarkerTask" else coords)[e.attrib["name"]] = float(e.findtext("weight") or 1.0)
    # The setup pulls only the lumbar flexion towards neutral. Markers on the hip and shoulder
    # centres barely tell the lumbar's bending and axial turn from turning the pelvis, so IK
    # turned the pelvis against the trunk, and the hip angles with it: those two get the
    # flexion's pull too (docs/opensim.md).
    coords.update({c: coords.get(LUMBAR[0], LUMBAR_PULL) for c in LUMBAR[1:] if c not in coords})
    return OpenSimSetup(folder, {m: w for m, w in markers.items() if m in MARKERS}, coords)


def session_markers(keypoints: np.ndarray) -> np.ndarray:
    """(N, 25, 3) keypoints -> (N, len(MARKERS), 3) in MARKERS order (still metres, Z up)."""
    return keypoints[:, [INDEX[k] for k in MARKERS.values()]]


def upright_stretch(keypoints: np.ndarray, rate_hz: float) -> slice | None:
    """The UPRIGHT_SECONDS of frames with the trunk within UPRIGHT_TRUNK_DEG of vertical and
    each leg's ankle below its knee below its hip, the straightest (trunk tilt + knee flexion)
    of them; None when there is none. Gaps (NaN) are never upright."""
    P = {k: keypoints[:, INDEX[k]] for k in ("pelvis", "neck", "left_hip", "left_knee", "left_ankle",
                                             "right_hip", "right_knee", "right_ankle")}
    tilt = np.degrees(trunk_lean(keypoints))
    ok = tilt <= UPRIGHT_TRUNK_DEG  # NaN compares false
    score = tilt.copy()
    for s in ("left", "right"):
        a, b = P[f"{s}_knee"] - P[f"{s}_hip"], P[f"{s}_ankle"] - P[f"{s}_knee"]
        ok &= (a[:, 2] < 0) & (b[:, 2] < 0)
        cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        score += np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) / 2
    n = max(int(round(UPRIGHT_SECONDS * rate_hz)), 2)
    if len(ok) < n:
        return None
    win_ok = np.convolve(ok.astype(float), np.ones(n), "valid") >= n - 0.5
    if not win_ok.any():
        return None
    win_score = np.convolve(np.where(ok, score, 0.0), np.ones(n), "valid")
    start = int(np.argmin(np.where(win_ok, win_score, np.inf)))
    return slice(start, start + n)


def rest_trial(dims: BodyDimensions, frames: int = 10) -> np.ndarray:
    """The subject's skeleton standing at rest with the identified link lengths: (frames, 25, 3)."""
    sk = Skeleton(dims)
    return np.repeat(sk.keypoint_positions(sk.neutral())[None], frames, axis=0)


def measurement_lengths(keypoints: np.ndarray) -> dict[str, float]:
    """Mean joint-centre distances of the scale setup's limb measurements (m) over the frames."""
    pairs = {"thigh": ("hip", "knee"), "shank": ("knee", "ankle"), "arm": ("shoulder", "elbow"),
             "forearm": ("elbow", "wrist"), "torso": ("shoulder", "hip")}
    out = {n: float(np.nanmean([np.linalg.norm(keypoints[:, INDEX[f"{s}_{a}"]] - keypoints[:, INDEX[f"{s}_{b}"]], axis=1)
                                for s in ("left", "right")]))
           for n, (a, b) in pairs.items()}
    out["pelvis"] = float(np.nanmean(np.linalg.norm(keypoints[:, INDEX["left_hip"]] - keypoints[:, INDEX["right_hip"]], axis=1)))
    return out


def adapted_model(osim: Any, setup: OpenSimSetup, path: Path) -> None:
    """The generic model with the BlazePose marker set, the joint-centre markers on the joints."""
    model = osim.Model(str(setup.model))
    model.updateMarkerSet(osim.MarkerSet(str(setup.folder / MARKER_SET)))
    markers = model.updMarkerSet()
    for name in UNMAPPED:
        markers.remove(markers.get(name))
    model.finalizeConnections()
    model.initSystem()
    for name, (_, joint) in JOINT_CENTRES.items():
        frame = model.getJointSet().get(joint).getParentFrame()
        marker = markers.get(name)
        marker.setParentFrameName("/bodyset/" + frame.findBaseFrame().getName())
        marker.set_location(frame.findTransformInBaseFrame().p())
    for name in MARKERS:  # Pose2Sim's file fixes some landmarks and not others
        markers.get(name).set_fixed(name not in PLACED)
    # Markers on the shoulder, elbow and wrist centres leave the upper arm's axial rotation free
    # while the elbow is straight: IK then may turn the arm half around, onto the branch where
    # the elbow would bend backwards (held at 0 by its range), and track on there. The model's
    # own range (+-90 degrees, not enforced in the generic model) keeps it on the physiological one.
    for name in CLAMPED:
        model.updCoordinateSet().get(name).set_clamped(True)
    model.finalizeConnections()
    model.printToXML(str(path))


def scale(osim: Any, setup: OpenSimSetup, generic: Path, trc: Path, t: tuple[float, float], out: Path) -> None:
    """OpenSim's ScaleTool with Pose2Sim's measurements on the markers of `trc` over times `t`."""
    root = ET.parse(setup.folder / SCALE_SETUP).getroot()
    # OpenSim reads the setup's file names relative to the setup file: all of them sit in out's folder
    values = {"GenericModelMaker": {"model_file": generic.name, "marker_set_file": "Unassigned"},
              "ModelScaler": {"marker_file": trc.name, "time_range": f"{t[0]:.6f} {t[1]:.6f}", "output_model_file": "Unassigned",
                              "output_scale_file": "Unassigned"},
              "MarkerPlacer": {"apply": "true", "marker_file": trc.name, "time_range": f"{t[0]:.6f} {t[1]:.6f}",
                               "output_model_file": out.name, "output_motion_file": "Unassigned",
                               "output_marker_file": "Unassigned"}}
    for section, fields in values.items():
        node = root.find(f"ScaleTool/{section}")
        if node is None:
            raise OpenSimError(f"{setup.folder / SCALE_SETUP}: no {section}")
        for tag, text in fields.items():
            e = node.find(tag)
            (e if e is not None else ET.SubElement(node, tag)).text = text
    tasks = root.find("ScaleTool/MarkerPlacer/IKTaskSet/objects")
    if tasks is None:
        raise OpenSimError(f"{setup.folder / SCALE_SETUP}: no MarkerPlacer IKTaskSet")
    for m, w in setup.marker_weights.items():
        task = ET.SubElement(tasks, "IKMarkerTask", name=m)
        ET.SubElement(task, "apply").text = "true"
        ET.SubElement(task, "weight").text = str(w)
    path = out.with_name(out.stem + "_scale_setup.xml")
    ET.ElementTree(root).write(path)
    osim.ScaleTool(str(path)).run()  # 4.6 returns false without the marker placer: its output says
    if not out.is_file():
        raise OpenSimError(f"OpenSim's ScaleTool failed on {trc} ({t[0]:.3f}-{t[1]:.3f} s)")
    path.unlink()


def write_storage(path: Path, title: str, names: list[str], times: np.ndarray, values: np.ndarray,
                  in_degrees: bool) -> None:
    """OpenSim's Storage text format (.mot / .sto, version 1), one row per frame of `times`."""
    header = [title, "version=1", f"nRows={len(times)}", f"nColumns={len(names) + 1}",
              f"inDegrees={'yes' if in_degrees else 'no'}", "endheader", "\t".join(["time"] + names)]
    rows = np.column_stack([times, values])
    path.write_text("\n".join(header + ["\t".join(f"{v:.8f}" for v in r) for r in rows]) + "\n")


def undetermined(osim: Any, model_path: Path, used: list[str]) -> list[str]:
    """Coordinates that move none of the `used` markers (their limb has no data): IK cannot
    find them, so they are not reported."""
    model = osim.Model(str(model_path))
    state = model.initSystem()
    ms = model.getMarkerSet()

    def where() -> np.ndarray:
        model.realizePosition(state)
        return np.array([ms.get(m).getLocationInGround(state).to_numpy() for m in used])

    coords = model.getCoordinateSet()
    rest, out = where(), []
    for j in range(coords.getSize()):
        c = coords.get(j)
        v = c.getValue(state)
        c.setValue(state, v + 0.1, False)
        if np.abs(where() - rest).max() < 1e-9:
            out.append(c.getName())
        c.setValue(state, v, False)
    return out


def plot_angles(ik: IKResult, times: np.ndarray, path: Path) -> None:
    """The main joint angles (right solid, left dashed) over time; gaps stay gaps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..files import write_figure

    fig, axes = plt.subplots(len(MAIN_ANGLES), 1, figsize=(10, 1.7 * len(MAIN_ANGLES)), sharex=True)
    for ax, name in zip(axes, MAIN_ANGLES):
        for side, style in (("r", "-"), ("l", "--")):
            if f"{name}_{side}" in ik.names:
                ax.plot(times, ik.column(f"{name}_{side}"), style, label=side)
        ax.set_ylabel(f"{name}\n(deg)", fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    write_figure(fig, path, dpi=80)
    plt.close(fig)


def to_session_markers(keypoints: np.ndarray) -> np.ndarray:
    """Keypoints (N, 25, 3) as OpenSim marker positions (N, M, 3) in metres, Y up."""
    return session_markers(keypoints) @ Z_TO_Y_UP.T


def round_trip(session: Session, folder: Path, stem: str, progress: bool = True, fetch: bool = True) -> dict[str, Any]:
    """Write `stem`.trc, the scaled model `stem`_scaled.osim, the joint angles `stem`_ik.mot,
    OpenSim's marker errors `stem`_ik_marker_errors.sto and `stem`_joint_angles.png into
    `folder` (as they are, no staging: see cli.py); returns the summary."""
    from tqdm import tqdm

    from ..method.smoothing import runs

    osim = import_opensim()  # first: the one-line error before any work
    setup = opensim_setup(fetch)
    folder = folder.resolve()  # the ScaleTool works in its setup file's folder
    osim.Logger.removeFileSink()  # not into the working directory: next to the outputs
    osim.Logger.addFileSink(str(folder / f"{stem}_opensim.log"))
    osim.Logger.setLevelString("warn")
    osim.ModelVisualizer.addDirToGeometrySearchPaths(str(setup.folder / "Geometry"))
    P = session_markers(session.keypoints)
    seen = np.isfinite(P).all(axis=2)  # (N, M)
    frames = seen.any(axis=1) & np.isfinite(session.angles).all(axis=1)
    if not frames.any():
        raise OpenSimError("no tracked frame to run OpenSim on")
    missing = [m for j, m in enumerate(MARKERS) if not seen[frames, j].any()]
    segments = runs(frames)
    times = np.round(session.times, 6)  # as the TRC has them: OpenSim looks frames up by time
    info: dict[str, Any] = {"frames": session.n_frames, "tracked": int(frames.sum()), "segments": len(segments),
                            "rate_hz": session.rate_hz, "missing_markers": missing, "warnings": []}
    if missing:
        info["warnings"].append(f"no data in any frame for marker(s) {', '.join(missing)} "
                                f"({', '.join(MARKERS[m] for m in missing)}): left out of scaling and IK")
    trc = folder / f"{stem}.trc"
    write_marker_trc(trc, list(MARKERS), np.where(frames[:, None, None], P, np.nan), session.rate_hz, times)
    generic = folder / f"{stem}_generic.osim"
    adapted_model(osim, setup, generic)
    keypoints = np.where(frames[:, None, None], session.keypoints, np.nan)
    stretch = upright_stretch(keypoints, session.rate_hz)
    # the skeleton of the most frames: the identified one, not a track's provisional first 0.5 s
    held = [seg for seg in session.segments() if frames[seg].any()] or segments
    rest = rest_trial(session.dims_at(max(held, key=lambda seg: seg.stop - seg.start).start))
    check = measurement_lengths(rest)
    scaled = folder / f"{stem}_scaled.osim"
    if stretch is not None and not missing:
        scale(osim, setup, generic, trc, (times[stretch.start], times[stretch.stop - 1]), scaled)
        got = measurement_lengths(keypoints[stretch])
        info["scaled_on"] = {"upright_stretch_s": [float(times[stretch.start]), float(times[stretch.stop - 1])],
                             "vs_link_lengths_pct": {k: 100.0 * (got[k] / check[k] - 1.0) for k in check}}
    else:
        # No upright stretch (or a limb without data): the identified link lengths, standing at rest.
        static = folder / f"{stem}_static_from_link_lengths.trc"
        write_marker_trc(static, list(MARKERS), session_markers(rest), session.rate_hz, np.arange(len(rest)) / session.rate_hz)
        scale(osim, setup, generic, static, (0.0, (len(rest) - 1) / session.rate_hz), scaled)
        why = "a limb has no markers" if missing else f"no {UPRIGHT_SECONDS} s upright stretch"
        info["scaled_on"] = {"link_lengths": why}
        info["warnings"].append(f"{why}: the model is scaled from the identified link lengths")
    generic.unlink()
    if missing:
        setup = replace(setup, marker_weights={m: w for m, w in setup.marker_weights.items() if m not in missing})
    with tqdm(total=int(frames.sum()), desc="OpenSim IK", unit="frame", disable=not progress, leave=False) as bar:
        ik = inverse_kinematics(osim, setup, scaled, trc, times, segments, bar)
    lost = undetermined(osim, scaled, list(setup.marker_weights)) if missing else []
    keep = [j for j, n in enumerate(ik.names) if n not in lost]
    if lost:
        info["warnings"].append(f"coordinates {', '.join(lost)} move no marker with data: not reported")
    ik = IKResult([ik.names[j] for j in keep], ik.rotational[keep], ik.values[:, keep], ik.errors, ik.per_marker)
    mot, sto = folder / f"{stem}_ik.mot", folder / f"{stem}_ik_marker_errors.sto"
    write_storage(mot, "Coordinates", ik.names, times, ik.values, in_degrees=True)
    write_storage(sto, "Marker errors", ["total_squared_error", "marker_error_RMS", "marker_error_max"], times,
                  ik.errors, in_degrees=False)
    plot_angles(ik, times, folder / f"{stem}_joint_angles.png")
    rms = ik.errors[frames, 1] * 1000.0
    info.update({"files": [str(folder / f"{stem}{s}") for s in (".trc", "_scaled.osim", "_ik.mot", "_ik_marker_errors.sto",
                                                                 "_joint_angles.png", "_opensim.log")],
                 "marker_rms_mm": {"median": float(np.median(rms)), "p95": float(np.percentile(rms, 95)),
                                   "max": float(np.max(rms))},
                 "marker_rms_mm_each": {m: 1000.0 * v for m, v in ik.per_marker.items()}})
    if not info["scaled_on"].get("upright_stretch_s"):
        info["files"].insert(1, str(folder / f"{stem}_static_from_link_lengths.trc"))
    osim.Logger.removeFileSink()
    info["ik"] = ik
    return info
