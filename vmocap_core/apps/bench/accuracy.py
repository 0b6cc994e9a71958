"""`vmocap bench accuracy`: the synthetic multi-camera benchmark.

Ground-truth motions are projected into the 4-camera benchmark rig (1024x768, 60 Hz), PCMs are
synthesized with the documented, seeded noise model (vmocap_core.pcm.synthetic), and two
reconstructions are scored against the ground truth on the same PCMs:
- method: this project's spatiotemporal filter (lattice search, weighted IK, IIR, second IK),
  with the trunk-tilt input rotation of paper III-B;
- baseline: per-frame confidence-weighted triangulation of the heatmap peaks (dropping the
  worst camera while the reprojection error exceeds 15 px, as Pose2Sim does) + the same
  low-pass filter, no rotation: what triangulation pipelines like Pose2Sim or Anipose do.
Frames are scored from the first frame where the method is tracking.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from tqdm import tqdm

from ...files import output_folder, write_figure
from ...method.config import PipelineConfig
from ...method.filter import make_filter
from ...method.offline import reconstruct
from ...method.pipeline import Pipeline
from ...method.skeleton import BONES
from ...method.triangulation import triangulate_robust
from ...motion import Motion, extend, load_motion, resample
from ...paths import DATA, SHARED_DATA
from ...pcm.synthetic import SyntheticPcmSource, benchmark_rig
from ..metrics import acceleration_error, bone_length_std, jitter, table_one
from . import add_tracker_arguments, tracker_settings

RATE_HZ = 60.0
MIN_SECONDS = 4.0
BUNDLED = DATA / "motions"


@dataclass
class MotionRun:
    motion: Motion
    method: np.ndarray  # (T, 25, 3)
    baseline: np.ndarray
    score: np.ndarray  # (T,) mean marker weight per view
    status: list[str]
    first_tracked: int


def default_motions() -> list[Path]:
    shared = SHARED_DATA / "motions"
    for d in (BUNDLED, shared):
        files = sorted(d.glob("*.npz"))
        if files:
            return files
    return []


def prepare(path: Path) -> Motion:
    return extend(resample(load_motion(path), RATE_HZ), MIN_SECONDS)


def run_motion(motion: Motion, seed: int = 0, config: PipelineConfig | None = None, rotation: bool = True,
               progress: bool = False) -> MotionRun:
    """Run method and baseline on one motion's synthetic PCMs."""
    config = config or PipelineConfig.of(fps=RATE_HZ)
    centre = np.nanmean(motion.positions[:, 0], axis=0)
    rig = benchmark_rig(centre)
    source = SyntheticPcmSource(rig, motion.positions, motion.present, seed=seed, fps=RATE_HZ)
    # Offline: the live pass without lag, the whole-clip pass afterwards.
    tracker = Pipeline(rig, config.replace(smoothing_lag_frames=0) if config.skeleton.offline else config)
    # The same low-pass filter as the method's (lag compensation included).
    base_filter = make_filter(config.skeleton)
    T = len(source)
    method = np.full((T, 25, 3), np.nan)
    baseline = np.full((T, 25, 3), np.nan)
    score = np.zeros(T)
    results = []
    last_base = np.full((source.channels.size, 3), np.nan)
    for t in tqdm(range(T), desc=motion.name, disable=not progress, leave=False):
        rot = tracker.tilt() if rotation else None
        pcm = source.render(t, rot)
        results.append(tracker.step(pcm).skeleton)
        # Baseline: same PCMs, the upright input (triangulation pipelines do not rotate).
        pcm0 = pcm if rot is None else source.render(t, None)
        uv, val = pcm0.peaks()
        pts, _ = triangulate_robust(rig, uv, val, max_error_px=15.0)
        pts = np.where(np.isfinite(pts), pts, last_base)  # hold the last estimate
        last_base = pts
        if np.isfinite(pts).all():
            baseline[t, source.channels] = base_filter(pts)
    if config.skeleton.offline:
        results = reconstruct(results, config.skeleton)
    # By stamp: a fixed-lag result is the frame `lag` steps back.
    status = ["initializing"] * T
    for r in results:
        t = int(round(r.stamp_ns * RATE_HZ / 1e9))
        status[t] = r.status
        if r.status == "tracking":
            method[t] = r.keypoints
            score[t] = float(r.scores[source.channels].mean() / len(rig))
    tracked = [i for i, s in enumerate(status) if s == "tracking"]
    return MotionRun(motion, method, baseline, score, status, tracked[0] if tracked else T)


