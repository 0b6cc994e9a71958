"""Offline (whole-recording) reconstruction: what a recorded session allows that a live
tracker cannot.

The causal tracker runs first (its lattice search needs the previous frame's skeleton); its
virtual markers and weights are kept. Then, on the whole recording:
1. identification (II-C) on the virtual markers of every tracked frame (or the confident ones,
   `offline_identify_quantile`): medians over thousands of frames instead of the live 0.5 s,
   so the link lengths are robust to outliers;
   the waist height is chosen by the mean fit over frames spread through the recording;
2. per tracked segment (a gap or re-initialization ends one; nothing is interpolated across;
   up to `offline_bridge_frames` frame sets the images disagreed with stay gaps inside one):
   first IK (II-E) of the identified skeleton to the markers, forward;
3. a Rauch-Tung-Striebel smoother (smoothing.py) of the first IK's keypoints, forward and
   backward over the segment (no lag);
4. second IK to the smoothed keypoints, so the output keeps constant link lengths.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
from tqdm import tqdm

from ..errors import VmocapError
from ..keypoints import KEYPOINTS
from .config import SkeletonConfig
from .consistency import RESUME_GAP_S
from .filter import smoother_model
from .ik import solve_ik
from .init import identify_dimensions, initial_pose, refine_offsets
from .landmarks import LandmarkModel, load_landmarks
from .results import FEEDBACK_STATUSES, TrackResult
from .skeleton import Skeleton
from .smoothing import gaussian_smooth, rts_smooth, runs

N_KP = len(KEYPOINTS)
WAIST_RATIOS = (0.2, 0.35, 0.5, 0.65)


class OfflineError(VmocapError):
    """A recording that the offline pass cannot reconstruct (e.g. never tracked)."""


def smooth_keypoints(x: np.ndarray, config: SkeletonConfig) -> np.ndarray:
    """The offline smoother of one segment's keypoints (T, 25, 3)."""
    if config.offline_smoother == "gaussian":
        return gaussian_smooth(x, config.offline_gaussian_sigma_frames)
    return rts_smooth(x, smoother_model(config))


def _spread(n: int, k: int) -> np.ndarray:
    return np.unique(np.linspace(0, n - 1, min(k, n)).round().astype(int))


def confident(markers: np.ndarray, weights: np.ndarray, quantile: float) -> np.ndarray:
    """Markers (N, 25, 3) with those below `quantile` of their keypoint's weights (N, 25) over
    the recording set to NaN (0: all kept)."""
    if quantile <= 0:
        return markers
    w = np.where(weights > 0, weights, np.nan)
    known = np.isfinite(w).any(axis=0)
    thr = np.full(w.shape[1], np.inf)
    thr[known] = np.nanquantile(w[:, known], quantile, axis=0)
    return np.where((weights >= thr)[:, :, None], markers, np.nan)


def identify_subject(frames: np.ndarray, max_fit_error_m: float, n_fit: int = 16, n_offsets: int = 48,
                     landmarks: LandmarkModel | None = None) -> Skeleton:
    """Skeleton of the subject from virtual markers (N, 25, 3; NaN unknown; joint centres) of
    a whole recording: link lengths by medians over all frames, waist height by the mean fit
    over `n_fit` frames spread through it, face/foot offsets on `n_offsets` frames."""
    dims = identify_dimensions(frames, landmarks)
    bad = [f.name for f in dataclasses.fields(dims) if isinstance(getattr(dims, f.name), float)
           and not np.isfinite(getattr(dims, f.name))]
    if bad:
        raise OfflineError(f"cannot identify the subject: no measurement of {', '.join(bad)}")
    pick = frames[_spread(len(frames), n_fit)]
    best: tuple[float, Skeleton, np.ndarray | None] | None = None
    for ratio in WAIST_RATIOS:
        sk = Skeleton(dataclasses.replace(dims, waist_ratio=ratio))
        costs, q_first = [], None
        for f in pick:
            w = np.isfinite(f).all(axis=1).astype(float)
            fit = solve_ik(sk, initial_pose(sk, f), f, w, 60, damping=1e-2, regularization=1e-6, line_search=True)
            costs.append(fit.cost)
            q_first = fit.q if q_first is None else q_first
        rms = float(np.sqrt(np.nanmedian(costs)))
        if best is None or rms < best[0]:
            best = (rms, sk, q_first)
    if best is None:
        raise OfflineError("cannot identify the subject: no frame to fit")
    rms, sk, q0 = best
    if not rms <= max_fit_error_m:
        raise OfflineError(f"the markers do not show one body: median fit {rms * 1000:.0f} mm RMS")
    sub = frames[_spread(len(frames), n_offsets)]
    return refine_offsets(sk, sub, q0)


