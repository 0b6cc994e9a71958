"""Camera calibration: boards, intrinsics (Zhang), rig extrinsics with bundle adjustment."""

from .boards import Board, CharucoBoard, CheckerBoard, Detection, load_board
from .geometry import SceneObservations
from .observe import CameraViews, detect_camera
from .reference import (
    compare_extrinsics,
    compare_intrinsics,
    load_caliscope,
    load_qualisys,
    load_qualisys_intrinsics,
    load_reference,
)
from .rig import CalibrationResult, CameraReport, calibrate_rig

__all__ = [
    "Board", "CharucoBoard", "CheckerBoard", "Detection", "load_board", "SceneObservations", "CameraViews",
    "detect_camera", "compare_extrinsics", "compare_intrinsics", "load_caliscope", "load_qualisys", "load_qualisys_intrinsics",
    "load_reference", "CalibrationResult", "CameraReport", "calibrate_rig",
]