def score_run(run: MotionRun) -> dict[str, object]:
    m = run.motion
    frames = np.arange(run.first_tracked, m.n_frames)
    scored = m.present.copy()
    gt = m.positions[frames]
    method = table_one(run.method[frames], gt, scored)
    baseline = table_one(run.baseline[frames], gt, scored)
    method["bone_length_std_m"] = bone_length_std(run.method[frames], BONES)
    baseline["bone_length_std_m"] = bone_length_std(np.where(scored[None, :, None], run.baseline[frames], np.nan), BONES)
    method["jitter_m_s2"] = jitter(run.method[frames], RATE_HZ, scored)
    baseline["jitter_m_s2"] = jitter(run.baseline[frames], RATE_HZ, scored)
    method["accel_error_m_s2"] = acceleration_error(run.method[frames], gt, RATE_HZ, scored)
    baseline["accel_error_m_s2"] = acceleration_error(run.baseline[frames], gt, RATE_HZ, scored)
    method["tracked_pct"] = float(np.mean([s == "tracking" for s in run.status[run.first_tracked:]]) * 100)
    return {
        "inverted": m.is_inverted(),
        "frames": int(m.n_frames),
        "init_frames": int(run.first_tracked),
        "method": method,
        "baseline": baseline,
    }


def _pool(results: list[dict[str, Any]], who: str) -> dict[str, float | None]:
    """Frame-weighted pooling of per-motion figures."""
    keys = ("mpjpe_mm", "pck50", "pck100", "pck150")
    out: dict[str, float | None] = {}
    n = np.array([r[who]["n"] for r in results], dtype=float)
    for k in keys:
        v = np.array([r[who][k] if r[who][k] is not None else np.nan for r in results], dtype=float)
        ok = np.isfinite(v)
        out[k] = float((v[ok] * n[ok]).sum() / n[ok].sum()) if ok.any() else None
    groups: dict[str, dict[str, float] | None] = {}
    for g in ("head", "upper_body", "lower_body"):
        rows = [r[who]["groups"][g] for r in results if r[who]["groups"][g] is not None]
        groups[g] = None
        if rows:  # a clip never tracked has n = 0 and None figures: it adds nothing
            gn = np.array([row["n"] for row in rows], float)
            full = [(row, w) for row, w in zip(rows, gn) if w > 0 and all(row[k] is not None for k in keys)]
            if full:
                total = sum(w for _, w in full)
                groups[g] = {k: float(sum(row[k] * w for row, w in full) / total) for k in keys}
    out["groups"] = groups  # type: ignore[assignment]
    out["bone_length_std_m"] = max(r[who]["bone_length_std_m"] for r in results)
    a = np.array([r[who]["accel_error_m_s2"] for r in results], dtype=float)
    ok = np.isfinite(a) & (n > 0)
    out["accel_error_m_s2"] = float((a[ok] * n[ok]).sum() / n[ok].sum()) if ok.any() else None
    return out


def summarize(per_motion: dict[str, dict[str, object]]) -> dict[str, object]:
    summary: dict[str, object] = {}
    for label, inv in (("regular", False), ("inverted", True)):
        rows = [r for r in per_motion.values() if r["inverted"] == inv]
        if rows:
            summary[label] = {"method": _pool(rows, "method"), "baseline": _pool(rows, "baseline"), "motions": len(rows)}
    return summary


