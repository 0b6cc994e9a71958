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
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from .. import paths
from ..cameras.projection import Camera, Rig
from ..errors import RigFileError, VmocapError
from ..keypoints import INDEX, KEYPOINTS

REPO = paths.REPO
FPS = 60.0
QUALISYS_SUBPIXELS = 64
# Qualisys camera axes: x right, y up, z backwards; OpenCV's: x right, y down, z forward.
QUALISYS_TO_OPENCV = np.diag([1.0, -1.0, -1.0])
# 60 fps: a Butterworth at 20 Hz, since 8 Hz lags ~3 px behind fast limbs (the speed-adaptive
# default: 12.17 vs 11.63 px). The clip lasts 1.7 s: output from the provisional fit instead of
# a 0.5 s identification phase (which left 67 of 100 frames tracked).
TRACKER_SETTINGS = {"fps": FPS, "filter_kind": "butterworth", "filter_cutoff_hz": 20.0, "identify_seconds": 0.0}
# Lines drawn for the overlay (pairs of keypoint names).
LIMBS = (
    ("left_shoulder", "right_shoulder"), ("left_hip", "right_hip"), ("left_shoulder", "left_hip"),
    ("right_shoulder", "right_hip"), ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
    ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"), ("left_hip", "left_knee"),
    ("left_knee", "left_ankle"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
    ("left_ankle", "left_heel"), ("left_heel", "left_toe"), ("left_ankle", "left_toe"),
    ("right_ankle", "right_heel"), ("right_heel", "right_toe"), ("right_ankle", "right_toe"),
    ("neck", "nose"), ("nose", "left_eye"), ("nose", "right_eye"), ("left_eye", "left_ear"),
    ("right_eye", "right_ear"), ("pelvis", "neck"),
)


def log(msg: str) -> None:
    print(f"vmocap demo: {msg}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------ calibration
def load_qualisys_rig(path: str | Path, sizes: dict[str, tuple[int, int]] | None = None) -> Rig:
    """Full rig (intrinsics, distortion, extrinsics) from a Qualisys .qca.txt calibration.

    `transform` holds the camera position (mm) and a rotation whose rows are the Qualisys camera
    axes in world coordinates (y up, z backwards): world->camera for OpenCV is
    R = diag(1, -1, -1) @ rows, t = -R @ position. Intrinsics are in 1/64 pixel relative to the
    sensor; the video field of view gives the crop. `sizes` (name -> (w, h)) overrides the image
    size where a video was stored cropped at the right/bottom (e.g. 1080 of 1088 columns).
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise RigFileError(path, "xml", str(exc)) from None
    cams: list[Camera] = []
    for cam in root.iter("camera"):
        name = cam.get("serial") or f"cam{len(cams) + 1:02d}"
        tr, it, fov = cam.find("transform"), cam.find("intrinsic"), cam.find("fov_video")
        if tr is None or it is None or fov is None:
            raise RigFileError(path, f"camera {name}", "missing transform, intrinsic or fov_video")
        try:
            rows = np.array([[float(tr.get(f"r{i}{j}")) for j in (1, 2, 3)] for i in (1, 2, 3)])
            pos = np.array([float(tr.get(a)) for a in "xyz"]) / 1000.0
            fx = float(it.get("focalLengthU")) / QUALISYS_SUBPIXELS
            fy = float(it.get("focalLengthV")) / QUALISYS_SUBPIXELS
            cx = float(it.get("centerPointU")) / QUALISYS_SUBPIXELS - float(fov.get("left"))
            cy = float(it.get("centerPointV")) / QUALISYS_SUBPIXELS - float(fov.get("top"))
            dist = [float(it.get(k)) for k in ("radialDistortion1", "radialDistortion2", "tangentalDistortion1",
                                               "tangentalDistortion2", "radialDistortion3")]
            w = int(fov.get("right")) - int(fov.get("left")) + 1
            h = int(fov.get("bottom")) - int(fov.get("top")) + 1
        except (TypeError, ValueError) as exc:
            raise RigFileError(path, f"camera {name}", f"bad number ({exc})") from None
        if sizes and name in sizes:
            w, h = sizes[name]
        R = QUALISYS_TO_OPENCV @ rows
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cams.append(Camera(name, K, dist, R, -R @ pos, w, h))
    if not cams:
        raise RigFileError(path, "cameras", "no camera")
    return Rig(cams)


def video_paths(demo: Path) -> dict[str, Path]:
    vids = sorted((demo / "videos").glob("cam*.mp4"))
    if not vids:
        raise VmocapError(f"{demo}/videos: no cam*.mp4")
    return {p.stem: p for p in vids}


def video_sizes(videos: dict[str, Path]) -> dict[str, tuple[int, int]]:
    import cv2

    out = {}
    for name, p in videos.items():
        cap = cv2.VideoCapture(str(p))
        out[name] = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        cap.release()
    return out


# ------------------------------------------------------------------------------ videos -> bag
def videos_to_bag(videos: dict[str, Path], rig: Rig, bag: Path, max_frames: int | None = None, quality: int = 90,
                  raw: bool = False) -> int:
    """Write the synchronized videos as JPEG CompressedImage + CameraInfo per camera
    (stamp = frame index / 60 fps). Returns the number of frame sets. raw=True writes
    sensor_msgs/Image (bgr8) on NS/CAM/image_raw instead (about 25 MB per frame set before
    the bag's zstd compression; the camera node reads either)."""
    import cv2
    from tqdm import tqdm

    from ..bag import BagWriter
    from ..bag import messages as M
    from ..graph_config import Topics

    topics = Topics()
    caps = {c.name: cv2.VideoCapture(str(videos[c.name])) for c in rig}
    n = min(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) for cap in caps.values())
    if max_frames:
        n = min(n, max_frames)
    bag.parent.mkdir(parents=True, exist_ok=True)
    tmp = bag.with_suffix(".part")
    written = 0
    with BagWriter(tmp, compression="zstd" if raw else "none") as writer:
        for f in tqdm(range(n), desc="videos -> bag", unit="frame", file=sys.stderr):
            ns = int(round(f * 1e9 / FPS))
            frames = {}
            for name, cap in caps.items():
                ok, img = cap.read()
                if not ok:
                    break
                frames[name] = img
            if len(frames) < len(caps):
                break
            for cam in rig:
                if raw:
                    writer.write(topics.image(cam.name), "sensor_msgs/msg/Image", M.image_msg(frames[cam.name], ns, cam.name), ns)
                    writer.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, ns), ns)
                    continue
                ok, jpg = cv2.imencode(".jpg", frames[cam.name], [cv2.IMWRITE_JPEG_QUALITY, quality])
                writer.write(topics.image(cam.name) + "/compressed", "sensor_msgs/msg/CompressedImage",
                             {"header": M.header(ns, cam.name), "format": "jpeg", "data": jpg.tobytes()}, ns)
                writer.write(topics.camera_info(cam.name), "sensor_msgs/msg/CameraInfo", M.camera_info_msg(cam, ns), ns)
            written += 1
    for cap in caps.values():
        cap.release()
    tmp.replace(bag)
    return written


