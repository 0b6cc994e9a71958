"""`vmocap demo`: the whole pipeline on real videos (Pose2Sim's Demo_SinglePerson).

Steps (each reported on stderr):
1. fetch the `pose2sim==0.10.49` wheel with pip (no install; cached in <repo>/models/pose2sim
   or ~/.cache/vmocap/pose2sim, shared with the calibration tests) and unpack the demo folder;
2. convert its Qualisys calibration (Calib.qca.txt) to a vmocap rig file;
3. convert the 4 synchronized 60 fps videos into a rosbag2 MCAP in bags/ (JPEG
   sensor_msgs/CompressedImage + CameraInfo per camera, ~100 MB);
4. run the pipeline on the bag: by default the ROS 2 node graph (`vmocap launch`: camera node
   playing the bag, decoding its JPEGs to sensor_msgs/Image, CNN PCM node, markers, skeleton, recorder); with
   `--mode in-process` the same stages in this process: the real CNN (pcm.BlazePosePcm: detector
   to initialize, crops from the fed-back skeleton while tracking), MarkerStage (triangulation /
   lattice search), SkeletonStage (IK, IIR, second IK); outputs recorded into an MCAP;
5. write the report folder: skeleton reprojected over the 4 views (MP4 + contact sheet),
   3D trajectories, bone-length constancy, reprojection error per camera and keypoint, PCM
   score over time, per-stage timing, report.md and summary.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ...calibration.reference import load_qualisys
from ...paths import REPO
from .data import _count_frame_sets, _video_frames, log, video_paths, video_sizes, videos_to_bag
from .report import render_overlays, write_report
from .runs import TRACKER_SETTINGS, live_rate, recording_from_graph, run_graph, run_pipeline


# ------------------------------------------------------------------------------ CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=REPO / "reports" / "demo", help="report folder")
    parser.add_argument("--bag", type=Path, default=REPO / "bags" / "pose2sim_demo.mcap", help="MCAP bag of the videos")
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--no-video", action="store_true", help="skip the overlay MP4 / contact sheet")
    parser.add_argument("--rebuild-bag", action="store_true", help="convert the videos again even if the bag exists")
    parser.add_argument("--mode", choices=("graph", "in-process"), default="graph",
                        help="graph: the ROS 2 node graph (vmocap launch) playing the bag (default); "
                             "in-process: the same stages in this process on the compressed bag (no DDS, faster)")
    parser.add_argument("--graph-rate", type=float, default=None,
                        help="bag playback rate in graph mode (x real time); default: the rate this CPU keeps up "
                             "with, from its JPEG decoding and CNN times (at most 1; the report says which)")
    parser.add_argument("--binning", type=int, choices=(1, 2, 4), default=1,
                        help="decode the 1920x1088 JPEGs reduced this many times (REP 104 binning; the CNN's crops "
                             "are cut from the reduced images): less CPU per frame set, at some accuracy")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an earlier run's files in --out, and --bag when it must be converted again")


# what a run writes into --out, per mode (rig, recording and graph files; then the report)
RUN_FILES = {"graph": ("rig.yaml", "graph.yaml", "graph_outputs.mcap", "graph.log", "graph_recorder.log"),
             "in-process": ("rig.yaml", "outputs.mcap")}
REPORT_FILES = ("pcm_score.png", "trajectories_3d.png", "bone_lengths.png", "reprojection_error.png", "summary.json",
                "recording.npz", "report.md")
VIDEO_FILES = ("overlay.mp4", "contact_sheet.png")


def run(args: argparse.Namespace) -> int:
    from ...calibration.datasets import pose2sim_demo
    from ...cameras.rig_file import save_rig
    from ...errors import OutputPathError
    from ...files import check_output
    from ...pcm.fetch import fetch as fetch_models

    products = [args.out / n for n in RUN_FILES[args.mode] + REPORT_FILES + (() if args.no_video else VIDEO_FILES)]
    for p in products:  # before anything is fetched or written: a refusal costs nothing
        check_output(p, [args.bag], args.overwrite)
    log("fetching the pose2sim==0.10.49 wheel (pip download --no-deps, cached)")
    demo = pose2sim_demo(fetch=True)
    if demo is None:
        print("vmocap demo: could not obtain the Pose2Sim demo", file=sys.stderr)
        return 1
    videos = video_paths(demo)
    calib = demo / "calibration" / "Calib.qca.txt"
    inputs = [calib, *videos.values()]
    for p in products:
        check_output(p, inputs, overwrite=True)  # existing files were checked above; here: none is an input
    log("PCM models: checking the cache (builds it on a fresh machine, as `vmocap models fetch`)")
    fetch_models(quiet=True)
    rig = load_qualisys(calib, video_sizes(videos))
    args.out.mkdir(parents=True, exist_ok=True)
    save_rig(rig, args.out / "rig.yaml", args.overwrite, inputs)
    log(f"rig {rig.names} -> {args.out / 'rig.yaml'}")
    want = min(_video_frames(videos), args.frames or 10**9)
    if args.bag.exists() and not args.rebuild_bag and _count_frame_sets(args.bag, rig) == want:
        n = want
        log(f"reusing {args.bag} ({n} frame sets; --rebuild-bag to convert again)")
    else:
        if args.bag.exists() and not (args.rebuild_bag or args.overwrite):
            raise OutputPathError(f"{args.bag}: holds other frame sets than the {want} asked for; refusing to replace "
                                  "it (pass --rebuild-bag or --overwrite to convert the videos again, or --bag)")
        n = videos_to_bag(videos, rig, args.bag, args.frames, overwrite=True)  # replacing it was asked for above
        log(f"{n} frame sets -> {args.bag}")
    t0 = time.perf_counter()
    if args.mode == "graph":
        rate, why = (args.graph_rate, "--graph-rate") if args.graph_rate else live_rate(args.bag, rig, binning=args.binning)
        log(f"node graph on {args.bag} at {rate} x real time ({why})")
        recorded = run_graph(args.bag, args.out / "rig.yaml", rig, args.out, n, rate, args.binning, args.overwrite)
        rec = recording_from_graph(recorded, rig, n)
        mode = (f"ROS 2 node graph (vmocap launch: camera, CNN PCM, markers, skeleton in one process, recorder apart), "
                f"bag played at {rate} x real time ({why})")
    else:
        rec = run_pipeline(args.bag, rig, args.out / "outputs.mcap", n, args.threads, binning=args.binning,
                           overwrite=args.overwrite)
        mode = "in-process pipeline (the graph's stage classes, no DDS)"
    info = {"pipeline_s": time.perf_counter() - t0, "bag": str(args.bag), "mode": mode,
            "processed_frames": int(sum(s != "dropped" for s in rec["status"])), "tracker_settings": TRACKER_SETTINGS}
    if not args.no_video:
        info["overlays"] = render_overlays(args.bag, rig, rec, args.out)
    summary = write_report(rig, rec, args.out, info)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print((args.out / "report.md").read_text())
    failure = demo_failure(summary)
    if failure:
        print(f"vmocap demo: FAILED: {failure} (report: {args.out / 'report.md'})", file=sys.stderr)
        return 1
    return 0


def demo_failure(summary: dict) -> str | None:
    """Why the demo's result is unusable (None when it is not): a report full of NaN must not
    exit 0 (`vmocap models check` is the first thing to run when the CNN is the cause)."""
    if summary["tracking_frames"] == 0:
        return (f"the tracker never tracked in {summary['frames']} frame sets (no subject initialized; "
                "check the CNN with `vmocap models check`)")
    if not np.isfinite(summary["median_reprojection_px"]):
        return "the median reprojection error is not finite"
    return None