def plot_run(run: MotionRun, path: Path, inputs: Iterable[Path] = ()) -> None:
    """MPJPE and PCM score over time as `path`, replacing an earlier plot but never one of `inputs`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = run.motion
    t = np.arange(m.n_frames) / RATE_HZ
    err_m = np.nanmean(np.linalg.norm(run.method - m.positions, axis=-1)[:, m.present], axis=1) * 1000
    err_b = np.nanmean(np.linalg.norm(run.baseline - m.positions, axis=-1)[:, m.present], axis=1) * 1000
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    a.plot(t, err_m, label="method")
    a.plot(t, err_b, label="baseline", alpha=0.7)
    a.set_ylabel("MPJPE (mm)")
    a.set_title(f"{m.name}{' (inverted)' if m.is_inverted() else ''}")
    a.legend()
    b.plot(t, run.score)
    b.set_ylabel("PCM score (mean W / cameras)")
    b.set_xlabel("time (s)")
    fig.tight_layout()
    write_figure(fig, path, inputs, dpi=90)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--motion", nargs="+", type=Path, help="motion .npz files (default: the bundled clips)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print JSON only")
    parser.add_argument("--plots", type=Path, help="write MPJPE/score plots (PNG) into this folder")
    parser.add_argument("--no-rotation", action="store_true", help="disable the trunk-tilt input rotation")
    add_tracker_arguments(parser)


def run(args: argparse.Namespace) -> int:
    files = args.motion or default_motions()
    if not files:
        print("no motion files found")
        return 2
    config = PipelineConfig.from_dict(tracker_settings(args, RATE_HZ))
    per_motion: dict[str, dict[str, object]] = {}
    if args.plots:  # the plots are named after the motions: each is checked against them when written
        output_folder(args.plots, inputs=files)
    for path in tqdm(files, desc="motions", disable=args.json):
        motion = prepare(path)
        r = run_motion(motion, args.seed, config, rotation=not args.no_rotation, progress=not args.json)
        per_motion[motion.name] = score_run(r)
        if args.plots:
            plot_run(r, args.plots / f"{motion.name}.png", files)
    result = {"motions": per_motion, "summary": summarize(per_motion), "seed": args.seed, "config": config.to_dict()}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print_table(result)
    return 0


def _fmt(v: object) -> str:
    return "   -  " if v is None else f"{v:6.1f}"


def print_table(result: dict[str, Any]) -> None:
    print(f"{'motion':<14}{'inv':>4} | {'method MPJPE':>12} {'PCK50':>6} {'PCK100':>6} {'PCK150':>6} | {'baseline MPJPE':>14} {'PCK100':>6} | ratio")
    for name, r in result["motions"].items():
        m, b = r["method"], r["baseline"]
        ratio = m["mpjpe_mm"] / b["mpjpe_mm"] if m["mpjpe_mm"] and b["mpjpe_mm"] else float("nan")
        print(f"{name:<14}{'yes' if r['inverted'] else 'no':>4} | {_fmt(m['mpjpe_mm']):>12} {_fmt(m['pck50'])} {_fmt(m['pck100'])} {_fmt(m['pck150'])} | "
              f"{_fmt(b['mpjpe_mm']):>14} {_fmt(b['pck100'])} | {ratio:.2f}")
    print()
    for label, s in result["summary"].items():
        m, b = s["method"], s["baseline"]
        print(f"{label.upper()} ({s['motions']} motions): method MPJPE {m['mpjpe_mm']:.1f} mm, PCK@50/100/150 "
              f"{m['pck50']:.1f}/{m['pck100']:.1f}/{m['pck150']:.1f} %, acceleration error {_fmt(m['accel_error_m_s2']).strip()} m/s^2, "
              f"bone-length std {m['bone_length_std_m']:.1e} m; "
              f"baseline MPJPE {b['mpjpe_mm']:.1f} mm, PCK@100 {b['pck100']:.1f} %; ratio {m['mpjpe_mm'] / b['mpjpe_mm']:.2f}")
        for g in ("head", "upper_body", "lower_body"):
            mg, bg = m["groups"][g], b["groups"][g]
            if mg:
                print(f"    {g:<11} method {mg['mpjpe_mm']:6.1f} mm PCK100 {mg['pck100']:5.1f} % | baseline {bg['mpjpe_mm']:6.1f} mm PCK100 {bg['pck100']:5.1f} %")