def bag_frame_sets(bag: Path, rig: Rig):
    """(stamp_ns, images in rig order) of the bag's camera images (JPEG CompressedImage, or raw
    Image), by stamp."""
    import cv2

    from ..bag import BagReader
    from ..bag import messages as M
    from ..graph_config import Topics

    topics = Topics()
    pending: dict[int, dict[int, np.ndarray]] = {}
    with BagReader(bag) as reader:
        want = {}
        for i, c in enumerate(rig):
            raw = topics.image(c.name)
            want[raw + "/compressed" if raw + "/compressed" in reader.topics else raw] = i
        missing = [t for t in want if t not in reader.topics]
        if missing:
            raise VmocapError(f"{bag}: no topics {missing}")
        for m in reader.messages(list(want)):
            msg = m.decode()
            ns = M.stamp_ns(msg)
            if m.topic.endswith("/compressed"):
                img = cv2.imdecode(np.frombuffer(bytes(msg["data"]), np.uint8), cv2.IMREAD_COLOR)
                if img is None:
                    raise VmocapError(f"{bag}: undecodable image on {m.topic} at {ns} ns")
            else:
                img = M.image_array(msg)
            pending.setdefault(ns, {})[want[m.topic]] = img
            if len(pending[ns]) == len(rig):
                imgs = pending.pop(ns)
                yield ns, [imgs[i] for i in range(len(rig))]


