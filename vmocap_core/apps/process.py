"""The graph's pipeline without DDS: `vmocap process IN.mcap -o OUT.mcap`.

The pieces here are the ones the rclpy nodes call, so the graph and the offline run compute
the same thing from the same bytes:
- `PcmAssembler`: PCM (Image, CameraInfo) messages of the views -> frame sets -> PcmViews
  (what vmocap_markers does with its subscriptions);
- `TrackerPipeline`: MarkerStage then SkeletonStage, the skeleton of frame t-1 fed back to the
  lattice search of frame t (vmocap_markers + vmocap_skeleton);
- `result_messages`: TrackResult -> output message dicts (what vmocap_skeleton publishes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from ..bag import BagReader, BagWriter
from ..bag import messages as M
from ..cameras.bag import decode_compressed
from ..cameras.projection import Rig
from ..cameras.sync import ApproximateSync
from ..errors import BagError, HeatmapError
from ..export.session import SUBJECT_STATUS
from ..graph_config import Topics
from ..keypoints import KEYPOINTS, indices
from ..outputs.streams import SubjectOutputs
from ..paths import REPO
from ..pcm.views import PcmViews

IMAGE = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"
CLOUD = "sensor_msgs/msg/PointCloud2"
JOINTS = "sensor_msgs/msg/JointState"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"


def channel_keypoints(names: Iterable[str]) -> np.ndarray:
    names = list(names)
    return indices(names) if names else np.arange(len(KEYPOINTS))


class PcmAssembler:
    """Pairs each view's heatmap Image with its CameraInfo (same stamp) and synchronizes the
    views into frame sets. `add_*` return the PcmViews that became complete."""

    def __init__(self, rig: Rig, views: list[str], keypoints: np.ndarray, tolerance_ns: int = 1_000_000,
                 min_views: int = 2, silent_after_ns: int = 500_000_000) -> None:
        self.rig = rig
        self.views = list(views)
        self.keypoints = np.asarray(keypoints)
        self.sync: ApproximateSync[tuple[dict, dict]] = ApproximateSync(
            self.views, tolerance_ns, min_cameras=min_views, silent_after_ns=silent_after_ns, max_queue=60)
        self._half: dict[str, dict[int, tuple[str, dict]]] = {v: {} for v in self.views}
        self.bad_views = 0
        self.last_error = ""

    def _add(self, view: str, kind: str, msg: dict) -> list[PcmViews]:
        t = M.stamp_ns(msg)
        pending = self._half[view]
        other = pending.pop(t, None)
        if other is None:
            pending[t] = (kind, msg)
            if len(pending) > 60:  # a partner that never comes: forget the oldest
                pending.pop(min(pending))
            return []
        if other[0] == kind:  # duplicate of the same half: keep the newer one
            pending[t] = (kind, msg)
            return []
        pair = (msg, other[1]) if kind == "image" else (other[1], msg)
        return self._frame_sets(self.sync.add(view, t, pair))

    def add_image(self, view: str, msg: dict) -> list[PcmViews]:
        return self._add(view, "image", msg)

    def add_info(self, view: str, msg: dict) -> list[PcmViews]:
        return self._add(view, "info", msg)

    def flush(self) -> list[PcmViews]:
        return self._frame_sets(self.sync.flush())

    def _frame_sets(self, sets: list) -> list[PcmViews]:
        out = []
        for fs in sets:
            pairs = [fs.items[v] for v in self.views if v in fs.items]
            try:
                pcm = M.pcm_views(pairs, self.rig, self.keypoints)
            except (HeatmapError, BagError) as exc:
                self.bad_views += 1
                self.last_error = str(exc)
                continue
            pcm.stamp_ns = fs.stamp_ns
            out.append(pcm)
        return out


@dataclass
class TrackerPipeline:
    """MarkerStage + SkeletonStage with the deterministic feedback of frame t-1."""

    rig: Rig
    config: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        from ..method.tracker import MarkerStage, SkeletonStage, TrackerConfig

        cfg = TrackerConfig.from_dict(self.config)
        self.markers = MarkerStage(self.rig, cfg)
        self.skeleton = SkeletonStage(cfg)

    def step(self, pcm: PcmViews):
        m = self.markers.step(pcm)
        r = self.skeleton.step(m)
        self.markers.feedback(feedback_of(r))
        return m, r


def feedback_of(result: Any) -> np.ndarray | None:
    """What the skeleton stage feeds back to the lattice search (None: re-initialize)."""
    from ..method.tracker import FEEDBACK_STATUSES

    return result.raw_keypoints if result.status in FEEDBACK_STATUSES else None


def markers_message(markers: Any) -> dict:
    residual = markers.residual_px if markers.residual_px is not None else np.full(len(KEYPOINTS), np.nan)
    return M.keypoint_cloud(markers.stamp_ns, markers.positions, markers.weights, markers.kind, residual, markers.cameras)


def markers_from_message(msg: dict) -> Any:
    """Inverse of `markers_message` (the cloud carries positions, weights and kind)."""
    from ..method.tracker import Markers

    P, S, kind = M.cloud_keypoints(msg)
    if P is None:
        P = np.full((len(KEYPOINTS), 3), np.nan)
    residual, cameras = M.cloud_marker_extras(msg)
    return Markers(M.stamp_ns(msg), P, S, kind, residual_px=residual, cameras=cameras)


def result_messages(topics: Topics, result: Any, wanted: Callable[[str], bool] | None = None,
                    subject: Any = None) -> Iterator[tuple[str, str, dict]]:
    """(topic, type, message) of one TrackResult in publishing order: the feedback first (the
    lattice search of the next frame waits for it), then, with a `subject`
    (outputs.streams.SubjectOutputs), robot_description and /tf_static when the skeleton is
    new, then joint_states (what controllers wait for; the URDF's joints), root_pose, /tf,
    keypoints and the MarkerArray. Each message is built when it is taken, and not at all where
    `wanted(topic)` is False (nobody listens)."""
    from ..outputs import streams
    from ..outputs.urdf import base_pose, joint_positions

    t = result.stamp_ns
    tracking = result.status == "tracking"
    want = wanted or (lambda topic: True)
    if want(topics.feedback):
        yield topics.feedback, CLOUD, M.keypoint_cloud(t, feedback_of(result))
    if subject is not None:
        yield from subject.start(topics, t)
        if tracking:
            yield from subject.description(topics, t, result.dims)
    if tracking:
        positions, base = joint_positions(result.q), base_pose(result.q)
        if want(topics.joint_states):
            yield topics.joint_states, JOINTS, streams.joint_state(t, positions)
        if want(topics.root_pose):
            yield topics.root_pose, streams.POSE, streams.root_pose(t, base)
        if subject is not None and want(topics.tf):
            yield subject.tf(topics, t, positions, base)
    if want(topics.keypoints):
        yield topics.keypoints, CLOUD, M.keypoint_cloud(t, result.keypoints if tracking else None, result.scores)
    if want(topics.skeleton):
        yield topics.skeleton, MARKER_ARRAY, M.skeleton_markers(t, result.keypoints if tracking else None)


def pcm_topics(bag_topics: dict[str, str], topics: Topics, views: list[str] | None) -> list[str]:
    """View names of the PCM topics present in a bag."""
    prefix = f"{topics.ns}/pcm/"
    found = sorted(
        t[len(prefix): -len("/heatmaps")] for t, ty in bag_topics.items()
        if t.startswith(prefix) and t.endswith("/heatmaps") and ty == IMAGE
    )
    if views:
        missing = [v for v in views if v not in found]
        if missing:
            raise BagError(f"the bag has no PCM topics for views {missing} (found {found})")
        return list(views)
    return found


# --------------------------------------------------------------------------------- offline
def process_bag(
    in_path: str | Path,
    out_path: str | Path,
    rig: Rig,
    tracker: dict[str, Any] | None = None,
    keypoints: Iterable[str] = (),
    views: list[str] | None = None,
    namespace: str = "/vmocap",
    tolerance_ns: int = 1_000_000,
    min_views: int = 2,
    recover: bool = False,
    progress: bool = True,
    model: str = "blazepose",
    provider: Any = None,
) -> dict[str, Any]:
    """Run the pipeline over the PCM topics of a bag (or, when it has none, over its camera
    images with the CNN `model`, or the given PCM `provider`); write the graph's outputs to
    out_path (log time = capture stamp). Returns counts and the time per frame."""
    from tqdm import tqdm

    topics = Topics(namespace)
    kp = channel_keypoints(keypoints)
    with BagReader(in_path, recover=recover) as reader:
        view_names = pcm_topics(reader.topics, topics, views)
        if not view_names:
            cams = [c.name for c in rig if _image_topic(reader, topics, c.name)]
            if len(cams) < 2:
                raise BagError(f"{in_path}: neither PCM topics under {topics.ns}/pcm/ nor images "
                               f"{topics.image('CAM')} of at least 2 rig cameras")
            return _process_images(reader, out_path, rig, cams, topics, tracker, model, tolerance_ns,
                                   min_views, progress, provider)
        asm = PcmAssembler(rig, view_names, kp, tolerance_ns, min_views)
        offline = bool((tracker or {}).get("offline"))
        # Offline: the live pass without lag; its results are kept for the whole-recording pass.
        pipe = TrackerPipeline(rig, dict(tracker or {}, smoothing_lag_frames=0) if offline else dict(tracker or {}))
        kept: list[tuple[Any, Any]] = []
        subject = SubjectOutputs(rig)
        by_topic = {}
        for v in view_names:
            by_topic[topics.pcm(v)] = (v, "image")
            by_topic[topics.pcm_info(v)] = (v, "info")
        total = sum(reader.message_counts.get(t, 0) for t in by_topic) // 2
        stats: dict[str, Any] = {"frames": 0, "tracking": 0, "seconds": 0.0}
        with BagWriter(out_path, compression="zstd") as writer:
            bar = tqdm(total=total, unit="frame", desc="process", disable=not progress, file=sys.stderr)

            def handle(pcms: list[PcmViews]) -> None:
                for pcm in pcms:
                    t0 = time.perf_counter()
                    markers, result = pipe.step(pcm)
                    stats["seconds"] += time.perf_counter() - t0
                    if offline:
                        kept.append((markers, result))
                    else:
                        _write_outputs(writer, topics, markers, result, pcm.stamp_ns, stats, subject)
                        _write_subject(writer, pipe.skeleton, result, stats)
                bar.update(len(pcms))

            for m in reader.messages(list(by_topic)):
                view, kind = by_topic[m.topic]
                msg = m.decode()
                handle(asm.add_image(view, msg) if kind == "image" else asm.add_info(view, msg))
            handle(asm.flush())
            bar.close()
            if offline and kept:
                _write_offline(writer, topics, kept, pipe.skeleton.config, stats, progress, subject)
            if asm.bad_views and stats["frames"] == 0:
                raise HeatmapError(f"{in_path}: no usable PCM frame set ({asm.bad_views} rejected): {asm.last_error}")
            st = asm.sync.stats().as_dict()
            stats.pop("_subject", None)
            writer.write(Topics.diagnostics, DIAG, M.diagnostics_msg(reader.end_ns, [
                (0, "vmocap_process: sync", "offline", {k: json.dumps(v) for k, v in st.items()}),
            ]), reader.end_ns)
    stats["sync"] = st
    stats["rejected_frame_sets"] = asm.bad_views
    stats["ms_per_frame"] = 1e3 * stats["seconds"] / max(stats["frames"], 1)
    return stats


def write_results(writer: BagWriter, topics: Topics, result, stamp_ns: int, subject: SubjectOutputs | None) -> None:
    """A TrackResult's output messages (not the internal feedback) into a bag at its stamp."""
    for topic, ty, msg in result_messages(topics, result, wanted=lambda topic: topic != topics.feedback, subject=subject):
        if topic in (topics.robot_description, topics.tf_static):
            writer.add_topic(topic, ty, latched=True)
        writer.write(topic, ty, msg, stamp_ns)


def _write_outputs(writer: BagWriter, topics: Topics, markers, result, stamp_ns: int, stats: dict[str, Any],
                   subject: SubjectOutputs | None = None) -> None:
    """One frame set's graph outputs (markers and results, not the internal feedback) and counts."""
    writer.write(topics.markers, CLOUD, markers_message(markers), stamp_ns)
    write_results(writer, topics, result, stamp_ns, subject)
    stats["frames"] += 1
    stats["tracking"] += result.status == "tracking"


def _write_subject(writer: BagWriter, stage: Any, result: Any, stats: dict[str, Any]) -> None:
    """The subject's body dimensions (what a BVH export needs) on /diagnostics, whenever the
    live skeleton stage starts tracking with a new identification."""
    sk = stage.skeleton
    if result.status == "tracking" and sk is not None and stats.get("_subject") is not sk:
        stats["_subject"] = sk
        writer.write(Topics.diagnostics, DIAG, subject_message(result.stamp_ns, sk.dims), result.stamp_ns)


def subject_message(stamp_ns: int, dims: Any) -> dict:
    return M.diagnostics_msg(stamp_ns, [(0, SUBJECT_STATUS, "body dimensions (m)", {"dims": json.dumps(dims.to_dict())})])


def _write_offline(writer: BagWriter, topics: Topics, kept: list, config: Any, stats: dict[str, Any],
                   progress: bool, subject: SubjectOutputs | None = None) -> None:
    """The whole-recording pass (offline.py) over the live results, then the outputs."""
    from ..method.offline import identify_and_reconstruct

    t0 = time.perf_counter()
    results, sk = identify_and_reconstruct([r for _, r in kept], config, progress=progress)
    stats["seconds"] += time.perf_counter() - t0
    first = next(r.stamp_ns for r in results if r.status == "tracking")
    writer.write(Topics.diagnostics, DIAG, subject_message(first, sk.dims), first)
    for (markers, _), result in zip(kept, results):
        _write_outputs(writer, topics, markers, result, result.stamp_ns, stats, subject)


def _process_images(reader: BagReader, out_path, rig: Rig, cams: list[str], topics: Topics, tracker, model: str,
                    tolerance_ns: int, min_views: int, progress: bool, provider: Any = None) -> dict[str, Any]:
    """Images (raw or compressed) -> approximate-time sync -> CNN (crops from the previous frame's skeleton) ->
    tracker: what vmocap_pcm + vmocap_markers + vmocap_skeleton do, frame set by frame set."""
    from tqdm import tqdm

    provider = provider or make_model_provider(model, rig)
    sync: ApproximateSync[np.ndarray] = ApproximateSync(cams, max(tolerance_ns, 8_000_000), min_cameras=min_views)
    offline = bool((tracker or {}).get("offline"))
    pipe = TrackerPipeline(rig, dict(tracker or {}, smoothing_lag_frames=0) if offline else dict(tracker or {}))
    kept: list[tuple[Any, Any]] = []
    subject = SubjectOutputs(rig)
    want = {str(_image_topic(reader, topics, c)): c for c in cams}  # every camera has one (process_bag)
    compressed = {t for t in want if t.endswith("/compressed")}
    stats: dict[str, Any] = {"frames": 0, "tracking": 0, "seconds": 0.0, "pcm": provider.name}
    feedback = None
    with BagWriter(out_path, compression="zstd") as writer:
        bar = tqdm(total=min(reader.message_counts.get(t, 0) for t in want), unit="frame", desc="process (CNN)",
                   disable=not progress, file=sys.stderr)

        def handle(sets: list) -> None:
            nonlocal feedback
            for fs in sets:
                t0 = time.perf_counter()
                names = [c for c in rig.names if c in fs.items]
                idx = np.array([rig.names.index(c) for c in names])
                pcm = provider.infer([fs.items[c] for c in names], idx, fs.stamp_ns, feedback)
                markers, result = pipe.step(pcm)
                feedback = feedback_of(result)
                stats["seconds"] += time.perf_counter() - t0
                if offline:
                    kept.append((markers, result))
                else:
                    _write_outputs(writer, topics, markers, result, fs.stamp_ns, stats, subject)
                    _write_subject(writer, pipe.skeleton, result, stats)
            bar.update(len(sets))

        for m in reader.messages(list(want)):
            msg = m.decode()
            image = decode_compressed(msg) if m.topic in compressed else M.image_array(msg)
            handle(sync.add(want[m.topic], M.stamp_ns(msg), image))
        handle(sync.flush())
        bar.close()
        if offline and kept:
            _write_offline(writer, topics, kept, pipe.skeleton.config, stats, progress, subject)
    stats.pop("_subject", None)
    stats["sync"] = sync.stats().as_dict()
    stats["ms_per_frame"] = 1e3 * stats["seconds"] / max(stats["frames"], 1)
    return stats


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


# --------------------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", help="MCAP bag with PCM topics (NS/pcm/VIEW/heatmaps + camera_info), "
                        "or with camera images (NS/CAM/image_raw: the CNN runs)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write the graph outputs to")
    parser.add_argument("--config", default=None, help="graph config (rig, keypoints, tracker.*); default config/graph.yaml")
    parser.add_argument("--rig", default=None, help="rig YAML (overrides the config's)")
    parser.add_argument("--recover", action="store_true", help="read a truncated bag up to the damage")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")
    parser.add_argument("--offline", action="store_true", help="offline mode: whole-recording identification, "
                        "RTS smoother, second IK (tracker.offline)")
    parser.add_argument("--plots", type=Path, default=None, help="write joint-angle and keypoint-speed plots (PNG) here")


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
    tracker = cfg.tracker_dict(p)
    if args.offline:
        tracker["offline"] = True
    stats = process_bag(
        args.input, args.output, rig, tracker=tracker, keypoints=p["pcm_keypoints"],
        views=p["views"] or None, namespace=p["namespace"], tolerance_ns=int(p["sync_tolerance_ms"] * 1e6),
        min_views=p["min_cameras"], recover=args.recover, progress=not args.no_progress,
        model=cfg.node_params("vmocap_pcm")["model"] if cfg.node_params("vmocap_pcm")["source"] == "model" else "blazepose",
    )
    if args.json:
        print(json.dumps(stats))
    else:
        print(f"{stats['frames']} frame sets, {stats['tracking']} tracked, "
              f"{stats['ms_per_frame']:.2f} ms per frame -> {args.output}")
    if args.plots:
        from ..export.plots import plot_session
        from ..export.session import load_session

        for f in plot_session(load_session(args.output), args.plots):
            print(f"plot: {f}")
    return 0


