"""Calibration of the int8 landmark model from detector crops of the Pose2Sim demo videos.

Writes `vmocap_core/data/pcm/<model>_int8.json` with quantize.calibrate (the method is in
quantize.py). Run by hand when the converter or the quantizer changes:
`python -m vmocap_core.pcm.int8_calibration`. This module joins the model cache (fetch.py), the
float models and quantize.py, so quantize.py imports none of them (fetch.py builds the int8 model
with quantize.build).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import ModelError
from . import fetch
from .quantize import EXTRA_SPANS, INT8_SPAN, KEEP_FLOAT, calibrate, calibration_path


def calibration_crops(models: Path, step: int = 2) -> np.ndarray:
    """(N, 256, 256, 3) uint8 BGR crops of the person in the Pose2Sim demo videos (detector
    crops, every `step`-th frame of each camera); `models` is the model cache directory."""
    import cv2

    from ..calibration.datasets import pose2sim_demo
    from .blazepose import BlazePoseLandmark
    from .crops import Crops
    from .detector import PoseDetector

    demo = pose2sim_demo(fetch=True)
    if demo is None:
        raise ModelError("the Pose2Sim demo videos are needed for calibration")
    # the cached float files directly: the cache manifest names the calibration file's checksum
    det = PoseDetector(models / "pose_detection.onnx")
    lm = BlazePoseLandmark(models / "pose_landmark_full.onnx", precision="float")
    crops = []
    for video in sorted((demo / "videos").glob("cam*.mp4")):
        cap = cv2.VideoCapture(str(video))
        k = 0
        while True:
            ok, img = cap.read()
            if not ok:
                break
            if k % step == 0:
                for d in det.detect([img])[0][:1]:
                    c, side, rot = d.crop()
                    crops.append(lm.sample([img], lm.views_from_crops(Crops([0], [c], [side], [rot])))[0])
            k += 1
    return np.stack(crops)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vmocap_core.pcm.int8_calibration", description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--model", default="pose_landmark_full", choices=sorted(INT8_SPAN))
    ap.add_argument("--step", type=int, default=2, help="every N-th video frame")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    models = fetch.model_dir()
    crops = calibration_crops(models, args.step)
    calib = calibrate(models / f"{args.model}.onnx", crops, INT8_SPAN[args.model], calibration_path(args.model),
                      KEEP_FLOAT.get(args.model, ()), EXTRA_SPANS.get(args.model, ()))
    print(f"{calibration_path(args.model)}: {len(crops)} crops, {len(calib['quantize_nodes'])} nodes int8 "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
