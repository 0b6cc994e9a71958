"""`vmocap bench speed`: back-end time per frame (lattice search + IK + filter + second IK).

Setup: the benchmark rig (4 cameras, 1024x768, PCMs at stride 4), every keypoint of the model
(25 PCM channels), lattice k=5, a skeleton animated with smooth joint motions, PCMs from the
documented synthetic noise model. PCM synthesis is not timed; only the tracker's stages are.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
from tqdm import tqdm

from ...cameras.projection import Rig
from ...keypoints import KEYPOINTS
from ...method.config import PipelineConfig
from ...method.pipeline import Pipeline
from ...method.skeleton import Skeleton
from ...pcm.synthetic import NoiseModel, SyntheticPcmSource, benchmark_rig
from ...pcm.views import PcmViews


def animated_keypoints(n_frames: int, fps: float = 60.0, seed: int = 0) -> np.ndarray:
    """(T, 25, 3) keypoints of the default skeleton walking in place with swinging limbs."""
    sk = Skeleton()
    rng = np.random.default_rng(seed)
    amp = rng.uniform(0.1, 0.5, 40)
    freq = rng.uniform(0.3, 1.5, 40)
    phase = rng.uniform(0, 2 * np.pi, 40)
    out = np.empty((n_frames, len(KEYPOINTS), 3))
    for t in range(n_frames):
        a = amp * np.sin(2 * np.pi * freq * t / fps + phase)
        a[:3] = [0.3 * np.sin(0.5 * t / fps), 0.0, 0.95]  # root translation
        a[3:6] *= 0.3
        for name, sign in (("left_elbow", -1), ("right_elbow", -1), ("left_knee", 1), ("right_knee", 1)):
            i = sk.joint_names.index(name)
            a[i] = sign * abs(a[i])
        out[t] = sk.keypoint_positions(sk.from_angles(a))
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=int, default=300, help="timed frames (after initialization)")
    parser.add_argument("--k", type=int, default=5, help="lattice half-width in cells")
    parser.add_argument("--full-lattice", action="store_true", help="time the full lattice instead of coarse-to-fine")
    parser.add_argument("--stride", type=int, default=4,
                        help="PCM stride in image pixels (4: 256x192 maps as the accuracy benchmark; 16: 64x48, "
                             "about the size of BlazePose's 64x64 maps)")
    parser.add_argument("--json", action="store_true")


def run(args: argparse.Namespace) -> int:
    fps = 60.0
    warm = 30
    gt = animated_keypoints(args.frames + warm, fps)
    rig = benchmark_rig(np.array([0.0, 0.0, 0.0]))
    noise = NoiseModel(stride=args.stride, sigma_cells=2.0 * 4 / args.stride)  # same Gaussian width in pixels
    source = SyntheticPcmSource(rig, gt, np.ones(len(KEYPOINTS), bool), seed=1, fps=fps, noise=noise)
    cfg = PipelineConfig.of(fps=fps, lattice_k=args.k, coarse_to_fine=not args.full_lattice)
    tracker = Pipeline(rig, cfg)
    pcms = [source.render(t) for t in tqdm(range(len(gt)), desc="synthesizing PCMs", disable=args.json)]
    stages: dict[str, list[float]] = {"lattice": [], "ik": [], "filter": [], "ik2": []}
    total: list[float] = []
    for t, pcm in enumerate(tqdm(pcms, desc="tracking", disable=args.json)):
        t0 = time.perf_counter()
        r = tracker.step(pcm).skeleton
        dt = time.perf_counter() - t0
        if t >= warm and r.status == "tracking" and tracker.skeleton.timings:
            total.append(dt)
            for k, v in {**tracker.markers.timings, **tracker.skeleton.timings}.items():
                stages[k].append(v)
    if not total:
        print("the tracker never started tracking")
        return 1

    def stat(v: list[float]) -> dict[str, float]:
        a = np.array(v) * 1000.0
        return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95))}

    result = {
        "backend_ms": stat(total),
        "stages_ms": {k: stat(v) for k, v in stages.items()},
        "cameras": len(rig),
        "keypoints": len(KEYPOINTS),
        "lattice_points": (2 * args.k + 1) ** 3,
        "coarse_to_fine": cfg.markers.coarse_to_fine,
        "map_size": list(source.map_size),
        "frames": len(total),
    }
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(f"back end per frame: median {result['backend_ms']['median']:.2f} ms, p95 {result['backend_ms']['p95']:.2f} ms "
              f"({len(rig)} cameras, {len(KEYPOINTS)} keypoints, {(2 * args.k + 1) ** 3} lattice points"
              f"{', coarse-to-fine' if cfg.markers.coarse_to_fine else ''}, maps {source.map_size[0]}x{source.map_size[1]}, {len(total)} frames)")
        for k, v in result["stages_ms"].items():
            print(f"  {k:<8} median {v['median']:.2f} ms  p95 {v['p95']:.2f} ms")
    return 0


def time_pipeline(frames: list[PcmViews], rig: Rig, config: PipelineConfig | None, n: int,
                  period_ns: int = 33_333_333) -> dict[str, float]:
    """Per-frame-set time (ms) of Pipeline.step over `n` frame sets handed out as the graph's
    PCM node hands them out from a bag (`frames` looped, stamps one period apart): the
    offline cost that the graph's end-to-end latency compares with."""
    pipe = Pipeline(rig, config)
    ms = np.empty(n)
    for k in range(n):
        src = frames[k % len(frames)]
        pcm = dataclasses.replace(src, stamp_ns=k * period_ns)
        t0 = time.perf_counter()
        pipe.step(pcm)
        ms[k] = 1e3 * (time.perf_counter() - t0)
    return {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)), "mean": float(ms.mean()), "n": n}