def _count_frame_sets(bag: Path, rig: Rig, raw: bool = False) -> int:
    from ..bag import BagReader
    from ..errors import BagError
    from ..graph_config import Topics

    suffix = "" if raw else "/compressed"
    try:
        with BagReader(bag) as reader:
            return min(reader.message_counts.get(Topics().image(c.name) + suffix, 0) for c in rig)
    except BagError:
        return -1


def _video_frames(videos: dict[str, Path]) -> int:
    import cv2

    counts = []
    for p in videos.values():
        cap = cv2.VideoCapture(str(p))
        counts.append(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        cap.release()
    return min(counts)


# ------------------------------------------------------------------------------ pipeline
def run_pipeline(bag: Path, rig: Rig, out_bag: Path, n_frames: int, threads: int = 2,
                 settings: dict[str, Any] | None = None) -> dict:
    """The pipeline on the bag's images with the real CNN; records everything the report needs.
    `settings`: the method's tunables (default TRACKER_SETTINGS)."""
    from tqdm import tqdm

    from ..bag import BagWriter
    from ..graph_config import Topics
    from ..method.config import PipelineConfig
    from ..method.pipeline import ImageSet, Pipeline
    from ..outputs.messages import CLOUD, markers_message, write_results
    from ..outputs.streams import SubjectOutputs
    from ..pcm.peaks import camera_keypoints
    from ..pcm.providers import ModelPcmProvider

    topics = Topics()
    pipe = Pipeline(rig, PipelineConfig.from_dict(TRACKER_SETTINGS if settings is None else settings),
                    ModelPcmProvider(rig, threads=threads))
    subject = SubjectOutputs(rig)
    rec: dict[str, list] = {k: [] for k in ("stamp", "status", "keypoints", "raw", "markers", "uv", "w", "score", "weights",
                                             "t_decode", "t_pcm", "t_markers", "t_skeleton", "n_views", "links")}
    cameras = np.arange(len(rig))
    it = bag_frame_sets(bag, rig)
    with BagWriter(out_bag, compression="zstd") as writer:
        bar = tqdm(total=n_frames, desc="pipeline", unit="frame", file=sys.stderr)
        while True:
            t0 = time.perf_counter()
            try:
                ns, images = next(it)
            except StopIteration:
                break
            t1 = time.perf_counter()
            res = pipe.step(ImageSet(ns, images, cameras))
            result, markers, pcm = res.skeleton, res.markers, res.pcm
            writer.write(topics.markers, CLOUD, markers_message(markers), ns)
            write_results(writer, topics, result, ns, subject)
            uv, w = camera_keypoints(pcm, len(rig))
            for k, v in (("stamp", ns), ("status", result.status), ("keypoints", result.keypoints),
                         ("raw", result.raw_keypoints), ("markers", markers.positions), ("uv", uv),
                         ("w", w), ("score", markers.score), ("weights", markers.weights), ("t_decode", t1 - t0),
                         ("t_pcm", pipe.timings["pcm"]), ("t_markers", pipe.timings["markers"]),
                         ("t_skeleton", pipe.timings["skeleton"]), ("n_views", pcm.n_views), ("links", result.link_lengths)):
                rec[k].append(v)
            bar.update(1)
        bar.close()
    out = {k: (np.array(v) if k not in ("status", "links") else v) for k, v in rec.items()}
    return out


# ------------------------------------------------------------------------------ node graph
def run_graph(bag: Path, rig_yaml: Path, rig: Rig, out_dir: Path, n_frames: int, rate: float = 0.05) -> Path:
    """The ROS 2 node graph (camera from the bag: JPEG CompressedImage decoded in the camera
    node, or raw Image; CNN PCM node, markers, skeleton, recorder) as `vmocap launch`
    processes; returns the recorded MCAP (outputs + PCMs).

    The bag is played at `rate` x real time so the CNN on this CPU keeps up (frames the PCM
    node cannot take are dropped by design: freshness over completeness)."""
    import os
    import signal
    import subprocess

    import yaml
    from tqdm import tqdm

    from ..graph_config import Topics, stage_sections

    topics = Topics()
    record = [topics.keypoints, topics.joint_states, topics.markers, topics.skeleton, Topics.diagnostics]
    record += [topics.pcm(c.name) for c in rig] + [topics.pcm_info(c.name) for c in rig]
    output = out_dir / "graph_outputs.mcap"
    stages = stage_sections(TRACKER_SETTINGS)
    cfg = {
        "/**": {"ros__parameters": {"rig": str(rig_yaml), "cameras": [""], "namespace": topics.ns,
                                    "pcm_keypoints": [""], "use_sim_time": False, **stages["/**"]}},
        "vmocap_camera": {"ros__parameters": {"source": "bag", "uri": str(bag), "rate": rate, "loop": False,
                                              "start_offset": 0.0}},
        "vmocap_pcm": {"ros__parameters": {"source": "model", "model": "blazepose", "min_cameras": 2,
                                           "silent_after_ms": 5000.0, "use_feedback": True, "queue_depth": 50}},
        "vmocap_markers": {"ros__parameters": {"min_cameras": 2, "silent_after_ms": 5000.0,
                                               "feedback_timeout_ms": 2000.0, "views": [""],
                                               **stages["vmocap_markers"]}},
        "vmocap_skeleton": {"ros__parameters": stages["vmocap_skeleton"]},
        "vmocap_recorder": {"ros__parameters": {"output": str(output), "topics": record, "compression": "zstd"}},
        "vmocap_launch": {"mode": "processes", "fastdds_profile": str(REPO / "config" / "fastdds_shm.xml"),
                          "nodes": ["vmocap_camera", "vmocap_pcm", "vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]},
    }
    cfg_path = out_dir / "graph.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    launch = [sys.executable, "-m", "vmocap_core.cli", "launch", str(cfg_path), "--nodes"]
    back = ["vmocap_pcm", "vmocap_markers", "vmocap_skeleton", "vmocap_recorder"]
    procs: list[subprocess.Popen] = []

    def stop(proc: subprocess.Popen) -> None:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)  # the launcher stops its nodes; the recorder flushes
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    log_main, log_cam = out_dir / "graph.log", out_dir / "graph_camera.log"
    with open(log_main, "w") as lf, open(log_cam, "w") as lc:
        try:
            # The camera starts only once the other nodes are up (else the first frames, the
            # ones that initialize the tracker, would go to a PCM node still loading its model).
            procs.append(subprocess.Popen(launch + back, stdout=lf, stderr=subprocess.STDOUT, env=env, cwd=REPO))
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline and procs[0].poll() is None:
                if all(f"READY {n}" in log_main.read_text() for n in back):
                    break
                time.sleep(0.5)
            else:
                raise VmocapError(f"the node graph did not start; see {log_main}")
            procs.append(subprocess.Popen(launch + ["vmocap_camera"], stdout=lc, stderr=subprocess.STDOUT, env=env, cwd=REPO))
            seconds = int(n_frames / FPS / rate + 15)  # playback + the last frames through the graph
            for _ in tqdm(range(seconds), desc="node graph", unit="s", file=sys.stderr):
                if any(p.poll() is not None for p in procs):
                    break
                time.sleep(1.0)
        finally:
            for proc in reversed(procs):
                stop(proc)
    if not output.exists():
        raise VmocapError(f"the node graph wrote no {output}; see {out_dir / 'graph.log'}")
    return output


def recording_from_graph(path: Path, rig: Rig, n_frames: int) -> dict:
    """The report's per-frame record from the graph's recorded topics (frame f = stamp f/60 s)."""
    from ..bag import BagReader
    from ..bag import messages as M
    from ..graph_config import Topics
    from ..pcm.assembly import PcmAssembler, channel_keypoints
    from ..pcm.peaks import camera_keypoints
    topics = Topics()
    stamps = np.array([int(round(f * 1e9 / FPS)) for f in range(n_frames)], dtype=np.int64)
    index = {int(s): f for f, s in enumerate(stamps)}
    J, C = len(KEYPOINTS), len(rig)
    nan3 = np.full((n_frames, J, 3), np.nan)
    rec: dict[str, Any] = {"stamp": stamps, "status": ["dropped"] * n_frames, "keypoints": nan3.copy(), "raw": nan3.copy(),
           "markers": nan3.copy(), "uv": np.full((n_frames, C, J, 2), np.nan), "w": np.zeros((n_frames, C, J)),
           "score": np.zeros(n_frames), "weights": np.zeros((n_frames, J)), "n_views": np.zeros(n_frames, int)}
    for k in ("t_decode", "t_pcm", "t_markers", "t_skeleton"):
        rec[k] = np.full(n_frames, np.nan)  # per-stage timing: `vmocap bench graph` measures the graph
    asm = PcmAssembler(rig, rig.names, channel_keypoints([]), tolerance_ns=1_000_000, min_views=1)
    pcm_topics = {topics.pcm(c.name): (c.name, "image") for c in rig} | {topics.pcm_info(c.name): (c.name, "info") for c in rig}

    def take(pcms) -> None:
        for pcm in pcms:
            f = index.get(int(pcm.stamp_ns))
            if f is not None:
                rec["uv"][f], rec["w"][f] = camera_keypoints(pcm, C)
                rec["n_views"][f] = pcm.n_views

    node_timing: dict[str, dict[str, float]] = {}
    with BagReader(path) as reader:
        for m in reader.messages():
            msg = m.decode()
            if m.topic == Topics.diagnostics:
                for st in msg.get("status", []):  # the nodes' own processing time (last report wins)
                    kv = {e["key"]: e["value"] for e in st.get("values", [])}
                    if "proc_ms_p50" in kv:
                        node_timing[st["name"]] = {"median_ms": float(kv["proc_ms_p50"]), "p95_ms": float(kv["proc_ms_p95"]),
                                                   "frames": float(kv.get("proc_ms_n", "nan"))}
                continue
            if m.topic in pcm_topics:
                view, kind = pcm_topics[m.topic]
                take(asm.add_image(view, msg) if kind == "image" else asm.add_info(view, msg))
                continue
            f = index.get(M.stamp_ns(msg)) if isinstance(msg, dict) and "header" in msg else None
            if f is None:
                continue
            if m.topic == topics.keypoints:
                P, S, _ = M.cloud_keypoints(msg)
                rec["status"][f] = "tracking" if P is not None else "initializing"
                if P is not None:
                    rec["keypoints"][f] = P
                    rec["raw"][f] = P
            elif m.topic == topics.markers:
                P, S, _ = M.cloud_keypoints(msg)
                if P is not None:
                    rec["markers"][f] = P
                rec["weights"][f] = S
        take(asm.flush())
    rec["node_timing"] = node_timing
    seen = rec["n_views"] > 0
    rec["score"] = np.where(seen, rec["weights"].sum(axis=1) / np.maximum(rec["n_views"], 1) / J, 0.0)
    return rec


# ------------------------------------------------------------------------------ report
def reprojection_errors(rig: Rig, rec: dict, min_weight: float = 0.5, which: str = "keypoints") -> np.ndarray:
    """(N, C, 25) pixel distance between the projected output skeleton (or `which` = "raw" /
    "markers") and the CNN's 2D keypoints (PCM centroids) where the CNN is confident; NaN
    elsewhere or when not tracking."""
    kp = rec[which]  # (N, 25, 3)
    proj, front = rig.project(np.nan_to_num(kp))  # (C, N, 25, 2)
    proj = proj.transpose(1, 0, 2, 3)
    err = np.linalg.norm(proj - rec["uv"], axis=-1)  # (N, C, 25)
    ok = (rec["w"] >= min_weight) & np.isfinite(err) & front.transpose(1, 0, 2) & np.isfinite(kp).all(axis=-1)[:, None, :]
    return np.where(ok, err, np.nan)


def free_triangulation_errors(rig: Rig, rec: dict, min_weight: float = 0.5) -> np.ndarray:
    """Reference for the reprojection error: per frame, the CNN's 2D keypoints triangulated
    freely (weighted DLT, no skeleton, no filter, the worst view dropped above 20 px), reprojected.
    (N, C, 25) like reprojection_errors."""
    from ..method.triangulation import triangulate_robust

    n = len(rec["uv"])
    pts = np.full((n, len(KEYPOINTS), 3), np.nan)
    for f in range(n):
        pts[f], _ = triangulate_robust(rig, np.nan_to_num(rec["uv"][f]), rec["w"][f])
    return reprojection_errors(rig, {**rec, "free": pts}, min_weight, which="free")


def draw_skeleton(img: np.ndarray, uv: np.ndarray, color=(0, 255, 0), thickness: int = 4) -> None:
    import cv2

    for a, b in LIMBS:
        pa, pb = uv[INDEX[a]], uv[INDEX[b]]
        if np.isfinite(pa).all() and np.isfinite(pb).all():
            cv2.line(img, tuple(int(x) for x in pa), tuple(int(x) for x in pb), color, thickness, cv2.LINE_AA)
    for p in uv:
        if np.isfinite(p).all():
            cv2.circle(img, tuple(int(x) for x in p), thickness + 2, (0, 0, 255), -1, cv2.LINE_AA)


def render_overlays(bag: Path, rig: Rig, rec: dict, out_dir: Path, scale: float = 0.25) -> dict:
    """MP4 of the 4 views side by side with the reprojected skeleton, and a contact sheet."""
    import cv2

    kp = rec["keypoints"]
    proj, _ = rig.project(np.nan_to_num(kp))  # (C, N, 25, 2)
    proj = np.where(np.isfinite(kp).all(axis=-1)[None, ..., None], proj, np.nan)
    n = len(kp)
    sheet_idx = set(np.linspace(0, n - 1, 4).round().astype(int).tolist())
    sheet_rows = []
    writer = None
    mp4 = out_dir / "overlay.mp4"
    for f, (ns, images) in enumerate(bag_frame_sets(bag, rig)):
        if f >= n:
            break
        tiles = []
        for c, img in enumerate(images):
            img = img.copy()
            draw_skeleton(img, proj[c, f])
            status = rec["status"][f]
            cv2.putText(img, f"{rig[c].name} t={ns / 1e9:.2f}s {status}", (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 1.6,
                        (255, 255, 255), 4, cv2.LINE_AA)
            h, w = img.shape[:2]
            tile = cv2.resize(img, (int(1088 * scale), int(1920 * scale)))
            tiles.append(tile)
        row = np.hstack(tiles)
        if writer is None:
            writer = cv2.VideoWriter(str(mp4), cv2.VideoWriter.fourcc(*"mp4v"), FPS, (row.shape[1], row.shape[0]))
        writer.write(row)
        if f in sheet_idx:
            sheet_rows.append(row)
    if writer is not None:
        writer.release()
    sheet = out_dir / "contact_sheet.png"
    if sheet_rows:
        cv2.imwrite(str(sheet), np.vstack(sheet_rows))
    return {"mp4": mp4.name, "contact_sheet": sheet.name, "mp4_ok": mp4.exists() and mp4.stat().st_size > 0}


def write_report(rig: Rig, rec: dict, out_dir: Path, info: dict) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..method.skeleton import BONES

    t = (rec["stamp"] - rec["stamp"][0]) / 1e9
    tracking = np.array([s == "tracking" for s in rec["status"]])
    kp = rec["keypoints"]
    err = reprojection_errors(rig, rec)
    # Reprojection error per camera and keypoint.
    per_cam = {rig[c].name: float(np.nanmedian(err[:, c])) for c in range(len(rig))}
    per_kp = {KEYPOINTS[j]: float(np.nanmedian(err[:, :, j])) for j in range(len(KEYPOINTS)) if np.isfinite(err[:, :, j]).any()}
    median_all = float(np.nanmedian(err)) if np.isfinite(err).any() else float("nan")
    free = free_triangulation_errors(rig, rec)
    both = np.isfinite(err) & np.isfinite(free)  # same samples for the comparison
    median_free = float(np.median(free[both])) if both.any() else float("nan")
    median_same = float(np.median(err[both])) if both.any() else float("nan")
    face = np.array([INDEX[n] for n in ("nose", "left_eye", "right_eye", "left_ear", "right_ear")])
    body = np.setdiff1d(np.arange(len(KEYPOINTS)), face)
    median_body = float(np.nanmedian(err[:, :, body])) if np.isfinite(err[:, :, body]).any() else float("nan")
    median_body_free = float(np.nanmedian(free[:, :, body])) if np.isfinite(free[:, :, body]).any() else float("nan")
    free_kp = {KEYPOINTS[j]: float(np.nanmedian(free[:, :, j])) for j in range(len(KEYPOINTS)) if np.isfinite(free[:, :, j]).any()}
    raw = reprojection_errors(rig, rec, which="raw")
    median_raw = float(np.nanmedian(raw)) if np.isfinite(raw).any() else float("nan")
    # Bone lengths of the output skeleton.
    bones = {}
    for name, (a, b) in BONES.items():
        L = np.linalg.norm(kp[:, INDEX[a]] - kp[:, INDEX[b]], axis=-1)[tracking]
        L = L[np.isfinite(L)]
        if L.size:
            bones[name] = {"mean_m": float(L.mean()), "std_mm": float(L.std() * 1000), "range_mm": float(np.ptp(L) * 1000)}
    # Timing.
    if rec.get("node_timing"):
        timing = {f"node {k}": {"mean_ms": float("nan"), "median_ms": v["median_ms"], "p95_ms": v["p95_ms"]}
                  for k, v in rec["node_timing"].items()}
    else:
        timing = {k[2:]: {"mean_ms": float(np.mean(rec[k]) * 1000), "median_ms": float(np.median(rec[k]) * 1000),
                          "p95_ms": float(np.percentile(rec[k], 95) * 1000)}
                  for k in ("t_decode", "t_pcm", "t_markers", "t_skeleton")}

    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, rec["score"], label="mean PCM score per view (marker weights)")
    ax.fill_between(t, 0, 1, where=~tracking, color="0.85", label="not tracking")
    ax.set_xlabel("time (s)"); ax.set_ylabel("score"); ax.set_ylim(0, 1); ax.legend(); fig.tight_layout()
    fig.savefig(out_dir / "pcm_score.png", dpi=100); plt.close(fig)

    fig = plt.figure(figsize=(7, 7))
    ax3 = fig.add_subplot(projection="3d")
    for name in ("pelvis", "nose", "left_wrist", "right_wrist", "left_ankle", "right_ankle"):
        p = kp[:, INDEX[name]]
        ax3.plot(p[:, 0], p[:, 1], p[:, 2], label=name)
    last = np.nonzero(np.isfinite(kp).all(axis=(1, 2)))[0]
    if last.size:
        q = kp[last[-1]]
        for a, b in LIMBS:
            ax3.plot(*np.stack([q[INDEX[a]], q[INDEX[b]]]).T, color="k", lw=1)
    ax3.set_xlabel("x (m)"); ax3.set_ylabel("y (m)"); ax3.set_zlabel("z (m)"); ax3.legend(fontsize=7)
    fig.tight_layout(); fig.savefig(out_dir / "trajectories_3d.png", dpi=100); plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    for name, (a, b) in BONES.items():
        L = np.linalg.norm(kp[:, INDEX[a]] - kp[:, INDEX[b]], axis=-1)
        ax.plot(t, L * 100, label=name)
    ax.set_xlabel("time (s)"); ax.set_ylabel("length (cm)"); ax.legend(fontsize=6, ncol=3); fig.tight_layout()
    fig.savefig(out_dir / "bone_lengths.png", dpi=100); plt.close(fig)

    fig, ax = plt.subplots(figsize=(10, 3.5))
    kps = list(per_kp)
    mat = np.array([[np.nanmedian(err[:, c, INDEX[k]]) if np.isfinite(err[:, c, INDEX[k]]).any() else np.nan for k in kps]
                    for c in range(len(rig))])
    im = ax.imshow(mat, cmap="viridis", aspect="auto")
    ax.set_xticks(range(len(kps)), kps, rotation=70, fontsize=7); ax.set_yticks(range(len(rig)), rig.names)
    fig.colorbar(im, label="median px"); fig.tight_layout(); fig.savefig(out_dir / "reprojection_error.png", dpi=100)
    plt.close(fig)

    summary = {
        "frames": int(len(t)),
        "tracking_frames": int(tracking.sum()),
        "first_tracking_s": float(t[tracking][0]) if tracking.any() else None,
        "median_reprojection_px": median_all,
        "median_reprojection_px_first_ik": median_raw,
        "median_reprojection_px_free_triangulation": median_free,
        "median_reprojection_px_same_samples": median_same,
        "median_reprojection_px_body_no_face": median_body,
        "median_reprojection_px_body_no_face_free_triangulation": median_body_free,
        "reprojection_px_per_camera": per_cam,
        "reprojection_px_per_keypoint": per_kp,
        "bone_lengths": bones,
        "timing": timing,
        **info,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    np.savez_compressed(out_dir / "recording.npz",
                        **{k: np.asarray(v) for k, v in rec.items() if k not in ("links", "node_timing")})
    md = [
        "# vmocap demo: Pose2Sim Demo_SinglePerson", "",
        f"{summary['frames']} frame sets at {FPS:.0f} fps, 4 cameras 1088x1920 (cam01/cam02 videos are "
        "stored 1080 wide, cropped at the right). Tracking in "
        f"{summary['tracking_frames']} frames (from t = {summary['first_tracking_s']} s). Run: "
        f"{info.get('mode', 'in-process pipeline')}; frame sets processed: {info.get('processed_frames', summary['frames'])}.", "",
        f"**Median reprojection error** of the output skeleton against the CNN's confident 2D keypoints "
        f"(PCM centroids, peak >= 0.5), all cameras and keypoints: **{median_all:.1f} px** (target <= 12 px). "
        + ("" if rec.get("node_timing") else f"Before the low-pass filter (first IK): {median_raw:.1f} px. ")
        + f"Reference on the same samples: free "
        f"per-frame triangulation of the same 2D keypoints (no skeleton, no filter) reprojects with "
        f"{median_free:.1f} px (ours {median_same:.1f} px). Without the 5 face keypoints: ours "
        f"{median_body:.1f} px, free triangulation {median_body_free:.1f} px (the face keypoints hang on a "
        "rigid head that pivots at the shoulder midpoint, BlazePose having no neck keypoint).", "",
        "| camera | median px |", "|---|---|", *[f"| {k} | {v:.1f} |" for k, v in per_cam.items()], "",
        "| keypoint | median px | free triangulation px |", "|---|---|---|",
        *[f"| {k} | {v:.1f} | {free_kp.get(k, float('nan')):.1f} |" for k, v in per_kp.items()], "",
        "Bone lengths of the output while tracking (the skeleton keeps its links constant):", "",
        "| bone | mean (m) | std (mm) | range (mm) |", "|---|---|---|---|",
        *[f"| {k} | {v['mean_m']:.3f} | {v['std_mm']:.2f} | {v['range_mm']:.2f} |" for k, v in bones.items()], "",
        "Time per frame set (this machine, shared CPU):", "",
        "| stage | mean ms | median ms | p95 ms |", "|---|---|---|---|",
        *[f"| {k} | {v['mean_ms']:.1f} | {v['median_ms']:.1f} | {v['p95_ms']:.1f} |" for k, v in timing.items()], "",
        "Files: " + ", ".join(sorted(p.name for p in out_dir.iterdir() if p.is_file())) + ".",
    ]
    (out_dir / "report.md").write_text("\n".join(md) + "\n")
    return summary


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
    parser.add_argument("--graph-rate", type=float, default=0.05, help="bag playback rate in graph mode (x real time)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from ..calibration.datasets import pose2sim_demo
    from ..cameras.rig_file import save_rig
    from ..pcm.fetch import fetch as fetch_models

    log("PCM models: checking the cache (builds it on a fresh machine, as `vmocap models fetch`)")
    fetch_models(quiet=True)
    log("fetching the pose2sim==0.10.49 wheel (pip download --no-deps, cached)")
    demo = pose2sim_demo(fetch=True)
    if demo is None:
        print("vmocap demo: could not obtain the Pose2Sim demo", file=sys.stderr)
        return 1
    videos = video_paths(demo)
    rig = load_qualisys_rig(demo / "calibration" / "Calib.qca.txt", video_sizes(videos))
    args.out.mkdir(parents=True, exist_ok=True)
    save_rig(rig, args.out / "rig.yaml")
    log(f"rig {rig.names} -> {args.out / 'rig.yaml'}")
    want = min(_video_frames(videos), args.frames or 10**9)
    if args.bag.exists() and not args.rebuild_bag and _count_frame_sets(args.bag, rig) == want:
        n = want
        log(f"reusing {args.bag} ({n} frame sets; --rebuild-bag to convert again)")
    else:
        n = videos_to_bag(videos, rig, args.bag, args.frames)
        log(f"{n} frame sets -> {args.bag}")
    t0 = time.perf_counter()
    if args.mode == "graph":
        log(f"node graph on {args.bag} at {args.graph_rate} x real time")
        recorded = run_graph(args.bag, args.out / "rig.yaml", rig, args.out, n, args.graph_rate)
        rec = recording_from_graph(recorded, rig, n)
        mode = "ROS 2 node graph (vmocap launch: camera from bag, CNN PCM, markers, skeleton, recorder)"
    else:
        rec = run_pipeline(args.bag, rig, args.out / "outputs.mcap", n, args.threads)
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
