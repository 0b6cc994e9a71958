"""`vmocap bench opensim`: OpenSim joint angles of processed sessions against exact truth.

Each session goes through the OpenSim round trip (export/opensim.py: TRC, scaling, IK); the
truth keypoints of the same frames go through OpenSim's IK on the same scaled model, so the
model's joint definitions cancel and what is left is our tracking's error as a biomechanics lab
would see it: RMSE per joint angle in degrees (left and right pooled), and OpenSim's IK marker
RMS error. Sessions: the processed MCAP files and rendered recordings of a `vmocap bench images
--out DIR` run (--images DIR), and the synthetic benchmark's motions (synthetic heatmap bags
through `vmocap process --offline`).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ...export.markers import write_marker_trc
from ...export.opensim import (
    MAIN_ANGLES,
    MARKERS,
    import_opensim,
    inverse_kinematics,
    opensim_setup,
    round_trip,
    session_markers,
    undetermined,
)
from ...export.session import Session, load_session
from ...method.smoothing import runs

SYNTHETIC_SECONDS = 4.0
TARGETS_DEG = {"hip_flexion": 5.0, "knee_angle": 5.0}  # the others: OTHERS_DEG
SHOULDER = "shoulder"  # the upper arm's direction error (shoulder_turn), scored instead of arm_flex / arm_add
SCORED = ("hip_flexion", "hip_adduction", "knee_angle", "ankle_angle", SHOULDER, "elbow_flex")
OTHERS_DEG = 8.0


def compare(session: Session, stamps: np.ndarray, truth: np.ndarray, folder: Path) -> dict[str, Any]:
    """Round trip of `session`, and the truth (stamps (T,), keypoints (T, 25, 3)) through OpenSim's
    IK on the session's scaled model: RMSE per main joint angle (deg) and the marker errors."""
    osim = import_opensim()
    info = round_trip(session, folder, "est", progress=False)
    est_frames = np.isfinite(info.pop("ik").values).all(axis=1)
    idx = np.round((stamps - session.t0_ns) * session.rate_hz / 1e9).astype(np.int64)
    inside = (idx >= 0) & (idx < session.n_frames)
    grid = np.full_like(session.keypoints, np.nan)
    grid[idx[inside]] = truth[inside]
    times = np.round(session.times, 6)
    trc = folder / "truth.trc"
    write_marker_trc(trc, list(MARKERS), session_markers(grid), session.rate_hz, times)
    M = session_markers(grid)
    used = [m for j, m in enumerate(MARKERS) if np.isfinite(M[:, j]).all(axis=1).any()]  # the clip's truth has them
    setup = opensim_setup()
    setup = replace(setup, marker_weights={m: w for m, w in setup.marker_weights.items() if m in used})
    frames = np.isfinite(M[:, [list(MARKERS).index(m) for m in used]]).all(axis=(1, 2))
    scaled = folder / "est_scaled.osim"
    # Both through the same model and the same markers: only what the truth can define is scored
    true = inverse_kinematics(osim, setup, scaled, trc, times, runs(frames))
    est = inverse_kinematics(osim, setup, scaled, folder / "est.trc", times, runs(frames & est_frames))
    lost = set(undetermined(osim, scaled, used))
    rmse = {}
    for name in MAIN_ANGLES:
        d = np.concatenate([est.column(f"{name}_{s}") - true.column(f"{name}_{s}") for s in ("r", "l")])
        d = (d + 180.0) % 360.0 - 180.0  # a turn apart is the same pose (IK's angles are not wrapped)
        d = d[np.isfinite(d)]
        rmse[name] = float(np.sqrt(np.mean(d**2))) if d.size and f"{name}_r" not in lost else None
    both = np.isfinite(est.values).all(axis=1) & frames
    if "arm_flex_r" not in lost:
        turn = np.concatenate([shoulder_turn(osim, scaled, est, true, s) for s in ("r", "l")])
        turn = turn[np.isfinite(turn)]
        rmse[SHOULDER] = float(np.sqrt(np.mean(turn**2))) if turn.size else None
    return {"frames": int(both.sum()), "rmse_deg": rmse, "marker_rms_mm": info["marker_rms_mm"],
            "truth_marker_rms_mm": float(np.nanmedian(true.errors[frames, 1]) * 1000.0), "scored_markers": used,
            "not_in_truth": sorted(lost), "scaled_on": info["scaled_on"],
            "warnings": info["warnings"]}


def shoulder_turn(osim: Any, model_path: Path, a: Any, b: Any, side: str) -> np.ndarray:
    """Per frame, the angle (deg) between the upper arm's long axis in the trunk of two IK
    results: the shoulder's flexion and abduction as one figure. Its coordinates (arm_flex,
    arm_add, arm_rot) are a Cardan sequence that loses a degree of freedom with the arm raised
    sideways, where equal arm directions can have angles far apart; the arm's own axial
    rotation is left out (with markers on joint centres only the elbow's bend defines it)."""
    model = osim.Model(str(model_path))
    state = model.initSystem()
    coords = model.getCoordinateSet()
    names = [f"arm_flex_{side}", f"arm_add_{side}", f"arm_rot_{side}"]
    humerus, torso = model.getBodySet().get(f"humerus_{side}"), model.getBodySet().get("torso")

    def long_axis(q: np.ndarray) -> np.ndarray:
        for name, v in zip(names, np.radians(q)):
            coords.get(name).setValue(state, float(v), False)
        model.realizePosition(state)
        R = humerus.findTransformBetween(state, torso).R()
        return np.array([R.get(i, 1) for i in range(3)])  # the humerus's y axis: along the bone

    qa = np.stack([a.column(n) for n in names], axis=1)
    qb = np.stack([b.column(n) for n in names], axis=1)
    out = np.full(len(qa), np.nan)
    for i in np.flatnonzero(np.isfinite(qa).all(axis=1) & np.isfinite(qb).all(axis=1)):
        out[i] = np.degrees(np.arccos(np.clip(long_axis(qa[i]) @ long_axis(qb[i]), -1.0, 1.0)))
    return out


