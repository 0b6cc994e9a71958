"""The low-pass of II-F and the motion model of the RTS smoothers, as a SkeletonConfig asks."""

from __future__ import annotations

from typing import Protocol

from .iir import LowPassFilter
from .one_euro import OneEuroFilter
from .smoothing import MotionModel


class FilterSettings(Protocol):
    """The SkeletonConfig fields read here; a protocol, so that this module stays below config.py,
    whose validation builds the filter and the motion model."""

    fps: float
    filter_kind: str
    filter_min_cutoff_hz: float
    filter_beta: float
    filter_derivative_cutoff_hz: float
    filter_order: int
    filter_cutoff_hz: float
    filter_lag_compensation: bool
    smoother_model: str
    smoother_process_noise: float
    smoother_measurement_noise_m: float


def make_filter(config: FilterSettings) -> LowPassFilter | OneEuroFilter:
    """The low-pass of II-F that `config` asks for (fresh state)."""
    if config.filter_kind == "one_euro":
        return OneEuroFilter(config.filter_min_cutoff_hz, config.filter_beta, config.fps, config.filter_derivative_cutoff_hz)
    return LowPassFilter(config.filter_order, config.filter_cutoff_hz, config.fps, config.filter_lag_compensation)


def smoother_model(config: FilterSettings) -> MotionModel:
    """The kinematic model of the RTS smoothers (fixed-lag live, fixed-interval offline)."""
    return MotionModel(config.smoother_model, config.smoother_process_noise, config.smoother_measurement_noise_m,
                       config.fps)
