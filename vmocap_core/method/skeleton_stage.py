"""The skeleton stage (paper II-C, II-E, II-F): virtual markers -> the subject's skeleton.

Identification once the views agree (init.py); then per frame the weighted first IK to the
virtual markers (ik.py, eq. 3-4) with a motion prior, the low-pass of the keypoint positions
(filter.py; or a fixed-lag RTS smoother), and the second IK to the smoothed positions, so the
output is smooth and keeps constant link lengths. The markers carry the check of the previous
skeleton against the images (consistency.py): a skeleton the views keep disagreeing with is
"uncertain" (tracked, not output) and then "lost" (started over).
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import numpy as np

from ..keypoints import INDEX
from .config import SkeletonConfig
from .consistency import RESUME_GAP_S, Verdict, ViewCheck, WeightTrend
from .filter import make_filter, smoother_model
from .held import held_warning
from .ik import solve_ik
from .ik import warm_up as warm_up_ik
from .init import InitFrames, fit_skeleton, identify_dimensions, length_offset
from .landmarks import load_landmarks
from .one_euro import OneEuroFilter
from .path_gate import PathGate
from .results import N_KP, Markers, TrackResult
from .skeleton import Skeleton
from .smoothing import FixedLagSmoother

REACQUIRE_LENGTHS = 0.15  # a body found again whose link lengths are the subject's within this (median ratio)
# A new body whose link lengths are within this of a skeleton identified for someone who left
# (`SkeletonStage.known`): that person come back. Tighter than REACQUIRE_LENGTHS: the
# skeleton may be another person's.
REMEMBERED_LENGTHS = 0.05


class SkeletonStage:
    """Markers -> skeleton: identification, first IK (eq. 3-4), low-pass, second IK."""

    def __init__(self, config: SkeletonConfig | None = None) -> None:
        self.config = config or SkeletonConfig()
        self.skeleton: Skeleton | None = None
        self._buffer = InitFrames(self.config.init_frames, limb_gaps=self.config.identify_frames > 0)
        self._identify: list[np.ndarray] | None = None  # markers of the identification phase
        self._identify_start_ns = 0  # capture stamp of its first frame set
        self._q_raw: np.ndarray | None = None
        self._q_out: np.ndarray | None = None
        self._filter = make_filter(self.config)
        self._landmarks = load_landmarks(self.config.landmarks)
        self._last_correction: tuple[np.ndarray | None, np.ndarray] = (None, np.zeros((N_KP, 3)))
        # Fixed-lag mode: the smoother and the frames (stamp, weights, markers, first-IK q) it delays.
        lag = self.config.smoothing_lag_frames
        self._lag = FixedLagSmoother(smoother_model(self.config), lag) if lag > 0 else None
        self._delayed: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=lag + 1)
        self.status = "initializing"
        cfg = self.config
        self.verdict = Verdict(cfg.check_min_agreement, cfg.check_uncertain_frames, cfg.check_recover_frames,
                               cfg.check_lost_frames, cfg.check_fail_agreement, cfg.check_fail_frames,
                               cfg.check_min_support, cfg.check_fail_support)
        self.init_problem: str | None = None  # why the last skeleton fit failed (init_report.py)
        self.disagreement: ViewCheck | None = None  # the check behind an "uncertain" or check-"lost" step
        self.unsupported: float | None = None  # the markers' support behind an "uncertain" step (below check_min_support)
        self.weights = WeightTrend(cfg.check_weight_window)
        self.path = PathGate(cfg.check_resume_max_m, cfg.check_resume_horizon_s)
        # metres (horizontal) from the subject's path behind a "lost" step, and the bound (path_gate.py)
        self.strayed: tuple[float, float] | None = None
        self._pelvis = np.full(3, np.nan)  # the track's hip centre (the last first IK's)
        self.outside: int | None = None  # the cameras holding the trunk behind an "uncertain" step (fewer than 2)
        self.faded: float | None = None  # the markers' weight ratio behind an "uncertain" step (below check_min_weight_ratio)
        self._last_stamp: int | None = None
        # frame sets in a row that passed every rule since the output was held (None: flowing)
        self._passed: int | None = None
        self.resuming: int | None = None  # the passing frame sets behind an "uncertain" step (below check_resume_frames)
        # The skeleton identified for the subject: kept when the subject is lost, so that finding
        # it again needs no new identification phase (II-C identifies a body once).
        self.identified: Skeleton | None = None
        # Skeletons identified for people who left (several people: PeopleTracker): a new body
        # that is one of them needs no identification phase either.
        self.known: list[Skeleton] = []
        self._joint_names = Skeleton().joint_names
        self.timings: dict[str, float] = {}
        warm_up_ik()

    @property
    def joint_names(self) -> list[str]:
        return self._joint_names

    @property
    def provisional(self) -> bool:
        """Output from the provisional skeleton (identify_output), whose lengths change at identification's end."""
        return self._identify is not None and self.config.identify_output

    def reset(self) -> None:
        self.skeleton = None
        self._buffer.clear()
        self._identify = None
        self._q_raw = self._q_out = None
        self._filter.reset()
        if self._lag is not None:
            self._lag.reset()
        self._delayed.clear()
        self.verdict.reset()
        self.weights.reset()
        self.path.reset()
        self._passed = None
        self.status = "initializing"

    def warning(self, status: str, names: list[str]) -> str | None:
        """Why the last step's status is `status` (uncertain or lost) when the images said so,
        for the diagnostics (None when they did not; held.py)."""
        return held_warning(self, status, names)

    def step(self, markers: Markers) -> TrackResult:
        self.disagreement = self.unsupported = self.outside = self.faded = self.strayed = self.resuming = None
        if markers.kind == "lattice" and self.skeleton is not None:
            # markers again after frame sets without any (every view covered, or none came for
            # RESUME_GAP_S): the skeleton is the one from before, so the output waits for the
            # images to agree with it again
            resumed = self.status == "lost" or (self._last_stamp is not None
                                                and markers.stamp_ns - self._last_stamp > RESUME_GAP_S * 1e9)
            verdict = self.verdict.update(markers.check)
            if resumed and verdict == "ok" and self._doubt():
                verdict = "uncertain"
            if verdict != "ok":  # what the diagnostics name: the keypoints and views that disagree
                self.disagreement = self.verdict.last
            judged = self.verdict.min_agreement > 0
            support = markers.support
            # this frame set's own markers, most of them seen by one camera only: the skeleton
            # fitted to them is not output, the track goes on (the next check decides)
            unsupported = judged and support is not None and support < self.config.check_min_support
            # a trunk whole in one camera's image only (walking out of the others): its depth
            # along that camera's rays is the landmark model's guess at the image edges, and
            # the skeleton slides with it while the views left agree
            trunk = markers.trunk_views
            outside = judged and trunk is not None and trunk < 2
            ratio = self.weights.ratio(markers.weights, markers.check, markers.inside, markers.contested)
            faded = judged and ratio is not None and ratio < self.config.check_min_weight_ratio
            if verdict == "ok" and unsupported:
                verdict, self.unsupported = "uncertain", support
            elif verdict == "ok" and outside:
                verdict, self.outside = "uncertain", trunk
            elif verdict == "ok" and faded:
                verdict, self.faded = "uncertain", ratio
            # held back before: output resumes on the check_resume_frames-th frame set in a row
            # that passes every rule (the hysteresis forgives one bad check only while it flows)
            passed = not (self.verdict.disagreed or unsupported or outside or faded)
            if self._passed is not None:
                self._passed = self._passed + 1 if passed else 0
                if verdict == "ok" and self._passed < self.config.check_resume_frames:
                    verdict = "uncertain"
                    if self.verdict.disagreed:
                        self.disagreement = self.verdict.last
                    else:
                        self.resuming = self._passed
            if verdict == "lost":  # the images disagreed for check_lost_frames: start over
                # off the subject's path: look where it was heading (None: where the track is)
                seed = self.path.strayed(markers.stamp_ns, self._pelvis)
                self.reset()
                self.status = "lost"
                result = self._empty(markers, "lost")
                result.seed = seed
            else:
                was = self.status
                result = self._track(markers)
                if verdict == "uncertain" and result.status == "tracking":
                    if was == "tracking":  # the path's last points may already lean on another body
                        self.path.doubt(markers.stamp_ns)
                    result.status = self.status = "uncertain"
                elif result.status == "tracking":
                    result = self._confirmed(markers, result, resumed=was == "uncertain")
            if markers.check is not None:
                result.confidence = markers.check.confidence.copy()
            if result.status == "uncertain" and self._passed is None:
                self._passed = int(passed)  # output held: count the frame sets that pass from here
            elif result.status == "tracking":
                self._passed = None
            return result
        if markers.kind == "triangulated" and self.skeleton is not None:
            self.reset()
            self.status = "lost"
        if self.skeleton is None:
            return self._initialize(markers)
        self.status = "lost"
        return self._empty(markers, "lost")

    def _confirmed(self, markers: Markers, result: TrackResult, resumed: bool) -> TrackResult:
        """A frame set the images agree with: on the subject's path, or, back from doubt far
        from it, another body (path_gate.py): lost, with where to look for the subject. When
        the detector's census saw nobody else in view, the body the images agree with is the
        subject, off its path by its own motion (a flip, a dive): the track goes on."""
        pelvis = result.raw_keypoints[INDEX["pelvis"]]
        seed = self.path.strayed(markers.stamp_ns, pelvis) if resumed and markers.others != 0 else None
        if seed is not None:
            self.strayed = (float(np.linalg.norm((pelvis - seed)[:2])), self.path.bound(markers.stamp_ns))
            self.reset()
            self.status = "lost"
            lost = self._empty(markers, "lost")
            lost.seed = seed
            return lost
        self.path.add(markers.stamp_ns, pelvis)
        return result

    def _track(self, markers: Markers) -> TrackResult:
        cfg = self.config
        sk = self.skeleton
        assert sk is not None  # step tracks only with a skeleton
        t0 = time.perf_counter()
        dt = self._skipped_interval(markers.stamp_ns)
        rate = cfg.fps if dt is None else 1.0 / dt
        centres = self._centres(markers.positions, self._q_raw)
        first = solve_ik(sk, self._q_raw, centres, markers.weights, cfg.ik_iterations,
                         damping=cfg.ik_damping, regularization=cfg.ik_regularization,
                         prior=self._q_raw, prior_weight=cfg.ik_prior_weight * (rate / 60.0) ** 2)
        self._q_raw = first.q
        sites = self._sites(first.keypoints, first.q)
        self._pelvis = sites[INDEX["pelvis"]]
        if self._identify is not None:
            if not cfg.identify_output:
                return self._identifying(markers, centres, sites)
            done = self._identify_step(markers)
            if done is not None:  # identified: the pose carries on with the new skeleton
                sk, first = done
                self.skeleton = self.identified = sk
                self._q_raw = first.q.copy()
                centres = self._centres(markers.positions, first.q)
                sites = self._sites(first.keypoints, first.q)
                self._pelvis = sites[INDEX["pelvis"]]
            if self._q_out is None:  # the phase's first output: the second IK starts at the first's pose
                self._q_out = first.q.copy()
        t1 = time.perf_counter()
        frame = (markers.stamp_ns, markers.weights.copy(), centres.copy(), first.q)
        if self._lag is not None:
            smooth = self._lag(first.keypoints)
            self._delayed.append(frame)
            if smooth is None:
                return self._smoothing(markers, sites)
            frame = self._delayed[0]  # the output is the frame `lag` back
        elif isinstance(self._filter, OneEuroFilter):
            smooth = self._filter(first.keypoints, dt)
        else:
            smooth = self._filter(first.keypoints)
        t2 = time.perf_counter()
        second = solve_ik(sk, self._q_out, smooth, np.ones(N_KP), cfg.second_ik_iterations,
                          damping=cfg.ik_damping, regularization=cfg.ik_regularization)
        if second.cost > cfg.second_ik_restart_m**2:
            # The smoothed targets lie near the first IK's pose: restart from it when the
            # warm start is caught in another branch (e.g. an arm twisted at a joint limit).
            retry = solve_ik(sk, frame[3], smooth, np.ones(N_KP), cfg.second_ik_iterations,
                             damping=cfg.ik_damping, regularization=cfg.ik_regularization)
            if retry.cost < second.cost:
                second = retry
        self._q_out = second.q
        self.status = "tracking"
        angles = sk.to_angles(second.q)
        t3 = time.perf_counter()
        self.timings = {"ik": t1 - t0, "filter": t2 - t1, "ik2": t3 - t2}
        return TrackResult(frame[0], "tracking", angles, self._joint_names,
                           second.keypoints, sites, frame[1], frame[2], sk.dims.bone_lengths(), sk.dims,
                           feedback_stamp_ns=markers.stamp_ns)

    def _centres(self, positions: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Virtual markers (the CNN's landmarks) -> joint centres, with the segments turned as
        in pose q (the previous frame's: the turn in 1/60 s moves an offset by < 1 mm)."""
        if self._landmarks is None or self.skeleton is None:
            return positions
        return positions - self._correction(q)

    def _sites(self, keypoints: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Joint centres in pose q -> where the CNN's landmarks are: what the lattice search
        and the crops are fed back."""
        if self._landmarks is None or self.skeleton is None:
            return keypoints.copy()
        return keypoints + self._correction(q)

    def _correction(self, q: np.ndarray) -> np.ndarray:
        """The landmark offsets in pose q; the feedback's pose is the next frame set's warm
        start, so each pose's correction is computed once."""
        assert self._landmarks is not None and self.skeleton is not None
        if self._last_correction[0] is not q:
            self._last_correction = (q, self._landmarks.correction(self.skeleton, q))
        return self._last_correction[1]

    def _smoothing(self, markers: Markers, raw: np.ndarray) -> TrackResult:
        """Fixed-lag window filling: feedback, no output yet."""
        self.status = "smoothing"
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, "smoothing", np.full(40, np.nan), self._joint_names, nan, raw.copy(),
                           markers.weights.copy(), markers.positions.copy(), {})

    def _skipped_interval(self, stamp_ns: int) -> float | None:
        """Seconds since the previous frame set when frame sets were skipped (a graph that falls
        behind), so the prior and the filter follow the real time; None at the nominal rate."""
        last, self._last_stamp = self._last_stamp, stamp_ns
        if last is None or stamp_ns <= last:
            return None
        dt = (stamp_ns - last) / 1e9
        nominal = 1.0 / self.config.fps
        return None if abs(dt / nominal - 1.0) < 0.25 else float(min(dt, 10 * nominal))

    def _empty(self, markers: Markers, status: str) -> TrackResult:
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, status, np.full(40, np.nan), self._joint_names, nan, nan.copy(),
                           markers.weights.copy(), markers.positions.copy(), {})

    def _initialize(self, markers: Markers) -> TrackResult:
        cfg = self.config
        status = "lost" if self.status == "lost" else "initializing"
        self.status = "initializing"
        if markers.kind != "triangulated":
            return self._empty(markers, status)
        frames = self._buffer.add(markers.positions)
        if frames is None:
            return self._empty(markers, status)
        fitted = fit_skeleton(frames, cfg.init_max_fit_error_m, landmarks=self._landmarks)
        if fitted is None:
            self._buffer.drop_oldest()
            self.init_problem = (f"the views agree, but {cfg.init_frames} frame sets of triangulated keypoints do not "
                                 f"fit one skeleton within init_max_fit_error_m = {cfg.init_max_fit_error_m:g} m")
            return self._empty(markers, status)
        self.init_problem = None
        sk, fit = fitted
        again = self._same_subject(markers, sk, fit)
        if again is not None:
            return self._start_tracking(markers, *again)
        self.skeleton = sk
        self._q_raw = fit.q.copy()
        if cfg.identify_frames > 0:
            self._identify = []
            self._identify_start_ns = markers.stamp_ns
            if cfg.identify_output:
                self._doubt()  # as _start_tracking: output once the images agree
            return self._identifying(markers, self._centres(markers.positions, fit.q), self._sites(fit.keypoints, fit.q))
        return self._start_tracking(markers, sk, fit)

    def _same_subject(self, markers: Markers, sk: Skeleton, fit: Any) -> tuple[Skeleton, Any] | None:
        """A body identified before found again: its skeleton posed on the new triangulation,
        when the newly fitted link lengths are its own (median ratio within REACQUIRE_LENGTHS of
        this track's own skeleton, REMEMBERED_LENGTHS of a `known` one; the nearest first) and
        it fits within init_max_fit_error_m; None for a body to identify anew."""
        new = sk.dims.bone_lengths()
        before = self.skeleton  # borrowed below: each candidate's landmark offsets
        near: list[tuple[float, int, Skeleton]] = []
        bounds = [(self.identified, REACQUIRE_LENGTHS)] + [(k, REMEMBERED_LENGTHS) for k in self.known]
        for i, (known, bound) in enumerate(bounds):
            if known is None:
                continue
            off = length_offset(new, known.dims.bone_lengths())
            if off <= bound:
                near.append((off, i, known))
        for _, _, known in sorted(near, key=lambda n: n[:2]):
            self.skeleton = known  # its landmark offsets turn the markers into joint centres
            centres = self._centres(markers.positions, fit.q)
            w = np.isfinite(centres).all(axis=1).astype(float)
            refit = solve_ik(known, fit.q, centres, w, 30, damping=1e-2, regularization=1e-6, line_search=True)
            if np.sqrt(refit.cost) <= self.config.init_max_fit_error_m:
                return known, refit
        self.skeleton = before
        return None

    def _remembered(self, markers: Markers) -> tuple[Skeleton, Any] | None:
        """During identification, every init_frames-th frame set: the skeleton of someone who
        left (`known`) when the last init_frames frame sets have its link lengths (_same_subject).
        The first fit of a person walking back in is made while parts of them are still outside
        some views, and its lengths may miss theirs; a few frame sets later they are in view."""
        cfg = self.config
        assert self._identify is not None  # called while identifying
        if not self.known or len(self._identify) % cfg.init_frames:
            return None
        frames = np.array(self._identify[-cfg.init_frames:])
        # the fit costs tens of ms: only for lengths near a known body's (the landmarks' own
        # lengths, before their offsets are removed, as the fit's first pass takes them)
        rough = identify_dimensions(frames).bone_lengths()
        if min(length_offset(rough, k.dims.bone_lengths()) for k in self.known) > REACQUIRE_LENGTHS:
            return None
        fitted = fit_skeleton(frames, cfg.init_max_fit_error_m, self._q_raw, self._landmarks)
        return None if fitted is None else self._same_subject(markers, *fitted)

    def _identify_step(self, markers: Markers) -> tuple[Skeleton, Any] | None:
        """One frame set of the identification phase, its markers collected for identify_seconds of capture time
        (fewer frame sets when some are skipped: a graph that falls behind starts as late as one that keeps up);
        at the phase's end (or a remembered body recognized) the skeleton and its fit to this frame set."""
        cfg = self.config
        assert self._identify is not None and self.skeleton is not None  # started by the first fit
        self._identify.append(np.where((markers.weights > 0)[:, None], markers.positions, np.nan))
        again = self._remembered(markers)
        if again is not None:
            self._identify = None
            return again
        span_frames = (markers.stamp_ns - self._identify_start_ns) * 1e-9 * cfg.fps + 1
        if len(self._identify) < cfg.identify_frames and span_frames < cfg.identify_frames - 0.5:
            return None
        frames = np.array(self._identify)
        self._identify = None
        fitted = fit_skeleton(frames, cfg.init_max_fit_error_m, self._q_raw, self._landmarks)
        if fitted is not None:
            return fitted
        centres = self._centres(markers.positions, self._q_raw)
        fit = solve_ik(self.skeleton, self._q_raw, centres, np.isfinite(frames[-1]).all(axis=1).astype(float),
                       30, damping=1e-2, regularization=1e-6, line_search=True)
        return self.skeleton, fit

    def _identifying(self, markers: Markers, centres: np.ndarray, raw: np.ndarray) -> TrackResult:
        """Identification without output (identify_output false): "identifying" until _identify_step's skeleton."""
        done = self._identify_step(markers)
        if done is not None:
            return self._start_tracking(markers, *done)
        self.status = "identifying"
        nan = np.full((N_KP, 3), np.nan)
        return TrackResult(markers.stamp_ns, "identifying", np.full(40, np.nan), self._joint_names, nan, raw.copy(),
                           markers.weights.copy(), centres.copy(), {})

    def _start_tracking(self, markers: Markers, sk: Skeleton, fit: Any) -> TrackResult:
        """Tracking starts, its output once the images agree with the skeleton (Verdict.doubt):
        a skeleton identified or found again by triangulation may fit the wrong body (views that
        see another person, a body identified while it dived into a roll)."""
        result = self._started(markers, sk, fit)
        if self._doubt() and result.status == "tracking":
            result.status = self.status = "uncertain"
        return result

    def _doubt(self) -> bool:
        """A track (re)starting is output once check_confirm_frames agreed with it; False: the check is off."""
        if self.verdict.min_agreement <= 0 or self.config.check_confirm_frames <= 0:
            return False
        self.verdict.doubt(self.config.check_confirm_frames)
        return True

    def _started(self, markers: Markers, sk: Skeleton, fit: Any) -> TrackResult:
        self.skeleton = self.identified = sk
        self._q_raw = fit.q.copy()
        self._q_out = fit.q.copy()
        self._filter.reset()
        self._filter(fit.keypoints)
        centres, sites = self._centres(markers.positions, fit.q), self._sites(fit.keypoints, fit.q)
        if self._lag is not None:
            self._lag.reset()
            self._delayed.clear()
            self._delayed.append((markers.stamp_ns, markers.weights.copy(), centres.copy(), fit.q.copy()))
            self._lag(fit.keypoints)
            return self._smoothing(markers, sites)
        self.status = "tracking"
        return TrackResult(markers.stamp_ns, "tracking", sk.to_angles(fit.q), self._joint_names, fit.keypoints,
                           sites, markers.weights.copy(), centres,
                           sk.dims.bone_lengths(), sk.dims)
