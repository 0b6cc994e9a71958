"""`vmocap bench cnn`: where the CNN budget of the tracking configuration goes, variant by variant.

Each variant of the BlazePose landmark model (pcm/budget.py: heatmap convolution slimmed to the
channels used, input size) runs on the bundled self-check crops (resized to its input), in
turn with every other variant (A B C A B C ...), so that all see the same load on a shared CPU:
- per crop: one crop, one thread;
- frame set: the tracking configuration's 4 crops, `--threads` threads (runner.py "views").
Every figure is also given as the ratio to the published network (256 x 256, all 39 heatmap
channels) of the same precision, run by run (median of the ratios), for the wall time and for
the process CPU time (the steadier figure where other processes share the cores). int8 is measured only where the self-check passes.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from typing import Callable

import cv2
import numpy as np
from tqdm import tqdm

from ...errors import ModelError
from ...pcm import budget, fetch, selfcheck
from ...pcm.blazepose import BlazePoseLandmark
from ...pcm.model import DEFAULT_THREADS

# label -> BlazePoseLandmark options; "published" first (the reference of the ratios)
VARIANTS: dict[str, dict] = {
    "published": {"slim": False, "input_size": 256},
    "slim": {"slim": True, "input_size": 256},
    "slim_224": {"slim": True, "input_size": 224},
    "slim_192": {"slim": True, "input_size": 192},
}
FRAME_SET_CROPS = 4


def _crops(side: int, n: int) -> np.ndarray:
    ref = selfcheck.reference_crops()
    batch = np.concatenate([ref] * (-(-n // len(ref))))[:n]
    if side == batch.shape[1]:
        return np.ascontiguousarray(batch)
    return np.stack([cv2.resize(c, (side, side), interpolation=cv2.INTER_AREA) for c in batch])


def _interleaved(fns: dict[str, Callable[[], object]], repeat: int, label: str,
                 quiet: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """variant -> (wall ms, process CPU ms) per run."""
    for fn in fns.values():  # warm-up: allocations, onnxruntime's first-run planning
        fn(), fn()
    runs: dict[str, tuple[list[float], list[float]]] = {k: ([], []) for k in fns}
    for _ in tqdm(range(repeat), desc=label, leave=False, disable=quiet):
        for k, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            runs[k][0].append((time.perf_counter() - t0) * 1e3)
            runs[k][1].append((time.process_time() - c0) * 1e3)
    return {k: (np.array(w), np.array(c)) for k, (w, c) in runs.items()}


def _summary(runs: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> dict[str, float]:
    # CPU time is the steadier figure on a shared CPU: a preempted run costs wall time, not CPU
    (wall, cpu), (ref_wall, ref_cpu) = runs, ref
    return {"median_ms": round(float(np.median(wall)), 2), "min_ms": round(float(wall.min()), 2),
            "ratio_to_published": round(float(np.median(wall / ref_wall)), 3),
            "cpu_ms": round(float(np.median(cpu)), 2), "cpu_ratio_to_published": round(float(np.median(cpu / ref_cpu)), 3)}


def measure(repeat: int = 20, threads: int = DEFAULT_THREADS, variants: dict[str, dict] | None = None,
            quiet: bool = False) -> dict:
    variants = variants or VARIANTS
    check = selfcheck.verdict("full")
    result: dict = {"cpu": check.cpu.describe(), "int8_correct": check.int8_correct, "int8_kernels": check.int8_kernels,
                    "threads": threads, "loadavg_before": list(os.getloadavg()), "precisions": {}}
    precisions = ["float"] + (["int8"] if check.int8_correct else [])
    for precision in precisions:
        path = fetch.model_path("pose_landmark_full" + (check.int8_build if precision == "int8" else ""))
        config = check.session_config if precision == "int8" else None
        one, four, crops1, crops4 = {}, {}, {}, {}
        for name, opts in variants.items():
            kw = dict(precision=precision, session_config=config, **opts)
            one[name] = BlazePoseLandmark(path, threads=1, **kw)
            four[name] = BlazePoseLandmark(path, threads=threads, **kw)
            crops1[name] = _crops(one[name].input_size[0], 1)
            crops4[name] = _crops(one[name].input_size[0], FRAME_SET_CROPS)
        per_crop = _interleaved({k: functools.partial(m.run, crops1[k]) for k, m in one.items()}, repeat,
                                f"{precision}, 1 crop, 1 thread", quiet)
        frame_set = _interleaved({k: functools.partial(m.run, crops4[k]) for k, m in four.items()}, repeat,
                                 f"{precision}, {FRAME_SET_CROPS} crops, {threads} threads", quiet)
        ref = next(iter(variants))
        result["precisions"][precision] = {
            k: {"per_crop": _summary(per_crop[k], per_crop[ref]), "frame_set": _summary(frame_set[k], frame_set[ref])}
            for k in variants
        }
    result["loadavg_after"] = list(os.getloadavg())
    return result


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeat", type=int, default=20, help="interleaved runs per variant")
    parser.add_argument("--threads", type=int, default=DEFAULT_THREADS, help="threads of the frame-set figure")
    parser.add_argument("--sizes", type=int, nargs="*", default=None,
                        help=f"input sizes of the slim variants (default 256 224 192; from {budget.INPUT_SIZES})")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    variants = dict(VARIANTS)
    if args.sizes is not None:
        for s in args.sizes:
            budget.input_size(s)  # validates
        variants = {"published": VARIANTS["published"], **{("slim" if s == 256 else f"slim_{s}"):
                                                          {"slim": True, "input_size": s} for s in args.sizes}}
    if args.repeat < 1:
        raise ModelError("--repeat must be >= 1")
    r = measure(args.repeat, args.threads, variants, quiet=args.json)
    if args.json:
        print(json.dumps(r, indent=1))
        return 0
    print(f"CPU: {r['cpu']}; load {r['loadavg_before'][0]:.1f} -> {r['loadavg_after'][0]:.1f}")
    if not r["int8_correct"]:
        print("int8 failed the self-check on this CPU: float only")
    for precision, rows in r["precisions"].items():
        print(f"{precision}: per crop (1 thread) | {FRAME_SET_CROPS}-crop frame set ({r['threads']} threads): "
              "wall ms median, ratio to published | CPU ms median, ratio")
        for k, v in rows.items():
            cells = [f"{x['median_ms']:7.2f} {x['ratio_to_published']:.3f} | {x['cpu_ms']:7.2f} {x['cpu_ratio_to_published']:.3f}"
                     for x in (v["per_crop"], v["frame_set"])]
            print(f"  {k:10s} {cells[0]}   {cells[1]}")
    return 0
