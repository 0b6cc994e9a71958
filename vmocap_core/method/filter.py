"""The low-pass of II-F and the motion model of the RTS smoothers, as a SkeletonConfig asks."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .iir import LowPassFilter
from .one_euro import OneEuroFilter
from .smoothing import MotionModel

if TYPE_CHECKING:
    from .config import SkeletonConfig


def make_filter(config: SkeletonConfig) -> LowPassFilter | OneEuroFilter:
    """The low-pass of II-F that `config` asks for (fresh state)."""
    if config.filter_kind == "one_euro":
        return OneEuroFilter(config.filter_min_cutoff_hz, config.filter_beta, config.fps, config.filter_derivative_cutoff_hz)
    return LowPassFilter(config.filter_order, config.filter_cutoff_hz, config.fps, config.filter_lag_compensation)


def smoother_model(config: SkeletonConfig) -> MotionModel:
    """The kinematic model of the RTS smoothers (fixed-lag live, fixed-interval offline)."""
    return MotionModel(config.smoother_model, config.smoother_process_noise, config.smoother_measurement_noise_m,
                       config.fps)