# --------------------------------------------------------------------------------- PCM providers
class BagPcmProvider:
    """Heatmaps read from a bag's PCM topics, handed out in order, one frame set per call
    (looping): stands in for the CNN while keeping the rest of the graph real."""

    name = "bag"

    def __init__(self, path: str | Path, rig: Rig, keypoints: np.ndarray, namespace: str = "/vmocap") -> None:
        topics = Topics(namespace)
        with BagReader(path) as reader:
            views = pcm_topics(reader.topics, topics, None)
            if not views:
                raise BagError(f"{path}: no PCM topics under {topics.ns}/pcm/")
            asm = PcmAssembler(rig, views, keypoints)
            sel = {topics.pcm(v): (v, "image") for v in views} | {topics.pcm_info(v): (v, "info") for v in views}
            self.frames: list[PcmViews] = []
            for m in reader.messages(list(sel)):
                v, kind = sel[m.topic]
                self.frames += asm.add_image(v, m.decode()) if kind == "image" else asm.add_info(v, m.decode())
            self.frames += asm.flush()
        if not self.frames:
            raise BagError(f"{path}: no complete PCM frame set")
        self._k = 0

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        src = self.frames[self._k % len(self.frames)]
        self._k += 1
        return PcmViews(src.maps, src.image_to_map, src.camera, src.keypoints, src.valid, src.presence, stamp_ns)


