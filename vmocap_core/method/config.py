"""The method's tunables: one dataclass per stage, read from that stage's node section.

MarkersConfig  -> the marker stage (initial triangulation, lattice search, re-acquisition,
                  lost person): the `vmocap_markers` section of a graph config.
SkeletonConfig -> the skeleton stage (identification, first IK, low-pass, second IK, and the
                  offline passes): the `vmocap_skeleton` section; `fps` is the graph's frame
                  rate, set once in the shared '/**' section.
PipelineConfig -> both, for code that runs the whole method in one place.

Every `from_dict` rejects a key no stage declares, naming it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, TypeVar

from ..errors import VmocapError


class ConfigError(VmocapError, ValueError):
    """A tunable of the method that is unknown or out of range."""


_C = TypeVar("_C", bound="_Stage")


class _Stage:
    """from_dict / to_dict / replace shared by the stage configs."""

    @classmethod
    def from_dict(cls: type[_C], d: dict[str, Any] | None) -> _C:
        d = dict(d or {})
        unknown = sorted(set(d) - cls.names())
        if unknown:
            raise ConfigError(f"unknown {cls.__name__} parameters: {', '.join(unknown)} "
                              f"(known: {', '.join(sorted(cls.names()))})")
        cfg = cls(**d)
        cfg.validate()
        return cfg

    @classmethod
    def names(cls) -> set[str]:
        return {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def replace(self: _C, **changes: Any) -> _C:
        cfg = dataclasses.replace(self, **changes)  # type: ignore[type-var]
        cfg.validate()
        return cfg

    def validate(self) -> None:
        pass


@dataclass
class MarkersConfig(_Stage):
    """PCMs -> virtual markers (II-C triangulation, II-D lattice search)."""

    lattice_k: int = 5
    lattice_spacing: float = 0.02  # metres; sub-lattice refinement recovers the precision
    coarse_to_fine: bool = True  # same volume, ~9x fewer samples; measured equal to the full search
    subcell: bool = True
    prediction: str = "previous"  # lattice centre: "previous" (paper) or "constant_velocity"
    min_views: int = 2  # a marker seen by fewer views gets weight 0
    # Our addition (refinement.py): move each lattice marker to the robust triangulation of the
    # views' own PCM peaks within `refine_radius_cells` of its projection (False = the lattice
    # argmax, as in the paper). W stays the lattice sum.
    refine_markers: bool = True
    refine_radius_cells: int = 5
    refine_max_error_px: float = 12.0
    reacquire_weight: float = 1.0  # a marker weaker than this triggers a search at its PCM peaks
    reacquire_radius: float = 0.6  # metres from the previous keypoint a re-acquired one may lie
    reacquire_after: int = 2  # consecutive weak frames before the search at the PCM peaks
    # Our addition (mirror.py): a view whose maps read a limb group this many times higher with
    # its left and right swapped (and at least unmirror_min_value) is read swapped; 0: never
    unmirror_ratio: float = 1.5
    unmirror_min_value: float = 0.5
    init_max_reprojection_px: float = 12.0  # views agree: triangulation residual below this
    # a centroid counts when its PCM peak is at least this, before the landmark visibility
    # weighed it (PcmViews.visibility): the start triangulates the CNN's guesses of hidden
    # keypoints too, as the paper's II-C does, and checks them by their residuals
    init_min_peak: float = 0.3
    lost_score: float = 0.15  # mean marker weight per view below this ...
    lost_frames: int = 10  # ... for this many frames -> re-initialize

    def validate(self) -> None:
        if self.refine_radius_cells < 1 or self.refine_max_error_px <= 0:
            raise ConfigError("refine_radius_cells must be >= 1 and refine_max_error_px > 0")
        if self.lattice_k < 0 or self.lattice_spacing <= 0:
            raise ConfigError("lattice_k must be >= 0 and lattice_spacing > 0")
        if self.prediction not in ("previous", "constant_velocity"):
            raise ConfigError(f"prediction must be 'previous' or 'constant_velocity', not {self.prediction!r}")


@dataclass
class SkeletonConfig(_Stage):
    """Virtual markers -> skeleton (II-C identification, II-E IK, II-F low-pass, second IK)."""

    fps: float = 60.0
    ik_iterations: int = 3  # first IK (to the virtual markers), warm-started
    second_ik_iterations: int = 1  # second IK (to the smoothed positions, which move little)
    ik_damping: float = 1e-3
    ik_regularization: float = 1e-5
    # Motion prior of the first IK (our addition): weight of the squared tangent-space distance
    # to the previous frame's pose against the weighted mean squared marker residual (m^2),
    # given for 60 fps and scaled by (rate / 60)^2: the motion per frame scales with 1 / rate.
    ik_prior_weight: float = 2e-3
    second_ik_restart_m: float = 0.02  # RMS fit error of the second IK that triggers a restart
    # Low-pass (II-F): "one_euro" (first order, cutoff rising with each keypoint's speed; our
    # default, see docs/benchmarks.md) or "butterworth" (the paper's fixed IIR, settings below).
    filter_kind: str = "one_euro"
    filter_min_cutoff_hz: float = 1.0
    filter_beta: float = 10.0  # Hz of cutoff per m/s
    filter_derivative_cutoff_hz: float = 2.0
    filter_order: int = 1
    filter_cutoff_hz: float = 3.0
    filter_lag_compensation: bool = True
    # Rauch-Tung-Striebel smoothing of the first IK's keypoints (smoothing.py) on a kinematic
    # model ("cv" constant velocity, "ca" constant acceleration). smoothing_lag_frames > 0
    # replaces the low-pass live: each output is the frame that many frames back.
    smoothing_lag_frames: int = 0
    smoother_model: str = "ca"
    smoother_process_noise: float = 2000.0  # (m/s^3)^2/Hz for "ca", (m/s^2)^2/Hz for "cv"
    smoother_measurement_noise_m: float = 0.02
    # Offline mode (offline.py, whole recordings only): identification on all tracked frames,
    # first IK, fixed-interval smoothing ("rts" or zero-phase "gaussian"), second IK. Read by
    # `vmocap process` and `vmocap bench accuracy`; the live stage ignores it.
    offline: bool = False
    offline_smoother: str = "rts"
    offline_gaussian_sigma_frames: float = 1.5
    offline_ik_iterations: int = 3
    offline_ik_prior_weight: float = 5e-4  # weaker than live: the smoother does the prior's work
    offline_second_ik_iterations: int = 3
    # At most this many frame sets in a row that the images disagreed with ("uncertain") inside
    # a track do not end its segment: they stay gaps in the output, but the smoother carries the
    # motion across them (0: every such frame set ends a segment).
    offline_bridge_frames: int = 3
    # Identification from confident markers only: each keypoint's markers whose weight reaches
    # this quantile of its weights over the recording (0: every marker). On rendered images with
    # the real CNN 0.75 identifies better (docs/image_benchmark.md); on the synthetic noise
    # model, whose weights say less about a marker's error, it does worse: off by default.
    offline_identify_quantile: float = 0.0
    init_frames: int = 5  # consecutive frames the views agree in (II-C; skeleton_stage: limb keypoints' gaps)
    # Our addition: after the provisional fit on those frames, track this long and identify
    # the link lengths again on all of those frames' virtual markers; the output keeps these.
    # 0: the provisional fit is final (the paper).
    identify_seconds: float = 0.5
    # Output during identification, from the provisional skeleton (its link lengths from
    # init_frames frame sets; the identified ones replace them at the phase's end, the filter
    # carrying the pose across): a body 0.5 s sooner for a controller. False: no output then.
    identify_output: bool = True
    init_max_fit_error_m: float = 0.04  # skeleton fit residual (RMS) to confirm
    # Where the PCM model's keypoints lie relative to the joint centres (landmarks.py): "auto"
    # (the PCM source's own: "blazepose" for the CNN, "none" for the synthetic PCMs and PCM
    # bags), "none" (joint centres), a shipped model ("blazepose") or a YAML file.
    landmarks: str = "auto"
    # Never confidently wrong (consistency.py): the fed-back skeleton's keypoints against each
    # view's PCM peaks. Below `check_min_agreement` (mean fraction of agreeing views per
    # keypoint) for `check_uncertain_frames` frame sets in a row the status is "uncertain" (no
    # output, tracking goes on), below `check_fail_agreement` for `check_fail_frames` in a row
    # (1: at once; a frame set every view contradicts is a body the skeleton is not on), until
    # `check_recover_frames` agree in a row; uncertain for `check_lost_frames` in a row: "lost",
    # start over from triangulation. check_min_agreement 0 disables the check. A frame set
    # also counts as disagreeing when fewer than `check_min_support` of the keypoints seen are
    # held by two cameras or more (one camera's rays do not fix a point); and a frame set whose
    # own lattice markers are below it is not output (uncertain for that frame set alone);
    # below `check_fail_support` it counts as failing, like check_fail_agreement.
    check_min_agreement: float = 0.6
    check_min_support: float = 0.6
    check_fail_agreement: float = 0.35
    check_fail_support: float = 0.35
    check_uncertain_frames: int = 3
    check_fail_frames: int = 1
    check_recover_frames: int = 5
    check_lost_frames: int = 30
    # A track (identified, or the subject found again) starts uncertain: output once this many
    # frame sets agreed with its skeleton (the first check of a new skeleton is the next frame
    # set's); 0: output from its first frame set.
    check_confirm_frames: int = 1
    # After a frame set held back (uncertain, for whatever reason), the output resumes on the
    # `check_resume_frames`-th frame set in a row that passes every rule: a track that flickers
    # between held and passing lies on the edge of another body or of the maps (1: at once).
    check_resume_frames: int = 2
    # A frame set whose markers weigh less than this share of the track's median over its last
    # `check_weight_window` frame sets (mean weight of the keypoints seen) is not output: the
    # CNN's maps fading, or the crops losing the body in several cameras at once, as a body
    # turns over while the tracker still follows what is left (0: off).
    check_min_weight_ratio: float = 0.55
    check_weight_window: int = 30
    # A track back from "uncertain" whose hip centre lies horizontally farther than
    # `check_resume_max_m` from where the confirmed track stopped or was heading (its velocity
    # carried for at most `check_resume_horizon_s`) has slid onto another body: lost, and the detector
    # looks for the subject at the expected place (path_gate.py; 0: off). Not while the
    # detector's census counts nobody else in view (Markers.others 0): then it is the subject.
    check_resume_max_m: float = 0.3
    check_resume_horizon_s: float = 0.4

    def validate(self) -> None:
        from .filter import make_filter, smoother_model

        if not 0 <= self.check_fail_agreement <= self.check_min_agreement <= 1:
            raise ConfigError("check_fail_agreement <= check_min_agreement must lie in [0, 1]")
        if not 0 <= self.check_fail_support <= self.check_min_support <= 1:
            raise ConfigError("check_fail_support <= check_min_support must lie in [0, 1]")
        if min(self.check_uncertain_frames, self.check_fail_frames, self.check_recover_frames, self.check_lost_frames) < 1:
            raise ConfigError("check_uncertain_frames, check_fail_frames, check_recover_frames and check_lost_frames must be >= 1")
        if self.check_confirm_frames < 0:
            raise ConfigError("check_confirm_frames must be >= 0")
        if self.check_resume_frames < 1:
            raise ConfigError("check_resume_frames must be >= 1")
        if not 0 <= self.check_min_weight_ratio < 1 or self.check_weight_window < 2:
            raise ConfigError("check_min_weight_ratio must lie in [0, 1) and check_weight_window be >= 2")
        if self.check_resume_max_m < 0 or self.check_resume_horizon_s < 0:
            raise ConfigError("check_resume_max_m and check_resume_horizon_s must be >= 0")

        if self.fps <= 0 or self.identify_seconds < 0:
            raise ConfigError("fps must be positive and identify_seconds >= 0")
        if self.ik_prior_weight < 0 or self.ik_regularization < 0:
            raise ConfigError("IK weights and regularizations must be >= 0")
        if not 0 < self.filter_cutoff_hz < self.fps / 2:
            raise ConfigError("filter_cutoff_hz must be below half the frame rate")
        if self.filter_kind not in ("one_euro", "butterworth"):
            raise ConfigError(f"filter_kind must be 'one_euro' or 'butterworth', not {self.filter_kind!r}")
        if self.smoothing_lag_frames < 0 or self.offline_smoother not in ("rts", "gaussian"):
            raise ConfigError("smoothing_lag_frames must be >= 0, offline_smoother 'rts' or 'gaussian'")
        if (self.offline_ik_iterations < 1 or self.offline_second_ik_iterations < 1 or self.offline_ik_prior_weight < 0
                or self.offline_bridge_frames < 0):
            raise ConfigError("offline IK iterations must be >= 1, the prior weight and offline_bridge_frames >= 0")
        if not 0 <= self.offline_identify_quantile < 1:
            raise ConfigError("offline_identify_quantile must lie in [0, 1)")
        from .landmarks import LandmarkError, load_landmarks

        try:
            load_landmarks(self.landmarks)
        except LandmarkError as exc:
            raise ConfigError(str(exc)) from None
        try:
            make_filter(self)  # the filter's and the motion model's own checks
            smoother_model(self)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    @property
    def identify_frames(self) -> int:
        """Frames of the identification phase (identify_seconds at this frame rate)."""
        return round(self.identify_seconds * self.fps)


@dataclass
class PipelineConfig:
    """Both stages' configs. `of(**flat)` and `from_dict(flat)` route each key to the stage
    that declares it."""

    markers: MarkersConfig = field(default_factory=MarkersConfig)
    skeleton: SkeletonConfig = field(default_factory=SkeletonConfig)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "PipelineConfig":
        d = dict(d or {})
        m_names, s_names = MarkersConfig.names(), SkeletonConfig.names()
        unknown = sorted(set(d) - m_names - s_names)
        if unknown:
            raise ConfigError(f"unknown method parameters: {', '.join(unknown)}")
        return cls(MarkersConfig.from_dict({k: v for k, v in d.items() if k in m_names}),
                   SkeletonConfig.from_dict({k: v for k, v in d.items() if k in s_names}))

    @classmethod
    def of(cls, **flat: Any) -> "PipelineConfig":
        return cls.from_dict(flat)

    def replace(self, **flat: Any) -> "PipelineConfig":
        return PipelineConfig.from_dict(self.to_dict() | flat)

    def to_dict(self) -> dict[str, Any]:
        return self.markers.to_dict() | self.skeleton.to_dict()

    @property
    def fps(self) -> float:
        return self.skeleton.fps