def _first_ik(sk: Skeleton, markers: np.ndarray, weights: np.ndarray, data: np.ndarray, config: SkeletonConfig,
              bar: tqdm) -> tuple[np.ndarray, np.ndarray]:
    """Forward first IK over one segment: (q (T, nq), keypoints (T, 25, 3)); frames that are not
    `data` (T,) keep the last pose and have NaN keypoints: no measurement for the smoother."""
    T = len(markers)
    w0 = np.where(np.isfinite(markers[0]).all(axis=1), weights[0], 0.0)
    q = solve_ik(sk, initial_pose(sk, markers[0]), markers[0], w0, 60, damping=1e-2, regularization=1e-6,
                 line_search=True).q
    qs, kps = np.empty((T, len(q))), np.empty((T, N_KP, 3))
    prior_w = config.offline_ik_prior_weight * (config.fps / 60.0) ** 2
    for t in range(T):
        if not data[t]:
            qs[t], kps[t] = q, np.nan
            continue
        r = solve_ik(sk, q, markers[t], weights[t], config.offline_ik_iterations, damping=config.ik_damping,
                     regularization=config.ik_regularization, prior=q if prior_w > 0 else None, prior_weight=prior_w)
        q = r.q
        qs[t], kps[t] = r.q, r.keypoints
        bar.update()
    return qs, kps


def _second_ik(sk: Skeleton, targets: np.ndarray, q_first: np.ndarray, data: np.ndarray, config: SkeletonConfig,
               bar: tqdm) -> tuple[np.ndarray, np.ndarray]:
    """Second IK to the smoothed keypoints (warm start; restart from the first IK's pose when
    the fit stays poor, as the live stage does); frames that are not `data` are skipped."""
    T = len(targets)
    ones = np.ones(N_KP)
    qs, kps = np.empty_like(q_first), np.empty_like(targets)
    q = q_first[0]
    for t in range(T):
        if not data[t]:  # a bridged gap: no output there
            qs[t], kps[t] = q, np.nan
            continue
        r = solve_ik(sk, q, targets[t], ones, config.offline_second_ik_iterations, damping=config.ik_damping,
                     regularization=config.ik_regularization)
        if r.cost > config.second_ik_restart_m**2:
            retry = solve_ik(sk, q_first[t], targets[t], ones, config.offline_second_ik_iterations,
                             damping=config.ik_damping, regularization=config.ik_regularization)
            r = retry if retry.cost < r.cost else r
        q = r.q
        qs[t], kps[t] = r.q, r.keypoints
        bar.update()
    return qs, kps


def segments(stamps_ns: np.ndarray, tracked: np.ndarray, bridgeable: np.ndarray | None = None,
             bridge: int = 0) -> list[slice]:
    """Runs of tracked frames, also split where frame sets are missing (a stamp step over 1.5
    frame periods): the smoother must not bridge a gap. Runs apart by at most `bridge` frames,
    all `bridgeable`, are one segment (the frames between are not tracked: no data)."""
    if len(stamps_ns) > 1:
        dt = np.diff(stamps_ns)
        jump = np.concatenate([[False], dt > 1.5 * np.median(dt)])
    else:
        jump = np.zeros(len(stamps_ns), dtype=bool)
    out = []
    for seg in runs(tracked):
        cuts = [seg.start] + [int(i) for i in np.flatnonzero(jump[seg.start + 1:seg.stop]) + seg.start + 1] + [seg.stop]
        out += [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:])]
    if bridgeable is None or bridge <= 0:
        return out
    merged: list[slice] = []
    for seg in out:
        prev = merged[-1] if merged else None
        if (prev is not None and 0 < seg.start - prev.stop <= bridge and bridgeable[prev.stop:seg.start].all()
                and not jump[prev.stop:seg.start + 1].any()):
            merged[-1] = slice(prev.start, seg.stop)
        else:
            merged.append(seg)
    return merged