def time_pipeline(frames: list[PcmViews], rig: Rig, tracker: dict[str, Any] | None, n: int,
                  period_ns: int = 33_333_333) -> dict[str, float]:
    """Per-frame-set time (ms) of TrackerPipeline.step over `n` frame sets handed out as the
    graph's PCM node hands them out from a bag (`frames` looped, stamps one period apart):
    the offline cost that the graph's end-to-end latency compares with."""
    pipe = TrackerPipeline(rig, dict(tracker or {}))
    ms = np.empty(n)
    for k in range(n):
        src = frames[k % len(frames)]
        pcm = PcmViews(src.maps, src.image_to_map, src.camera, src.keypoints, src.valid, src.presence, k * period_ns)
        t0 = time.perf_counter()
        pipe.step(pcm)
        ms[k] = 1e3 * (time.perf_counter() - t0)
    return {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)), "mean": float(ms.mean()), "n": n}


class SyntheticPcmProvider:
    """Heatmaps rendered from a motion clip's ground truth (vmocap_core.pcm.synthetic): the clip's
    frame at the frame set's stamp (stamp x fps, modulo the clip's length), so that PCM workers
    of different cameras render the same instant whatever frames each of them skipped; the input
    rotation follows the fed-back skeleton."""

    name = "synthetic"

    def __init__(self, rig: Rig, motion_path: str | Path, fps: float, seed: int | None = None) -> None:
        """seed None: from the camera names, so that per-camera workers draw independent noise
        (one seed for all would give every view the same false peaks and swaps)."""
        import zlib

        from ..motion import extend, load_motion, resample
        from ..pcm.synthetic import SyntheticPcmSource

        seed = zlib.crc32(",".join(rig.names).encode()) if seed is None else seed
        motion = extend(resample(load_motion(motion_path), fps), 2.0)
        self.source = SyntheticPcmSource(rig, motion.positions, motion.present, seed=seed, fps=fps)
        self.rig = rig
        self.fps = fps

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        from ..method.tracker import trunk_tilt

        rot = trunk_tilt(self.rig, feedback) if feedback is not None else None
        pcm = self.source.render(int(round(stamp_ns * self.fps / 1e9)) % len(self.source), rotation=rot)
        keep = np.isin(pcm.camera, cameras)
        return PcmViews(pcm.maps[keep], pcm.image_to_map[keep], pcm.camera[keep], pcm.keypoints,
                        pcm.valid[keep], pcm.presence[keep], stamp_ns)


