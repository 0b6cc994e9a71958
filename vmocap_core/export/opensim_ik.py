"""OpenSim's inverse kinematics over the tracked segments of a session (`vmocap opensim`): the IK
tool's solver with the setup's weights, each segment assembled afresh, the arms kept on their
physiological branch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np


class IKWeights(Protocol):
    """What IK takes of a setup (opensim.OpenSimSetup): the weights of its marker and coordinate tasks."""

    marker_weights: dict[str, float]
    coordinate_weights: dict[str, float]

# (arm_rot, elbow_flex) radians each segment's first frame is assembled from (_assemble_arms)
ARM_GUESSES = ((0.0, 0.3), (0.0, 1.5), (-1.0, 0.8), (1.0, 0.8))
ARM_RETRY_M2 = 2 * 0.02**2  # an arm's elbow and wrist this far off (squared, m^2): assembled again


@dataclass
class IKResult:
    names: list[str]  # the model's coordinates
    rotational: np.ndarray  # (C,) bool: an angle (written in degrees), else a translation (m)
    values: np.ndarray  # (N, C) degrees / metres, NaN in gaps
    errors: np.ndarray  # (N, 3) OpenSim's total squared error (m^2), RMS and max marker error (m)
    per_marker: dict[str, float]  # each marker's RMS error over the frames (m)

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.names.index(name)]


def _arm_errors(solver: Any, err: Any) -> dict[str, float]:
    """Per arm ("r", "l"), the squared errors of its elbow and wrist markers in the current pose."""
    solver.computeCurrentMarkerErrors(err)
    names = [solver.getMarkerNameForIndex(k) for k in range(err.size())]
    return {side: float(np.nansum([err.getElt(k) ** 2 for k, n in enumerate(names) if n in (f"{p}Elbow", f"{p}Wrist")]))
            for side, p in (("r", "R"), ("l", "L"))}


def _objective(solver: Any, err: Any, weights: dict[str, float]) -> float:
    """IK's weighted sum of squared marker errors (m^2) in the current pose."""
    solver.computeCurrentMarkerErrors(err)
    return float(np.nansum([weights.get(solver.getMarkerNameForIndex(k), 0.0) * err.getElt(k) ** 2 for k in range(err.size())]))


def _pose(state: Any, coords: Any) -> list[float]:
    return [coords.get(j).getValue(state) for j in range(coords.getSize())]


def _set_pose(state: Any, coords: Any, q: list[float]) -> None:
    for j, v in enumerate(q):
        coords.get(j).setValue(state, v, False)


def _assemble_arms(solver: Any, state: Any, coords: Any, err: Any) -> None:
    """Assemble from the current pose and from several guesses of each arm's axial rotation and
    elbow flexion, and keep, per arm, the one that fits its elbow and wrist markers best: with
    markers on joint centres, an elbow that straightens leaves the arm's axial rotation free, and
    IK may come out of it with the arm turned away and the elbow held straight (its range), a
    pose it then tracks on from (30-45 mm off at the elbow where the right one fits within 10).
    Every guess starts from the current pose of the rest of the body: an assembly moves the
    whole body, and one started from the last guess's result can land the legs and pelvis on
    another branch (a high kick's first frame after a gap: 12 -> 24 mm)."""
    start = _pose(state, coords)
    guesses = [tuple(coords.get(f"{c}_{side}").getValue(state) for side in "rl" for c in ("arm_rot", "elbow_flex"))]
    guesses += [(rot, flex, rot, flex) for rot, flex in ARM_GUESSES]
    fits: dict[str, list[tuple[float, float, float]]] = {"r": [], "l": []}
    for guess in guesses:
        _set_pose(state, coords, start)
        for k, side in enumerate("rl"):
            coords.get(f"arm_rot_{side}").setValue(state, guess[2 * k], False)
            coords.get(f"elbow_flex_{side}").setValue(state, guess[2 * k + 1], False)
        solver.assemble(state)
        for side, e in _arm_errors(solver, err).items():
            fits[side].append((e, coords.get(f"arm_rot_{side}").getValue(state), coords.get(f"elbow_flex_{side}").getValue(state)))
    _set_pose(state, coords, start)
    for side in "rl":
        _, rot, flex = min(fits[side], key=lambda f: f[0])
        coords.get(f"arm_rot_{side}").setValue(state, rot, False)
        coords.get(f"elbow_flex_{side}").setValue(state, flex, False)
    solver.assemble(state)


def inverse_kinematics(osim: Any, setup: IKWeights, model_path: Path, trc: Path, times: np.ndarray,
                       segments: list[slice], progress: Any = None) -> IKResult:
    """OpenSim's IK solver (the IK tool's solver, with its weights from Pose2Sim's IK setup) on
    every frame of `segments`; each segment starts from an assembly of its first frame, so
    nothing carries across a gap. `progress`: a tqdm bar advanced per frame."""
    model = osim.Model(str(model_path))
    state = model.initSystem()
    weights = osim.SetMarkerWeights()
    for m, w in setup.marker_weights.items():
        weights.cloneAndAppend(osim.MarkerWeight(m, w))
    markers = osim.MarkersReference(str(trc), weights)
    coords = model.getCoordinateSet()
    refs = osim.SimTKArrayCoordinateReference()
    for name, w in setup.coordinate_weights.items():
        ref = osim.CoordinateReference(name, osim.Constant(coords.get(name).getDefaultValue()))
        ref.setWeight(w)
        refs.push_back(ref)
    solver = osim.InverseKinematicsSolver(model, markers, refs, float("inf"))
    solver.setAccuracy(1e-5)
    C = coords.getSize()
    names = [coords.get(j).getName() for j in range(C)]
    rotational = np.array([coords.get(j).getMotionType() == 1 for j in range(C)])
    Q = np.full((len(times), C), np.nan)
    E = np.full((len(times), 3), np.nan)
    err = osim.SimTKArrayDouble()
    sq = np.full((len(times), len(setup.marker_weights)), np.nan)
    for seg in segments:
        state.setTime(float(times[seg.start]))
        _assemble_arms(solver, state, coords, err)
        for i in range(seg.start, seg.stop):
            state.setTime(float(times[i]))
            solver.track(state)
            if max(_arm_errors(solver, err).values()) > ARM_RETRY_M2:
                # A fresh assembly moves the whole body and can land on another branch of the
                # legs and pelvis (a high kick: 17 -> 51 mm): kept only where it fits better.
                tracked = _pose(state, coords)
                before = _objective(solver, err, setup.marker_weights)
                _assemble_arms(solver, state, coords, err)
                if _objective(solver, err, setup.marker_weights) > before:
                    _set_pose(state, coords, tracked)
                    solver.track(state)
            Q[i] = _pose(state, coords)
            solver.computeCurrentMarkerErrors(err)
            e = np.array([err.getElt(k) for k in range(err.size())])
            sq[i, : e.size] = e**2
            e = e[np.isfinite(e)]
            E[i] = (np.sum(e**2), np.sqrt(np.mean(e**2)), np.max(e)) if e.size else np.nan
            if progress is not None:
                progress.update(1)
    Q[:, rotational] = np.degrees(Q[:, rotational])
    per_marker = {}
    if segments:  # the solver knows its markers once it assembled
        with np.errstate(all="ignore"):
            rms = np.sqrt(np.nanmean(sq, axis=0))
        per_marker = {solver.getMarkerNameForIndex(k): float(rms[k]) for k in range(solver.getNumMarkersInUse())}
    return IKResult(names, rotational, Q, E, per_marker)