def tracked_frames(status: Sequence[str], stamps_ns: np.ndarray) -> np.ndarray:
    """(N,) bool: the frames that are data. Those whose skeleton the images disagreed with
    ("uncertain" within a track) are gaps; a track starts "uncertain" until the images agree
    with it (SkeletonStage._start_tracking, also after a gap of RESUME_GAP_S), and those frames
    are data once it went on to "tracking"."""
    s = np.asarray(status, dtype=object)
    tracked = np.isin(s, [x for x in FEEDBACK_STATUSES if x != "uncertain"])
    gap = np.concatenate([[True], np.diff(np.asarray(stamps_ns, dtype=np.int64)) > int(RESUME_GAP_S * 1e9)])
    for run in runs(s == "uncertain"):
        starts_a_track = gap[run.start] or s[run.start - 1] not in ("tracking", "smoothing")
        if starts_a_track and run.stop < len(s) and s[run.stop] == "tracking":
            tracked[run] = True
    return tracked


def reconstruct(results: Sequence[TrackResult], config: SkeletonConfig, progress: bool = False) -> list[TrackResult]:
    """The offline pass over the live tracker's results of a whole recording (one person):
    new results, one per input, "tracking" on every frame of a tracked segment (the
    identification phase included), the input's status elsewhere."""
    return identify_and_reconstruct(results, config, progress)[0]


def identify_and_reconstruct(results: Sequence[TrackResult], config: SkeletonConfig,
                             progress: bool = False) -> tuple[list[TrackResult], Skeleton]:
    """`reconstruct`, also returning the identified skeleton."""
    tracked = tracked_frames([r.status for r in results], np.array([r.stamp_ns for r in results], dtype=np.int64))
    if not tracked.any():
        raise OfflineError("the recording has no tracked frame: nothing to reconstruct")
    markers = np.array([np.where((r.scores > 0)[:, None], r.markers, np.nan) for r in results])
    weights = np.array([np.where(np.isfinite(r.markers).all(axis=1), r.scores, 0.0) for r in results])
    sk = identify_subject(confident(markers[tracked], weights[tracked], config.offline_identify_quantile),
                          config.init_max_fit_error_m, landmarks=load_landmarks(config.landmarks))
    out = list(results)
    names = results[0].joint_names
    lengths = sk.dims.bone_lengths()
    uncertain = np.array([r.status == "uncertain" for r in results])
    segs = segments(np.array([r.stamp_ns for r in results], dtype=np.int64), tracked, uncertain, config.offline_bridge_frames)
    bar = tqdm(total=2 * int(tracked.sum()), desc="offline IK", unit="frame", disable=not progress, leave=False)
    for seg in segs:
        m, w = markers[seg], weights[seg]
        q1, kp1 = _first_ik(sk, m, w, tracked[seg], config, bar)
        q2, kp2 = _second_ik(sk, smooth_keypoints(kp1, config), q1, tracked[seg], config, bar)
        for i, t in enumerate(range(seg.start, seg.stop)):
            if not tracked[t]:
                continue  # a bridged gap keeps its input (uncertain) result
            r = results[t]
            out[t] = TrackResult(r.stamp_ns, "tracking", sk.to_angles(q2[i]), names, kp2[i], kp1[i], r.scores,
                                 r.markers, lengths, sk.dims, confidence=r.confidence)
    bar.close()
    return out, sk