class ModelPcmProvider:
    """The CNN (vmocap_core.pcm.pipeline.BlazePosePcm): detector crops until a skeleton is fed
    back, then crops around the projected skeleton, rotated by the trunk tilt."""

    def __init__(self, rig: Rig, model: str = "", rotation: str = "all", threads: int = 2) -> None:
        from ..pcm.pipeline import BlazePosePcm

        variant = "lite" if model.endswith("lite") else "full"
        self.rig = rig
        self.pcm = BlazePosePcm(rig, rotation=rotation, threads=threads, variant=variant)
        lm = self.pcm.landmark
        self.name = f"blazepose-{variant} {lm.precision} (rotation {rotation})"
        self.precision, self.precision_reason = lm.precision, lm.precision_reason

    def infer(self, images: list[np.ndarray], cameras: np.ndarray, stamp_ns: int, feedback: np.ndarray | None) -> PcmViews:
        full: list[np.ndarray | None] = [None] * len(self.rig)
        for c, img in zip(cameras, images):
            full[int(c)] = img
        usable = feedback is not None and np.isfinite(feedback[[0, 1]]).all()
        return self.pcm.infer(full, keypoints=feedback if usable else None, stamp_ns=stamp_ns)


def make_model_provider(model: str, rig: Rig, rotation: str = "all", threads: int = 2) -> ModelPcmProvider:
    return ModelPcmProvider(rig, model, rotation, threads)
