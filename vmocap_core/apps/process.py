"""`vmocap process IN.mcap -o OUT.mcap`: the pipeline on a recording, without DDS.

The input is a bag's PCM topics (heatmaps) or its camera images (the CNN runs, its crops
following the fed-back skeleton). Either way each frame set goes through one
method.pipeline.Pipeline.step, and the outputs are the messages the graph publishes
(outputs/messages.py) at the frame set's capture stamp. With the offline mode the live
results are kept and the whole-recording pass (method/offline.py) writes the outputs.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from ..bag import BagReader, BagWriter
from ..bag import messages as M
from ..cameras.bag import REDUCED, decode_ahead_priority, decode_compressed, single_threaded_opencv
from ..cameras.projection import Rig
from ..cameras.sync import ApproximateSync
from ..errors import BagError, HeatmapError
from ..graph_config import Topics
from ..method.camera_check import image_problem
from ..method.config import PipelineConfig
from ..method.offline import OfflineError
from ..method.pipeline import FrameResult, ImageSet, Pipeline
from ..method.results import FEEDBACK_STATUSES
from ..method.time_offsets import camera_time_offsets
from ..outputs.messages import CLOUD, DIAG, markers_message, subject_message, write_results
from ..outputs.streams import SubjectOutputs
from ..paths import REPO
from ..pcm.assembly import PcmAssembler, channel_keypoints, pcm_topics
from ..pcm.peaks import camera_keypoints
from ..pcm.views import PcmViews
from .process_people import PeopleSteps

# Camera time offsets (method/time_offsets.py) from the cameras' 2D keypoints of the first
# frame sets: ~10 s at 60 Hz is plenty for whole frame sets and keeps it to a few seconds.
OFFSET_WINDOW = 600
OFFSET_MIN_TRACKED = 30
DECODE_THREADS = 2
DECODE_AHEAD = 8  # images decoded ahead of the pipeline: two frame sets of four cameras


def process_bag(
    in_path: str | Path,
    out_path: str | Path,
    rig: Rig,
    config: PipelineConfig | dict[str, Any] | None = None,
    keypoints: Iterable[str] = (),
    views: list[str] | None = None,
    namespace: str = "/vmocap",
    tolerance_ns: int = 1_000_000,
    min_views: int = 2,
    recover: bool = False,
    progress: bool = True,
    model: str = "blazepose",
    provider: Any = None,
    binning: int = 1,
    overwrite: bool = False,
    inputs: Iterable[str | Path] = (),
    max_people: int = 1,
) -> dict[str, Any]:
    """Run the pipeline over the PCM topics of a bag (or, when it has none, over its camera
    images with the CNN `model`, or the given PCM `provider`); write the graph's outputs to
    out_path (log time = capture stamp). Returns counts and the time per frame set.
    binning: compressed camera images are decoded reduced this many times (1, 2, 4, 8) and the
    CNN cuts its crops from them (ModelPcmProvider's binning): for subjects whose crops span
    more than binning x the CNN's 256 px, the same crops for a fraction of the decoding.
    out_path is never one of in_path and `inputs` (rig, config); an existing out_path is
    replaced only with `overwrite` (vmocap_core.files).
    max_people > 1: everyone in view up to that many, from images (method/people_tracker.py);
    the subject topics follow the first of them, every person is a REP-155 body (outputs/people.py)."""
    from tqdm import tqdm

    from ..files import check_output

    inputs = [in_path, *inputs]
    check_output(out_path, inputs, overwrite)  # before the model loads: a refusal costs nothing

    cfg = config if isinstance(config, PipelineConfig) else PipelineConfig.from_dict(config)
    # Offline: the live pass without lag; its results are kept for the whole-recording pass.
    offline = cfg.skeleton.offline
    if max_people < 1:
        raise BagError(f"max_people {max_people}: at least 1")
    live_cfg = cfg.replace(smoothing_lag_frames=0) if offline else cfg
    topics = Topics(namespace)
    stats: dict[str, Any] = {"frames": 0, "tracking": 0, "seconds": 0.0}
    kept: list[FrameResult] = []
    subject = SubjectOutputs(rig)
    with BagReader(in_path, recover=recover) as reader:
        view_names = pcm_topics(reader.topics, topics, views)
        frames: Iterator[PcmViews | ImageSet]
        if view_names and max_people > 1:
            raise BagError(f"{in_path}: several people (max_people {max_people}) need the camera images, the bag has PCMs")
        if view_names:
            pipe = Pipeline(rig, live_cfg)
            frames, total, sync_stats = _pcm_frame_sets(reader, rig, topics, view_names, channel_keypoints(keypoints),
                                                        tolerance_ns, min_views)
        else:
            cams = [c.name for c in rig if _image_topic(reader, topics, c.name)]
            if len(cams) < 2:
                raise BagError(f"{in_path}: neither PCM topics under {topics.ns}/pcm/ nor images "
                               f"{topics.image('CAM')} of at least 2 rig cameras")
            # images a binning graph recorded come reduced already (their CameraInfo says so)
            recorded = _recorded_binning(reader, topics, cams)
            seen = recorded * binning
            if seen not in REDUCED:
                raise BagError(f"{in_path}: images recorded with binning {recorded}, reduced {binning} times more: "
                               f"{seen} is not one of {sorted(REDUCED)}")
            pipe = Pipeline(rig, live_cfg, provider or _model_provider(model, rig, seen))
            stats["pcm"] = pipe.pcm.name  # type: ignore[union-attr]
            stats["binning"], stats["recorded_binning"] = seen, recorded
            stats["bad_images"] = {c: 0 for c in cams}
            frames, total, sync_stats = _image_frame_sets(reader, rig, topics, cams, max(tolerance_ns, 8_000_000),
                                                          min_views, binning, recorded, stats["bad_images"])
        people = PeopleSteps.over(pipe, rig, live_cfg, max_people, topics.ns, offline) if max_people > 1 else None
        warm_up = getattr(pipe.pcm, "warm_up", None)
        if warm_up is not None:  # the CNN's first run allocates and picks kernels: start-up, as in vmocap_pcm
            warm_up()
        with BagWriter(out_path, compression="zstd", overwrite=overwrite, inputs=inputs) as writer:
            stamps: list[int] = []
            start = time.perf_counter()  # the model is loaded: from here on it is the recording's own cost
            first_kp: list[tuple[np.ndarray, np.ndarray]] = []
            tracked_any = False
            for frame in tqdm(frames, total=total, unit="frame", desc="process", disable=not progress, file=sys.stderr):
                stamps.append(frame.stamp_ns)
                t0 = time.perf_counter()
                if people is None:
                    res = pipe.step(frame)
                else:
                    first = people.step(frame, writer, stats)
                    stats["seconds"] += time.perf_counter() - t0
                    if first is None:  # nobody in view: the subject topics say nothing
                        if not offline:  # offline: counted when written
                            stats["frames"] += 1
                        continue
                    res = first
                    t0 = time.perf_counter()
                stats["seconds"] += time.perf_counter() - t0
                tracked_any = tracked_any or res.status == "tracking"
                if len(stamps) <= OFFSET_WINDOW:  # the cameras' 2D keypoints of the first frame sets
                    first_kp.append(camera_keypoints(res.pcm, len(rig)))
                if not offline:
                    _write_frame(writer, topics, res, stats, subject)
                elif people is None:  # several people: each one's results are kept by PeopleSteps
                    kept.append(res)
            # offline, frame sets the live pass was still identifying on are enough
            if offline and people is not None:
                followed = people.followed
            else:
                followed = tracked_any or (offline and any(r.status in FEEDBACK_STATUSES for r in kept))
            if stamps and pipe.last is not None and not followed:
                assert pipe.last is not None  # after at least one frame set
                stats["not_tracked_because"] = why_not_tracked(pipe.last, rig, pipe.markers.config.init_max_reprojection_px,
                                                               pipe.skeleton.init_problem)
                if offline:
                    raise OfflineError(f"{in_path}: no frame set of {len(kept)} tracked, nothing to reconstruct: "
                                       f"{stats['not_tracked_because']}")
            if offline and people is not None:
                if not followed:
                    raise OfflineError(f"{in_path}: nobody's skeleton in {len(stamps)} frame sets, nothing to reconstruct")
                t0 = time.perf_counter()
                for first in people.reconstruct(cfg.replace(landmarks=pipe.config.skeleton.landmarks), writer, stats,
                                                progress):
                    if first is None:
                        stats["frames"] += 1
                    else:
                        _write_frame(writer, topics, first, stats, subject)
                stats["seconds"] += time.perf_counter() - t0
            elif offline and kept:
                # the live pass' landmark model (its PCM source resolved "auto")
                _write_offline(writer, topics, kept, cfg.replace(landmarks=pipe.config.skeleton.landmarks), stats,
                               progress, subject)
            stats["wall_s"] = time.perf_counter() - start
            st = sync_stats()
            if st.get("rejected_frame_sets") and stats["frames"] == 0:
                raise HeatmapError(f"{in_path}: no usable PCM frame set ({st['rejected_frame_sets']} rejected): "
                                   f"{st.get('last_error', '')}")
            writer.write(Topics.diagnostics, DIAG, M.diagnostics_msg(reader.end_ns, [
                (0, "vmocap_process: sync", "offline", {k: json.dumps(v) for k, v in st.items()}),
            ]), reader.end_ns)
    stats.pop("_subject", None)
    stats["rejected_frame_sets"] = st.pop("rejected_frame_sets", 0)
    st.pop("last_error", None)
    stats["sync"] = st
    stats["ms_per_frame"] = 1e3 * stats["seconds"] / max(stats["frames"], 1)
    # the recording's duration (one frame period more than first to last stamp) over the time
    # spent on it (reading, decoding, CNN, tracker, writing; not the start-up): > 1 is faster than real time
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    stats["recording_s"] = (stamps[-1] - stamps[0] + period) / 1e9 if stamps else 0.0
    stats["realtime_factor"] = stats["recording_s"] / stats["wall_s"] if stats["wall_s"] > 0 else 0.0
    if stats["tracking"] >= OFFSET_MIN_TRACKED and period > 0:
        fps = 1e9 / period
        offsets = camera_time_offsets(rig, np.array([k[0] for k in first_kp]), np.array([k[1] for k in first_kp]))
        stats["time_offsets"] = {o.camera: {"frames": o.frames, "ms": 1e3 * o.frames / fps, "error_px": o.error_px,
                                            "shifted_error_px": o.best_error_px, "out_of_step": o.out_of_step}
                                 for o in offsets}
        stats["out_of_step"] = [o.describe(fps) for o in offsets if o.out_of_step]
    return stats


def why_not_tracked(last: FrameResult, rig: Rig, init_max_reprojection_px: float, init_problem: Any) -> str:
    """Why no frame set was tracked, as the graph's WARN says it (init_report.py), from the last
    frame set's result and the skeleton stage's `init_problem`, or that the recording ended
    before the tracker's first output."""
    from ..method.init_report import not_initialized_reason

    ended = {"identifying": "identified (identify_seconds)", "smoothing": "smoothed (smoothing_lag_frames)"}
    if last.status in ended:
        return f"the recording ended while the subject was still being {ended[last.status]}"
    return not_initialized_reason(last.markers, rig.names, init_max_reprojection_px, init_problem)


def _pcm_frame_sets(reader: BagReader, rig: Rig, topics: Topics, views: list[str], keypoints: np.ndarray,
                    tolerance_ns: int, min_views: int) -> tuple[Iterator[PcmViews], int, Any]:
    """The bag's heatmap messages as PcmViews frame sets (as vmocap_markers assembles them)."""
    asm = PcmAssembler(rig, views, keypoints, tolerance_ns, min_views)
    by_topic = {topics.pcm(v): (v, "image") for v in views} | {topics.pcm_info(v): (v, "info") for v in views}

    def gen() -> Iterator[PcmViews]:
        for m in reader.messages(list(by_topic)):
            view, kind = by_topic[m.topic]
            msg = m.decode()
            yield from asm.add_image(view, msg) if kind == "image" else asm.add_info(view, msg)
        yield from asm.flush()

    def sync_stats() -> dict[str, Any]:
        return asm.sync.stats().as_dict() | {"rejected_frame_sets": asm.bad_views, "last_error": asm.last_error}

    total = sum(reader.message_counts.get(t, 0) for t in by_topic) // 2 // max(len(views), 1)
    return gen(), total, sync_stats


def _recorded_binning(reader: BagReader, topics: Topics, cams: list[str]) -> int:
    """The binning the cameras' images were recorded with: their first CameraInfo's binning_x
    (REP 104; 0 or no CameraInfo: 1). Cameras that disagree are an error."""
    found: dict[str, int] = {}
    infos = [t for t in (topics.camera_info(c) for c in cams) if t in reader.topics]
    for m in reader.messages(infos):
        msg = m.decode()
        found.setdefault(msg["header"]["frame_id"] or m.topic, M.camera_info_binning(msg)[0])
        if len(found) == len(infos):
            break
    if len(set(found.values())) > 1:
        raise BagError(f"the cameras' CameraInfo give different binnings: {found}")
    return next(iter(found.values()), 1)


def _image_frame_sets(reader: BagReader, rig: Rig, topics: Topics, cams: list[str], tolerance_ns: int,
                      min_views: int, binning: int = 1, recorded: int = 1,
                      bad: dict[str, int] | None = None) -> tuple[Iterator[ImageSet], int, Any]:
    """The bag's camera images (raw or compressed, the latter decoded reduced `binning` times)
    as synchronized ImageSets (as vmocap_pcm synchronizes its subscriptions). Images recorded
    `recorded` times binned are taken as they are. An image of another size than the rig's (so
    binned) or without contrast is left out of its set and counted in `bad`, as vmocap_pcm does;
    when a camera's first image has the wrong size, the rig or the binning is wrong: BagError."""
    sync: ApproximateSync[np.ndarray] = ApproximateSync(cams, tolerance_ns, min_cameras=min_views)
    want = {str(_image_topic(reader, topics, c)): c for c in cams}  # every camera has one (process_bag)
    compressed = {t for t in want if t.endswith("/compressed")}
    if binning > 1 and len(compressed) < len(want):
        raise BagError(f"binning {binning} applies to compressed images; raw images on {sorted(set(want) - compressed)}")
    seen = rig.binned(recorded * binning)
    bad = {} if bad is None else bad
    checked: set[str] = set()

    def usable(cam: str, image: np.ndarray) -> bool:
        c = seen[cam]
        if cam not in checked and image.shape[1::-1] != (c.width, c.height):
            raise BagError(f"{cam}: images of {image.shape[1]}x{image.shape[0]}, the rig's camera is {c.width}x{c.height}"
                           + (f" binned {recorded * binning} times" if recorded * binning > 1 else "")
                           + ": another rig, or a binning the bag's CameraInfo does not say (--binning)")
        checked.add(cam)
        problem = image_problem(image, c.width, c.height)
        if problem:
            bad[cam] = bad.get(cam, 0) + 1
        return not problem

    def image_sets(sets: list) -> Iterator[ImageSet]:
        for fs in sets:
            names = [c for c in rig.names if c in fs.items and usable(c, fs.items[c])]
            if names:  # fewer than min_views: the tracker reports the frame set as it is
                yield ImageSet(fs.stamp_ns, [fs.items[c] for c in names], np.array([rig.names.index(c) for c in names]))

    def gen() -> Iterator[ImageSet]:
        # JPEG decoding (~4 ms per 1088x1920 image) runs in threads, DECODE_AHEAD images ahead:
        # cv2 releases the GIL, so it overlaps the CNN of the frame set before instead of adding to it.
        pending: deque[tuple[str, int, Future]] = deque()
        single_threaded_opencv()
        jpeg = functools.partial(decode_compressed, binning=binning)
        with ThreadPoolExecutor(DECODE_THREADS, thread_name_prefix="vmocap-decode",
                                initializer=decode_ahead_priority) as pool:
            for m in reader.messages(list(want)):
                msg = m.decode()
                pending.append((want[m.topic], M.stamp_ns(msg), pool.submit(jpeg if m.topic in compressed else M.image_array, msg)))
                if len(pending) > DECODE_AHEAD:
                    cam, stamp, image = pending.popleft()
                    yield from image_sets(sync.add(cam, stamp, image.result()))
            while pending:
                cam, stamp, image = pending.popleft()
                yield from image_sets(sync.add(cam, stamp, image.result()))
        yield from image_sets(sync.flush())

    return gen(), min(reader.message_counts.get(t, 0) for t in want), lambda: sync.stats().as_dict()


def _model_provider(model: str, rig: Rig, binning: int = 1) -> Any:
    from ..pcm.providers import make_model_provider

    return make_model_provider(model, rig, binning=binning)


def _write_frame(writer: BagWriter, topics: Topics, res: FrameResult, stats: dict[str, Any],
                 subject: SubjectOutputs | None, dims_written: bool = True) -> None:
    """One frame set's graph outputs (markers and results, not the internal feedback), the
    subject's body dimensions when a new identification starts tracking, and the counts."""
    result, stamp = res.skeleton, res.markers.stamp_ns
    writer.write(topics.markers, CLOUD, markers_message(res.markers), stamp)
    write_results(writer, topics, result, stamp, subject)
    stats["frames"] += 1
    stats["tracking"] += result.status == "tracking"
    stats["uncertain"] = stats.get("uncertain", 0) + (result.status == "uncertain")  # the images disagreed
    if dims_written and result.status == "tracking" and result.dims is not None and stats.get("_subject") is not result.dims:
        stats["_subject"] = result.dims
        writer.write(Topics.diagnostics, DIAG, subject_message(result.stamp_ns, result.dims), result.stamp_ns)


def _write_offline(writer: BagWriter, topics: Topics, kept: list[FrameResult], config: PipelineConfig,
                   stats: dict[str, Any], progress: bool, subject: SubjectOutputs | None = None) -> None:
    """The whole-recording pass (method/offline.py) over the live results, then the outputs."""
    from dataclasses import replace

    from ..method.offline import identify_and_reconstruct

    t0 = time.perf_counter()
    results, sk = identify_and_reconstruct([r.skeleton for r in kept], config.skeleton, progress=progress)
    stats["seconds"] += time.perf_counter() - t0
    first = next(r.stamp_ns for r in results if r.status == "tracking")
    writer.write(Topics.diagnostics, DIAG, subject_message(first, sk.dims), first)
    for res, result in zip(kept, results):
        _write_frame(writer, topics, replace(res, skeleton=result), stats, subject, dims_written=False)


def _image_topic(reader: BagReader, topics: Topics, camera: str) -> str | None:
    """A camera's image topic in a bag: raw, else JPEG/PNG (`image_raw/compressed`), else None."""
    raw = topics.image(camera)
    return raw if raw in reader.topics else raw + "/compressed" if raw + "/compressed" in reader.topics else None


def joint_trajectory(path: str | Path, topic: str = "/vmocap/joint_states") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(stamps (N,), q (N, 40), names) of the JointState messages of a bag, by capture stamp."""
    stamps, qs, names = [], [], []
    with BagReader(path) as r:
        if topic not in r.topics:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 0)), []
        for m in r.messages([topic]):
            d = m.decode()
            stamps.append(M.stamp_ns(d))
            qs.append(np.asarray(d["position"]))
            names = d["name"]
    order = np.argsort(stamps, kind="stable")
    return np.asarray(stamps)[order], (np.stack(qs)[order] if qs else np.zeros((0, 0))), names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="MCAP bag with PCM topics (NS/pcm/VIEW/heatmaps + camera_info), "
                        "or with camera images (NS/CAM/image_raw: the CNN runs)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write the graph outputs to")
    parser.add_argument("--config", default=None, help="graph config (rig, keypoints, the vmocap_markers and vmocap_skeleton sections); default config/graph.yaml")
    parser.add_argument("--rig", default=None, help="rig YAML (overrides the config's)")
    parser.add_argument("--recover", action="store_true", help="read a damaged bag: a truncated one up to the damage, "
                        "one with damaged chunks without them (each skipped chunk is reported)")
    parser.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")
    parser.add_argument("--offline", action="store_true", help="offline mode: whole-recording identification, "
                        "RTS smoother, second IK (vmocap_skeleton.offline)")
    parser.add_argument("--plots", type=Path, default=None, help="write joint-angle and keypoint-speed plots (PNG) here")
    parser.add_argument("--binning", type=int, choices=(1, 2, 4, 8), default=1,
                        help="decode compressed images reduced this many times (JPEG DCT scaling, much cheaper) and "
                             "cut the CNN's crops from them; for crops larger than binning x 256 px. Images recorded "
                             "binned (CameraInfo binning_x) are recognized without it")
    parser.add_argument("--max-people", type=int, default=1,
                        help="track everyone in view up to this many (camera images, BlazePose): each person a "
                             "REP-155 body on /humans/bodies/...; the subject topics follow the first one")


def run(args: argparse.Namespace) -> int:
    # bad input (VmocapError) is reported by vmocap_core.cli.main
    from .. import graph_config
    from ..cameras.rig_file import load_rig

    cfg_path = Path(args.config) if args.config else REPO / "config" / "graph.yaml"
    cfg = graph_config.load(cfg_path)
    p = cfg.node_params("vmocap_markers")
    rig_path = args.rig or p["rig"]
    if not rig_path:
        print("vmocap process: no rig (give --rig or set 'rig' in the config)", file=sys.stderr)
        return 2
    rig = load_rig(rig_path)
    if p["cameras"]:
        rig = rig.subset(p["cameras"])
    if args.plots:  # before the work: a refusal costs nothing
        from ..export.plots import PLOT_FILES
        from ..files import output_folder

        output_folder(args.plots, PLOT_FILES, [args.input, rig_path, cfg_path, args.output])
    pipeline = cfg.pipeline_config()  # both stages' sections of the config
    if args.offline:
        pipeline = pipeline.replace(offline=True)
    stats = process_bag(
        args.input, args.output, rig, config=pipeline, keypoints=p["pcm_keypoints"],
        views=p["views"] or None, namespace=p["namespace"], tolerance_ns=int(p["sync_tolerance_ms"] * 1e6),
        min_views=p["min_cameras"], recover=args.recover, progress=not args.no_progress, binning=args.binning,
        model=cfg.node_params("vmocap_pcm")["model"] if cfg.node_params("vmocap_pcm")["source"] == "model" else "blazepose",
        overwrite=args.overwrite, inputs=[rig_path, cfg_path], max_people=args.max_people,
    )
    bad = {c: n for c, n in stats.get("bad_images", {}).items() if n}
    if bad:
        print(f"vmocap process: WARNING: images left out (wrong size or no contrast), per camera: {bad}", file=sys.stderr)
    for line in stats.get("out_of_step", []):
        print(f"vmocap process: WARNING: camera out of step? {line}", file=sys.stderr)
    failed = stats["frames"] > 0 and stats["tracking"] == 0
    if failed:
        print(f"vmocap process: ERROR: no frame set of {stats['frames']} tracked: {stats.get('not_tracked_because', '')}",
              file=sys.stderr)
    if args.json:
        print(json.dumps(stats))
    else:
        print(f"{stats['frames']} frame sets ({stats['recording_s']:.2f} s of recording), {stats['tracking']} tracked, "
              f"processed in {stats['wall_s']:.2f} s ({stats['realtime_factor']:.2f} x real time; pipeline "
              f"{stats['ms_per_frame']:.2f} ms per frame set) -> {args.output}")
    if args.plots:
        from ..export.plots import plot_session
        from ..export.session import load_session

        for f in plot_session(load_session(args.output), args.plots, [args.input, rig_path, cfg_path, args.output]):
            print(f"plot: {f}")
    return 1 if failed else 0