def image_sessions(folder: Path, config: str, groups: list[str]) -> list[tuple[str, Path, Path]]:
    """(clip, processed MCAP, rendered recording) of a `vmocap bench images --out folder` run."""
    report = json.loads((folder / "report.json").read_text())
    return [(label, folder / f"{label}_{config}.mcap", Path(row["recording"])) for label, row in report["clips"].items()
            if row["group"] in groups and (folder / f"{label}_{config}.mcap").is_file()]


def synthetic_session(path: Path, work: Path, seconds: float) -> tuple[Session, np.ndarray, np.ndarray]:
    """A motion's synthetic heatmap bag processed offline: (session, truth stamps, truth)."""
    from ...bag.synth import write_synthetic_bag
    from ...keypoints import KEYPOINTS
    from ...pcm.synthetic import benchmark_rig
    from ..process import process_bag
    from .accuracy import RATE_HZ, prepare

    m = prepare(path)
    n = min(len(m.positions), int(round(seconds * RATE_HZ)))
    rig = benchmark_rig(np.nanmean(m.positions[:n, 0], axis=0))
    t0 = 1_000_000_000_000
    bag, out = work / f"{path.stem}_pcm.mcap", work / f"{path.stem}.mcap"
    write_synthetic_bag(bag, rig, m.positions, m.present, n, fps=RATE_HZ, t0_ns=t0)
    process_bag(bag, out, rig, config={"fps": RATE_HZ, "offline": True},
                keypoints=[KEYPOINTS[i] for i in np.flatnonzero(m.present)], progress=False, overwrite=True)
    stamps = t0 + np.round(np.arange(n) * 1e9 / RATE_HZ).astype(np.int64)
    return load_session(out), stamps, m.positions[:n]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--images", type=Path, help="the --out folder of a `vmocap bench images` run")
    parser.add_argument("--config", default="rot-int8", help="which of its configs (default rot-int8)")
    parser.add_argument("--groups", nargs="+", default=["regular"], help="motion groups scored (default regular)")
    parser.add_argument("--synthetic", nargs="*", type=Path, help="motion .npz files for the synthetic benchmark "
                        "(no files: the shared motions)")
    parser.add_argument("--seconds", type=float, default=SYNTHETIC_SECONDS, help="synthetic session length")
    parser.add_argument("--out", type=Path, help="keep the OpenSim files here (default: a temporary folder)")
    parser.add_argument("--json", action="store_true")


def _pool(rows: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Frame-weighted RMSE per joint and the median IK marker error over the sessions."""
    w = {k: r["frames"] for k, r in rows.items()}
    out: dict[str, Any] = {}
    for name in (*MAIN_ANGLES, SHOULDER):
        vals = [(r["rmse_deg"].get(name), w[k]) for k, r in rows.items() if r["rmse_deg"].get(name) is not None]
        out[name] = float(np.sqrt(sum(v * v * n for v, n in vals) / sum(n for _, n in vals))) if vals else None
    meds = [r["marker_rms_mm"]["median"] for r in rows.values()]
    scored = {k: out[k] for k in SCORED if out[k] is not None}
    return {"rmse_deg": out, "marker_rms_mm_median": float(np.median(meds)) if meds else None,
            "unscored": [k for k in SCORED if out[k] is None],  # the truth cannot define them (no foot keypoints)
            "pass": bool(scored) and all(v <= TARGETS_DEG.get(k, OTHERS_DEG) for k, v in scored.items())}


def run(args: argparse.Namespace) -> int:
    from .accuracy import default_motions

    if args.images is None and args.synthetic is None:
        print("vmocap bench opensim: give --images DIR and/or --synthetic [MOTION ...]", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="vmocap-bench-opensim-") as tmp:
        root = args.out or Path(tmp)
        result: dict[str, Any] = {}
        if args.images is not None:
            from ..render.recording import read_truth

            rows = {}
            for label, processed, rec in image_sessions(args.images, args.config, args.groups):
                (root / "images" / label).mkdir(parents=True, exist_ok=True)
                rows[label] = compare(load_session(processed), *read_truth(rec), root / "images" / label)
            result["images"] = {"clips": rows, "pooled": _pool(rows)}
        if args.synthetic is not None:
            rows = {}
            for path in args.synthetic or default_motions():
                work = root / "synthetic" / path.stem
                work.mkdir(parents=True, exist_ok=True)
                rows[path.stem] = compare(*synthetic_session(path, work, args.seconds), work)
            result["synthetic"] = {"motions": rows, "pooled": _pool(rows)}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for bench, res in result.items():
            for name, r in next(v for k, v in res.items() if k != "pooled").items():
                print(f"{bench:9s} {name:12s} frames {r['frames']:4d}  IK marker RMS median {r['marker_rms_mm']['median']:5.1f} mm  "
                      + "  ".join(f"{k} {v:.1f}" for k, v in r["rmse_deg"].items() if v is not None))
            p = res["pooled"]
            print(f"{bench:9s} pooled RMSE (deg): " + "  ".join(f"{k} {v:.1f}" for k, v in p["rmse_deg"].items() if v is not None)
                  + f"; IK marker RMS median {p['marker_rms_mm_median']:.1f} mm; targets {'met' if p['pass'] else 'NOT met'}")
    return 0 if all(r["pooled"]["pass"] for r in result.values()) else 1
