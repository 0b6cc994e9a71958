"""BlazePose landmark model as the graph runs it: the model file and precision right for this
CPU (float, or the int8 build the self-check passes: selfcheck.py), and the paper's input
rotation. The network itself, its heatmap convention and keypoint mapping: blazepose_net.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..keypoints import INDEX, KEYPOINTS, LOWER_BODY
from . import fetch, selfcheck
from .blazepose_net import BlazePoseNet
from .crops import Crops

ROTATION_MODES = ("none", "all", "lower_body")


def views_per_camera(mode: str) -> int:
    """The most views rotated_crops gives one camera in rotation `mode` (lower_body: 2)."""
    return 2 if mode == "lower_body" else 1


# Measured on real frames (test_pcm_panoptic: 5 Panoptic views turned upside down): BlazePose's
# presence drops to ~0 and its upper-body heatmaps are ~44 cm off on an unrotated inverted person,
# so the paper's variant (upper body from the unrotated view) loses the upper body, while "all"
# reproduces the upright result exactly and costs one view per camera. Hence "all" by default.
DEFAULT_ROTATION = "all"
MIN_TILT = np.deg2rad(20.0)  # below this, the upright and rotated crops nearly coincide: one view


# "int8": pose_landmark_full_int8.onnx (quantize.py: the encoder after the stem in int8); "float":
# the converted model as it is; "auto" (default): int8 where the self-check passes on this CPU and
# int8 is faster (selfcheck.py), else float.
PRECISIONS = ("auto", "int8", "float")
INT8_VARIANTS = ("full",)  # lite has no int8 build
PRECISION_ENV = "VMOCAP_PCM_PRECISION"  # overrides the default precision (e.g. =float) in every process


def resolve_precision(variant: str, precision: str | None = None) -> str:
    """The requested precision: `precision` if given, else $VMOCAP_PCM_PRECISION, else "auto";
    "float" for a variant without an int8 build (unless int8 was asked for explicitly: error)."""
    import os

    chosen = precision or os.environ.get(PRECISION_ENV) or "auto"
    if chosen not in PRECISIONS:
        raise ModelError(f"BlazePose precision must be one of {PRECISIONS}, got {chosen!r}")
    if variant not in INT8_VARIANTS:
        if chosen == "int8" and precision is not None:
            raise ModelError(f"no int8 build of the {variant} landmark model (int8: {INT8_VARIANTS})")
        return "float"
    return chosen


class BlazePoseLandmark(BlazePoseNet):
    """pose_landmark_{full,lite}.onnx from the model cache (`vmocap models fetch`)."""

    def model_file(self, path: Path | str | None, precision: str | None,
                   session_config: dict[str, str] | None) -> tuple[Path | str, str, str, dict[str, str] | None]:
        """precision: "auto", "int8" or "float" (None: see `resolve_precision`; "auto" and "int8"
        run the self-check once per process, and "int8" raises where it fails); `path` overrides
        the cached model file (no self-check: the caller names the file and `precision` says what
        it is)."""
        request = resolve_precision(self.variant, precision)
        reason = f"{request} requested"
        int8_build = "_int8"  # the 8-bit build unless the self-check picked another for this CPU
        if path is None and request in ("auto", "int8"):
            check = selfcheck.verdict(self.variant)
            if request == "int8" and not check.int8_correct:
                raise ModelError(f"precision int8 was asked for, but {check.warning}")
            request = "int8" if request == "int8" else check.precision
            reason = check.reason
            if request == "int8":
                session_config, int8_build = check.session_config, check.int8_build
        chosen = "float" if request == "auto" else request
        name = f"pose_landmark_{self.variant}" + (int8_build if chosen == "int8" else "")
        return path or fetch.model_path(name), chosen, reason, session_config


def rotated_crops(
    camera: np.ndarray,
    center: np.ndarray,
    side: np.ndarray,
    tilt: np.ndarray,
    mode: str = DEFAULT_ROTATION,
    min_tilt: float = MIN_TILT,
) -> Crops:
    """Crops with the paper's input image rotation (III-B) for cameras with one body each.

    tilt: (C,) trunk tilt per camera (radians, crops.py convention; e.g. tracker.trunk_tilt).
    mode "none": upright crops; "all": every keypoint from the crop rotated by the tilt;
    "lower_body" (paper): where |tilt| >= min_tilt, two views of the camera, the upright crop
    for the upper body and head and the rotated crop for keypoints.LOWER_BODY; below min_tilt
    the two crops nearly coincide, so one upright view serves all keypoints (halves the CNN
    cost while the person stands).
    """
    if mode not in ROTATION_MODES:
        raise ModelError(f"rotation mode must be one of {ROTATION_MODES}, got {mode!r}")
    camera = np.asarray(camera, dtype=np.intp).reshape(-1)
    center = np.asarray(center, dtype=np.float64).reshape(-1, 2)
    side = np.asarray(side, dtype=np.float64).reshape(-1)
    tilt = np.asarray(tilt, dtype=np.float64).reshape(-1)
    C = camera.size
    every = np.ones((C, len(KEYPOINTS)), dtype=bool)
    if mode == "none":
        return Crops(camera, center, side, np.zeros(C), every)
    if mode == "all":
        return Crops(camera, center, side, tilt, every)
    lower = np.zeros(len(KEYPOINTS), dtype=bool)
    lower[[INDEX[k] for k in LOWER_BODY]] = True
    split = np.abs(np.angle(np.exp(1j * tilt))) >= min_tilt  # wrapped to (-pi, pi]
    upright_valid = np.where(split[:, None], ~lower[None], True)
    return Crops(
        camera=np.concatenate([camera, camera[split]]),
        center=np.concatenate([center, center[split]]),
        side=np.concatenate([side, side[split]]),
        rotation=np.concatenate([np.zeros(C), tilt[split]]),
        valid=np.concatenate([upright_valid, np.broadcast_to(lower, (int(split.sum()), len(KEYPOINTS)))]),
    )
